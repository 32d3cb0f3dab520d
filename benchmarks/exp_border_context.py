"""Experiment: is the network's border error caused by where a pixel lies in the input?

    python benchmarks/exp_border_context.py CHECKPOINT [--crop 96] [--offset 32]

The same pixels are predicted twice, both at the validation frames' own scale (no resizing):
once inside the whole frame, and once in a crop whose border runs through them (a crop of
``--crop`` pixels starting ``--offset`` pixels in from the left, right, top or bottom edge). Each
prediction is median-scaled over the crop's pixels. If the error of those pixels rises when they
sit at the input's border, position (the context cut off there, the padding) causes it; the
crop's own centre pixels, also predicted twice, show how much the crop costs everywhere.
Prints, per side, the mean |log error| of the band pixels (the outer 10% of the crop) and of the
crop's centre (its middle half in both axes), inside the whole frame and inside the crop.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from geodepth_lite import checkpoint, dataset, evaluate
from geodepth_lite.inference import collate
from geodepth_lite.metrics import EVAL_MAX_DEPTH, EVAL_MIN_DEPTH

SIDES = ("left", "right", "top", "bottom")


def crop_windows(height: int, width: int, crop: int, offset: int) -> dict:
    """side -> (rows, cols) of a crop x crop window whose ``side`` edge lies ``offset`` px inside the frame."""
    y0, x0 = (height - crop) // 2, (width - crop) // 2
    mid_y, mid_x = slice(y0, y0 + crop), slice(x0, x0 + crop)
    return {"left": (mid_y, slice(offset, offset + crop)),
            "right": (mid_y, slice(width - offset - crop, width - offset)),
            "top": (slice(offset, offset + crop), mid_x),
            "bottom": (slice(height - offset - crop, height - offset), mid_x)}


def regions(crop: int, side: str) -> dict:
    b = max(1, round(0.1 * crop))
    band = {"left": (slice(None), slice(0, b)), "right": (slice(None), slice(crop - b, crop)),
            "top": (slice(0, b), slice(None)), "bottom": (slice(crop - b, crop), slice(None))}[side]
    return {"band": band, "centre": (slice(crop // 4, crop - crop // 4), slice(crop // 4, crop - crop // 4))}


def abs_log_error(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray) -> np.ndarray:
    scale = np.median(gt[valid]) / np.median(pred[valid])
    return np.abs(np.log(pred * scale) - np.log(np.where(valid, gt, 1.0)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--crop", type=int, default=96, help="crop side in pixels (a multiple of 32)")
    ap.add_argument("--offset", type=int, default=32, help="how far inside the frame the crop's edge lies")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    net, cfg = checkpoint.load_model(args.checkpoint)
    net.eval()
    val = evaluate.open_eval_dataset(str(dataset.resolve_dataset(cfg)), split="val")
    loader = torch.utils.data.DataLoader(val, batch_size=8, shuffle=False, collate_fn=collate)
    sums = {}  # (side, region, "frame"|"crop") -> [sum of |e|, count]
    with torch.no_grad():
        for batch in loader:
            image, gt = batch["image"], batch["depth"][:, 0].double().numpy()
            valid = (gt > EVAL_MIN_DEPTH) & (gt < EVAL_MAX_DEPTH)
            whole = net(image)[:, 0].double().numpy()
            for side, (ys, xs) in crop_windows(*image.shape[-2:], args.crop, args.offset).items():
                cropped = net(image[:, :, ys, xs])[:, 0].double().numpy()
                for j in range(image.shape[0]):
                    g, v = gt[j][ys, xs], valid[j][ys, xs]
                    if not v.any():
                        continue
                    for where, pred in (("frame", whole[j][ys, xs]), ("crop", cropped[j])):
                        e = abs_log_error(pred, g, v)
                        for name, r in regions(args.crop, side).items():
                            acc = sums.setdefault((side, name, where), [0.0, 0])
                            acc[0] += float(e[r][v[r]].sum())
                            acc[1] += int(v[r].sum())
    mean = {k: s / max(n, 1) for k, (s, n) in sums.items()}
    print(f"{cfg['image_size']} px model, validation frames at their own size, crops of {args.crop} px "
          f"{args.offset} px inside the edge; mean |log error|")
    print("| crop's side | its band: in the whole frame | at the crop's border | x | crop centre: in the whole frame "
          "| in the crop | x |")
    print("|---|---|---|---|---|---|---|")
    for side in SIDES:
        b0, b1 = mean[(side, "band", "frame")], mean[(side, "band", "crop")]
        c0, c1 = mean[(side, "centre", "frame")], mean[(side, "centre", "crop")]
        print(f"| {side} | {b0:.4f} | {b1:.4f} | {b1 / b0:.2f} | {c0:.4f} | {c1:.4f} | {c1 / c0:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
