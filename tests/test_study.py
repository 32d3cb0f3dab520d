"""The study's run list, tables and ten-test family, on tables with known answers."""

import math

import numpy as np
import pytest
from scipy import stats

from geodepth_lite.evaluation import ablation, study
from geodepth_lite.training import config, run_cache

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
    teach = config.profile("teach")
    runs = study.study_runs(teach)
    assert len(runs) == 48 and len({(t, c, s) for t, c, s, _ in runs}) == 48
    default = {run_cache.checkpoint_dir(teach.run(c, s)) for c in (1, 2, 3, 4) for s in study.DEFAULT_SEEDS}
    ours = {run_cache.checkpoint_dir(run) for t, c, s, run in runs if t == "silog"}
    assert default <= ours
    l1 = [run.as_dict() for t, c, s, run in runs if t == "l1"]
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
    assert not any(t["too_wide"] for t in fam)
    inter = by[("l1 - silog", study.INTERACTION, "abs_rel")]
    d = 100 * np.array([-0.30 + 2 * e for e in eps]) - r
    assert inter["values"] == pytest.approx(d.tolist()) and inter["paper"] is None
    assert inter["verdict"].startswith("the geometric losses help more against the L1 baseline (by ")
    p = [t["p"] for t in fam]
    assert [t["rejected"] for t in fam] == ablation.holm(p)


def test_the_family_says_undecided_for_an_interval_wider_than_the_bound():
    """L1 Case 4 with seeds spread +-12% around 0 (sd 8 points): zero kept, the interval about
    [-11.4, +11.4], 22.8 points wide, the paper's -22% outside it. Over the bound of 20 points:
    "undecided", for it and for the interaction; with no bound the old words come back."""
    spread = [0.12, -0.12, 0.08, -0.08, 0.04, -0.04, 0.0, 0.0]
    tables = _tables({("l1", 4): spread})
    by = {(t["term"], t["case"], t["metric"]): t for t in study.family(tables)}
    l1, inter = by[("l1", 4, "rmse")], by[("l1 - silog", study.INTERACTION, "rmse")]
    assert 20 < l1["high"] - l1["low"] < 24 and l1["paper"] < l1["low"] and l1["too_wide"] and not l1["rejected"]
    assert l1["verdict"] == "undecided" and inter["verdict"] == "undecided" and inter["too_wide"]
    old = {(t["term"], t["case"], t["metric"]): t for t in study.family(tables, max_width=None)}
    assert old[("l1", 4, "rmse")]["verdict"] == f"no effect detected; effects beyond {l1['high']:.1f}% excluded"
    assert old[("l1 - silog", study.INTERACTION, "rmse")]["verdict"].startswith("no depth-term dependence detected")
    assert not old[("l1", 4, "rmse")]["too_wide"]


def test_interaction_words():
    assert study.interaction_verdict(-3.0, 2.0, -0.5, False) == \
        "no depth-term dependence detected; differences beyond 3.0 points excluded"
    # the close-ups' +-43 points: too wide to exclude anything (the bound: 20 points)
    assert study.interaction_verdict(-42.6, 43.0, 0.2, False, max_width=20.0) == "undecided"
    assert study.interaction_verdict(-42.6, 43.0, 0.2, False).endswith("beyond 43.0 points excluded")  # no bound
    assert study.interaction_verdict(-3.0, 2.0, -0.5, False, max_width=20.0).startswith("no depth-term")
    assert study.interaction_verdict(-45.0, -24.0, -34.5, True, max_width=20.0).startswith("the geometric")
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
    assert sub["paired | seeds"] == 2 and set(sub) < set(full)  # the subset's keys are the study's
    assert sub["paired | confirmation set | rmse | silog case4 | mean %"] == round(r[:2].mean(), 2)
    runs = study.run_record(tables, seeds=[0])
    assert len(runs) == len(study.CELLS) * len(METRICS)
    assert runs[f"l1 case4 seed0 | {study.PRIMARY} | rmse"] == round(0.10 * (1 - 0.30 + eps[0]), 4)


STEMS = [f"paired | {study.PRIMARY} | {m} | silog case{c}" for c in (2, 3, 4) for m in ("rmse", "abs_rel")]


def _record(values: dict) -> dict:
    """A paired record from per-seed values {stem: array of r_s}."""
    rec = {"paired | seeds": float(len(next(iter(values.values()))))}
    for stem, v in values.items():
        rec[f"{stem} | mean %"], rec[f"{stem} | sd %"] = float(v.mean()), float(v.std(ddof=1))
    return rec


def _problems(fresh: dict, committed: dict) -> list[str]:
    return [line for c in study.check_subset(fresh, committed) for line in c["problems"]]


