"""The exploratory arms of docs/exploratory_plan.md: the matching rule and its measurement, the run
list, the comparisons on tables with known answers, and the committed record and tables."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import stats

from geodepth_lite.core import losses
from geodepth_lite.core.model import DepthNet
from geodepth_lite.data.datasets import load_split, resolve_dataset
from geodepth_lite.evaluation import exploratory, study, study2
from geodepth_lite.evaluation import tables as tbl
from geodepth_lite.training import checkpoint, config, inference, run_cache

SEEDS = range(8)


@pytest.mark.parametrize("ratio, want", [(1.7707206351397355, 0.018), (3.0, 0.03), (1.0, 0.01), (0.3333, 0.0033),
                                         (1.234, 0.012), (1.25, 0.013)])
def test_the_matching_rule_rounds_to_two_significant_digits(ratio, want):
    assert exploratory.matched_lambda3(ratio) == want


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_the_matching_rule_refuses_a_ratio_that_is_no_ratio(bad):
    with pytest.raises(ValueError, match="positive number"):
        exploratory.matched_lambda3(bad)


def _brute_terms(cfg: dict, model, ds) -> dict:
    """The two SDF terms written out: batches of the profile's size, each batch's term (no cache)
    weighted by its frames."""
    out = {}
    g = cfg["sdf_grid"]
    for sampling in ("bbox", "frustum"):
        total, n = 0.0, 0
        for i in range(0, len(ds), cfg["batch_size"]):
            b = inference.collate([ds[j] for j in range(i, min(i + cfg["batch_size"], len(ds)))])
            with torch.no_grad():
                pred = model(b["image"]).float()
            options = losses.SDFOptions(grid=(g, g, g), cache=None, sampling=sampling)
            term = losses.sdf_loss(pred, b["depth"], b["K"], options, mask=b.get("valid"))
            total, n = total + float(term) * len(pred), n + len(pred)
        out[sampling] = total / n
    return out


def test_the_measurement_is_the_two_terms_on_the_runs_predictions():
    """measure_ratio on a finished smoke Case 1 run (an untrained network saved as one) equals the two
    terms computed batch by batch without the validation code, and the two differ, so swapping the
    samplings or measuring one twice would be seen."""
    smoke = config.profile("smoke")
    cfg = smoke.run(1, 0).as_dict()
    folder = run_cache.checkpoint_dir(smoke.run(1, 0))
    folder.mkdir(parents=True)
    torch.manual_seed(0)
    net = DepthNet(input_pad=int(cfg.get("input_pad", 0)), depth_range=cfg.get("head_range"))
    checkpoint.save_checkpoint(folder / checkpoint.CHECKPOINT_NAME,
                               {"model": net.state_dict(), "cfg": cfg, "complete": True, "epoch": cfg["epochs"]})
    m = exploratory.measure_ratio(smoke)
    model, _ = checkpoint.load_model(folder / checkpoint.CHECKPOINT_NAME)
    ds = load_split(resolve_dataset(cfg), "val", cfg["image_size"], limit=cfg["val_frames"])
    want = _brute_terms(cfg, model, ds)
    assert m["frames"] == len(ds) > 0
    assert m["bbox"] == pytest.approx(want["bbox"], rel=1e-5)
    assert m["frustum"] == pytest.approx(want["frustum"], rel=1e-5)
    assert abs(want["bbox"] / want["frustum"] - 1) > 0.05
    assert m["ratio"] == pytest.approx(want["bbox"] / want["frustum"], rel=1e-5)


def test_the_measurement_needs_the_finished_run():
    with pytest.raises(FileNotFoundError, match="no finished Case 1 run"):
        exploratory.measure_ratio(config.profile("smoke"))


def _record(folder, **rec):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / exploratory.MATCH_JSON).write_text(json.dumps(rec))
    return folder


def test_a_matching_record_is_read_bounded_and_must_follow_the_rule(tmp_path):
    good = _record(tmp_path / "a", ratio=1.7707, lambda3=0.018)
    assert exploratory.read_match(good)["lambda3"] == 0.018
    wrong = _record(tmp_path / "b", ratio=1.7707, lambda3=0.01)  # the box grid's weight, not the matched one
    with pytest.raises(ValueError, match="not a matching record"):
        exploratory.read_match(wrong)
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / exploratory.MATCH_JSON).write_text("[" * 100_000)
    with pytest.raises(ValueError, match="larger than|not a matching record"):
        exploratory.read_match(tmp_path / "c")
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / exploratory.MATCH_JSON).write_text("[" * 5000 + "]" * 5000)
    with pytest.raises(ValueError, match="not a matching record"):
        exploratory.read_match(tmp_path / "d")


def test_the_run_list_is_the_plans_sixteen_runs():
    teach = config.profile("teach")
    runs = exploratory.arm_runs(0.018, teach)
    assert len(runs) == 16 and sorted({s for _, _, s, _ in runs}) == list(SEEDS)
    cfgs = {(a, s): run.as_dict() for a, c, s, run in runs}
    e1, e2 = cfgs[("E1", 0)], cfgs[("E2", 0)]
    assert (e1["depth_term"], e1["lambdas"], e1["sdf_sampling"], e1["sdf_grid"]) == ("silog", [1.0, 0.0, 0.018],
                                                                                       "frustum", 8)
    assert (e2["depth_term"], e2["lambdas"], e2["sdf_sampling"]) == ("l1", [1.0, 1.0, 0.01], "bbox")
    # arm B is E1 at lambda3 = 0.01: only the weight differs
    b3 = config.make_config("teach", 3, 0, **study2.arm_settings("B", 3))
    assert {k for k in e1 if e1[k] != b3[k]} == {"lambdas"}
    # no run is one of either study's
    earlier = {run_cache.checkpoint_dir(run) for *_, run in study.study_runs(teach)}
    earlier |= {run_cache.checkpoint_dir(run) for *_, run in study2.study_runs(teach)}
    assert not earlier & {run_cache.checkpoint_dir(run) for *_, run in runs}


def _tables(levels: dict) -> dict:
    rows = [{"depth_term": t, "case": c, "seed": s, "set": study.PRIMARY, "frames": 480,
             **{m: float(v) for m in study.METRIC_COLUMNS}}
            for (t, c), per_seed in levels.items() for s, v in enumerate(per_seed)]
    return {"runs": rows, "baselines": []}


def test_the_comparisons_have_known_answers():
    rng = np.random.default_rng(0)
    base = 0.10 * (1 + np.arange(8) / 50)
    change = {"E1": -0.13 + 0.004 * rng.standard_normal(8), "E2": np.array([3, -3, 2, -2, 1, -1, 0.5, -0.5]) / 1000}
    first = _tables({("silog", 1): base, ("l1", 1): 2 * base})
    arms = _tables({("silog", 3): base * (1 + change["E1"]), ("l1", 4): 2 * base * (1 + change["E2"])})
    comps = exploratory.arm_comparisons(first, arms)
    assert [(t["arm"], t["metric"]) for t in comps] == [("E1", "rmse"), ("E1", "abs_rel"),
                                                        ("E2", "rmse"), ("E2", "abs_rel")]
    for t in comps:
        r = 100 * change[t["arm"]]
        lo, hi = stats.t.interval(0.95, 7, loc=r.mean(), scale=stats.sem(r))
        assert t["values"] == pytest.approx(r.tolist(), abs=1e-9)
        assert (t["mean"], t["low"], t["high"]) == pytest.approx((r.mean(), lo, hi), abs=1e-9)
        assert t["p"] == pytest.approx(stats.ttest_1samp(r, 0).pvalue, rel=1e-9)
    e1 = comps[0]
    assert e1["verdict"] == "paper's size reproduced" and e1["paper"] == -13
    assert comps[2]["verdict"].startswith("no effect detected")
    # paired with the other depth term's Case 1 (a planted wrong pairing) the numbers change
    swapped = _tables({("silog", 1): 2 * base, ("l1", 1): base})
    assert exploratory.arm_comparisons(swapped, arms)[0]["mean"] != pytest.approx(e1["mean"], abs=1)
    assert all(line.startswith("exploratory, ") for line in exploratory.lines(comps))


# ----------------------------------------------------------------------- the committed record
@pytest.fixture(scope="module")
def committed():
    folder = exploratory.committed_dir()
    if not (folder / "runs.csv").exists():
        pytest.skip("the exploratory arms' tables are not committed yet")
    return {"match": exploratory.read_match(), "arms": exploratory.read_arms(),
            "provenance": tbl.read_csv(folder / study.PROVENANCE_CSV, "")}


def test_the_committed_runs_are_the_plans_runs(committed):
    lam = committed["match"]["lambda3"]
    assert lam == 0.018
    want = {(exploratory.ARM_CELLS[a][0], c, s): run.hash
            for a, c, s, run in exploratory.arm_runs(lam, config.profile("teach"))}
    got = {(r["depth_term"], int(r["case"]), int(r["seed"])): r["config_hash"] for r in committed["provenance"]}
    assert got == want
    runs = committed["arms"]["runs"]
    assert {(r["arm"], r["seed"]) for r in runs if r["set"] == study.PRIMARY} == {(a, s) for a in ("E1", "E2")
                                                                                  for s in SEEDS}
    assert all(r["frames"] == 480 for r in runs if r["set"] == study.PRIMARY)


def test_the_docs_table_is_the_committed_comparisons(committed):
    """docs/training_and_evaluation.md's table of the arms is computed from the committed tables; the
    row of a comparison whose interval end is 0.1 points off is not in it."""
    text = (Path(__file__).resolve().parent.parent / "docs" / "training_and_evaluation.md").read_text()
    comps = exploratory.arm_comparisons(study.read_tables(), committed["arms"])
    rows = exploratory.markdown_rows(comps)
    assert len(rows) == 4 and all(r in text for r in rows), [r for r in rows if r not in text]
    off = exploratory.markdown_rows([{**comps[0], "high": comps[0]["high"] + 0.1}])[0]
    assert off not in text
