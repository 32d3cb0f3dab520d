"""Evaluation of a trained model with the seven depth metrics (paper Section 4.3).

Protocol (monodepth2 / AF-SfMLearner, shared by every table of the workbook):
the prediction is resized to the ground truth's size, pixels with
``min_depth < gt < max_depth`` (and the dataset's ``valid`` mask, if any) are kept,
the prediction is median-scaled per frame (the paper's Eq. in Section 4.3),
clamped, and the seven metrics (Abs Rel, Sq Rel, RMSE, RMSE log, a1, a2, a3) are
computed per frame by ``metrics.compute_depth_metrics`` and averaged over frames,
overall and per group (organ; texture x lighting group).

``evaluate_model`` is what the notebooks call: it returns plain dicts (no pandas)
and, given ``out_dir``, writes ``metrics.json``, ``frames.csv`` (one row per
frame), ``tables.md`` and error-map PNGs laid out like the paper's Fig. 7, as one set:
all of them or, on a failure, none (an earlier set in that folder is kept whole).
It is ``evaluate_predictor`` for a network: any function images -> depth is scored
the same way, which is how the trivial baselines of ``baselines.py`` get their rows.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import os
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np
import torch

from geodepth_lite import baselines, utils
from geodepth_lite.inference import FLIPS, check_flips, collate
from geodepth_lite.metrics import EVAL_MAX_DEPTH, EVAL_MIN_DEPTH, METRIC_NAMES, eval_mask, median_scale

METRIC_KEYS = METRIC_NAMES  # the seven metrics of Section 4.3, named once in metrics.py
METRIC_LABELS = {"abs_rel": "Abs Rel", "sq_rel": "Sq Rel", "rmse": "RMSE", "rmse_log": "RMSE log",
                 "a1": "a1", "a2": "a2", "a3": "a3"}


# --------------------------------------------------------------------------- datasets


def open_eval_dataset(name: str, *, split: str = "test", root: str | os.PathLike | None = None,
                      progress: bool = False, **kw: Any):
    """A dataset to evaluate on, at its native resolution.

    name: a synthetic manifest name (built on demand with ``synth.ensure_dataset``), a
    synthetic dataset directory, or one of the public datasets (``loaders.REGISTRY``; needs
    ``root``, read by ``loaders.open_dataset``, extra keywords such as ``group``/``organ``/
    ``limit`` passed on; its ``max_depth``, the largest depth its encoding holds, bounds the
    evaluation mask). ``split`` applies to synthetic datasets.
    """
    from geodepth_lite import loaders

    if name in loaders.REGISTRY:
        if root is None:
            raise ValueError(f"--root is required for the public dataset {name!r} (the folder you downloaded)")
        return loaders.open_dataset(name, root, **kw)
    from geodepth_lite.dataset import SyntheticDepthDataset

    path = Path(name).expanduser()
    if path.is_dir() and (path / "manifest.json").exists():
        ds_root = path
    else:
        from geodepth_lite import synth

        ds_root = Path(synth.ensure_dataset(name, overrides=kw.pop("overrides", None), progress=progress))
    if not (ds_root / split).is_dir():
        have = sorted(p.name for p in ds_root.iterdir() if (p / "frames.jsonl").exists())
        raise ValueError(f"split {split!r} not in {ds_root}; available: {', '.join(have) or 'none'}")
    return SyntheticDepthDataset(ds_root, split)


# --------------------------------------------------------------------------- evaluation


def _frame_metrics(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None, min_depth: float,
                   max_depth: float) -> dict:
    from geodepth_lite.metrics import compute_depth_metrics

    if valid is not None:
        gt = np.where(valid, gt, 0.0)  # outside the metric's (min_depth, max_depth) mask
    m = compute_depth_metrics(pred[None], gt[None], min_depth=min_depth, max_depth=max_depth)
    out = {k: float(m[k]) for k in METRIC_KEYS}
    ratios = np.asarray(m.get("ratios", [np.nan]), dtype=np.float64).ravel()
    out["ratio"] = float(ratios[0]) if ratios.size else float("nan")
    return out


def summarize(rows: list[dict], by: str | None = None) -> dict:
    """Mean of the per-frame metrics (the protocol's average over frames), overall or per ``by``."""
    if by is None:
        if not rows:
            return {"n": 0, **{k: float("nan") for k in METRIC_KEYS}}
        return {"n": len(rows), **{k: float(np.mean([r[k] for r in rows])) for k in METRIC_KEYS}}
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(str(r.get(by, "")), []).append(r)
    return {g: summarize(rs) for g, rs in sorted(groups.items())}


def _as_depth_batch(pred: Any) -> np.ndarray:
    """A predictor's output (numpy or torch; N x H x W or N x 1 x H x W) as float32 N x H x W."""
    if hasattr(pred, "detach"):
        pred = pred.detach().float().cpu().numpy()
    pred = np.asarray(pred, dtype=np.float32)
    if pred.ndim == 4 and pred.shape[1] == 1:
        pred = pred[:, 0]
    if pred.ndim != 3:
        raise ValueError(f"a predictor must return N x H x W (or N x 1 x H x W) depth, got shape {pred.shape}")
    return pred


def _evaluate(predictors: dict[str, Callable], dataset, *, batch_size: int = 8, error_maps: int = 0,
              min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH, progress: bool = False,
              desc: str = "evaluate") -> tuple[dict[str, dict], list[dict]]:
    """One pass over ``dataset`` scoring every predictor: ({name: result}, error-map examples of the first)."""
    from tqdm.auto import tqdm

    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=False,
                                         collate_fn=collate)
    rows: dict[str, list[dict]] = {name: [] for name in predictors}
    skipped: dict[str, list[dict]] = {name: [] for name in predictors}
    examples: list[dict] = []
    first = next(iter(predictors), None)
    for batch in tqdm(loader, desc=desc, disable=not progress, leave=False):
        gt = batch["depth"].numpy()[:, 0]
        valid = batch["valid"].numpy()[:, 0].astype(bool) if "valid" in batch else None
        for name, predict_fn in predictors.items():
            pred = _as_depth_batch(predict_fn(batch["image"]))
            if pred.shape != gt.shape:  # the protocol scores predictions at the ground truth's size
                raise ValueError(f"predictor {name!r} returned depth of shape {pred.shape} for ground truth "
                                 f"{gt.shape}: resize the prediction to the frame's size")
            for j in range(pred.shape[0]):
                index = int(batch["index"][j])
                if not np.isfinite(pred[j]).all():
                    raise NonFiniteDepth(f"{name or 'the predictor'} gives non-finite depth (NaN or inf) for frame "
                                     f"{frame_name(dataset, index)}: nothing written")
                record = {"index": index, "organ": str(batch["organ"][j]), "group": str(batch["group"][j])}
                frame_valid = eval_mask(gt[j], min_depth, max_depth, None if valid is None else valid[j])
                if not frame_valid.any():  # skipped, named, counted; the other frames are still scored
                    if name == first:
                        warnings.warn(f"skipping frame {frame_name(dataset, index)}: no valid ground-truth pixel",
                                      stacklevel=2)
                    skipped[name].append({**record, **{k: float("nan") for k in (*METRIC_KEYS, "ratio")},
                                          "skipped": "no valid ground-truth pixel"})
                    continue
                m = _frame_metrics(pred[j], gt[j], None if valid is None else valid[j], min_depth, max_depth)
                rows[name].append({**record, **m, "skipped": ""})
                if name == first and len(examples) < error_maps:
                    examples.append({"image": batch["image"][j].permute(1, 2, 0).numpy(), "gt": gt[j],
                                     "pred": pred[j] * m["ratio"], "index": rows[name][-1]["index"],
                                     "valid": None if valid is None else valid[j]})
    if first is not None and not rows[first]:
        n = len(skipped[first])
        raise ValueError(f"no frame of the {n} evaluated has a valid ground-truth pixel (depth in "
                         f"({min_depth:g}, {max_depth:g}), finite)" if n else "the dataset has no frame")
    results = {}
    for name, rs in rows.items():
        frames = sorted(rs + skipped[name], key=_frame_order) if skipped[name] else rs
        results[name] = {"name": name, "n": len(rs), "overall": summarize(rs), "by_group": summarize(rs, "group"),
                         "by_organ": summarize(rs, "organ"), "frames": frames,
                         "skipped": [frame_name(dataset, r["index"]) for r in skipped[name]]}
    return results, examples