def test_the_subset_check_passes_fresh_draws_and_catches_a_moved_effect():
    """Brute force: draw a study of 8 seeds and a retrained subset of 3 from one per-seed
    distribution (mean -4, sd 1.5 points) many times. The check must pass at least FRESH_LEVEL of
    the pairs, and catch Case 3's RMSE moved by 8 points (about 5 sd of one seed) most of the time.
    It cannot catch 2 points: three fresh seeds leave that inside the range."""
    rng = np.random.default_rng(0)
    trials, passed, caught = 400, 0, {2.0: 0, 8.0: 0}
    moved = f"paired | {study.PRIMARY} | rmse | silog case3"
    for _ in range(trials):
        committed = _record({k: rng.normal(-4.0, 1.5, 8) for k in STEMS})
        fresh = _record({k: rng.normal(-4.0, 1.5, 3) for k in STEMS})
        passed += not _problems(fresh, committed)
        for shift in caught:
            wrong = {**fresh, f"{moved} | mean %": fresh[f"{moved} | mean %"] + shift}
            caught[shift] += any(line.startswith(moved) for line in _problems(wrong, committed))
    assert passed / trials >= study.FRESH_LEVEL - 0.015, passed / trials
    assert caught[8.0] / trials >= 0.8, caught
    assert caught[2.0] / trials <= 0.1, caught


def test_the_subset_check_names_what_is_out_of_range():
    committed = _record({k: np.array([-4.0, -2.0, -6.0, -3.0, -5.0, -4.5, -3.5, -4.0]) for k in STEMS})
    stem = STEMS[2]
    (lo, hi), (s_lo, s_hi) = study.prediction_ranges(committed, stem, 3, 2 * len(STEMS))
    # known answer: t(1 - 0.01 / 24, 7) sd sqrt(1/8 + 1/3) around the mean
    sd = committed[f"{stem} | sd %"]
    half = stats.t.ppf(1 - 0.01 / 24, 7) * sd * math.sqrt(1 / 8 + 1 / 3)
    assert (lo, hi) == pytest.approx((-4.0 - half, -4.0 + half))
    assert s_lo < sd < s_hi
    fresh = {**committed, "paired | seeds": 3.0, f"{stem} | mean %": hi - 0.01}
    assert _problems(fresh, committed) == []
    fresh[f"{stem} | mean %"], fresh[f"{stem} | sd %"] = hi + 0.01, s_hi + 0.01
    assert [p.split(":")[0] for p in _problems(fresh, committed)] == [f"{stem} | mean %", f"{stem} | sd %"]
    with pytest.raises(KeyError, match="no test"):
        study.check_subset({**fresh, "paired | other | rmse | l1 case4 | mean %": 0.0,
                            "paired | other | rmse | l1 case4 | sd %": 1.0}, committed)


def test_claims_and_cell_statistics():
    eps = [0.01, -0.01, 0.005, -0.005, 0.0, 0.002, -0.002, 0.0]
    tables = _tables({("silog", 4): [-0.10 + e for e in eps], ("l1", 1): [2.0] * 8, ("l1", 4): [1.5] * 8})
    lines = study.claims(tables)
    assert len(lines) == 12 and lines[4].startswith(f"{study.PRIMARY}, RMSE: Case 4 vs Case 1 (silog) -> direction")
    # silog runs score 0.09-0.107; L1 Case 1 3x that (0.30-0.32), L1 Case 4 2.5x; the baseline 0.3
    assert lines[-2] == (f"{study.PRIMARY}, silog runs below every baseline in Abs Rel: 32 of 32; "
                         "at least 20% below the best baseline: 32 of 32")
    assert lines[-1] == (f"{study.PRIMARY}, L1 runs below every baseline in Abs Rel: 8 of 16; "  # Case 4: 0.25-0.27
                         "at least 20% below the best baseline: 0 of 16")
    mean, sd = study.cell_stats(tables, study.PRIMARY, "rmse")[("silog", 1)]
    v = [0.10 * (1 + s / 100) for s in range(8)]
    assert (mean, sd) == pytest.approx((np.mean(v), np.std(v, ddof=1)))


@pytest.fixture(scope="module")
def committed():
    return study.read_tables(frames=True)


def test_the_committed_study_is_whole_and_its_runs_are_the_means_of_their_frames(committed):
    assert study.check_tables(committed, frames_per_run=480) == []
    assert {r["set"] for r in committed["runs"]} == {study.PRIMARY, ablation.HELDOUT, study.CLOSEUPS}


def test_a_wrong_study_table_is_caught(committed):
    """Case 3's paired RMSE change moved by 3 points (every silog Case 3 run's RMSE on the
    confirmation set 3% of Case 1 lower in runs.csv alone), one run dropped, one frame dropped."""
    case1 = {r["seed"]: r["rmse"] for r in committed["runs"]
             if (r["depth_term"], r["case"], r["set"]) == ("silog", 1, study.PRIMARY)}
    moved = [dict(r) for r in committed["runs"]]
    for r in moved:
        if (r["depth_term"], r["case"], r["set"]) == ("silog", 3, study.PRIMARY):
            r["rmse"] -= 0.03 * case1[r["seed"]]
    wrong = {**committed, "runs": moved}
    problems = study.check_tables(wrong)
    assert len(problems) == 8 and all("('silog', 3, " in p and "rmse" in p for p in problems)
    before = {(t["case"], t["metric"]): t for t in study.family(committed)}
    after = {(t["case"], t["metric"]): t for t in study.family(wrong)}
    assert after[(3, "rmse")]["mean"] == pytest.approx(before[(3, "rmse")]["mean"] - 3.0, abs=1e-6)
    dropped = {**committed, "runs": [r for r in committed["runs"] if (r["depth_term"], r["seed"]) != ("l1", 7)
                                     or r["case"] != 4]}
    assert study.check_tables(dropped) == ["run ('l1', 4, 7) is missing"]
    short = {**committed, "frames": committed["frames"][1:]}
    assert len(study.check_tables(short)) == 1 and "479 frame rows" in study.check_tables(short)[0]


