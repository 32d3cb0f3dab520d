"""The second confirmatory study of docs/study_plan_2.md: the paper's losses switched on.

Arm A trains Cases 2 and 4 at the paper's implied weight lambda2 = 1 (lambda3 = 0.01 as in the
first study); arm B trains Case 3 with the SDF samples chosen on the validation split
(:data:`ARM_B_SETTINGS`). Seeds 0-7, the ``teach`` recipe: 24 runs. The reference is the first
study's committed silog Case 1 (``notebooks/study/``), paired by seed; it is not trained again.

The tables have the first study's columns plus ``arm`` (``runs.csv``, ``frames.csv.gz``,
``baselines.csv``); the committed copies are in ``notebooks/study2/``. :func:`family` is the
plan's analysis: six paired t-tests (A2, A4, B3 x RMSE, Abs Rel), Holm's rule, Bonferroni t
intervals and the verdict rule with its "too wide" bound, and beside them the robustness tests
that never decide a verdict: the exact sign-flip permutation test (Holm over the six) and the
bootstrap over seeds and scenes.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from geodepth_lite import utils
from geodepth_lite.evaluation import ablation, study
from geodepth_lite.evaluation import tables as tbl
from geodepth_lite.evaluation.ablation import ALPHA, WIDTH_BOUND  # "too wide": hi - lo > 20 points
from geodepth_lite.evaluation.study import PRIMARY, SEEDS
from geodepth_lite.training import config, run_cache
from geodepth_lite.training.config import Profile, RunConfig

ARM_B_SETTINGS: dict = {"sdf_sampling": "frustum"}  # arm B's SDF samples (docs/teach_recipe.md's rule)
ARM_A_WEIGHTS = (1.0, 0.01)  # arm A's (lambda2, lambda3): the paper's implied lambda2 = 1, lambda3 as before
ARMS = {"A": (2, 4), "B": (3,)}  # arm: its cases
TESTS = (("A", 2), ("A", 4), ("B", 3))  # family()'s comparisons, in order, each for RMSE then Abs Rel
REFERENCE = ("silog", 1)                # the first study's cell every comparison is paired with
FRAMES_PER_SCENE = 20                   # scenario_study_confirm's frames_per_scene
N_SCENES = 24                           # its 480 test frames / 20
BOOT_REPS = 10_000
BOOT_SEED = 2
MAX_SIGN_FLIP_SEEDS = 20                # the exact test enumerates 2^n assignments


def committed_dir() -> Path:
    """``notebooks/study2/``: the committed tables of the second study."""
    return utils.checkout_path("notebooks", "study2")


def arm_settings(arm: str, case: int) -> dict:
    """The settings of arm ``arm``'s ``case`` beyond the profile's: arm A the case's lambdas with
    (lambda2, lambda3) = :data:`ARM_A_WEIGHTS` (``config.case_lambdas``: Case 2 [1, 1, 0], Case 4
    [1, 1, 0.01]), arm B :data:`ARM_B_SETTINGS`."""
    if arm == "A":
        return {"lambdas": config.case_lambdas(case, ARM_A_WEIGHTS)}
    return dict(ARM_B_SETTINGS)


def study_runs(prof: Profile, seeds=SEEDS) -> list[tuple[str, int, int, RunConfig]]:
    """Every run of the study as (arm, case, seed, its configuration for ``run_cache.ensure_runs``)
    (:func:`arm_settings`): arm A's Cases 2 and 4, then arm B's Case 3, each at ``seeds``."""
    return [(arm, case, int(s), prof.run(case, int(s), **arm_settings(arm, case))) for arm, cases in ARMS.items()
            for case in cases for s in seeds]


def arm_of(case: int) -> str:
    """The arm that trains ``case`` (each case belongs to one arm)."""
    return next(arm for arm, cases in ARMS.items() if case in cases)


def train(prof: Profile, seeds=SEEDS, *, workers: int | None = None,
          progress: bool = False) -> dict[tuple[str, int, int], Path]:
    """Train (or reuse, or continue) every run of the study; {(arm, case, seed): checkpoint}. Each
    run trained here is scored by the process that trained it (``study.score_run``)."""
    runs = study_runs(prof, seeds)
    study.evaluation_sets(prof, progress=progress)  # built before the workers, which score on them
    paths = run_cache.ensure_runs([run for *_, run in runs], workers=workers, progress=progress,
                                  after=functools.partial(study.score_run, prof))
    return {(a, c, s): p for (a, c, s, _), p in zip(runs, paths)}


def score(checkpoints: dict[tuple[str, int, int], Path], sets: dict[str, Any], *,
          progress: bool = False) -> tuple[list[dict], list[dict]]:
    """Score every run on every set (``study.score``): (run rows, frame rows of the primary set), in
    the first study's columns (``depth_term`` is silog) with ``arm`` first."""
    keyed = {("silog", c, s): p for (_, c, s), p in checkpoints.items()}
    runs, frames = study.score(keyed, sets, progress=progress)
    return ([{"arm": arm_of(r["case"]), **r} for r in runs], [{"arm": arm_of(f["case"]), **f} for f in frames])