class NonFiniteDepth(ValueError):
    """A predictor returned NaN or infinite depth: its numbers would be meaningless, so nothing is written."""


def _frame_order(row: dict) -> int:
    return row["index"]


def frame_name(dataset, index: int) -> str:
    """A frame as a reader finds it: its image file where the dataset records one, else its index."""
    frames = getattr(dataset, "frames", None)
    if isinstance(frames, list) and 0 <= index < len(frames) and isinstance(frames[index], dict):
        rgb = frames[index].get("rgb")
        if rgb:
            return f"{index} ({rgb})"
    return str(index)


def evaluate_predictors(predictors: dict[str, Callable], dataset, *, batch_size: int = 8,
                        min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH,
                        progress: bool = False) -> dict[str, dict]:
    """``evaluate_predictor`` for several predictors in one pass over ``dataset``: {name: result}."""
    return _evaluate(predictors, dataset, batch_size=batch_size, min_depth=min_depth, max_depth=max_depth,
                     progress=progress, desc="evaluate " + ", ".join(predictors))[0]


def evaluate_predictor(predict_fn: Callable, dataset, *, batch_size: int = 8,
                       out_dir: str | os.PathLike | None = None, error_maps: int = 4, min_depth: float = EVAL_MIN_DEPTH,
                       max_depth: float = EVAL_MAX_DEPTH, progress: bool = False, name: str = "",
                       baselines: dict | None = None) -> dict:
    """Evaluate any depth predictor on ``dataset`` (items as ``SyntheticDepthDataset``'s; optional "valid").

    predict_fn: images B x 3 x H x W (torch, in [0, 1]) -> depth B x H x W or B x 1 x H x W
    (numpy or torch) at the frames' own size H x W; a model (``evaluate_model``) or a
    baseline (``baselines.py``) alike, so every row of a table is scored the same way.
    Returns {"name", "n", "overall": {metric: mean}, "by_group": {group: {...}},
    "by_organ": {organ: {...}}, "frames": [one dict per frame: index, organ, group,
    seven metrics, median-scaling ratio]}. ``baselines`` ({name: result} from
    ``evaluate_baselines``) is kept under "baselines" and adds rows to the overall
    table. With ``out_dir`` also writes metrics.json, frames.csv, tables.md and
    ``error_maps`` PNGs (input | GT | prediction | Abs Rel map), as one set or none
    (``write_results``).
    """
    results, examples = _evaluate({name: predict_fn}, dataset, batch_size=batch_size, error_maps=error_maps,
                                  min_depth=min_depth, max_depth=max_depth, progress=progress,
                                  desc=f"evaluate {name}".strip())
    result = results[name]
    if baselines:
        result["baselines"] = baselines
    if out_dir is not None:
        write_results(result, out_dir, examples, min_depth=min_depth, max_depth=max_depth)
    return result


