"""The second study's run list, tables and six-test family with its robustness tests, on tables
with known answers."""

import itertools
import math

import numpy as np
import pytest
from scipy import stats

from geodepth_lite.data import manifest as mf
from geodepth_lite.data import synth
from geodepth_lite.evaluation import ablation, study, study2
from geodepth_lite.training import config, run_cache

METRICS = study.METRIC_COLUMNS
SEEDS = range(8)


def _frames_tables(level: dict, scene_effect=None, n_scenes=study2.N_SCENES, per=2, arm=None) -> dict:
    """Tables whose run (term, case, seed) has, in every metric, frames of value
    level[(term, case)][seed] * (1 + scene_effect[scene]) (``per`` frames per scene, indexes
    scene * 20 + j), and a runs row equal to the mean of its frames."""
    scene_effect = np.zeros(n_scenes) if scene_effect is None else np.asarray(scene_effect)
    runs, frames = [], []
    for (term, case), per_seed in level.items():
        for s, v in enumerate(per_seed):
            vals = [v * (1 + scene_effect[k]) for k in range(n_scenes) for _ in range(per)]
            extra = {"arm": study2.arm_of(case)} if arm else {}
            runs.append({**extra, "depth_term": term, "case": case, "seed": s, "set": study.PRIMARY,
                         "frames": len(vals), **{m: float(np.mean(vals)) for m in METRICS}})
            frames += [{**extra, "depth_term": term, "case": case, "seed": s,
                        "index": k * study2.FRAMES_PER_SCENE + j, "organ": "colon", "group": "g",
                        **{m: v * (1 + scene_effect[k]) for m in (*METRICS, "ratio")}}
                       for k in range(n_scenes) for j in range(per)]
    return {"runs": runs, "frames": frames, "baselines": []}


def _pair(changes: dict, base=None):
    """(tables1, tables2): silog Case 1 at ``base`` per seed, and the arms' cases at base * (1 + change)."""
    base = np.array([0.10 * (1 + s / 50) for s in SEEDS]) if base is None else np.asarray(base)
    t1 = _frames_tables({("silog", 1): base})
    t2 = _frames_tables({("silog", c): base * (1 + np.asarray(changes[c])) for c in (2, 3, 4)}, arm=True)
    return t1, t2


def test_the_run_list_is_24_runs_with_each_arms_settings():
    teach = config.profile("teach")
    runs = study2.study_runs(teach)
    assert len(runs) == 24 and len({(c, s) for _, c, s, _ in runs}) == 24
    assert {(a, c) for a, c, _, _ in runs} == {("A", 2), ("A", 4), ("B", 3)}
    assert all(dict(run.overrides) == study2.ARM_B_SETTINGS for a, _, _, run in runs if a == "B")
    assert sorted({s for _, _, s, _ in runs}) == list(range(8))
    cfgs = {(c, s): run.as_dict() for _, c, s, run in runs}
    # arm A: lambda2 = 1 on the gradient + normal terms, lambda3 = 0.01 on the SDF term (Case 4 only)
    assert {tuple(cfgs[(c, 0)]["lambdas"]) for c in (2, 4)} == {(1.0, 1.0, 0.0), (1.0, 1.0, 0.01)}
    assert cfgs[(3, 0)]["lambdas"] == config.make_config("teach", 3, 0)["lambdas"]
    assert all(cfgs[(3, s)][k] == v for s in SEEDS for k, v in study2.ARM_B_SETTINGS.items())
    assert {cfg["depth_term"] for cfg in cfgs.values()} == {"silog"}
    # none of the study's runs is one of the first study's (or the default ablation's)
    first = {run_cache.checkpoint_dir(run) for *_, run in study.study_runs(teach)}
    assert not first & {run_cache.checkpoint_dir(run) for *_, run in runs}


def test_scene_of_is_the_scene_plans():
    m = mf.load_manifest("scenario_study_confirm")
    assert m["frames_per_scene"] == study2.FRAMES_PER_SCENE and m["splits"]["test"] == 20 * study2.N_SCENES
    plan = synth.scene_plan(m, "test")
    assert len(plan) == study2.N_SCENES
    for scene in plan:
        assert {int(study2.scene_of(i)) for i, _ in scene["frames"]} == {scene["scene"]}
    assert study2.scene_of(np.array([0, 19, 20, 479])).tolist() == [0, 0, 1, 23]