def write_tables(out: str | Path, runs: list[dict], frames: list[dict], baselines: list[dict],
                 sessions: list[dict] | None = None) -> Path:
    """Write runs.csv, frames.csv.gz, baselines.csv and provenance.csv into ``out`` (``study.write_tables``)."""
    return study.write_tables(out, runs, frames, baselines, sessions)


def read_tables(folder: str | Path | None = None, frames: bool = False) -> dict:
    """The second study's tables from ``folder`` (default: the committed ``notebooks/study2/``),
    numbers as numbers: {"runs", "baselines", "frames" (only with ``frames``)}. A missing folder or
    table is a FileNotFoundError naming it."""
    folder = Path(folder) if folder else committed_dir()
    if not folder.is_dir():
        raise FileNotFoundError(f"the second study's tables not found: no folder {folder} "
                                "(`python -m geodepth_lite reproduce --study2` writes them)")
    hint = " (`python -m geodepth_lite reproduce --study2` writes it)"
    out = {"runs": [study.typed_row(r) for r in tbl.read_csv(folder / "runs.csv", hint)],
           "baselines": [study.typed_row(r) for r in tbl.read_csv(folder / "baselines.csv", hint)]}
    if frames:
        out["frames"] = [study.typed_row(r) for r in tbl.read_csv(folder / "frames.csv.gz", hint)]
    return out


def check_tables(tables: dict, frames_per_run: int | None = None) -> list[str]:
    """What is wrong with the second study's tables (``study.check_tables`` with this study's runs),
    plus any row whose ``arm`` is not its case's; one line each, none when whole."""
    want = {("silog", c, int(s)) for cases in ARMS.values() for c in cases for s in SEEDS}
    problems = study.check_tables(tables, frames_per_run, want=want)
    cases = {c for cs in ARMS.values() for c in cs}
    bad = sorted({(r["case"], r["seed"], str(r.get("arm"))) for r in (*tables["runs"], *tables.get("frames", ()))
                  if r["case"] in cases and r.get("arm") != arm_of(r["case"])})
    problems += [f"run ('silog', {c}, {s}): arm {a!r}, expected {arm_of(c)!r}" for c, s, a in bad]
    return problems


def scene_of(index) -> np.ndarray:
    """The scene of confirmation frame ``index`` (int or array): ``index // 20``.

    Why: ``synth.scene_plan`` gives scene k the frames ``range(k * frames_per_scene, (k + 1) *
    frames_per_scene)`` of the split, each frame's ``index`` in ``frames.jsonl`` is that number
    (``synth.frame_record``), and the evaluation keeps it (``SyntheticDepthDataset`` returns the
    record's ``index``, ``study.score`` writes it). ``scenario_study_confirm`` has
    ``frames_per_scene`` = 20 and 480 test frames: scenes 0-23. ``tests/test_study2.py`` checks
    this against the manifest and the scene plan."""
    return np.asarray(index) // FRAMES_PER_SCENE


# ----------------------------------------------------------------------------- the robustness tests


