"""The study's run list, tables and ten-test family, on tables with known answers."""

import math

import numpy as np
import pytest
from scipy import stats

from geodepth_lite import ablation, config, run_cache, study

METRICS = study.METRIC_COLUMNS


def _tables(change: dict, seeds=range(8), base=0.10) -> dict:
    """Study tables whose run (term, case, seed) scores base * (1 + seed / 100) * (1 + change[(term, case)][seed])
    in every metric on the primary set, and one baseline row."""
    runs = []
    for term, case in study.CELLS:
        for s in seeds:
            v = base * (1 + s / 100) * (1 + change.get((term, case), [0.0] * 8)[s])
            runs.append({"depth_term": term, "case": case, "seed": s, "set": study.PRIMARY, "frames": 480,
                         **{m: v for m in METRICS}})
    baselines = [{"set": study.PRIMARY, "baseline": "constant", **{m: 0.3 for m in METRICS}}]
    return {"runs": runs, "baselines": baselines}


def test_the_study_is_48_runs_and_its_silog_seeds_0_to_2_are_the_default_ablation():
    runs = study.study_runs("teach")
    assert len(runs) == 48 and len({(t, c, s) for t, c, s, _ in runs}) == 48
    default = {run_cache.checkpoint_dir("teach", c, s) for c in (1, 2, 3, 4) for s in study.DEFAULT_SEEDS}
    ours = {run_cache.checkpoint_dir("teach", c, s, **o) for t, c, s, o in runs if t == "silog"}
    assert default <= ours
    l1 = [config.make_config("teach", c, s, **o) for t, c, s, o in runs if t == "l1"]
    assert {cfg["depth_term"] for cfg in l1} == {"l1"} and {cfg["case"] for cfg in l1} == {1, 4}
    assert config.make_config("teach", 1, 0)["depth_term"] == "silog"


def test_the_family_computes_the_plans_ten_tests():
    eps = [0.01, -0.01, 0.005, -0.005, 0.0, 0.002, -0.002, 0.0]
    change = {("silog", 4): [-0.10 + e for e in eps], ("l1", 4): [-0.30 + 2 * e for e in eps],
              ("silog", 2): [-0.05 + e for e in eps], ("silog", 3): [0.0 + e for e in eps]}
    fam = study.family(_tables(change))
    assert len(fam) == 10 and [(t["term"], t["case"], t["metric"]) for t in fam][:2] == \
        [("silog", 2, "rmse"), ("silog", 2, "abs_rel")]
    by = {(t["term"], t["case"], t["metric"]): t for t in fam}
    c4 = by[("silog", 4, "rmse")]
    r = 100 * np.array([-0.10 + e for e in eps])  # base and the seed factor cancel in the ratio
    assert c4["values"] == pytest.approx(r.tolist()) and c4["mean"] == pytest.approx(r.mean())
    half = stats.t.ppf(1 - 0.05 / 20, 7) * r.std(ddof=1) / math.sqrt(8)  # Bonferroni: 1 - 0.05 / 10
    assert (c4["low"], c4["high"]) == pytest.approx((r.mean() - half, r.mean() + half))
    # -10% +/- 1: differs from 0, the paper's -22% far outside: smaller than the paper
    assert c4["verdict"] == "direction reproduced, smaller than the paper (paper's value excluded)"
    assert by[("silog", 3, "rmse")]["verdict"].startswith("no effect detected; effects beyond")
    inter = by[("l1 - silog", study.INTERACTION, "abs_rel")]
    d = 100 * np.array([-0.30 + 2 * e for e in eps]) - r
    assert inter["values"] == pytest.approx(d.tolist()) and inter["paper"] is None
    assert inter["verdict"].startswith("the geometric losses help more against the L1 baseline (by ")
    p = [t["p"] for t in fam]
    assert [t["rejected"] for t in fam] == ablation.holm(p)


def test_interaction_words():
    assert study.interaction_verdict(-3.0, 2.0, -0.5, False) == \
        "no depth-term dependence detected; differences beyond 3.0 points excluded"
    assert study.interaction_verdict(1.0, 4.0, 2.5, True).startswith("opposite")
    assert study.interaction_verdict(-9.0, -4.0, -6.5, True) == \
        "the geometric losses help more against the L1 baseline (by 4.0 to 9.0 points)"


def test_tables_round_trip_and_a_missing_table_is_named(tmp_path):
    runs = [{"depth_term": "silog", "case": 1, "seed": 0, "set": study.PRIMARY, "frames": 2,
             **{m: study._fmt(0.1 + i / 1000) for i, m in enumerate(METRICS)}}]
    frames = [{"depth_term": "silog", "case": 1, "seed": 0, "index": i, "organ": "colon", "group": "T1-L1",
               **{m: study._fmt(0.1 + i / 100) for m in (*METRICS, "ratio")}} for i in range(2)]
    base = [{"set": study.PRIMARY, "baseline": "constant", **{m: "0.3" for m in METRICS}}]
    out = study.write_tables(tmp_path / "study", runs, frames, base)
    back = study.read_tables(out, frames=True)
    assert back["runs"][0]["case"] == 1 and back["runs"][0]["rmse"] == pytest.approx(0.102)
    assert [f["index"] for f in back["frames"]] == [0, 1] and back["baselines"][0]["abs_rel"] == 0.3
    (out / "baselines.csv").unlink()
    with pytest.raises(FileNotFoundError, match=r"baselines\.csv.*reproduce --study"):
        study.read_tables(out)


def test_the_paired_record_of_the_study_and_of_its_silog_subset():
    eps = [0.01, -0.01, 0.005, -0.005, 0.0, 0.002, -0.002, 0.0]
    tables = _tables({("silog", 4): [-0.10 + e for e in eps], ("l1", 4): [-0.30 + e for e in eps]})
    full = study.paired_record(tables)
    assert full["paired | seeds"] == 8 and len(full) == 1 + 2 * 10
    r = 100 * np.array([-0.10 + e for e in eps])
    assert full["paired | confirmation set | rmse | silog case4 | mean %"] == round(r.mean(), 2)
    assert full["paired | confirmation set | abs_rel | silog case4 | sd %"] == round(r.std(ddof=1), 2)
    assert full["paired | confirmation set | rmse | l1 - silog | mean %"] == pytest.approx(-20.0, abs=0.01)
    silog_only = {"runs": [r_ for r_ in tables["runs"] if r_["depth_term"] == "silog"],
                  "baselines": tables["baselines"]}
    sub = study.paired_record(silog_only, seeds=study.DEFAULT_SEEDS)
    assert sub["paired | seeds"] == 3 and set(sub) < set(full)  # the subset's keys are the study's
    assert sub["paired | confirmation set | rmse | silog case4 | mean %"] == round(r[:3].mean(), 2)
    runs = study.run_record(tables, seeds=[0])
    assert len(runs) == len(study.CELLS) * len(METRICS)
    assert runs[f"l1 case4 seed0 | {study.PRIMARY} | rmse"] == round(0.10 * (1 - 0.30 + eps[0]), 4)
