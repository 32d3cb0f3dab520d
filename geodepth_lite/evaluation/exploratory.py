"""The exploratory arms of docs/exploratory_plan.md, beside (not inside) the second study.

E1 trains Case 3 with the frustum SDF samples at a weight matched to the first study's 8^3 box grid
(:func:`matched_lambda3`, from :func:`measure_ratio`); E2 trains Case 4 with the paper's L1 depth term at
arm A's weights (lambda2, lambda3) = (1, 0.01). Seeds 0-7 each, the ``teach`` recipe: 16 runs. Each arm
is paired by seed with the first study's committed Case 1 of its own depth term.

:func:`arm_comparisons` reports each of the four (arm x RMSE, Abs Rel) on its own: mean paired relative
change, paired t-test p and 95% Student-t interval, with no multiplicity correction, and the second
study's verdict words applied to that interval, marked exploratory. The committed tables are in
``notebooks/study2/exploratory/``.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np
import torch

from geodepth_lite.data.datasets import load_split, resolve_dataset
from geodepth_lite.evaluation import ablation, study, study2
from geodepth_lite.evaluation import tables as tbl
from geodepth_lite.evaluation.ablation import WIDTH_BOUND
from geodepth_lite.evaluation.study import PRIMARY, SEEDS
from geodepth_lite.training import checkpoint, config, run_cache, train
from geodepth_lite.training.config import Profile, RunConfig

BOX_LAMBDA3 = 0.01          # the first study's and arm B's lambda3
E2_WEIGHTS = (1.0, 0.01)    # E2's (lambda2, lambda3): arm A's
ARM_CELLS = {"E1": ("silog", 3), "E2": ("l1", 4)}  # arm: (depth term, case)
LEVEL = 0.95                # each comparison's own interval: no multiplicity correction
FOLDER = "exploratory"      # beside the second study's tables
MATCH_JSON = "match.json"
MAX_MATCH_BYTES = 2**16


def matched_lambda3(ratio: float, base: float = BOX_LAMBDA3) -> float:
    """The plan's matching rule: ``base`` x ``ratio`` (box-grid term / frustum term), rounded to two
    significant digits."""
    if not (math.isfinite(ratio) and ratio > 0):
        raise ValueError(f"the ratio of the SDF terms must be a positive number, got {ratio!r}")
    v = base * ratio
    return float(f"{v:.2g}")


def measure_ratio(prof: Profile, seed: int = 0) -> dict:
    """The plan's measurement: the unweighted SDF term that validation reports (``train.validate``'s
    ``val_sdf``) on ``profile``'s validation split, on the predictions of its finished silog Case 1
    run at ``seed``, with the box grid and with the frustum samples; {"bbox", "frustum", "ratio",
    "checkpoint", "frames"}. The run must exist (it is not trained here)."""
    run = prof.run(1, seed)
    cfg = run.as_dict()
    path = run_cache.checkpoint_dir(run) / checkpoint.CHECKPOINT_NAME
    if not run_cache.is_complete(run):
        raise FileNotFoundError(f"{path}: no finished Case 1 run (seed {seed}) of the {prof.name} profile to "
                                "measure on")
    model, _ = checkpoint.load_model(path)
    root = resolve_dataset(cfg)
    ds = load_split(root, "val", cfg["image_size"], limit=cfg["val_frames"])
    space = train.frame_space(root, "val", cfg["image_size"])
    out = {"checkpoint": path.parent.name, "frames": len(ds)}
    for sampling in ("bbox", "frustum"):
        c = {**cfg, "lambdas": [1.0, 0.0, 1.0], "sdf_sampling": sampling, "val_sdf": True}
        with torch.no_grad():
            out[sampling] = float(train.validate(model, ds, c, torch.device("cpu"), space=space)["val_sdf"])
    out["ratio"] = out["bbox"] / out["frustum"]
    return out


def committed_dir() -> Path:
    """``notebooks/study2/exploratory/``: the committed tables and the matching record."""
    return study2.committed_dir() / FOLDER


def read_match(folder: str | Path | None = None) -> dict:
    """The matching record (``match.json``), bounded: a dict with "ratio" and "lambda3", else a
    ValueError naming the file."""
    path = (Path(folder) if folder else committed_dir()) / MATCH_JSON
    if path.stat().st_size > MAX_MATCH_BYTES:
        raise ValueError(f"{path}: larger than {MAX_MATCH_BYTES} bytes, not a matching record")
    try:
        rec = json.loads(path.read_bytes())
        ok = isinstance(rec, dict) and all(isinstance(rec.get(k), (int, float)) for k in ("ratio", "lambda3"))
    except (ValueError, RecursionError):
        ok = False
    if not ok or matched_lambda3(rec["ratio"]) != rec["lambda3"]:
        raise ValueError(f"{path}: not a matching record (JSON with a ratio and the lambda3 the plan's rule gives)")
    return rec


def run_settings(arm: str, lambda3: float, prof: Profile) -> dict:
    """The run settings of ``arm`` beyond ``profile``'s (``lambda3``: E1's matched weight)."""
    term, case = ARM_CELLS[arm]
    if arm == "E1":
        return {**study.run_overrides(prof, term), "lambdas": config.case_lambdas(case, (0.0, lambda3)),
                "sdf_sampling": "frustum"}
    return {**study.run_overrides(prof, term), "lambdas": config.case_lambdas(case, E2_WEIGHTS)}


def arm_runs(lambda3: float, prof: Profile, seeds=SEEDS) -> list[tuple[str, int, int, RunConfig]]:
    """Every run of the two arms as (arm, case, seed, its configuration), E1's eight then E2's."""
    return [(arm, ARM_CELLS[arm][1], int(s), prof.run(ARM_CELLS[arm][1], int(s), **run_settings(arm, lambda3, prof)))
            for arm in ARM_CELLS for s in seeds]


def train_arms(lambda3: float, prof: Profile, seeds=SEEDS, *, workers: int | None = None,
               progress: bool = False) -> dict[tuple[str, int, int], Path]:
    """Train (or reuse) every run; {(arm, case, seed): checkpoint}; each scored by its own worker."""
    runs = arm_runs(lambda3, prof, seeds)
    study.evaluation_sets(prof, progress=progress)
    paths = run_cache.ensure_runs([run for *_, run in runs], workers=workers, progress=progress,
                                  after=functools.partial(study.score_run, prof))
    return {(a, c, s): p for (a, c, s, _), p in zip(runs, paths)}


def score_arms(checkpoints: dict[tuple[str, int, int], Path], sets: dict, *,
               progress: bool = False) -> tuple[list[dict], list[dict]]:
    """(run rows, frame rows of the primary set) in the studies' columns with ``arm`` first."""
    keyed = {(ARM_CELLS[a][0], c, s): p for (a, c, s), p in checkpoints.items()}
    arm_of = {cell: a for a, cell in ARM_CELLS.items()}
    runs, frames = study.score(keyed, sets, progress=progress)
    return ([{"arm": arm_of[(r["depth_term"], r["case"])], **r} for r in runs],
            [{"arm": arm_of[(f["depth_term"], f["case"])], **f} for f in frames])