def min_sign_flip_p(n: int) -> float:
    """The smallest two-sided p the exact sign-flip test can reach with ``n`` paired values:
    2 / 2^n (only the observed signs and their mirror image are as extreme, when all agree)."""
    return 2.0 / 2 ** int(n)


def smallest_p(n: int = len(SEEDS), m: int = 2 * len(TESTS), alpha: float = ALPHA) -> dict:
    """The smallest p each test can reach with ``n`` seeds, against Holm's levels for ``m`` tests:
    {"t-test": 0.0 (no floor), "sign-flip": 2 / 2^n, "holm first level": alpha / m,
    "holm last level": alpha, "sign-flip reaches holm first level": bool, "bootstrap": None
    (an interval, not a p)}."""
    first = alpha / m
    return {"t-test": 0.0, "sign-flip": min_sign_flip_p(n), "holm first level": first, "holm last level": alpha,
            "sign-flip reaches holm first level": min_sign_flip_p(n) <= first, "bootstrap": None}


def sign_flip_p(values) -> float:
    """The exact two-sided sign-flip permutation p of the mean of ``values`` (paired differences):
    the share of all 2^n sign assignments whose mean is at least as far from 0 as the observed
    one (equality within a relative 1e-9, so float rounding does not drop the observed one)."""
    d = np.asarray(values, dtype=np.float64)
    n = d.size
    if n == 0:
        return 1.0
    if n > MAX_SIGN_FLIP_SEEDS:
        raise ValueError(f"the exact sign-flip test enumerates 2^n assignments; n = {n} > {MAX_SIGN_FLIP_SEEDS}")
    bits = (np.arange(2 ** n)[:, None] >> np.arange(n)[None, :]) & 1  # (2^n, n)
    means = np.abs(((1 - 2 * bits) * d).mean(axis=1))
    obs = abs(d.mean())
    tol = 1e-9 * max(float(np.abs(d).mean()), 1e-300)
    return float(np.mean(means >= obs - tol))


def _scene_sums(rows: list[dict], metric: str, n_scenes: int) -> tuple[np.ndarray, np.ndarray]:
    """(sum of ``metric`` over a run's frames in each scene, number of them), each (n_scenes,)."""
    idx = scene_of(np.array([f["index"] for f in rows], dtype=np.int64))
    if rows and (idx.min() < 0 or idx.max() >= n_scenes):
        raise ValueError(f"frame index {int(max(f['index'] for f in rows))} outside the {n_scenes} scenes")
    vals = np.array([f[metric] for f in rows], dtype=np.float64)
    return (np.bincount(idx, weights=vals, minlength=n_scenes), np.bincount(idx, minlength=n_scenes).astype(float))


def bootstrap_draws(n_seeds: int, n_scenes: int = N_SCENES, reps: int = BOOT_REPS,
                    seed: int = BOOT_SEED) -> tuple[np.ndarray, np.ndarray]:
    """The bootstrap's replicates: (seed counts (reps, n_seeds), scene counts (reps, n_scenes)),
    how often each seed and scene is drawn in each replicate. ``numpy.random.default_rng(seed)``
    draws all replicates' seed positions first (``integers(0, n_seeds, (reps, n_seeds))``), then
    all their scenes (``integers(0, n_scenes, (reps, n_scenes))``); every test of :func:`family`
    uses the same replicates."""
    rng = np.random.default_rng(seed)
    s_idx = rng.integers(0, n_seeds, size=(reps, n_seeds))
    k_idx = rng.integers(0, n_scenes, size=(reps, n_scenes))
    return _counts(s_idx, n_seeds), _counts(k_idx, n_scenes)


def _counts(idx: np.ndarray, n: int) -> np.ndarray:
    rows = np.repeat(np.arange(idx.shape[0]), idx.shape[1])
    out = np.zeros((idx.shape[0], n))
    np.add.at(out, (rows, idx.ravel()), 1.0)
    return out