def evaluate_model(model, dataset, *, image_size: int | None = None, batch_size: int = 8,
                   out_dir: str | os.PathLike | None = None, error_maps: int = 4, min_depth: float = EVAL_MIN_DEPTH,
                   max_depth: float = EVAL_MAX_DEPTH, progress: bool = False, name: str = "",
                   baselines: dict | None = None, flips: str = "none") -> dict:
    """``evaluate_predictor`` for a network: each batch resized to the network's ``image_size``,
    predicted (with test-time ``flips``, see ``inference.predict_depth``) and resized back. Same
    result dict and files."""
    from geodepth_lite.inference import predict_depth

    check_flips(flips)

    def predict_fn(images: torch.Tensor) -> torch.Tensor:
        return predict_depth(model, images, image_size, flips).cpu()

    return evaluate_predictor(predict_fn, dataset, batch_size=batch_size, out_dir=out_dir, error_maps=error_maps,
                              min_depth=min_depth, max_depth=max_depth, progress=progress, name=name,
                              baselines=baselines)


def cached_predictor(predict_fn: Callable) -> Callable:
    """``predict_fn`` that remembers its answer to each batch of images, keyed by their bytes.

    A second pass over the same frames in the same batches (the metrics of ``evaluate_predictor``,
    then ``border_error_map``) then predicts nothing again: with test-time flips a network pass
    per mirroring is saved. Answers are kept as float32 N x H x W arrays for as long as the
    returned function lives; its ``calls`` attribute counts the batches ``predict_fn`` really saw.
    """
    import hashlib

    store: dict[bytes, np.ndarray] = {}

    def predict(images: torch.Tensor) -> np.ndarray:
        a = images.detach().cpu().contiguous().numpy()
        key = hashlib.blake2b(a.tobytes(), digest_size=20).digest() + repr((a.shape, a.dtype.str)).encode()
        if key not in store:
            predict.calls += 1
            store[key] = _as_depth_batch(predict_fn(images)).copy()
        return store[key].copy()

    predict.calls = 0
    return predict


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
    from tqdm.auto import tqdm

    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=False, collate_fn=collate)
    if groups is not None and len(groups) != len(dataset):
        raise ValueError(f"border_error_map: {len(groups)} group labels for {len(dataset)} frames")
    if clusters is not None and len(clusters) != len(dataset):
        raise ValueError(f"border_error_map: {len(clusters)} cluster labels for {len(dataset)} frames")
    signed = absolute = count = None
    per_group: dict[str, list] = {}  # label -> [signed sum, |e| sum, count, frames]
    per_frame: list[np.ndarray] = []  # each frame's (|e| sum, count) per region, for the bootstrap
    frame_index: list[int] = []  # their places in the dataset
    seen = 0
    for batch in tqdm(loader, desc="border error map", disable=not progress, leave=False):
        gt = batch["depth"].numpy()[:, 0].astype(np.float64)  # (B, H, W)
        valid = eval_mask(gt, min_depth, max_depth, batch["valid"].numpy()[:, 0] if "valid" in batch else None)
        pred = _as_depth_batch(predict_fn(batch["image"])).astype(np.float64)  # (B, H, W)
        if pred.shape != gt.shape:
            raise ValueError(f"predictor returned depth of shape {pred.shape} for ground truth {gt.shape}")
        if signed is None:
            signed, absolute, count = (np.zeros(gt.shape[1:]) for _ in range(3))
        elif gt.shape[1:] != signed.shape:
            raise ValueError(f"border_error_map needs frames of one size, got {gt.shape[1:]} after {signed.shape}")
        for j in range(gt.shape[0]):
            v = valid[j] & (pred[j] > 0) & np.isfinite(pred[j])
            if not v.any():
                continue
            ratio = median_scale(pred[j][v], gt[j][v])
            e = np.where(v, np.log(np.where(v, pred[j] * ratio, 1.0)) - np.log(np.where(v, gt[j], 1.0)), 0.0)
            signed += e
            absolute += np.abs(e)
            count += v
            regions = band_regions(*e.shape, band)
            per_frame.append(np.array([[np.abs(e[r]).sum(), v[r].sum()] for r in regions.values()]))
            frame_index.append(seen + j)
            if groups is not None:
                acc = per_group.setdefault(groups[seen + j], [np.zeros_like(e), np.zeros_like(e), np.zeros_like(e), 0])
                acc[0] += e
                acc[1] += np.abs(e)
                acc[2] += v
                acc[3] += 1
        seen += gt.shape[0]
    if signed is None:
        raise ValueError("border_error_map: the dataset has no frame")
    with np.errstate(invalid="ignore", divide="ignore"):
        out = {"signed": signed / count, "abs": absolute / count, "count": count}
    out["bands"], out["ratios"] = border_bands(absolute, count, band)
    stacked = np.stack(per_frame)  # (frames, 5 regions, (|e| sum, count))
    out["intervals"] = bootstrap_band_ratios(
        stacked, n_boot=n_boot, clusters=None if clusters is None else [clusters[i] for i in frame_index])
    with np.errstate(invalid="ignore", divide="ignore"):
        out["frame_bands"] = {k: stacked[:, i, 0] / stacked[:, i, 1] for i, k in enumerate(band_regions(1, 1))}
    out["frame_index"] = np.array(frame_index)
    if groups is not None:
        out["groups"] = {}
        for label, (g_signed, g_abs, g_count, frames) in sorted(per_group.items()):
            bands, ratios = border_bands(g_abs, g_count, band)
            out["groups"][label] = {"frames": frames, "bands": bands, "ratios": ratios,
                                    "signed": border_bands(g_signed, g_count, band)[0]}
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