def test_sign_flip_p_known_answers_and_brute_force():
    assert study2.sign_flip_p([1.0, 2, 3, 4, 5, 6, 7, 8]) == 2 / 256 == study2.min_sign_flip_p(8)
    assert study2.sign_flip_p([-1.3] * 8) == 2 / 256  # ties: all 256 flips' |mean| computed in floats
    # n = 3 by hand: d = (1, 2, -4), mean -1/3. Flip sums: +-1 +-2 +-4 -> |sum| in {7, 5, 3, 1, 1, 3, 5, 7};
    # |observed sum| = 1, so all 8 are at least as extreme: p = 1. d = (3, 2, 1): sums 6, 4, 2, 0, 0, 2, 4, 6:
    # only +-6 reach 6: p = 2/8.
    assert study2.sign_flip_p([1.0, 2.0, -4.0]) == 1.0
    assert study2.sign_flip_p([3.0, 2.0, 1.0]) == 0.25
    # d = (5, 1, 1, -1): sum 6; flips with |sum| >= 6: (5,1,1,1)->8, (5,1,1,-1)->6, (5,1,-1,1)->6, (5,-1,1,1)->6,
    # and their mirror images: 8 of 16
    assert study2.sign_flip_p([5.0, 1.0, 1.0, -1.0]) == 0.5
    rng = np.random.default_rng(0)
    for n in (3, 4, 6):
        d = rng.normal(0.5, 1.0, n)
        means = [abs(np.mean(np.array(s) * d)) for s in itertools.product((1, -1), repeat=n)]
        want = np.mean([m >= abs(d.mean()) - 1e-12 for m in means])
        assert study2.sign_flip_p(d) == pytest.approx(want, abs=1e-15)
    assert study2.sign_flip_p([0.3, -0.1, 0.2]) != study2.sign_flip_p([0.3, 0.1, 0.2])  # can fail


def test_the_smallest_p_and_holms_first_level():
    s = study2.smallest_p(8, 6)
    assert s["sign-flip"] == 2 / 256 and s["holm first level"] == pytest.approx(0.05 / 6)
    assert s["sign-flip reaches holm first level"] and s["t-test"] == 0.0
    assert not study2.smallest_p(8, 8)["sign-flip reaches holm first level"]  # 0.0078 > 0.05 / 8 = 0.00625
    assert not study2.smallest_p(7, 6)["sign-flip reaches holm first level"]  # 2/128 = 0.0156


CHANGES = {2: [-0.10 + e for e in (0.01, -0.01, 0.005, -0.005, 0.0, 0.002, -0.002, 0.0)],  # -10% +- 1
           4: [0.004, -0.006, 0.002, 0.001, -0.003, 0.005, -0.002, 0.0],                   # about 0
           3: [-0.05, 0.02, -0.30, 0.10, -0.25, 0.05, -0.20, 0.15]}                         # wide


@pytest.fixture(scope="module")
def fam():
    t1, t2 = _pair(CHANGES)
    return study2.family(t1, t2, reps=2000)


def test_the_family_computes_the_plans_six_tests(fam):
    assert [(t["arm"], t["case"], t["metric"]) for t in fam] == [
        ("A", 2, "rmse"), ("A", 2, "abs_rel"), ("A", 4, "rmse"), ("A", 4, "abs_rel"), ("B", 3, "rmse"),
        ("B", 3, "abs_rel")]
    a2 = fam[0]
    r = 100 * np.array(CHANGES[2])
    assert a2["values"] == pytest.approx(r.tolist()) and a2["mean"] == pytest.approx(r.mean())
    assert a2["p"] == pytest.approx(stats.ttest_1samp(r, 0.0).pvalue, rel=1e-9)
    half = stats.t.ppf(1 - 0.05 / 12, 7) * r.std(ddof=1) / math.sqrt(8)  # Bonferroni 1 - 0.05 / 6, two tails
    assert a2["level"] == pytest.approx(1 - 0.05 / 6)
    assert (a2["low"], a2["high"]) == pytest.approx((r.mean() - half, r.mean() + half))
    assert a2["paper"] == -10.0 and a2["rejected"] and a2["verdict"] == "paper's size reproduced"
    assert fam[1]["paper"] == -20.4 and fam[1]["verdict"].startswith("direction reproduced, smaller")
    x = max(-fam[2]["low"], fam[2]["high"])
    assert fam[2]["verdict"] == f"no effect detected; effects beyond {x:.1f}% excluded"
    b3 = fam[4]
    assert b3["too_wide"] and b3["high"] - b3["low"] > 20 and not b3["rejected"] and b3["verdict"] == "undecided"
    assert [t["rejected"] for t in fam] == ablation.holm([t["p"] for t in fam])
    assert [t["sign_flip_rejected"] for t in fam] == ablation.holm([t["sign_flip_p"] for t in fam])
    assert fam[0]["sign_flip_p"] == 2 / 256 and fam[0]["sign_flip_rejected"]
    assert study2.claims(fam)[4] == f"{study.PRIMARY}, RMSE: B3: Case 3 with arm B's SDF samples vs Case 1 -> undecided"