def bootstrap_interval(arm_sums, arm_counts, ref_sums, ref_counts, draws, level: float) -> tuple[float, float]:
    """The bootstrap interval of the mean relative change over seeds and scenes.

    ``*_sums`` / ``*_counts``: (n_seeds, n_scenes) per-scene sums of the metric and frame counts of
    each seed's run (the arm's and the reference's); ``draws``: :func:`bootstrap_draws`. In each
    replicate a run's mean is that of its frames in the drawn scenes (scene k counted as often as it
    is drawn), a seed's change 100 (arm / reference - 1), the replicate's value the mean over the
    drawn seeds. Returns the (1 - level) / 2 and (1 + level) / 2 percentiles."""
    seed_w, scene_w = draws
    m_arm = (scene_w @ np.asarray(arm_sums).T) / (scene_w @ np.asarray(arm_counts).T)  # (reps, n_seeds)
    m_ref = (scene_w @ np.asarray(ref_sums).T) / (scene_w @ np.asarray(ref_counts).T)
    r = 100 * (m_arm / m_ref - 1)
    values = (seed_w * r).sum(axis=1) / seed_w.sum(axis=1)
    lo, hi = np.percentile(values, [100 * (1 - level) / 2, 100 * (1 + level) / 2])
    return float(lo), float(hi)


# ----------------------------------------------------------------------------- the family


def label(t: dict) -> str:
    """A test of :func:`family` in words: "A2: Case 2 at lambda2 = 1 vs Case 1"."""
    what = {"A": "at lambda2 = 1", "B": "with arm B's SDF samples"}[t["arm"]]
    return f"{t['arm']}{t['case']}: Case {t['case']} {what} vs Case 1"


def run_values(tables: dict, cell, metric: str, set_name: str) -> dict[int, float]:
    """{seed: the metric} of the runs of ``cell`` = (depth term, case) on ``set_name`` in a study's tables."""
    term, case = cell
    return {r["seed"]: r[metric] for r in tables["runs"]
            if (r["depth_term"], r["case"], r["set"]) == (term, case, set_name)}


def _decision(rejected: bool, mean: float) -> int:
    return (1 if mean > 0 else -1) if rejected else 0


def _words(d: int) -> str:
    return {0: "keeps 0", -1: "rejects 0 (lower)", 1: "rejects 0 (higher)"}[d]


