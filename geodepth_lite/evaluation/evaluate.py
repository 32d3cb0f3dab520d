"""Evaluation of a trained model with the seven depth metrics (paper Section 4.2.1): scoring.

Protocol (monodepth2 / AF-SfMLearner, shared by every table of the workbook):
the prediction is resized to the ground truth's size, pixels with
``min_depth < gt < max_depth`` (and the dataset's ``valid`` mask, if any) are kept,
the prediction is median-scaled per frame (the paper's Eq. in Section 4.2.1),
clamped, and the seven metrics (Abs Rel, Sq Rel, RMSE, RMSE log, a1, a2, a3) are
computed per frame by ``metrics.compute_depth_metrics`` and averaged over frames,
overall and per group (organ; texture x lighting group).

``evaluate_model`` is what the notebooks call: it returns plain dicts (no pandas)
and, given ``out_dir``, writes ``metrics.json``, ``frames.csv`` (one row per
frame), ``tables.md`` and error-map PNGs laid out like the paper's Fig. 7, as one set:
all of them or, on a failure, none (``tables.write_results``).
It is ``evaluate_predictor`` for a network: any function images -> depth is scored
the same way, which is how the trivial baselines of ``baselines.py`` get their rows
(``evaluate_baselines``).

Beside it: ``tables.py`` (tables and result files), ``border.py`` (the border error map),
``viz.py`` (error-map figures) and ``evaluate_cli.py`` (the ``evaluate`` command).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
import torch
from tqdm.auto import tqdm

from geodepth_lite.core.errors import UserError
from geodepth_lite.core.metrics import EVAL_MAX_DEPTH, EVAL_MIN_DEPTH, METRIC_NAMES, compute_depth_metrics, eval_mask
from geodepth_lite.data import datasets, synth
from geodepth_lite.data.datasets import SyntheticDepthDataset, resolve_dataset
from geodepth_lite.evaluation import baselines
from geodepth_lite.evaluation.tables import write_results
from geodepth_lite.training import checkpoint as checkpoints  # evaluate_checkpoint's argument is named checkpoint
from geodepth_lite.training.inference import check_flips, collate, pick_device, predict_depth

METRIC_KEYS = METRIC_NAMES  # the seven metrics of Section 4.2.1, named once in core/metrics.py


# --------------------------------------------------------------------------- datasets


def open_eval_dataset(name: str, *, split: str = "test", root: str | os.PathLike | None = None,
                      progress: bool = False, **kw: Any):
    """A dataset to evaluate on, at its native resolution.

    name: a synthetic manifest name (built on demand with ``synth.ensure_dataset``), a
    synthetic dataset directory, or one of the public datasets (``datasets.REGISTRY``; needs
    ``root``, read by ``datasets.open_dataset``, extra keywords such as ``group``/``organ``/
    ``limit`` passed on; its ``max_depth``, the largest depth its encoding holds, bounds the
    evaluation mask). ``split`` applies to synthetic datasets.
    """
    if name in datasets.REGISTRY:
        if root is None:
            raise UserError(f"--root is required for the public dataset {name!r} (the folder you downloaded)")
        return datasets.open_dataset(name, root, **kw)
    path = Path(name).expanduser()
    if path.is_dir() and (path / "manifest.json").exists():
        ds_root = path
    else:
        ds_root = Path(synth.ensure_dataset(name, overrides=kw.pop("overrides", None), progress=progress))
    if not (ds_root / split).is_dir():
        have = sorted(p.name for p in ds_root.iterdir() if (p / "frames.jsonl").exists())
        raise UserError(f"split {split!r} not in {ds_root}; available: {', '.join(have) or 'none'}")
    return SyntheticDepthDataset(ds_root, split)


# --------------------------------------------------------------------------- evaluation


def _frame_metrics(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None, min_depth: float,
                   max_depth: float) -> dict:
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


def as_depth_batch(pred: Any) -> np.ndarray:
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
            pred = as_depth_batch(predict_fn(batch["image"]))
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
        raise UserError(f"no frame of the {n} evaluated has a valid ground-truth pixel (depth in "
                         f"({min_depth:g}, {max_depth:g}), finite)" if n else "the dataset has no frame")
    results = {}
    for name, rs in rows.items():
        frames = sorted(rs + skipped[name], key=_frame_order) if skipped[name] else rs
        results[name] = {"name": name, "n": len(rs), "overall": summarize(rs), "by_group": summarize(rs, "group"),
                         "by_organ": summarize(rs, "organ"), "frames": frames,
                         "skipped": [frame_name(dataset, r["index"]) for r in skipped[name]]}
    return results, examples


class NonFiniteDepth(UserError):
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
    (``tables.write_results``).
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
    check_flips(flips)

    def predict_fn(images: torch.Tensor) -> torch.Tensor:
        return predict_depth(model, images, image_size, flips).cpu()

    return evaluate_predictor(predict_fn, dataset, batch_size=batch_size, out_dir=out_dir, error_maps=error_maps,
                              min_depth=min_depth, max_depth=max_depth, progress=progress, name=name,
                              baselines=baselines)


def prediction_examples(models: dict, dataset, indices: list[int], *, min_depth: float = EVAL_MIN_DEPTH,
                        max_depth: float = EVAL_MAX_DEPTH, flips: str = "none") -> list[dict]:
    """Examples for ``viz.error_map_figure``: frames ``indices`` of ``dataset`` predicted by each model.

    models: {label: (model, image_size)}; each prediction (with test-time ``flips``,
    ``inference.predict_depth``) is median-scaled to the frame's ground truth (as the metrics see
    it). One label gives "pred"; several give "preds".
    """
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
    check_flips(flips)
    model, cfg = checkpoints.load_model(checkpoint, pick_device(device))
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


# --------------------------------------------------------------------------- the baselines, scored


def mean_map_training_root(dataset, cfg: dict | None = None, progress: bool = False) -> tuple[Path | None, str]:
    """Where the ``evaluate`` CLI fits the mean depth map for ``dataset``: (dataset root, note).

    The synthetic dataset's own train split when it has one; otherwise (public datasets,
    held-out sets with a test split only) the checkpoint's training dataset ``cfg["dataset"]``
    (built with ``synth.ensure_dataset`` if missing). (None, why) when neither is available.
    """
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
    Returns {name: result} with the keys of ``evaluate_model``'s result ("name", "n",
    "overall", "by_group", "by_organ", "frames") plus "description" and "notes".
    """
    names = list(baselines.BASELINES) if names is None else list(names)
    unknown = [n for n in names if n not in baselines.BASELINES]
    if unknown:
        raise UserError(f"unknown baseline(s) {unknown}: choose from {', '.join(baselines.BASELINES)}")
    notes: dict[str, list[str]] = {n: [] for n in names}
    predictors: dict[str, Any] = {}
    sizes: set[tuple[int, int]] = set()  # the frame sizes the mean depth map was applied at
    mean_map = None
    for name in names:
        if name == "constant":
            predictors[name] = baselines.constant_depth
        elif name == "shading_prior":
            predictors[name] = lambda images: baselines.shading_prior(images, sigma=sigma)
            if sigma != 2.0:
                notes[name].append(f"Gaussian sigma {sigma:g} px")
        elif name == "mean_depth_map":
            mean_map = _mean_depth_map(train_root_or_mean_map, mean_map_note, notes[name])
            if mean_map is not None:
                predictors[name] = _mean_map_predictor(mean_map, sizes)
    results = evaluate_predictors(predictors, dataset, batch_size=batch_size, min_depth=min_depth,
                                  max_depth=max_depth, progress=progress) if predictors else {}
    if "mean_depth_map" in predictors:
        other = sorted(sizes - {tuple(mean_map.shape)})
        if other:
            notes["mean_depth_map"].append("resized (nearest) to the evaluated frames: "
                                           + ", ".join(f"{h}x{w}" for h, w in other))
    out = {}
    for name in names:
        if name not in predictors:  # the mean depth map, not fitted: an empty row
            res = {"name": name, "n": 0, "overall": summarize([]), "by_group": {}, "by_organ": {},
                   "frames": []}
        else:
            res = results[name]
        out[name] = {**res, "description": baselines.BASELINES[name], "notes": notes[name]}
    return out


