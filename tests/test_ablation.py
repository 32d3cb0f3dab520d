"""The ablation's statistics: paired differences, Student-t intervals, verdicts, records."""

import math

import numpy as np
import pytest

from geodepth_lite.evaluation import ablation


def test_t_interval_hand_computed():
    # values 1, 2, 3: mean 2, sd 1, t(0.975, 2) = 4.302653 -> half width 4.302653 / sqrt(3)
    m, lo, hi = ablation.t_interval([1.0, 2.0, 3.0])
    half = 4.302652729911275 / math.sqrt(3)
    assert m == pytest.approx(2.0) and lo == pytest.approx(2 - half) and hi == pytest.approx(2 + half)
    assert ablation.t_interval([5.0])[1:] == (-math.inf, math.inf)


def test_holm_step_down_hand_computed():
    # m = 4, alpha 0.05: thresholds 0.0125, 0.0167, 0.025, 0.05 for the sorted p-values
    assert ablation.holm([0.01, 0.04, 0.03, 0.005]) == [True, False, False, True]  # 0.03 > 0.025 stops
    assert ablation.holm([0.01, 0.02, 0.03, 0.04]) == [True, False, False, False]  # 0.02 > 0.0167 stops
    assert ablation.holm([0.04, 0.015, 0.02, 0.01]) == [True, True, True, True]
    assert ablation.holm([0.02, 0.001]) == [True, True]  # 0.001 <= 0.025, then 0.02 <= 0.05
    assert ablation.holm([0.029, 0.009, 0.5] + [0.9] * 9) == [False] * 12  # 0.009 > 0.05 / 12 stops at once
    # a rule without the correction (every p <= 0.05 rejected) would pass these two: Holm must not
    assert ablation.holm([0.03, 0.04]) == [False, False]


def test_size_verdicts_follow_the_plans_rule():
    v = ablation.size_verdict
    assert v(-15.0, -8.0, -11.0, -13.0, True) == "paper's size reproduced"
    assert v(-5.1, -0.7, -2.9, -13.0, True) == "direction reproduced, smaller than the paper (paper's value excluded)"
    assert v(-40.0, -30.0, -35.0, -22.0, True) == "direction reproduced, larger than the paper (paper's value excluded)"
    assert v(0.7, 5.1, 2.9, -13.0, True) == "opposite"
    assert v(-2.7, 1.9, -0.4, -20.4, False) == "no effect detected; effects beyond 2.7% excluded"
    assert v(-25.0, 3.0, -11.0, -20.4, False) == "undecided"


def test_an_interval_wider_than_the_bound_reads_undecided():
    """The confirmatory studies' bound: twice the paper's smallest change (10%), 20 points. Zero
    kept with a wider interval is "undecided" even when the paper's value lies outside it; a
    rejected comparison keeps its words, and without a bound nothing changes."""
    v = ablation.size_verdict
    assert ablation.WIDTH_BOUND == 20.0
    assert v(-15.3, 11.4, -2.0, -20.4, False) == "no effect detected; effects beyond 15.3% excluded"  # no bound
    assert v(-15.3, 11.4, -2.0, -20.4, False, max_width=20.0) == "undecided"  # 26.7 points wide
    assert v(-9.3, 8.3, -0.5, -25.4, False, max_width=20.0) == "no effect detected; effects beyond 9.3% excluded"
    assert v(-10.0, 10.0, 0.0, -25.4, False, max_width=20.0).startswith("no effect detected")  # 20: not wider
    assert v(-10.0, 10.01, 0.0, -25.4, False, max_width=20.0) == "undecided"
    assert v(-40.0, -15.0, -27.0, -22.0, True, max_width=20.0) == "paper's size reproduced"
    assert v(5.0, 30.0, 17.0, -22.0, True, max_width=20.0) == "opposite"


