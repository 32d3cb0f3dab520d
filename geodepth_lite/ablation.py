"""The four-case ablation of Section 4.2.1 as paired experiments, with intervals and computed verdicts.

The paper trains each loss combination once and reports its reduction of RMSE and Abs Rel
against Case 1 (depth + smoothness). One run per case cannot separate a loss's effect from
the luck of one initialisation, so here every case is trained with the same seeds, and the
runs are **paired by seed**: with seed s every case starts from the same weights and sees
the frames in the same order (``utils.seed_everything`` before the network is built, the
same DataLoader generator), so case k minus Case 1 at seed s removes most of the seed's luck.

For each claim (case k lowers metric m against Case 1) the paired differences
d_s = m(case k, seed s) - m(case 1, seed s) give a mean and a 95% Student-t interval
(n - 1 degrees of freedom). The verdict is read from the interval alone:

- ``reproduced``: the whole interval is below 0 (case k is better, as the paper says);
- ``opposite``: the whole interval is above 0 (case k is worse);
- ``undecided at this power``: the interval contains 0 (more seeds or a larger profile needed).

Everything is evaluated on the training recipe's test split (in domain) and on the held-out
texture x lighting groups (unseen appearance: the paper's own ablation is cross-domain, it
trains on synthetic data and tests on EndoSLAM), beside the three trivial baselines.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from scipy import stats

from geodepth_lite import baselines, checkpoint, config, datasets, evaluate, run_cache, synth, tables

CASE_NAMES = {1: "depth + smooth", 2: "+ grad + normal", 3: "+ SDF", 4: "all five"}
# Section 4.2.1: the paper's reduction against Case 1, in percent (negative = better)
PAPER_REDUCTION = {2: {"rmse": -10.0, "abs_rel": -20.4}, 3: {"rmse": -13.0, "abs_rel": -25.4},
                   4: {"rmse": -22.0, "abs_rel": -36.3}}
HELDOUT_GROUPS = {"T1-L1": "heldout_T1L1", "T2-L2": "heldout_T2L2", "T3-L3": "heldout_T3L3"}
IN_DOMAIN = "test split"
HELDOUT = "held-out T x L"
VERDICTS = ("reproduced", "opposite", "undecided at this power")


def evaluation_sets(profile: str, progress: bool = False) -> dict[str, Any]:
    """{IN_DOMAIN: the profile's test split, HELDOUT: the three held-out groups' test frames together}."""
    prof = config.get_profile(profile)
    test = evaluate.open_eval_dataset(prof["dataset"], split="test", progress=progress)
    parts = [evaluate.open_eval_dataset(str(synth.ensure_dataset(m, overrides=prof["heldout_overrides"],
                                                                  progress=progress)), split="test")
             for m in HELDOUT_GROUPS.values()]
    return {IN_DOMAIN: test, HELDOUT: torch.utils.data.ConcatDataset(parts)}


def baseline_scores(profile: str, sets: dict[str, Any]) -> dict[str, dict[str, dict]]:
    """{set: {baseline: overall metrics}}; the mean depth map is fitted on the profile's training split."""
    root = datasets.resolve_dataset(config.make_config(profile, 1, 0))
    mean_map = baselines.fit_mean_depth_map(root, "train")
    return {name: {b: r["overall"] for b, r in evaluate.evaluate_baselines(ds, mean_map).items()}
            for name, ds in sets.items()}


def run(profile: str, cases: list[int], seeds: list[int], *, workers: int | None = None,
        progress: bool = False) -> dict:
    """Train (or reuse) every (case, seed) and score each on every evaluation set.

    Returns {"profile", "cases", "seeds", "scores": {(case, seed): {set: overall metrics}},
    "baselines": {set: {baseline: overall metrics}}, "frames": {set: n}, "checkpoints": {...}}.
    """
    runs = [(c, s) for c in cases for s in seeds]
    paths = run_cache.ensure_checkpoints(profile, runs, workers=workers)
    sets = evaluation_sets(profile, progress=progress)
    scores = {}
    for run_key, path in paths.items():
        model, cfg = checkpoint.load_model(path)
        scores[run_key] = {name: evaluate.evaluate_model(model, ds, image_size=cfg["image_size"])["overall"]
                           for name, ds in sets.items()}
    return {"profile": profile, "cases": list(cases), "seeds": list(seeds), "scores": scores,
            "baselines": baseline_scores(profile, sets), "frames": {k: len(v) for k, v in sets.items()},
            "checkpoints": paths}


def t_interval(values, level: float = 0.95) -> tuple[float, float, float]:
    """(mean, low, high): the Student-t interval of the mean of ``values`` (n - 1 degrees of freedom).

    With fewer than two values the interval is infinite (nothing is known about the spread).
    """
    x = np.asarray(values, dtype=np.float64)
    m = float(x.mean())
    if x.size < 2:
        return m, -math.inf, math.inf
    half = float(stats.t.ppf(0.5 + level / 2, x.size - 1) * x.std(ddof=1) / math.sqrt(x.size))
    return m, m - half, m + half