def border_map_figure(maps: dict, title: str = ""):
    """Two panels: the mean signed log error (diverging colours) and the mean |log error| per pixel."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8.4, 3.6))
    lim = float(np.nanmax(np.abs(maps["signed"]))) or 1.0
    im = axes[0].imshow(maps["signed"], cmap="RdBu_r", vmin=-lim, vmax=lim)
    axes[0].set_title("mean signed log error\n(red: too far, blue: too near)")
    fig.colorbar(im, ax=axes[0], fraction=0.046)
    im = axes[1].imshow(maps["abs"], cmap="magma", vmin=0)
    ratios = ", ".join(f"{k} {v:.2f}" for k, v in maps["ratios"].items())
    axes[1].set_title(f"mean |log error|\nborder / centre: {ratios}", fontsize=9)
    fig.colorbar(im, ax=axes[1], fraction=0.046)
    for ax in axes:
        ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def evaluate_checkpoint(checkpoint: str | os.PathLike, dataset: str = "scenario_teach", *, split: str = "test",
                        root: str | os.PathLike | None = None, out_dir: str | os.PathLike | None = None,
                        device: str | None = None, batch_size: int = 8, error_maps: int = 4,
                        progress: bool = False, baselines: bool = False, flips: str = "none", **kw: Any) -> dict:
    """``evaluate_model`` for a checkpoint file on a dataset named as in ``open_eval_dataset``.

    flips: test-time flips of the network's prediction (``inference.predict_depth``).

    baselines: also score the trivial baselines (``baselines.BASELINES``) on the same frames
    and add them to the result ("baselines") and the overall table. The mean depth map is fitted
    on the dataset's own train split, else on the checkpoint's training dataset (``cfg["dataset"]``).
    """
    from geodepth_lite.checkpoint import load_model
    from geodepth_lite.inference import pick_device

    check_flips(flips)
    model, cfg = load_model(checkpoint, pick_device(device))
    ds = open_eval_dataset(dataset, split=split, root=root, progress=progress, **kw)
    max_depth = getattr(ds, "max_depth", EVAL_MAX_DEPTH)  # a public dataset's own encoding bounds the mask
    base = None
    if baselines:

        train_root, note = mean_map_training_root(ds, cfg, progress=progress)
        base = evaluate_baselines(ds, train_root, batch_size=batch_size, progress=progress, mean_map_note=note,
                                     max_depth=max_depth)
    try:
        return evaluate_model(model, ds, image_size=cfg["image_size"], batch_size=batch_size, out_dir=out_dir,
                              error_maps=error_maps, progress=progress, name=f"{dataset}/{split}", baselines=base,
                              max_depth=max_depth, flips=flips)
    except NonFiniteDepth as exc:
        raise NonFiniteDepth(f"checkpoint {checkpoint} is unusable: {exc}") from None


# --------------------------------------------------------------------------- tables and files


def fmt(x: Any, digits: int = 3) -> str:
    """A table cell: floats rounded to ``digits`` decimals, the rest as text."""
    if isinstance(x, (float, np.floating)):
        return "nan" if not np.isfinite(x) else f"{x:.{digits}f}"
    return str(x)


def markdown_table(columns: list[str], rows: Iterable[Iterable[Any]], digits: int = 3) -> str:
    """A GitHub-flavoured markdown table (floats rounded to ``digits``)."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(fmt(c, digits) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def metrics_table(result: dict, by: str | None = None) -> dict:
    """{"columns", "rows"} of the seven metrics: one row overall (plus one per baseline in
    ``result["baselines"]``), or one per group/organ."""
    columns = [by or "set", "frames"] + [METRIC_LABELS[k] for k in METRIC_KEYS]
    baselines = result.get("baselines") or {}
    if by is None and baselines:  # the model's row, then one row per baseline on the same frames
        columns[0] = "method"
        parts = {f"model ({result['name']})" if result.get("name") else "model": result["overall"]}
        parts.update({f"baseline: {k}": b["overall"] for k, b in baselines.items()})
    elif by is None:
        parts = {result.get("name") or "all": result["overall"]}
    else:
        parts = result[f"by_{by}"]
    rows = [[g, s["n"]] + [s[k] for k in METRIC_KEYS] for g, s in parts.items()]
    return {"columns": columns, "rows": rows}


OUTPUT_SET = ("metrics.json", "frames.csv", "tables.md", "error_maps")  # one evaluation's files, replaced whole
STAGING_PREFIX = ".eval-staging-"  # hidden folder in the output folder where a new set is written first
PREVIOUS_PREFIX = ".eval-previous-"  # hidden folder that holds the replaced set until the new one is in place
TABLES_BYTES = 4 * 2**20  # room asked for metrics.json, frames.csv and tables.md before any work (a few kB each)
ERROR_MAP_BYTES = 2**20  # and per error-map PNG (about 0.1-0.3 MB at dpi 80)


def output_bytes_needed(error_maps: int) -> int:
    """A generous estimate of the bytes one evaluation writes: its tables and ``error_maps`` PNGs."""
    return TABLES_BYTES + max(0, int(error_maps)) * ERROR_MAP_BYTES


def _problem_reason(exc: utils.FileProblem) -> str:
    """The reason part of a :class:`utils.FileProblem` ("no space left on device"), without its path."""
    cause = exc.__cause__
    if isinstance(cause, OSError) and not isinstance(cause, utils.FileProblem):
        return utils.os_reason(cause)
    text = str(exc)
    prefix = f"{exc.path}: " if exc.path is not None else ""
    return text.split(prefix, 1)[1] if prefix and prefix in text else text


def prepare_output_dir(out: str | os.PathLike, need_bytes: int = 0) -> Path:
    """``out`` as a writable folder with ``need_bytes`` free, checked before any work (``utils.check_output_dir``).

    Any refusal is a :class:`utils.FileProblem` reading "cannot write <out>: <reason>" (a file of
    that name, a read-only or full disk, no permission), and the folders this call created are
    removed again.
    """
    out = Path(out)
    if os.path.lexists(out) and not out.is_dir():
        raise utils.FileProblem(f"cannot write {out}: a file of that name exists (the output must be a folder)", out)
    try:
        return utils.check_output_dir(out, need_bytes)
    except utils.FileProblem as exc:
        raise utils.FileProblem(f"cannot write {out}: {_problem_reason(exc)}", out) from exc