def test_the_notebook_states_the_verdicts_of_the_committed_tables(committed):
    """Notebook 05's committed verdict lines are study.claims of the committed tables, word for word
    and number for number; a flipped verdict is caught."""
    import nbformat

    from geodepth_lite import utils

    nb = nbformat.read(str(utils.project_root() / "notebooks" / "05_ablation.ipynb"), as_version=4)
    cell = next(c for c in nb.cells if c.cell_type == "code" and c.source.lstrip().startswith("# verdicts"))
    shown = "".join(o.get("text", "") for o in cell.outputs if o.get("name") == "stdout").splitlines()
    lines = study.claims(committed)
    assert shown == lines
    flipped = [line.replace("direction reproduced, smaller than the paper (paper's value excluded)",
                            "paper's size reproduced") for line in lines]
    assert flipped != lines  # the study has such a verdict, so the comparison above can fail


def test_the_smallest_change_the_cross_machine_check_catches(committed):
    """For Case 3's RMSE change of the committed study: a simulated retraining of 3 seeds whose
    true mean is shifted by the computed 80%-power amount (per-seed changes normal with the
    committed sd) is flagged by check_subset in about 80% of seeded draws; one shifted by a quarter
    of it rarely. A shift that puts the fresh mean's centre on the range's end is caught half the
    time (known answer of the analytic rate)."""
    rec = study.paired_record(committed)
    shifts = {s["test"]: s for s in study.detectable_shifts(rec, n_fresh=3)}
    assert len(shifts) == 6 and all(s["shift"] > 0 for s in shifts.values())
    stem = f"paired | {study.PRIMARY} | rmse | silog case3"
    c3 = shifts[stem.removeprefix("paired | ")]
    assert c3["range"] == pytest.approx((-8.14, 1.84), abs=0.01)  # the audit's "-8.1% to +1.8%"
    assert study.check_flag_rate(rec, stem, c3["shift"], n_fresh=3) == pytest.approx(0.8, abs=1e-6)
    assert study.check_flag_rate(rec, stem, c3["range"][1] - c3["mean"], n_fresh=3) == pytest.approx(0.5, abs=0.01)
    assert c3["flag_if_zero"] < 0.05  # "the SDF loss has no effect" is not told from the committed -3%
    stems = study.checked_stems(rec)
    rng = np.random.default_rng(1)

    def flagged(shift: float, reps: int) -> float:
        hits = 0
        for _ in range(reps):
            fresh = {"paired | seeds": 3.0}
            for k in stems:
                v = rng.normal(rec[f"{k} | mean %"] + (shift if k == stem else 0.0), rec[f"{k} | sd %"], 3)
                fresh[f"{k} | mean %"], fresh[f"{k} | sd %"] = round(v.mean(), 2), round(v.std(ddof=1), 2)
            hits += any(line.startswith(stem) for line in _problems(fresh, rec))
        return hits / reps

    assert 0.75 <= flagged(c3["shift"], 800) <= 0.85
    assert flagged(-c3["shift"], 200) >= 0.7  # the range is symmetric: either way
    assert flagged(c3["shift"] / 4, 200) <= 0.05


def test_the_docs_state_what_the_check_can_see_from_the_committed_tables(committed):
    """docs/training_and_evaluation.md holds study.detectable_markdown of the committed tables for
    the default 2 seeds and for 3, and the rates its prose names; a table for 4 seeds is not there."""
    from geodepth_lite import utils

    text = (utils.project_root() / "docs" / "training_and_evaluation.md").read_text()
    rec = study.paired_record(committed)
    assert study.detectable_markdown(rec) in text and study.detectable_markdown(rec, n_fresh=3) in text
    assert study.detectable_markdown(rec, n_fresh=4) not in text
    stem = f"paired | {study.PRIMARY} | rmse | silog case3"
    mean = rec[f"{stem} | mean %"]
    for n, harm, zero, gain in ((2, "64%", "0.3%", "85%"), (3, "94%", "0.8%", "57%")):
        assert f"{100 * study.check_flag_rate(rec, stem, 3 - mean, n_fresh=n):.0f}%" == harm
        assert f"{100 * study.check_flag_rate(rec, stem, -mean, n_fresh=n):.1f}%" == zero
        assert f"{100 * (1 - study.check_flag_rate(rec, stem, -8 - mean, n_fresh=n)):.0f}%" == gain
        assert all(x in text for x in (harm, zero, gain))
