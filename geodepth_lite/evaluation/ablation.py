"""The four-case ablation of Section 4.2.1 as paired experiments, with intervals and computed verdicts.

The paper trains each loss combination once and reports its reduction of RMSE and Abs Rel
against Case 1 (depth + smoothness). One run per case cannot separate a loss's effect from
the luck of one initialisation, so here every case is trained with the same seeds, and the
runs are **paired by seed**: with seed s every case starts from the same weights and sees
the frames in the same order (``utils.seed_everything`` before the network is built, the
same DataLoader generator), so case k minus Case 1 at seed s removes most of the seed's luck.

For each claim (case k changes metric m against Case 1 by the paper's percent) the seeds'
relative changes r_s = 100 (m(case k, s) / m(Case 1, s) - 1) give a mean, a paired t-test and
a Student-t interval (n - 1 degrees of freedom). All the claims shown together form one family:
whether a change differs from zero follows Holm's rule at a family-wise alpha of 0.05, and
the intervals are at the Bonferroni level 1 - 0.05 / m. The verdict carries the size
(:func:`size_verdict`, the rule of docs/study_plan.md): "paper's size reproduced", "direction
reproduced, smaller than the paper (paper's value excluded)", "no effect detected; effects
beyond X% excluded", "undecided" or "opposite".

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

from geodepth_lite.data import datasets, synth
from geodepth_lite.evaluation import baselines, evaluate, tables
from geodepth_lite.training import checkpoint, run_cache
from geodepth_lite.training.config import Profile

CASE_NAMES = {1: "depth + smooth", 2: "+ grad + normal", 3: "+ SDF", 4: "all five"}
# Section 4.2.1: the paper's reduction against Case 1, in percent (negative = better)
PAPER_REDUCTION = {2: {"rmse": -10.0, "abs_rel": -20.4}, 3: {"rmse": -13.0, "abs_rel": -25.4},
                   4: {"rmse": -22.0, "abs_rel": -36.3}}
HELDOUT_GROUPS = {"T1-L1": "heldout_T1L1", "T2-L2": "heldout_T2L2", "T3-L3": "heldout_T3L3"}
IN_DOMAIN = "test split"
HELDOUT = "held-out T x L"
ALPHA = 0.05  # family-wise error rate of the verdicts (Holm), two-sided
# The confirmatory studies' "too wide" bound (docs/study_plan.md, Amendments; docs/study_plan_2.md): an
# interval wider than twice the smallest change the paper reports (10%) cannot tell an effect of the
# paper's smallest size from none, so a comparison that keeps zero with such an interval is "undecided".
WIDTH_BOUND = 2 * min(abs(v) for per in PAPER_REDUCTION.values() for v in per.values())  # 20 points


def ablation_sets(prof: Profile, progress: bool = False) -> dict[str, Any]:
    """{IN_DOMAIN: the profile's test split, HELDOUT: the three held-out groups' test frames together}."""
    test = evaluate.open_eval_dataset(prof["dataset"], split="test", progress=progress)
    parts = [evaluate.open_eval_dataset(str(synth.ensure_dataset(m, overrides=prof["heldout_overrides"],
                                                                  progress=progress)), split="test")
             for m in HELDOUT_GROUPS.values()]
    return {IN_DOMAIN: test, HELDOUT: torch.utils.data.ConcatDataset(parts)}


def baseline_scores(prof: Profile, sets: dict[str, Any]) -> dict[str, dict[str, dict]]:
    """{set: {baseline: overall metrics}}; the mean depth map is fitted on the profile's training split."""
    root = datasets.resolve_dataset(prof.run(1, 0).as_dict())
    mean_map = baselines.fit_mean_depth_map(root, "train")
    return {name: {b: r["overall"] for b, r in evaluate.evaluate_baselines(ds, mean_map).items()}
            for name, ds in sets.items()}