def family(tables1: dict, tables2: dict, set_name: str = PRIMARY, seeds=None, alpha: float = ALPHA,
           max_width: float | None = WIDTH_BOUND, reps: int = BOOT_REPS, boot_seed: int = BOOT_SEED) -> list[dict]:
    """The plan's six tests, in order A2, A4, B3, each for RMSE then Abs Rel: each arm's run against
    the first study's silog Case 1 (``tables1``, :func:`study.read_tables`) at the same seed.

    r_s = 100 (m_arm(s) / m_case1(s) - 1) per seed, from the runs' mean metric on ``set_name``.
    One dict per test: "arm", "case", "metric", "label", "seeds", "values" (the r_s), "mean", "sd",
    "p" (paired t-test), "level" (1 - alpha / 6), "low"/"high" (the Bonferroni t interval),
    "rejected" (Holm over the six p), "paper", "too_wide" (high - low > ``max_width``), "verdict"
    (``ablation.size_verdict``); beside them, never deciding: "sign_flip_p" (exact, all 2^n sign
    assignments), "sign_flip_rejected" (Holm over the six), "boot_low"/"boot_high" (the bootstrap
    over seeds and scenes at the same level; None unless both tables were read with
    ``frames=True`` and ``set_name`` is the confirmation set), "boot_excludes_0", and
    "disagreements" (a line for each robustness test whose decision on 0 differs from the
    primary's; empty when they agree).
    """
    out = []
    for arm, case in TESTS:
        for metric in ablation.PAIRED_METRICS[::-1]:
            ref = run_values(tables1, REFERENCE, metric, set_name)
            mine = run_values(tables2, ("silog", case), metric, set_name)
            use = sorted(set(ref) & set(mine) if seeds is None else set(seeds))
            missing = [s for s in use if s not in ref or s not in mine]
            if missing or not use:
                raise KeyError(f"{arm}{case} {metric} on the {set_name}: no pair of runs for seed(s) "
                               f"{missing or 'any'}")
            v = 100 * (np.array([mine[s] for s in use]) / np.array([ref[s] for s in use]) - 1)
            out.append({"arm": arm, "case": case, "metric": metric, "seeds": use, "values": v.tolist(),
                        "mean": float(v.mean()), "sd": float(v.std(ddof=1)) if v.size > 1 else math.nan,
                        "p": study.paired_t_p(v), "sign_flip_p": sign_flip_p(v)})
    level = 1 - alpha / len(out)
    boot = set_name == PRIMARY and "frames" in tables1 and "frames" in tables2
    draws = bootstrap_draws(len(out[0]["seeds"]), N_SCENES, reps, boot_seed) if boot else None
    holm_t = ablation.holm([t["p"] for t in out], alpha)
    holm_sf = ablation.holm([t["sign_flip_p"] for t in out], alpha)
    for t, rejected, sf_rejected in zip(out, holm_t, holm_sf):
        _, t["low"], t["high"] = ablation.t_interval(t["values"], level)
        t["label"], t["level"], t["rejected"] = label(t), level, rejected
        t["paper"] = ablation.PAPER_REDUCTION[t["case"]][t["metric"]]
        t["too_wide"] = ablation.too_wide(t["low"], t["high"], max_width)
        t["verdict"] = ablation.size_verdict(t["low"], t["high"], t["mean"], t["paper"], rejected, max_width)
        t["sign_flip_rejected"] = sf_rejected
        t["boot_low"] = t["boot_high"] = t["boot_excludes_0"] = None
        if boot:
            sums = [_frame_sums(tb, cell, t["metric"], t["seeds"])
                    for tb, cell in ((tables2, ("silog", t["case"])), (tables1, REFERENCE))]
            t["boot_low"], t["boot_high"] = bootstrap_interval(*sums[0], *sums[1], draws, level)
            t["boot_excludes_0"] = not t["boot_low"] <= 0 <= t["boot_high"]
        primary = _decision(rejected, t["mean"])
        t["disagreements"] = []
        if _decision(sf_rejected, t["mean"]) != primary:
            t["disagreements"].append(f"sign-flip test (Holm) {_words(_decision(sf_rejected, t['mean']))}, "
                                      f"the t-test {_words(primary)}")
        if boot:
            b = 0 if not t["boot_excludes_0"] else (1 if t["boot_low"] > 0 else -1)
            if b != primary:
                t["disagreements"].append(f"bootstrap interval [{t['boot_low']:+.1f}, {t['boot_high']:+.1f}] "
                                          f"{_words(b)}, the t-test {_words(primary)}")
    return out


def _frame_sums(tables: dict, cell, metric: str, seeds, n_scenes: int = N_SCENES) -> tuple[np.ndarray, np.ndarray]:
    """(per-scene sums, per-scene counts), each (len(seeds), n_scenes), of ``cell``'s runs' frames."""
    term, case = cell
    by_seed: dict = {}
    for f in tables["frames"]:
        if (f["depth_term"], f["case"]) == (term, case):
            by_seed.setdefault(f["seed"], []).append(f)
    pairs = [_scene_sums(by_seed.get(s, []), metric, n_scenes) for s in seeds]
    counts = np.array([c for _, c in pairs])
    if (counts.sum(axis=1) == 0).any():
        raise KeyError(f"{term} Case {case}: no frame rows for some of the seeds {list(seeds)}")
    return np.array([s for s, _ in pairs]), counts


def disagreements(fam: list[dict]) -> list[str]:
    """One line per test of :func:`family` where a robustness test's decision on 0 differs from the
    primary (t-test, Holm) one; [] when all agree."""
    return [f"{t['label']}, {tbl.METRIC_LABELS[t['metric']]}: {line}" for t in fam for line in t["disagreements"]]


def claims(fam: list[dict]) -> list[str]:
    """The verdict of each test of :func:`family` as a sentence."""
    return [f"{PRIMARY}, {tbl.METRIC_LABELS[t['metric']]}: {t['label']} -> {t['verdict']}" for t in fam]