def _hidden_folder(out: Path, prefix: str) -> Path:
    """A new empty hidden folder in ``out`` (same file system, so renames out of it are atomic)."""
    try:
        return Path(tempfile.mkdtemp(prefix=prefix, dir=out))
    except OSError as exc:
        raise utils.FileProblem(f"cannot write {out}: {utils.os_reason(exc)}", out) from exc


def _remove_stale_sets(out: Path) -> None:
    """Delete the hidden staging / previous-set folders an evaluation killed mid-write left in ``out``."""
    for prefix in (STAGING_PREFIX, PREVIOUS_PREFIX):
        for folder in out.glob(prefix + "*"):
            if folder.is_dir() and not folder.is_symlink():
                shutil.rmtree(folder, ignore_errors=True)


def _remove_path(path: Path) -> None:
    """Delete a file or a folder tree, if present."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif os.path.lexists(path):
        path.unlink()


@contextlib.contextmanager
def _staged_file(staging: Path, out: Path, name: str) -> Iterator[Path]:
    """A temporary path for ``staging/name`` (``utils.atomic_path``: flushed, renamed when complete); a
    failure is a :class:`utils.FileProblem` naming the file's final place ``out/name``."""
    try:
        with utils.atomic_path(staging / name) as tmp:
            yield tmp
    except utils.FileProblem as exc:
        raise utils.FileProblem(f"cannot write {out / name}: {_problem_reason(exc)}", out / name) from exc


def _results_files(result: dict) -> dict[str, bytes]:
    """The text files of a result: {"metrics.json": ..., "frames.csv": ..., "tables.md": ...} as bytes."""
    summary = {k: v for k, v in result.items() if k != "frames"}
    if result.get("baselines"):
        summary["baselines"] = {name: {k: v for k, v in b.items() if k != "frames"}
                                for name, b in result["baselines"].items()}
    fields = ["index", "organ", "group", *METRIC_KEYS, "ratio", "skipped"]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for r in result["frames"]:
        w.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]) for k in fields if k in r})
    skipped = result.get("skipped", [])
    md = [f"# Evaluation {result.get('name', '')}".rstrip(), "", f"{result['n']} frames; median scaling per frame."
          + (f" {len(skipped)} skipped (no valid ground-truth pixel): {', '.join(skipped)}." if skipped else ""), ""]
    for by in (None, "organ", "group"):
        t = metrics_table(result, by)
        title = "Overall" if by is None else f"By {by}" + (" (model)" if result.get("baselines") else "")
        md += [f"## {title}", "", markdown_table(t["columns"], t["rows"]), ""]
        if by is None and result.get("baselines"):
            md += ["Baselines: trivial predictors scored on the same frames with the same protocol; "
                   "a model must beat them for its numbers to mean anything.", ""]
            for name, b in result["baselines"].items():
                md.append(f"- `{name}`: {b.get('description', '')}".rstrip())
                md += [f"  - {note}" for note in b.get("notes", [])]
            md.append("")
    return {"metrics.json": (json.dumps(summary, indent=2) + "\n").encode(), "frames.csv": buf.getvalue().encode(),
            "tables.md": "\n".join(md).encode()}


def _stage_results(result: dict, staging: Path, out: Path, examples: Iterable[dict] = (), *,
                   min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH) -> None:
    """Write the whole set (``_results_files`` and one error-map PNG per example) into ``staging``."""
    for name, data in _results_files(result).items():
        with _staged_file(staging, out, name) as tmp:
            tmp.write_bytes(data)
    examples = list(examples)
    if examples:
        import matplotlib.pyplot as plt  # no backend switch: a notebook's inline figures must keep showing

        for ex in examples:
            fig = error_map_figure([ex], min_depth=min_depth, max_depth=max_depth)
            try:
                with _staged_file(staging, out, f"error_maps/{ex['index']:06d}.png") as tmp:
                    fig.savefig(tmp, format="png", dpi=80, bbox_inches="tight")
            finally:
                plt.close(fig)


def _roll_back(out: Path, previous: Path, moved_aside: list[str], placed: list[str]) -> bool:
    """Undo a half-done ``_commit_results``: remove the new files put in ``out``, move the old ones back.

    Returns whether every old file is back in place (else some are still in ``previous``)."""
    ok = True
    for name in placed:
        with contextlib.suppress(OSError):
            _remove_path(out / name)
    for name in moved_aside:
        try:
            os.replace(previous / name, out / name)
        except OSError:
            ok = False
    return ok


def _commit_results(staging: Path, out: Path) -> None:
    """Swap the set in ``staging`` for the one in ``out``: every name of ``OUTPUT_SET``, new or old, at once.

    The old set's entries are first moved aside into a hidden folder, then the new ones moved
    in, by renames within one file system (no data is written in this phase). If any rename
    fails, the new entries are removed and the old ones moved back, and a
    :class:`utils.FileProblem` is raised; on success the old set is deleted.
    """
    previous = _hidden_folder(out, PREVIOUS_PREFIX)
    moved_aside: list[str] = []
    placed: list[str] = []
    try:
        for name in OUTPUT_SET:
            if os.path.lexists(out / name):
                os.replace(out / name, previous / name)
                moved_aside.append(name)
        for name in OUTPUT_SET:
            if os.path.lexists(staging / name):
                os.replace(staging / name, out / name)
                placed.append(name)
        utils.fsync_dir(out)
    except BaseException as exc:
        restored = _roll_back(out, previous, moved_aside, placed)
        if restored:
            shutil.rmtree(previous, ignore_errors=True)
        if not isinstance(exc, OSError):
            raise
        kept = "the previous results are kept" if restored else f"the previous results are in {previous}"
        raise utils.FileProblem(f"cannot write {out}: {utils.os_reason(exc)} ({kept})", out) from exc
    shutil.rmtree(previous, ignore_errors=True)