def test_a_deliberately_wrong_value_changes_the_verdict():
    """Arm A's Case 2 at the paper's -10% is reproduced; the same runs scored 5% better than they are
    move the interval off the paper's value, and the verdict says so."""
    t1, t2 = _pair(CHANGES)
    good = study2.family(t1, t2, reps=200)[0]
    wrong = {**t2, "runs": [dict(r) for r in t2["runs"]]}
    for r in wrong["runs"]:
        if r["case"] == 2:
            r["rmse"] *= 0.95
    bad = study2.family(t1, wrong, reps=200)[0]
    assert good["verdict"] == "paper's size reproduced"
    assert bad["verdict"] == "direction reproduced, larger than the paper (paper's value excluded)"


def test_zero_scene_spread_bootstrap_is_the_seed_bootstrap():
    """With every scene alike, a run's mean over drawn scenes is its mean: the bootstrap over seeds
    and scenes is the bootstrap over seeds alone, computed here by hand from the same draws."""
    t1, t2 = _pair(CHANGES)
    fam = study2.family(t1, t2)
    rng = np.random.default_rng(2)
    idx = rng.integers(0, 8, size=(10_000, 8))  # the seeds are drawn first
    lv = 1 - 0.05 / 6
    for t in fam:
        r = np.asarray(t["values"])
        want = np.percentile(r[idx].mean(axis=1), [100 * (1 - lv) / 2, 100 * (1 + lv) / 2])
        assert (t["boot_low"], t["boot_high"]) == pytest.approx(tuple(want), rel=1e-9, abs=1e-9)
    assert 100 * (1 - lv) / 2 == pytest.approx(0.4167, abs=1e-4)


def test_the_bootstrap_sees_the_scenes():
    """Scenes that differ in how much the arm changes them widen the interval beyond the seeds'
    alone; a brute-force replicate loop gives the same percentiles as the vectorised one."""
    n_sc = 6
    base = np.array([0.10 * (1 + s / 50) for s in SEEDS])
    effect = np.linspace(-0.3, 0.3, n_sc)
    t1 = _frames_tables({("silog", 1): base}, n_scenes=n_sc)
    t2 = _frames_tables({("silog", 3): base * 0.95}, scene_effect=effect, n_scenes=n_sc)
    sums2 = study2._frame_sums(t2, ("silog", 3), "rmse", list(SEEDS), n_sc)
    sums1 = study2._frame_sums(t1, ("silog", 1), "rmse", list(SEEDS), n_sc)
    draws = study2.bootstrap_draws(8, n_sc, reps=300, seed=5)
    lo, hi = study2.bootstrap_interval(*sums2, *sums1, draws, 0.9)
    rng = np.random.default_rng(5)
    s_idx, k_idx = rng.integers(0, 8, (300, 8)), rng.integers(0, n_sc, (300, n_sc))
    vals = []
    for si, ki in zip(s_idx, k_idx):
        arm = np.array([np.mean([base[s] * 0.95 * (1 + effect[k]) for k in ki]) for s in range(8)])
        ref = np.array([np.mean([base[s] for _ in ki]) for s in range(8)])
        vals.append(np.mean((100 * (arm / ref - 1))[si]))
    assert (lo, hi) == pytest.approx(tuple(np.percentile(vals, [5, 95])), rel=1e-9)
    assert hi - lo > 5  # the seeds alone give a single value (-5% at every seed): the spread is the scenes'