def _result(case_offsets, seed_effects, cases=(1, 2)):
    scores = {}
    for c in cases:
        for s, e in enumerate(seed_effects):
            m = {k: 0.5 for k in ablation.evaluate.METRIC_KEYS}
            m["abs_rel"] = 0.20 + e + case_offsets[c][s]
            scores[(c, s)] = {ablation.IN_DOMAIN: m}
    base = {ablation.IN_DOMAIN: {"constant": {"abs_rel": 0.33}, "shading_prior": {"abs_rel": 0.16}}}
    return {"cases": list(cases), "seeds": list(range(len(seed_effects))), "scores": scores, "baselines": base}


def test_pairing_removes_the_seed_effect():
    """Seeds differ a lot (0.00, 0.05, 0.10) but Case 2 is 0.01 better at every seed: paired, that is
    certain; unpaired (two independent means) it would drown in the seed spread."""
    r = _result({1: [0, 0, 0], 2: [-0.01, -0.011, -0.009]}, [0.0, 0.05, 0.10])
    p = ablation.paired(r, "abs_rel", ablation.IN_DOMAIN, 2)
    assert p["diffs"] == pytest.approx([-0.01, -0.011, -0.009])
    assert p["rel_diffs"] == pytest.approx([-5.0, -100 * 0.011 / 0.25, -100 * 0.009 / 0.3])
    assert p["rel"] == pytest.approx(sum(p["rel_diffs"]) / 3) and p["rel_high"] < 0 and p["p"] < 0.05
    stats = ablation.case_stats(r, ablation.IN_DOMAIN, "abs_rel")
    assert stats[1][1] == pytest.approx(0.05)  # the seed spread the pairing removed
    worse = _result({1: [0, 0, 0], 2: [0.02, 0.03, 0.025]}, [0.0, 0.05, 0.10])
    assert ablation.comparisons(worse)[0][3]["verdict"] == "opposite"  # [0]: Abs Rel, [1]: RMSE
    mixed = _result({1: [0, 0, 0], 2: [0.02, -0.03, 0.0]}, [0.0, 0.05, 0.10])
    assert ablation.comparisons(mixed)[0][3]["verdict"] == "undecided"


def test_baselines_margin_and_record():
    r = _result({1: [0, 0, 0], 2: [-0.1, -0.1, -0.1]}, [-0.08, -0.07, 0.0])
    # case 1: 0.12, 0.13, 0.20; case 2: 0.02, 0.03, 0.10; best baseline 0.16, 20% below it = 0.128
    beats = ablation.beats_baselines(r, ablation.IN_DOMAIN, "abs_rel", 0.2)
    assert beats == {(1, 0): True, (1, 1): False, (1, 2): False, (2, 0): True, (2, 1): True, (2, 2): True}
    rec = ablation.record(r)
    assert rec[f"case1 seed2 | {ablation.IN_DOMAIN} | abs_rel"] == 0.2
    assert rec[f"baselines | {ablation.IN_DOMAIN} | shading_prior | abs_rel"] == 0.16
    # Case 2 is 0.1 better at every seed: -0.1 / 0.12, -0.1 / 0.13, -0.1 / 0.20 of each seed's Case 1
    r_s = [-100 * 0.1 / 0.12, -100 * 0.1 / 0.13, -100 * 0.1 / 0.20]
    mean, sd = (rec[f"paired | {ablation.IN_DOMAIN} | abs_rel | case2 | {k} %"] for k in ("mean", "sd"))
    assert mean == pytest.approx(sum(r_s) / 3, abs=0.005) and sd == pytest.approx(np.std(r_s, ddof=1), abs=0.005)
    assert rec["paired | seeds"] == 3 and rec["paired | family size"] == len(ablation.comparisons(r))
    lines = ablation.claims(r)
    assert any("Abs Rel: Case 2 vs Case 1 -> " in line for line in lines)
    assert (f"{ablation.IN_DOMAIN}: runs below every baseline in Abs Rel: 5 of 6; "
            "at least 20% below the best baseline: 4 of 6") in lines