def write_results(result: dict, out_dir: str | os.PathLike, examples: Iterable[dict] = (), *,
                  min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH) -> None:
    """metrics.json, frames.csv, tables.md and error_maps/*.png in ``out_dir``, as one set or none.

    Guarantee: when this returns, ``out_dir`` holds exactly the new set (``OUTPUT_SET``; the
    error_maps folder holds this run's PNGs only, none if there are no examples); when it raises
    (full or read-only disk, an interrupt...), ``out_dir`` holds what it held before, an earlier
    run's set untouched and nothing new, and folders this call created are removed again.

    How: every file is first written and flushed into a hidden staging folder inside
    ``out_dir``; only then is the set swapped in by renames (``_commit_results``), which move no
    data and are undone if one fails. Other files in ``out_dir`` are left alone. Not covered:
    a power loss or kill -9 during the swap itself (a few renames) can leave part of either
    set, the rest being in a hidden ``.eval-previous-*`` folder; the next write_results into
    that folder deletes such leftovers. Two evaluations writing into one folder at the same time
    are not supported.
    """
    out = Path(out_dir)
    created = utils.missing_dirs(out)
    try:
        prepare_output_dir(out)
        _remove_stale_sets(out)
        staging = _hidden_folder(out, STAGING_PREFIX)
        try:
            _stage_results(result, staging, out, examples, min_depth=min_depth, max_depth=max_depth)
            _commit_results(staging, out)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    except BaseException:
        utils.remove_empty_dirs(created)
        raise


def abs_rel_map(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None, min_depth: float = EVAL_MIN_DEPTH,
                max_depth: float = EVAL_MAX_DEPTH) -> np.ndarray:
    """Per-pixel |gt - pred| / gt (NaN outside the valid mask) of a median-scaled prediction."""
    mask = eval_mask(gt, min_depth, max_depth, valid)
    err = np.abs(gt - np.clip(pred, min_depth, max_depth)) / np.where(mask, gt, 1.0)
    return np.where(mask, err, np.nan)


def error_map_figure(examples: list[dict], columns: tuple[str, ...] = ("input", "ground truth", "prediction", "error"),
                     min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH, err_max: float = 0.5,
                     row_labels: list[str] | None = None):
    """The paper's Fig. 7 layout: one row per frame, input | GT | (median-scaled) prediction | Abs Rel map.

    Each example: {"image": HxWx3 in [0,1], "gt": HxW, "pred": HxW already median-scaled,
    optional "preds": {label: HxW} for extra prediction columns (ablation), "valid"}.
    """
    import matplotlib.pyplot as plt

    extra = list(examples[0].get("preds", {}))
    cols = ["input", "ground truth"] + (extra if extra else ["prediction"]) + (["error"] if "error" in columns else [])
    fig, axes = plt.subplots(len(examples), len(cols), figsize=(2.2 * len(cols), 2.2 * len(examples)), squeeze=False)
    for i, ex in enumerate(examples):
        gt = ex["gt"]
        finite = gt[np.isfinite(gt) & (gt > min_depth)]
        vmin, vmax = (np.percentile(finite, 2), np.percentile(finite, 98)) if finite.size else (0, 1)
        preds = ex.get("preds") or {"prediction": ex["pred"]}
        panels = [("input", ex["image"], {}), ("ground truth", gt, dict(cmap="magma_r", vmin=vmin, vmax=vmax))]
        panels += [(k, v, dict(cmap="magma_r", vmin=vmin, vmax=vmax)) for k, v in preds.items()]
        if "error" in cols:
            last = list(preds.values())[-1]
            panels.append(("Abs Rel error", abs_rel_map(last, gt, ex.get("valid"), min_depth, max_depth),
                           dict(cmap="inferno", vmin=0, vmax=err_max)))
        for j, (title, img, kw) in enumerate(panels):
            ax = axes[i, j]
            ax.imshow(np.clip(img, 0, 1) if title == "input" else img, **kw)
            ax.set_xticks([]), ax.set_yticks([])
            if i == 0:
                ax.set_title(title, fontsize=9)
        if row_labels:
            axes[i, 0].set_ylabel(row_labels[i], fontsize=8)
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------- the baselines, scored


def mean_map_training_root(dataset, cfg: dict | None = None, progress: bool = False) -> tuple[Path | None, str]:
    """Where the ``evaluate`` CLI fits the mean depth map for ``dataset``: (dataset root, note).

    The synthetic dataset's own train split when it has one; otherwise (public datasets,
    held-out sets with a test split only) the checkpoint's training dataset ``cfg["dataset"]``
    (built with ``synth.ensure_dataset`` if missing). (None, why) when neither is available.
    """
    from geodepth_lite.dataset import SyntheticDepthDataset

    base = dataset
    while isinstance(base, torch.utils.data.Subset):
        base = base.dataset
    if isinstance(base, SyntheticDepthDataset) and (base.root / "train" / "frames.jsonl").is_file():
        note = "mean depth map fitted on the evaluated dataset's own train split"
        if base.split == "train":
            note += " (the evaluated frames themselves: an optimistic row)"
        return base.root, note
    if not (cfg or {}).get("dataset"):
        return None, ("mean depth map not fitted: the dataset has no train split "
                      "and the checkpoint names no training dataset")
    from geodepth_lite.dataset import resolve_dataset

    try:
        root = resolve_dataset(cfg, progress=progress)
    except (FileNotFoundError, ValueError) as exc:
        return None, (f"mean depth map not fitted: the checkpoint's training dataset {cfg['dataset']!r} "
                      f"is unavailable ({exc})")
    return root, (f"mean depth map fitted on the checkpoint's training dataset {cfg['dataset']!r} (train split; "
                  "the evaluated dataset has no train split of its own)")


