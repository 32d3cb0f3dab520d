"""What the border excess of a trained model is made of, per view kind (no training).

    python benchmarks/exp_border_anatomy.py CHECKPOINT [--flips hv] [--split test] [--dataset D] [--name NAME]

e.g. CHECKPOINT = runs/teach/checkpoints/case4_seed0-6c4b6bb6/checkpoint.pt, the teach ``predict`` model.

For each frame of the split (of the checkpoint's own dataset, or of ``--dataset``, e.g. a folder
made by ``synth.ensure_dataset(name, overrides=...)``: the same frames with one appearance range
held fixed), the prediction is median-scaled as the metrics see it and e = log(pred) - log(gt);
the regions are ``evaluate.band_regions``'s. Per view kind it prints, and appends as one row to
``benchmarks/tuning_log.jsonl``:

- ``ratio``: the worst band's mean |e| over the centre's (``evaluate.border_error_map``'s figure);
  the other figures are for that same band:
- ``spread``: the same ratio for |log gt - the frame's median log gt|, i.e. how much farther from
  the frame's typical depth the band's true depths lie than the centre's (the depth range is
  where a scale-free prediction has something to get wrong);
- ``coherence``: mean over frames and bands of |mean e in the band| / mean |e| in the band. Near 1,
  a frame's band is wrong as a whole (too near or too far throughout); near 0, pixel noise;
- ``ratio_contrast``: the ratio left once each frame's own log-depth contrast and offset are
  fitted to its ground truth (least squares, an oracle with two numbers per frame);
- ``floor_share``: the band's mean |e| of the ground truth itself, resized to the network's input
  (nearest, as the training frames) and back (bilinear, as ``inference.predict_depth``), as a
  share of the model's: what resolution alone costs there.

And over the wall-facing and close-up frames, the correlation of each frame's mean signed band
error with its appearance record's camera ``gamma``, ``exposure_stops`` and ``vignetting``.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
import network_experiment  # noqa: E402

from geodepth_lite import checkpoint, evaluate, inference  # noqa: E402

BANDS = evaluate.BORDER_BANDS


def frame_stats(pred: np.ndarray, gt: np.ndarray, small: np.ndarray) -> dict | None:
    """Region means of one frame (H x W float64 arrays; ``small`` the ground truth resized to the
    network's input and back): {region: {"abs", "signed", "spread", "contrast", "floor"}}."""
    v = (gt > evaluate.EVAL_MIN_DEPTH) & (gt < evaluate.EVAL_MAX_DEPTH) & (pred > 0) & np.isfinite(pred)
    if not v.any():
        return None
    lg = np.log(np.where(v, gt, 1.0))
    lp = np.log(np.where(v, pred, 1.0))
    e = lp + np.log(np.median(gt[v]) / np.median(pred[v])) - lg  # the median-scaled prediction's log error
    m = np.median(lg[v])
    a, c = np.linalg.lstsq(np.stack([lg[v] - m, np.ones(v.sum())], 1), lp[v], rcond=None)[0]
    rest = lp - (a * (lg - m) + c)  # what is left once the frame's own contrast and offset are allowed
    floor = np.log(np.where(v, small, 1.0)) - lg
    out = {}
    for name, r in evaluate.band_regions(*gt.shape).items():
        vv = v[r]
        if not vv.any():
            return None
        out[name] = {"abs": np.abs(e[r][vv]).mean(), "signed": e[r][vv].mean(), "spread": np.abs(lg[r][vv] - m).mean(),
                     "contrast": np.abs(rest[r][vv]).mean(), "floor": np.abs(floor[r][vv]).mean()}
    return out


def summarize(stats: list[dict]) -> dict:
    """Worst-band ratios (bands chosen by ``abs``) and the coherence of a list of frame_stats."""
    def means(key):
        return {r: float(np.mean([s[r][key] for s in stats])) for r in (*BANDS, "centre")}

    absolute = means("abs")
    worst = max(BANDS, key=lambda b: absolute[b])
    row = {"frames": len(stats), "worst": worst}
    for key, label in (("abs", "ratio"), ("spread", "spread"), ("contrast", "ratio_contrast")):
        m = means(key)
        row[label] = round(m[worst] / m["centre"], 3) if m["centre"] > 0 else None
    row["floor_share"] = round(means("floor")[worst] / absolute[worst], 3) if absolute[worst] > 0 else None
    row["coherence"] = round(float(np.mean([abs(s[b]["signed"]) / s[b]["abs"] for s in stats for b in BANDS
                                            if s[b]["abs"] > 0])), 3)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--flips", default="hv", choices=tuple(inference.FLIPS))
    ap.add_argument("--split", default="test")
    ap.add_argument("--dataset", default="", help="a dataset folder or manifest name (default: the checkpoint's own)")
    ap.add_argument("--name", default="", help="the log row's name (default: the checkpoint's folder)")
    ap.add_argument("--log", default=str(network_experiment.LOG))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    net, cfg = checkpoint.load_model(args.checkpoint)
    ds = evaluate.open_eval_dataset(args.dataset or cfg["dataset"], split=args.split)
    size = cfg["image_size"]
    loader = torch.utils.data.DataLoader(ds, batch_size=8, shuffle=False, collate_fn=inference.collate)
    per_view: dict[str, list] = {}
    signed, appearance = [], []
    for batch in loader:
        pred = inference.predict_depth(net, batch["image"], size, args.flips)[:, 0].double().numpy()
        depth = batch["depth"]
        small = F.interpolate(F.interpolate(depth, size=(size, size), mode="nearest-exact"), size=depth.shape[-2:],
                              mode="bilinear", align_corners=False)[:, 0].double().numpy()
        gt = depth[:, 0].double().numpy()
        for j in range(gt.shape[0]):
            frame = ds.frames[int(batch["index"][j])]
            s = frame_stats(pred[j], gt[j], small[j])
            if s is None:
                continue
            view = frame.get("view", "")
            per_view.setdefault(view, []).append(s)
            if view in ("wall", "closeup"):
                signed.append(np.mean([s[b]["signed"] for b in BANDS]))
                appearance.append(frame.get("appearance", {}))
    everything = [s for stats in per_view.values() for s in stats]
    row = {"name": (args.name or Path(args.checkpoint).parent.name) + f"_border_anatomy_{args.split}",
           "case": cfg["case"], "seed": cfg["seed"], "flips": args.flips, "split": args.split,
           "dataset": Path(args.dataset).name if args.dataset else cfg["dataset"],
           "settings": {k: cfg[k] for k in ("image_size", "border_weight", "input_pad") if k in cfg},
           # which weights: a retrain on another CPU gives other ones
           "checkpoint_sha256": hashlib.sha256(Path(args.checkpoint).read_bytes()).hexdigest()[:16],
           "all": summarize(everything), "by_view": {v: summarize(s) for v, s in sorted(per_view.items())}}
    for key in ("gamma", "exposure_stops", "vignetting"):
        x = np.array([np.nan if a.get(key) is None else a[key] for a in appearance], float)
        ok = np.isfinite(x)
        if ok.sum() > 2 and np.ptp(x[ok]) > 0:  # a field held fixed has no correlation to give
            r = np.corrcoef(x[ok], np.array(signed)[ok])[0, 1]
            row[f"wall_closeup_corr_signed_band_{key}"] = round(float(r), 3)
    print(evaluate.markdown_table(
        ["view", "frames", "worst band", "band / centre |e|", "band / centre spread of true log depth",
         "coherence", "band / centre after per-frame contrast", "resolution's share of the band's |e|"],
        [[v, r["frames"], r["worst"], r["ratio"], r["spread"], r["coherence"], r["ratio_contrast"], r["floor_share"]]
         for v, r in (("all", row["all"]), *row["by_view"].items())], digits=2))
    network_experiment.append_row(row, args.log)
    return 0


if __name__ == "__main__":
    sys.exit(main())