def read_arms(folder: str | Path | None = None) -> dict:
    """The arms' committed tables ({"runs", "baselines"}), numbers as numbers (``study2.read_tables``)."""
    return study2.read_tables(Path(folder) if folder else committed_dir())


def paired_change(ref_tables: dict, ref_cell, tables: dict, cell, metric: str, set_name: str):
    """(seeds, 100 (m / m_ref - 1) per seed): the runs of ``cell`` in ``tables`` against those of
    ``ref_cell`` in ``ref_tables`` at the seeds both hold, on ``set_name``."""
    ref = study2.run_values(ref_tables, ref_cell, metric, set_name)
    mine = study2.run_values(tables, cell, metric, set_name)
    seeds = sorted(set(ref) & set(mine))
    return seeds, 100 * (np.array([mine[s] for s in seeds]) / np.array([ref[s] for s in seeds]) - 1)


def arm_comparisons(first: dict, arms: dict, set_name: str = PRIMARY, level: float = LEVEL,
                max_width: float | None = WIDTH_BOUND) -> list[dict]:
    """Each arm against the first study's Case 1 of its depth term (``first``: ``study.read_tables()``),
    paired by seed, for RMSE then Abs Rel: one dict each with "arm", "depth_term", "case", "metric",
    "seeds", "values" (100 (m_arm / m_case1 - 1) per seed), "mean", "p" (paired t-test), "low"/"high"
    (Student-t interval at ``level``, no correction), "rejected" (p < 1 - level), "paper", "verdict"
    (``ablation.size_verdict``) and "label"."""
    out = []
    for arm, (term, case) in ARM_CELLS.items():
        for metric in ablation.PAIRED_METRICS[::-1]:
            seeds, v = paired_change(first, (term, 1), arms, (term, case), metric, set_name)
            if not seeds:
                raise KeyError(f"{arm} {metric} on the {set_name}: no seed with both runs")
            mean, low, high = ablation.t_interval(v, level)
            p = study.paired_t_p(v)
            paper = ablation.PAPER_REDUCTION[case][metric]
            out.append({"arm": arm, "depth_term": term, "case": case, "metric": metric, "seeds": seeds,
                        "values": v.tolist(), "mean": mean, "p": p, "low": low, "high": high, "level": level,
                        "rejected": bool(p < 1 - level), "paper": paper,
                        "verdict": ablation.size_verdict(low, high, mean, paper, bool(p < 1 - level), max_width),
                        "label": f"{arm}: {study.DEPTH_LABELS[term]} Case {case} vs {study.DEPTH_LABELS[term]} Case 1"})
    return out