def evaluate_baselines(dataset, train_root_or_mean_map: str | os.PathLike | np.ndarray | None, *,
                       names: Iterable[str] | None = None, sigma: float = 2.0, batch_size: int = 8,
                       min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH, progress: bool = False,
                       mean_map_note: str | None = None) -> dict[str, dict]:
    """Score the baselines ``names`` (default: all of ``baselines.BASELINES``) on ``dataset`` in one pass.

    train_root_or_mean_map: a synthetic dataset folder whose train split fits the mean depth map,
    an H x W map already fitted, or None (the mean map row is then left empty: n 0, NaN).
    Returns {name: result} with the keys of ``evaluate.evaluate_model``'s result ("name", "n",
    "overall", "by_group", "by_organ", "frames") plus "description" and "notes".
    """
    names = list(baselines.BASELINES) if names is None else list(names)
    unknown = [n for n in names if n not in baselines.BASELINES]
    if unknown:
        raise ValueError(f"unknown baseline(s) {unknown}: choose from {', '.join(baselines.BASELINES)}")
    notes: dict[str, list[str]] = {n: [] for n in names}
    predictors: dict[str, Any] = {}
    skipped: set[str] = set()
    for name in names:
        if name == "constant":
            predictors[name] = baselines.constant_depth
        elif name == "shading_prior":
            predictors[name] = lambda images: baselines.shading_prior(images, sigma=sigma)
            if sigma != 2.0:
                notes[name].append(f"Gaussian sigma {sigma:g} px")
        elif name == "mean_depth_map":
            if mean_map_note:
                notes[name].append(mean_map_note)
            if train_root_or_mean_map is None:
                skipped.add(name)
                if not mean_map_note:
                    notes[name].append("mean depth map not fitted: no training depths given")
                continue
            if isinstance(train_root_or_mean_map, (str, os.PathLike)):
                root = Path(train_root_or_mean_map)
                mean_map = baselines.fit_mean_depth_map(root, "train")
                n_train = sum(1 for line in (root / "train" / "frames.jsonl").read_text().splitlines() if line.strip())
                notes[name].append(f"fitted on the {n_train} frames of {root}/train "
                                   f"at {mean_map.shape[0]}x{mean_map.shape[1]}")
            else:
                mean_map = np.asarray(train_root_or_mean_map, dtype=np.float32)
                if mean_map.ndim != 2:
                    raise ValueError(f"a mean depth map must be H x W, got shape {mean_map.shape}")
                notes[name].append(f"a given {mean_map.shape[0]}x{mean_map.shape[1]} map")
            sizes: set[tuple[int, int]] = set()

            def predict_mean(images, mean_map=mean_map, sizes=sizes):
                sizes.add(tuple(int(s) for s in images.shape[-2:]))
                return baselines.apply_mean_depth_map(images, mean_map)

            predictors[name] = predict_mean
    results = evaluate_predictors(predictors, dataset, batch_size=batch_size, min_depth=min_depth,
                                  max_depth=max_depth, progress=progress) if predictors else {}
    if "mean_depth_map" in predictors:
        other = sorted(sizes - {tuple(mean_map.shape)})
        if other:
            notes["mean_depth_map"].append("resized (nearest) to the evaluated frames: "
                                           + ", ".join(f"{h}x{w}" for h, w in other))
    out = {}
    for name in names:
        if name in skipped:
            res = {"name": name, "n": 0, "overall": summarize([]), "by_group": {}, "by_organ": {},
                   "frames": []}
        else:
            res = results[name]
        out[name] = {**res, "description": baselines.BASELINES[name], "notes": notes[name]}
    return out


# --------------------------------------------------------------------------- CLI


def add_arguments_evaluate(parser: argparse.ArgumentParser) -> None:
    from geodepth_lite import loaders

    parser.add_argument("--checkpoint", default=None, help="checkpoint.pt written by `train` (not needed with --check)")
    parser.add_argument("--dataset", default="scenario_teach",
                        help="synthetic manifest name or dataset folder, or one of " + ", ".join(loaders.REGISTRY))
    parser.add_argument("--root", default=None, help="folder of a public dataset (its own layout)")
    parser.add_argument("--check", nargs="?", const="", default=None, metavar="MANIFEST",
                        help="public datasets: only count the frames of the paper's evaluation subsets under --root "
                        "and print expected and found counts (exit 0 when all match, 1 otherwise); MANIFEST: a "
                        "subset JSON (default: the dataset's own, data_manifests/eval_subsets/<dataset>.json)")
    parser.add_argument("--split", default="test", help="split of a synthetic dataset (default test)")
    parser.add_argument("--group", default=None, help="public datasets: keep one group (e.g. T1-L1)")
    parser.add_argument("--organ", default=None, help="public datasets: keep one organ (e.g. colon)")
    parser.add_argument("--limit", type=int, default=None, help="public datasets: first N frames only")
    parser.add_argument("--out", default=None, help="output folder (default runs/eval/<dataset>-<split>)")
    parser.add_argument("--error-maps", type=int, default=4, help="number of error-map PNGs (default 4)")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--device", default=None, help="cpu | cuda (default: CUDA when available)")
    parser.add_argument("--flips", choices=tuple(FLIPS), default="none",
                        help="test-time flips averaged into each prediction: none (default, one pass as in the "
                        "paper), h (left-right) or hv (all four mirrorings; what the teach predict model uses)")
    parser.add_argument("--no-baselines", action="store_true",
                        help="skip the trivial baselines (constant, mean depth map, shading prior) in the tables")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--no-verify", action="store_true",
                        help="synthetic datasets: skip checking the files against checksums.sha256 first")