def exploratory_vs_first(tables1: dict, tables2: dict, case: int = 4, metric: str = "rmse",
                         set_name: str = PRIMARY, level: float = 0.95) -> dict:
    """An exploratory comparison the plan did not register: arm A's ``case`` against the first study's
    silog ``case``, paired by seed. d_s = r_s(second study) - r_s(first study), each r_s in percent of the
    first study's silog Case 1 at seed s (points). Returns "values", "mean", "p" (paired t-test),
    "low"/"high" (the Student-t interval at ``level``, no multiplicity correction) and "seeds"."""
    ref = run_values(tables1, REFERENCE, metric, set_name)
    first = run_values(tables1, ("silog", case), metric, set_name)
    second = run_values(tables2, ("silog", case), metric, set_name)
    seeds = sorted(set(ref) & set(first) & set(second))
    if not seeds:
        raise KeyError(f"Case {case} {metric} on the {set_name}: no seed with runs in both studies")
    r1 = np.array([first[s] / ref[s] - 1 for s in seeds]) * 100
    r2 = np.array([second[s] / ref[s] - 1 for s in seeds]) * 100
    d = r2 - r1
    mean, low, high = ablation.t_interval(d, level)
    return {"seeds": seeds, "values": d.tolist(), "mean": mean, "p": study.paired_t_p(d), "low": low, "high": high,
            "level": level}


CONTROL_JSON = "concurrent_control.json"  # the concurrent control's record (benchmarks/concurrent_control.py)
MAX_CONTROL_BYTES = 2**20


def read_control(folder: str | Path | None = None) -> dict:
    """The concurrent control's record beside the second study's tables (default: the committed
    ``notebooks/study2/``): read only up to :data:`MAX_CONTROL_BYTES`, plain JSON with its rows and
    the six comparisons, else a ValueError naming the file."""
    path = (Path(folder) if folder else committed_dir()) / CONTROL_JSON
    if path.stat().st_size > MAX_CONTROL_BYTES:
        raise ValueError(f"{path}: larger than {MAX_CONTROL_BYTES} bytes, not a concurrent-control record")
    try:
        rec = json.loads(path.read_bytes())
        ok = (isinstance(rec, dict) and isinstance(rec.get("rows"), list) and isinstance(rec.get("seeds"), list)
              and all(isinstance(rec.get("six_comparisons", {}).get(k), list) for k in ("committed", "fresh_case1")))
    except (ValueError, RecursionError):
        ok = False
    if not ok:
        raise ValueError(f"{path}: not a concurrent-control record (JSON with rows, seeds and six_comparisons)")
    return rec


def control_lines(rec: dict) -> list[str]:
    """The record in words: per seed, the fresh run against the committed one on each set (percent,
    Abs Rel and RMSE); then each of the six comparisons with the committed Case 1 and with the fresh."""
    by = {(r["seed"], r["set"]): r for r in rec["rows"]}
    sets = list(dict.fromkeys(r["set"] for r in rec["rows"]))
    out = []
    for seed in rec["seeds"]:
        parts = [f"{s}: " + ("identical" if by[(seed, s)]["identical"] else
                             ", ".join(f"{m} {by[(seed, s)]['rel_diff_pct'][m]:+.2f}%" for m in ("abs_rel", "rmse")))
                 for s in sets]
        out.append(f"seed {seed}: " + "; ".join(parts))
    metrics = [m for _ in TESTS for m in ablation.PAIRED_METRICS[::-1]]  # family()'s order: RMSE, then Abs Rel
    for a, b, metric in zip(rec["six_comparisons"]["committed"], rec["six_comparisons"]["fresh_case1"], metrics):
        out.append(f"{a['label']}, {metric}: {a['mean']:+.2f} [{a['low']:+.2f}, {a['high']:+.2f}] -> with the "
                   f"fresh Case 1 {b['mean']:+.2f} [{b['low']:+.2f}, {b['high']:+.2f}]; {b['verdict']}")
    return out