def run(prof: Profile, cases: list[int], seeds: list[int], *, workers: int | None = None,
        progress: bool = False) -> dict:
    """Train (or reuse) every (case, seed) and score each on every evaluation set.

    Returns {"profile", "cases", "seeds", "scores": {(case, seed): {set: overall metrics}},
    "baselines": {set: {baseline: overall metrics}}, "frames": {set: n}, "checkpoints": {...}}.
    """
    runs = [(c, s) for c in cases for s in seeds]
    paths = dict(zip(runs, run_cache.ensure_runs([prof.run(c, s) for c, s in runs], workers=workers)))
    sets = ablation_sets(prof, progress=progress)
    scores = {}
    for run_key, path in paths.items():
        model, cfg = checkpoint.load_model(path)
        scores[run_key] = {name: evaluate.evaluate_model(model, ds, image_size=cfg["image_size"])["overall"]
                           for name, ds in sets.items()}
    return {"profile": prof.name, "cases": list(cases), "seeds": list(seeds), "scores": scores,
            "baselines": baseline_scores(prof, sets), "frames": {k: len(v) for k, v in sets.items()},
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


def holm(pvalues: list[float], alpha: float = ALPHA) -> list[bool]:
    """Holm's step-down rule: which of the hypotheses are rejected at family-wise level ``alpha``.

    Sort the p-values p_(1) <= ... <= p_(m); reject while p_(i) <= alpha / (m - i + 1), and stop
    at the first that is not (it and all larger ones are kept).
    """
    order = sorted(range(len(pvalues)), key=lambda i: pvalues[i])
    rejected = [False] * len(pvalues)
    for rank, i in enumerate(order):
        if not pvalues[i] <= alpha / (len(pvalues) - rank):
            break
        rejected[i] = True
    return rejected


def size_verdict(low: float, high: float, mean: float, paper: float, rejected: bool,
                 max_width: float | None = None) -> str:
    """The verdict on "case k changes the metric by the paper's ``paper`` percent", from the
    comparison's interval [low, high] (percent, negative = better) and whether the family's
    multiplicity rule (:func:`holm`) rejects zero for it. The rule of docs/study_plan.md:

    - zero rejected, on the paper's side: "paper's size reproduced" if low <= paper <= high,
      else "direction reproduced, smaller than the paper (paper's value excluded)" (or larger);
    - zero rejected, on the other side: "opposite";
    - zero kept: "no effect detected; effects beyond X% excluded" when the paper's value lies
      outside the interval (X = the interval's larger end in size), else "undecided";
    - zero kept and the interval wider than ``max_width`` points (high - low > max_width; None:
      no bound): "undecided", whatever the paper's value (the confirmatory studies pass
      :data:`WIDTH_BOUND`).
    """
    if rejected and (mean < 0) == (paper < 0):
        if low <= paper <= high:
            return "paper's size reproduced"
        smaller = abs(paper) > max(abs(low), abs(high))
        return (f"direction reproduced, {'smaller' if smaller else 'larger'} than the paper "
                "(paper's value excluded)")
    if rejected:
        return "opposite"
    if too_wide(low, high, max_width):
        return "undecided"
    if not low <= paper <= high:
        return f"no effect detected; effects beyond {max(abs(low), abs(high)):.1f}% excluded"
    return "undecided"


def too_wide(low: float, high: float, max_width: float | None) -> bool:
    """Whether the interval [low, high] is wider than ``max_width`` points (None: never)."""
    return max_width is not None and not high - low <= max_width


def paired(result: dict, metric: str, set_name: str, case: int, level: float = 0.95) -> dict:
    """Paired comparison of ``case`` against Case 1 on ``metric`` and ``set_name``.

    The unit is the seed: r_s = 100 (m(case, s) / m(Case 1, s) - 1), the relative change of seed
    s's run. Returns {"diffs": absolute per-seed differences, "rel_diffs": the r_s, "rel": their
    mean, "rel_low", "rel_high": its Student-t interval at ``level`` (percent of Case 1),
    "p": the two-sided p-value of the paired t-test of mean 0}.
    """
    seeds = result["seeds"]
    a = np.array([result["scores"][(case, s)][set_name][metric] for s in seeds])
    b = np.array([result["scores"][(1, s)][set_name][metric] for s in seeds])
    r = 100 * (a / b - 1)  # (n_seeds,)
    mean, low, high = t_interval(r, level)
    p = float(stats.ttest_1samp(r, 0.0).pvalue) if r.size > 1 and r.std() > 0 else (0.0 if mean else 1.0)
    return {"diffs": (a - b).tolist(), "rel_diffs": r.tolist(), "rel": mean, "rel_low": low, "rel_high": high,
            "p": p}


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


def comparisons(result: dict, alpha: float = ALPHA) -> list[tuple[str, str, int, dict]]:
    """Every claim the verdicts judge, in their order, as one family: (set, metric, case, comparison)
    for each evaluation set, each of PAIRED_METRICS and each case against Case 1.

    Each comparison is :func:`paired` at the Bonferroni level 1 - alpha / m (m = the family's
    size, so the m intervals cover their true values together with probability at least
    1 - alpha), plus "rejected" (Holm's rule over the m p-values), "paper" (the paper's percent)
    and "verdict" (:func:`size_verdict`).
    """
    keys = [(set_name, metric, c) for set_name in result["baselines"] for metric in PAIRED_METRICS
            for c in result["cases"] if c != 1]
    level = 1 - alpha / max(len(keys), 1)
    out = [(k[0], k[1], k[2], paired(result, k[1], k[0], k[2], level)) for k in keys]
    for (set_name, metric, c, p), rejected in zip(out, holm([p["p"] for *_, p in out], alpha)):
        paper = PAPER_REDUCTION[c][metric]
        p.update(rejected=rejected, paper=paper, level=level,
                 verdict=size_verdict(p["rel_low"], p["rel_high"], p["rel"], paper, rejected))
    return out


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
    out |= paired_summary(result)
    return out


def paired_summary(result: dict) -> dict[str, float]:
    """What every verdict's interval is made of, rounded to 0.01: per comparison (:func:`comparisons`)
    the mean and the sample sd of the per-seed relative changes r_s (percent of Case 1), and once
    the number of paired seeds and the family's size:
    {"paired | <set> | <metric> | case<k> | mean %": ..., "... | sd %": ..., "paired | seeds": n,
    "paired | family size": m}. The interval is mean -/+ t(1 - 0.05 / (2 m), n - 1) sd / sqrt(n).

    These are the numbers another computer's retraining can be held to: a fresh draw of the same
    seeds moves the mean by a predictable amount given the sd (``tests/test_results.py``), while
    the interval's ends at few seeds move with the re-estimated sd far more than the mean does.
    """
    family = comparisons(result)
    out = {"paired | seeds": float(len(result["seeds"])), "paired | family size": float(len(family))}
    for set_name, metric, c, p in family:
        r = np.asarray(p["rel_diffs"], dtype=np.float64)
        out[f"paired | {set_name} | {metric} | case{c} | mean %"] = round(float(r.mean()), 2)
        out[f"paired | {set_name} | {metric} | case{c} | sd %"] = round(float(r.std(ddof=1)) if r.size > 1
                                                                        else math.nan, 2)
    return out