def _mean_depth_map(source: str | os.PathLike | np.ndarray | None, note: str | None,
                    notes: list[str]) -> np.ndarray | None:
    """The mean depth map of ``evaluate_baselines``: fitted on the train split of ``source`` (a dataset
    folder), or ``source`` itself (an H x W map); None when ``source`` is None. Says which in ``notes``."""
    if note:
        notes.append(note)
    if source is None:
        if not note:
            notes.append("mean depth map not fitted: no training depths given")
        return None
    if isinstance(source, (str, os.PathLike)):
        root = Path(source)
        mean_map = baselines.fit_mean_depth_map(root, "train")
        n_train = sum(1 for line in (root / "train" / "frames.jsonl").read_text().splitlines() if line.strip())
        notes.append(f"fitted on the {n_train} frames of {root}/train "
                     f"at {mean_map.shape[0]}x{mean_map.shape[1]}")
    else:
        mean_map = np.asarray(source, dtype=np.float32)
        if mean_map.ndim != 2:
            raise ValueError(f"a mean depth map must be H x W, got shape {mean_map.shape}")
        notes.append(f"a given {mean_map.shape[0]}x{mean_map.shape[1]} map")
    return mean_map


def _mean_map_predictor(mean_map: np.ndarray, sizes: set[tuple[int, int]]) -> Callable:
    """The mean depth map as a predictor, noting in ``sizes`` each frame size it is applied at."""

    def predict_mean(images):
        sizes.add(tuple(int(s) for s in images.shape[-2:]))
        return baselines.apply_mean_depth_map(images, mean_map)

    return predict_mean