def beside(first: dict, second: dict, arms: dict, set_name: str = PRIMARY) -> list[dict]:
    """Each arm's mean relative change beside the runs the plan shows it with, each against the
    Case 1 of its own depth term at the same seeds: E1 beside arm B (B3) and the first study's
    silog Case 3; E2 beside A4 and the first study's L1 Case 4. One dict per (row, metric):
    "what", "metric", "mean" (points), "seeds"."""
    rows = [("E1: frustum, matched lambda3", arms, ("silog", 3), "silog"),
            ("B3: frustum, lambda3 = 0.01", second, ("silog", 3), "silog"),
            ("first study: box grid, lambda3 = 0.01", first, ("silog", 3), "silog"),
            ("E2: L1, lambda2 = 1", arms, ("l1", 4), "l1"),
            ("A4: silog, lambda2 = 1", second, ("silog", 4), "silog"),
            ("first study: L1, lambda2 = 0.003", first, ("l1", 4), "l1")]
    out = []
    for what, tables, cell, term in rows:
        for metric in ablation.PAIRED_METRICS[::-1]:
            seeds, v = paired_change(first, (term, 1), tables, cell, metric, set_name)
            out.append({"what": what, "metric": metric, "mean": float(v.mean()) if seeds else math.nan,
                        "seeds": seeds})
    return out


def lines(comps: list[dict]) -> list[str]:
    """:func:`arm_comparisons` in words, each marked exploratory."""
    return [f"exploratory, {PRIMARY}, {tbl.METRIC_LABELS[t['metric']]}: {t['label']}: {t['mean']:+.2f}% "
            f"[{t['low']:+.2f}, {t['high']:+.2f}] ({100 * t['level']:.0f}%, p = {t['p']:.3f}; paper {t['paper']:+.1f}%)"
            f" -> {t['verdict']}" for t in comps]


def markdown_rows(comps: list[dict]) -> list[str]:
    """:func:`arm_comparisons` as the rows of the docs' table: arm, metric, mean, 95% interval, p, paper,
    verdict (each marked exploratory)."""
    return [f"| {t['label']} | {tbl.METRIC_LABELS[t['metric']]} | {t['mean']:+.1f} | "
            f"[{t['low']:+.1f}, {t['high']:+.1f}] | {t['p']:.3f} | {t['paper']:+.1f} | exploratory: {t['verdict']} |"
            for t in comps]