def verdict(low: float, high: float, lower_is_better: bool = True) -> str:
    """The claim "case k improves on Case 1" read from the interval of (case k - Case 1)."""
    if not lower_is_better:
        low, high = -high, -low
    if high < 0:
        return "reproduced"
    if low > 0:
        return "opposite"
    return "undecided at this power"


def paired(result: dict, metric: str, set_name: str, case: int, level: float = 0.95) -> dict:
    """Paired comparison of ``case`` against Case 1 on ``metric`` and ``set_name``.

    Returns {"diffs": per-seed differences, "mean", "low", "high" (absolute units), "rel", "rel_low",
    "rel_high" (percent of Case 1's mean), "verdict"}.
    """
    seeds = result["seeds"]
    a = np.array([result["scores"][(case, s)][set_name][metric] for s in seeds])
    b = np.array([result["scores"][(1, s)][set_name][metric] for s in seeds])
    mean, low, high = t_interval(a - b, level)
    base = float(b.mean())
    lower_is_better = metric not in ("a1", "a2", "a3")
    return {"diffs": (a - b).tolist(), "mean": mean, "low": low, "high": high,
            "rel": 100 * mean / base, "rel_low": 100 * low / base, "rel_high": 100 * high / base,
            "verdict": verdict(low, high, lower_is_better)}


def case_stats(result: dict, set_name: str, metric: str) -> dict[int, tuple[float, float]]:
    """{case: (mean, sample sd)} of ``metric`` over the seeds on ``set_name``."""
    out = {}
    for c in result["cases"]:
        v = np.array([result["scores"][(c, s)][set_name][metric] for s in result["seeds"]])
        out[c] = (float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else math.nan)
    return out


def beats_baselines(result: dict, set_name: str, metric: str = "abs_rel", margin: float = 0.0) -> dict:
    """{(case, seed): True when the run's ``metric`` is below every baseline's by at least ``margin``
    (a fraction: 0.2 = 20% lower than the best baseline)}."""
    best = min(result["baselines"][set_name][b][metric] for b in result["baselines"][set_name])
    return {run: scores[set_name][metric] <= (1 - margin) * best for run, scores in result["scores"].items()}


PAIRED_METRICS = ("abs_rel", "rmse")  # the metrics whose paired intervals decide the verdicts


def comparisons(result: dict):
    """Every claim the verdicts judge, in their order: (set, metric, case, ``paired(...)``) for each
    evaluation set, each of PAIRED_METRICS and each case against Case 1."""
    for set_name in result["baselines"]:
        for metric in PAIRED_METRICS:
            for c in result["cases"]:
                if c != 1:
                    yield set_name, metric, c, paired(result, metric, set_name, c)


def claims(result: dict, margin: float = 0.2) -> list[str]:
    """The ablation's conclusions as sentences: verdict per claim and set, and how every run stands
    against the baselines. Computed from the numbers; the notebook prints them as they come."""
    lines = [f"{set_name}, {tables.METRIC_LABELS[metric]}: Case {c} vs Case 1 -> {p['verdict']}"
             for set_name, metric, c, p in comparisons(result)]
    for set_name in result["baselines"]:
        ok = beats_baselines(result, set_name, "abs_rel", 0.0)
        strong = beats_baselines(result, set_name, "abs_rel", margin)
        n = len(ok)
        lines.append(f"{set_name}: runs below every baseline in Abs Rel: {sum(ok.values())} of {n}; "
                     f"at least {100 * margin:.0f}% below the best baseline: {sum(strong.values())} of {n}")
    return lines


def record(result: dict, digits: int = 4) -> dict[str, float]:
    """Every number the ablation notebook shows that comes from trained weights, flat and rounded.

    The committed notebook prints this record; ``tests/test_results.py`` recomputes it on the
    machine at hand and compares within a stated tolerance (CPU kernels differ between
    machines, so trained weights do).
    """
    tree = {f"case{c} seed{s}": sets for (c, s), sets in sorted(result["scores"].items())}
    tree["baselines"] = result["baselines"]
    out = tables.flat_record(tree, digits)
    out |= paired_bounds(result)
    return out


def paired_bounds(result: dict) -> dict[str, float]:
    """The ends of every verdict's interval, in percent of Case 1's mean, rounded to 0.01:
    {"paired | <set> | <metric> | case<k> | low %": ..., "... | high %": ...}. A verdict is only as
    firm as its interval's distance from zero, so the record carries the interval, not only the word."""
    out = {}
    for set_name, metric, c, p in comparisons(result):
        out[f"paired | {set_name} | {metric} | case{c} | low %"] = round(p["rel_low"], 2)
        out[f"paired | {set_name} | {metric} | case{c} | high %"] = round(p["rel_high"], 2)
    return out