def verify_synthetic(dataset: str, split: str, *, own_train: bool = True, progress: bool = False) -> None:
    """Check a synthetic dataset's files against its checksums (``synth.check_dataset``) before any work:
    the evaluated ``split``, and its train split (where the mean-depth-map baseline is fitted) when
    ``own_train`` and the dataset has one."""
    from geodepth_lite import synth

    path = Path(dataset).expanduser()
    ds_root = (path if path.is_dir() and (path / "manifest.json").exists()
               else synth.ensure_dataset(dataset, progress=progress))
    with_train = own_train and (Path(ds_root) / "train" / "frames.jsonl").is_file()
    synth.check_dataset(ds_root, {split, "train"} if with_train else {split})


def run_evaluate(args: argparse.Namespace) -> int:
    """``evaluate``: check --out, verify the dataset, score the checkpoint, write the set of result files.

    --out is checked (a folder, writable, room for the tables) before the model is loaded; a run
    that fails leaves no folder it created behind, and never part of a result set
    (``write_results``)."""
    from geodepth_lite import loaders

    public = args.dataset in loaders.REGISTRY
    kw = {k: getattr(args, k) for k in ("group", "organ", "limit") if getattr(args, k) is not None}
    if kw and not public:
        raise ValueError(f"--{', --'.join(kw)} apply to the public datasets only, not {args.dataset!r}")
    if args.check is not None:  # the subset report only: no checkpoint, no metrics
        if not public:
            raise ValueError(f"--check applies to the public datasets ({', '.join(loaders.REGISTRY)}), "
                             f"not {args.dataset!r}")
        if kw:
            raise ValueError(f"--{', --'.join(kw)} do not apply to --check, which counts every frame under --root")
        if args.root is None:
            raise ValueError(f"--check needs --root, the folder of your copy of {args.dataset}")
        rows = loaders.dataset_class(args.dataset).check_eval_subsets(args.root, args.check or None)
        print(loaders.format_check(rows))
        return 0 if all(r["status"] == "ok" for r in rows) else 1
    if args.checkpoint is None:
        raise ValueError("--checkpoint is required (except with --check)")
    if args.error_maps < 0:
        raise ValueError(f"--error-maps must be >= 0, got {args.error_maps}")
    out = Path(args.out) if args.out else utils.runs_dir() / "eval" / f"{Path(args.dataset).name}-{args.split}"
    created = utils.missing_dirs(out)
    prepare_output_dir(out, output_bytes_needed(args.error_maps))  # before any work: a refusal costs nothing
    try:
        if not public and not args.no_verify:  # a synthetic dataset: its checksums first, before any work
            verify_synthetic(args.dataset, args.split, own_train=not args.no_baselines,
                             progress=not args.no_progress)
        result = evaluate_checkpoint(args.checkpoint, args.dataset, split=args.split, root=args.root, out_dir=out,
                                     device=args.device, batch_size=args.batch_size, error_maps=args.error_maps,
                                     progress=not args.no_progress, baselines=not args.no_baselines,
                                     flips=args.flips, **kw)
    except BaseException:
        utils.remove_empty_dirs(created)  # a failed run leaves no empty output folder behind
        raise
    t = metrics_table(result)
    print(markdown_table(t["columns"], t["rows"]))
    print(f"wrote {out / 'metrics.json'}, {out / 'frames.csv'}, {out / 'tables.md'}")
    return 0


def prediction_examples(models: dict, dataset, indices: list[int], *, min_depth: float = EVAL_MIN_DEPTH,
                        max_depth: float = EVAL_MAX_DEPTH, flips: str = "none") -> list[dict]:
    """Examples for ``error_map_figure``: frames ``indices`` of ``dataset`` predicted by each model.

    models: {label: (model, image_size)}; each prediction (with test-time ``flips``,
    ``inference.predict_depth``) is median-scaled to the frame's ground truth (as the metrics see
    it). One label gives "pred"; several give "preds".
    """
    from geodepth_lite.inference import predict_depth

    check_flips(flips)

    out = []
    for i in indices:
        item = dataset[i]
        gt = item["depth"][0].numpy()
        valid = item["valid"][0].numpy().astype(bool) if "valid" in item else None
        preds = {}
        for label, (model, size) in models.items():
            pred = predict_depth(model, item["image"][None], size, flips)[0, 0].cpu().numpy()
            ratio = _frame_metrics(pred, gt, valid, min_depth, max_depth)["ratio"]
            preds[label] = pred * ratio
        ex = {"image": item["image"].permute(1, 2, 0).numpy(), "gt": gt, "valid": valid, "index": int(item["index"])}
        if len(preds) == 1:
            ex["pred"] = next(iter(preds.values()))
        else:
            ex["preds"] = preds
            ex["pred"] = list(preds.values())[-1]
        out.append(ex)
    return out


def flat_record(tree: dict, digits: int = 4, keys: Iterable[str] = METRIC_KEYS) -> dict[str, float]:
    """A nested dict ending in metric dicts, flattened to {"a | b | metric": value rounded to ``digits``}.

    The notebooks print such a record of every number that comes from trained weights, so a
    test can compare a fresh run with the committed one within a tolerance.
    """
    out: dict[str, float] = {}

    def walk(node: dict, path: list[str]) -> None:
        if any(k in node for k in keys):
            for k in keys:
                if k in node:
                    out[" | ".join(path + [k])] = round(float(node[k]), digits)
            return
        for name, child in node.items():
            if isinstance(child, dict):
                walk(child, path + [str(name)])

    walk(tree, [])
    return out
