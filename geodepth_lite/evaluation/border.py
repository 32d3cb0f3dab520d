"""Is a predictor biased near the image border? The border error map and its bootstrap intervals.

``border_error_map`` averages each frame's per-pixel log error of the median-scaled prediction
(as the metrics of ``evaluate`` see it) over a dataset, sums it over the outer bands of the image
and the centre (``band_regions``), and gives each band's ratio to the centre with a percentile
bootstrap interval over frames or whole scenes (``bootstrap_band_ratios``). Notebook 06 reads a
network's border bias from it; ``viz.border_map_figure`` draws it.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from tqdm.auto import tqdm

from geodepth_lite.core.metrics import EVAL_MAX_DEPTH, EVAL_MIN_DEPTH, eval_mask, median_scale
from geodepth_lite.evaluation.evaluate import as_depth_batch
from geodepth_lite.training.inference import collate

BORDER_BANDS = ("top", "bottom", "left", "right")


def border_error_map(predict_fn: Callable, dataset, *, batch_size: int = 8, band: float = 0.1,
                     min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH,
                     groups: list[str] | None = None, clusters: list | None = None, n_boot: int = 2000,
                     progress: bool = False) -> dict:
    """Is a predictor biased near the image border? Per-pixel log errors averaged over ``dataset``.

    Each frame's prediction is median-scaled to its ground truth (as the metrics see it); then
    e = log(pred) - log(gt) on valid pixels. Returns {"signed": H x W mean e, "abs": H x W mean
    |e|, "count": H x W valid frames per pixel, "bands": mean |e| over the outer ``band``
    fraction of rows/columns on each side and over the centre (the middle half in both axes),
    "ratios": each border band's mean |e| over the centre's, "intervals": for each band, the 95%
    percentile bootstrap interval of its ratio over frames (``n_boot`` resamples of the frames
    with replacement, seeded; of whole clusters when ``clusters`` is given), so that a ratio's
    distance from a goal can be told from which frames happen to be in the set, "frame_bands":
    {region: each frame's mean |e| there} and "frame_index": those frames' places in ``dataset``
    (a frame with no valid pixel is left out), to find the frames that weigh most in a band}.
    Frames must share one size.

    groups: one label per frame (in dataset order), e.g. the view kind of each synthetic frame;
    then out["groups"] = {label: {"frames", "bands", "ratios", "signed"}} holds the same region
    means per label, "signed" being the mean e per region (negative: too near).

    clusters: one label per frame (in dataset order) for frames that are not independent draws,
    e.g. the scene of each synthetic frame (its frames share one tube, texture and camera path);
    the interval then resamples whole clusters, as :func:`bootstrap_band_ratios` says.
    """
    _check_labels(len(dataset), groups, clusters)
    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=False, collate_fn=collate)
    sums = None
    seen = 0
    for batch in tqdm(loader, desc="border error map", disable=not progress, leave=False):
        gt, valid, pred = _batch_depths(predict_fn, batch, min_depth, max_depth)
        if sums is None:
            sums = _BorderSums(gt.shape[1:], band)
        elif gt.shape[1:] != sums.signed.shape:
            raise ValueError(f"border_error_map needs frames of one size, got {gt.shape[1:]} after {sums.signed.shape}")
        for j in range(gt.shape[0]):
            frame = _log_error(pred[j], gt[j], valid[j])
            if frame is not None:
                sums.add(*frame, seen + j, groups)
        seen += gt.shape[0]
    if sums is None:
        raise ValueError("border_error_map: the dataset has no frame")
    return _summary(sums, n_boot, clusters, grouped=groups is not None)


def _check_labels(n: int, groups: list | None, clusters: list | None) -> None:
    """One group label and one cluster label (where given) per frame of the ``n``."""
    if groups is not None and len(groups) != n:
        raise ValueError(f"border_error_map: {len(groups)} group labels for {n} frames")
    if clusters is not None and len(clusters) != n:
        raise ValueError(f"border_error_map: {len(clusters)} cluster labels for {n} frames")


def _batch_depths(predict_fn: Callable, batch: dict, min_depth: float,
                  max_depth: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A batch's ground truth (float64 B x H x W), evaluation mask (bool) and prediction (float64)."""
    gt = batch["depth"].numpy()[:, 0].astype(np.float64)  # (B, H, W)
    valid = eval_mask(gt, min_depth, max_depth, batch["valid"].numpy()[:, 0] if "valid" in batch else None)
    pred = as_depth_batch(predict_fn(batch["image"])).astype(np.float64)  # (B, H, W)
    if pred.shape != gt.shape:
        raise ValueError(f"predictor returned depth of shape {pred.shape} for ground truth {gt.shape}")
    return gt, valid, pred


def _log_error(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """A frame's log error e = log(median-scaled pred) - log(gt) (0 off its valid pixels) and those
    valid pixels (where the prediction is also positive and finite); None when it has none."""
    v = valid & (pred > 0) & np.isfinite(pred)
    if not v.any():
        return None
    ratio = median_scale(pred[v], gt[v])
    e = np.where(v, np.log(np.where(v, pred * ratio, 1.0)) - np.log(np.where(v, gt, 1.0)), 0.0)
    return e, v


class _BorderSums:
    """The running sums of ``border_error_map``: per pixel, per group label, and per frame and region."""

    def __init__(self, shape: tuple[int, ...], band: float):
        self.band = band
        self.signed, self.absolute, self.count = (np.zeros(shape) for _ in range(3))
        self.per_group: dict[str, list] = {}  # label -> [signed sum, |e| sum, count, frames]
        self.per_frame: list[np.ndarray] = []  # each frame's (|e| sum, count) per region, for the bootstrap
        self.frame_index: list[int] = []  # their places in the dataset

    def add(self, e: np.ndarray, v: np.ndarray, index: int, groups: list[str] | None) -> None:
        """Frame ``index`` of the dataset, with log error ``e`` on its valid pixels ``v``."""
        self.signed += e
        self.absolute += np.abs(e)
        self.count += v
        regions = band_regions(*e.shape, self.band)
        self.per_frame.append(np.array([[np.abs(e[r]).sum(), v[r].sum()] for r in regions.values()]))
        self.frame_index.append(index)
        if groups is not None:
            acc = self.per_group.setdefault(groups[index], [np.zeros_like(e), np.zeros_like(e), np.zeros_like(e), 0])
            acc[0] += e
            acc[1] += np.abs(e)
            acc[2] += v
            acc[3] += 1


def _summary(sums: _BorderSums, n_boot: int, clusters: list | None, grouped: bool) -> dict:
    """``border_error_map``'s result from its sums (see there)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        out = {"signed": sums.signed / sums.count, "abs": sums.absolute / sums.count, "count": sums.count}
    out["bands"], out["ratios"] = border_bands(sums.absolute, sums.count, sums.band)
    stacked = np.stack(sums.per_frame)  # (frames, 5 regions, (|e| sum, count))
    out["intervals"] = bootstrap_band_ratios(
        stacked, n_boot=n_boot, clusters=None if clusters is None else [clusters[i] for i in sums.frame_index])
    with np.errstate(invalid="ignore", divide="ignore"):
        out["frame_bands"] = {k: stacked[:, i, 0] / stacked[:, i, 1] for i, k in enumerate(band_regions(1, 1))}
    out["frame_index"] = np.array(sums.frame_index)
    if grouped:
        out["groups"] = {}
        for label, (g_signed, g_abs, g_count, frames) in sorted(sums.per_group.items()):
            bands, ratios = border_bands(g_abs, g_count, sums.band)
            out["groups"][label] = {"frames": frames, "bands": bands, "ratios": ratios,
                                    "signed": border_bands(g_signed, g_count, sums.band)[0]}
    return out


def band_regions(H: int, W: int, band: float = 0.1) -> dict[str, tuple[slice, slice]]:
    """The regions of the border error map: the outer ``band`` fraction of rows or columns on each
    side ("top", "bottom", "left", "right") and the middle half in both axes ("centre")."""
    bh, bw = max(1, round(band * H)), max(1, round(band * W))
    return {"top": (slice(0, bh), slice(None)), "bottom": (slice(H - bh, H), slice(None)),
            "left": (slice(None), slice(0, bw)), "right": (slice(None), slice(W - bw, W)),
            "centre": (slice(H // 4, H - H // 4), slice(W // 4, W - W // 4))}


def bootstrap_band_ratios(per_frame: np.ndarray, n_boot: int = 2000, level: float = 0.95,
                          seed: int = 0, clusters: list | None = None) -> dict[str, tuple[float, float]]:
    """Percentile bootstrap interval of each border band's ratio (band mean |e| / centre mean |e|).

    per_frame: (frames, 5, 2) array of each frame's (|e| sum, valid count) in the regions of
    ``band_regions`` (in its order). Frames are resampled with replacement; each resample's ratio
    pools its frames' sums as ``border_bands`` pools the whole set's.

    clusters: one label per frame. Then whole clusters are resampled (a cluster bootstrap): frames
    of one scene resemble each other, so resampling them one by one treats them as more
    independent draws than they are and gives too narrow an interval.
    """
    if clusters is not None:
        if len(clusters) != per_frame.shape[0]:
            raise ValueError(f"bootstrap_band_ratios: {len(clusters)} cluster labels for {per_frame.shape[0]} frames")
        labels = list(dict.fromkeys(clusters))  # in order of first appearance
        where = {c: i for i, c in enumerate(labels)}
        summed = np.zeros((len(labels),) + per_frame.shape[1:])
        np.add.at(summed, [where[c] for c in clusters], per_frame)
        per_frame = summed  # a cluster's sums pool like one frame's
    n = per_frame.shape[0]
    if n_boot <= 0 or n == 0:
        return {}
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, n, size=(n_boot, n))
    sums = per_frame[picks].sum(axis=1)  # (n_boot, 5, 2)
    means = sums[..., 0] / np.maximum(sums[..., 1], 1)  # (n_boot, 5)
    centre = means[:, 4:5]
    ratios = np.where(centre > 0, means[:, :4] / np.where(centre > 0, centre, 1.0), np.nan)  # as border_bands
    lo, hi = 100 * (1 - level) / 2, 100 * (1 + level) / 2
    out = {}
    for i, k in enumerate(BORDER_BANDS):
        r = ratios[:, i][np.isfinite(ratios[:, i])]
        out[k] = (float(np.percentile(r, lo)), float(np.percentile(r, hi))) if r.size else (float("nan"),) * 2
    return out


def border_bands(abs_sum: np.ndarray, count: np.ndarray, band: float = 0.1) -> tuple[dict, dict]:
    """Mean |error| per region from per-pixel sums and counts: ({region: mean}, {border band: mean / centre})."""
    regions = band_regions(*abs_sum.shape, band)
    means = {k: float(abs_sum[r].sum() / max(count[r].sum(), 1)) for k, r in regions.items()}
    ratios = {k: means[k] / means["centre"] if means["centre"] > 0 else float("nan") for k in BORDER_BANDS}
    return means, ratios