def test_disagreements_are_named():
    """Arm A's Case 4 with a change rejected by the t-test but 3 seeds of 8 on the other side: the
    sign-flip test keeps 0 and the line names it."""
    changes = dict(CHANGES)
    changes[4] = [-0.03, -0.032, -0.028, -0.031, -0.029, -0.03, -0.03, 0.005]  # t p 0.0006, sign-flip 4/256
    t1, t2 = _pair(changes)
    fam = study2.family(t1, t2, reps=500)
    a4 = fam[2]
    lines = study2.disagreements(fam)
    assert a4["rejected"] and a4["sign_flip_p"] == 4 / 256 and not a4["sign_flip_rejected"]
    assert lines[0] == ("A4: Case 4 at lambda2 = 1 vs Case 1, RMSE: sign-flip test (Holm) keeps 0, "
                        "the t-test rejects 0 (lower)")
    assert a4["disagreements"] == [lines[0].split("RMSE: ")[1]]


def test_tables_round_trip_check_and_a_missing_folder_is_named(tmp_path):
    t1, t2 = _pair(CHANGES)
    runs = [{k: (study._fmt(v) if isinstance(v, float) else v) for k, v in r.items()} for r in t2["runs"]]
    frames = [{k: (study._fmt(v) if isinstance(v, float) else v) for k, v in f.items()} for f in t2["frames"]]
    out = study2.write_tables(tmp_path / "study2", runs, frames, [{"set": study.PRIMARY, "baseline": "constant",
                                                                   **{m: "0.3" for m in METRICS}}])
    back = study2.read_tables(out, frames=True)
    assert back["runs"][0]["arm"] == "A" and list(back["runs"][0])[0] == "arm"
    assert study2.check_tables(back, frames_per_run=48) == []
    moved = {**back, "runs": [dict(r, arm="B") if r["case"] == 2 and r["seed"] == 0 else r for r in back["runs"]]}
    assert study2.check_tables(moved, frames_per_run=48) == ["run ('silog', 2, 0): arm 'B', expected 'A'"]
    short = {**back, "runs": [r for r in back["runs"] if (r["case"], r["seed"]) != (3, 5)]}
    assert study2.check_tables(short, frames_per_run=48) == ["run ('silog', 3, 5) is missing"]
    with pytest.raises(FileNotFoundError, match=r"no folder .*nowhere .*reproduce --study2"):
        study2.read_tables(tmp_path / "nowhere")
    (out / "runs.csv").unlink()
    with pytest.raises(FileNotFoundError, match=r"runs\.csv"):
        study2.read_tables(out)


# ------------------------------------------------------------------ the committed second study
@pytest.fixture(scope="module")
def committed2():
    return study.read_tables(frames=True), study2.read_tables(frames=True)


def test_the_committed_second_study_is_whole_and_its_runs_are_the_means_of_their_frames(committed2):
    _, t2 = committed2
    assert study2.check_tables(t2, frames_per_run=480) == []
    assert len({(r["arm"], r["case"], r["seed"]) for r in t2["runs"]}) == 24
    assert {r["set"] for r in t2["runs"]} == {study.PRIMARY, ablation.HELDOUT, study.CLOSEUPS}
    dropped = {**t2, "runs": [r for r in t2["runs"] if (r["case"], r["seed"]) != (3, 5)]}
    assert study2.check_tables(dropped, frames_per_run=480), "a dropped run is caught"


def test_the_notebook_states_the_second_studys_verdicts_and_table(committed2):
    """Notebook 05's committed verdict lines and six-test table are those of the committed tables,
    word for word and number for number; a flipped verdict is caught."""
    import nbformat

    from geodepth_lite import utils

    nb = nbformat.read(str(utils.project_root() / "notebooks" / "05_ablation.ipynb"), as_version=4)
    cell = next(c for c in nb.cells
                if c.cell_type == "code" and c.source.lstrip().startswith("# second study: verdicts"))
    shown = "".join(o.get("text", "") for o in cell.outputs if o.get("name") == "stdout").splitlines()
    fam = study2.family(*committed2)
    lines = study2.claims(fam)
    assert shown[:len(lines)] == lines
    assert shown[len(lines) + 2:] == (study2.disagreements(fam) or [
        "nowhere: the sign-flip test and the bootstrap agree with the t-test on all six"])
    flipped = [line.replace("direction reproduced", "no effect detected", 1) for line in lines]
    assert flipped != shown[:len(lines)], "a changed verdict would be caught"
    table = next(c for c in nb.cells if c.cell_type == "code" and "family2 = study2.family" in c.source)
    text = "".join(o.get("text", "") for o in table.outputs if o.get("name") == "stdout")
    for t in fam:
        assert f"[{t['low']:+.1f}, {t['high']:+.1f}]" in text and f"{t['sign_flip_p']:.4f}" in text
        assert f"[{t['boot_low']:+.1f}, {t['boot_high']:+.1f}]" in text
