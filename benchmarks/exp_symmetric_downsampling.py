"""Experiment: does a downsampling that treats both image edges alike remove the border bias?

    python benchmarks/exp_symmetric_downsampling.py NAME [--set image_size=96] [--case 4] [--seed 0]

With padding 1 on even sizes, each stride-2 convolution and the max-pool of the ResNet18
encoder centre their windows on columns 0, 2, ..., W-2: they see the zero padding at the left
and top edges and never at the right and bottom, and the 1x1 stride-2 shortcuts skip the last
column. Here every stride-2 operation becomes its stride-1 version followed by 2x2 average
pooling (windows centred at 0.5, 2.5, ..., W-1.5: both edges alike), the same number of
parameters. The model is trained with the teach recipe into ``runs/tune/NAME`` and scored on
the validation split (Abs Rel, and the border error map's band / centre ratios and per-column
error); the row is appended to ``benchmarks/tuning_log.jsonl``. The package's network is not
changed: this is the measurement a change would start from.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from geodepth_lite import checkpoint, config, dataset, evaluate, inference, model, synth, train, utils

LOG = Path(__file__).with_name("tuning_log.jsonl")
BaseDepthNet = model.DepthNet


def symmetric(conv: nn.Conv2d) -> nn.Sequential:
    """A stride-2 convolution as the same convolution at stride 1, then 2x2 average pooling."""
    conv.stride = (1, 1)
    return nn.Sequential(conv, nn.AvgPool2d(2))


class SymmetricDepthNet(BaseDepthNet):
    """DepthNet whose encoder downsamples by stride-1 operations and 2x2 average pooling."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        e = self.encoder
        e.conv1 = symmetric(e.conv1)
        e.maxpool = nn.Sequential(nn.MaxPool2d(3, 1, 1), nn.AvgPool2d(2))
        for layer in (e.layer2, e.layer3, e.layer4):
            block = layer[0]
            block.conv1 = symmetric(block.conv1)
            conv, bn = block.downsample
            conv.stride = (1, 1)
            block.downsample = nn.Sequential(nn.AvgPool2d(2), conv, bn)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("name")
    ap.add_argument("--case", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a training setting (JSON value)")
    ap.add_argument("--log", default=str(LOG))
    args = ap.parse_args(argv)
    settings = {k: json.loads(v) for k, _, v in (s.partition("=") for s in args.set)}
    model.DepthNet = SymmetricDepthNet  # train.fit and checkpoint.load_model build the network from here
    cfg = config.make_config("teach", args.case, args.seed, **settings)
    run_dir = utils.runs_dir() / "tune" / args.name
    t0 = time.perf_counter()
    ckpt = train.fit(cfg, run_dir, resume=True, progress=False)
    minutes = (time.perf_counter() - t0) / 60
    net, _ = checkpoint.load_model(ckpt)
    torch.set_num_threads(cfg["threads"] or torch.get_num_threads())
    val = evaluate.open_eval_dataset(str(dataset.resolve_dataset(cfg)), split="val")
    with torch.no_grad():
        def predict(x):
            return inference.predict_depth(net, x, cfg["image_size"])

        result = evaluate.evaluate_predictor(predict, val, error_maps=0)
        border = evaluate.border_error_map(predict, val)
    columns = np.nanmean(border["abs"], axis=0)
    row = {"name": args.name, "case": args.case, "seed": args.seed, "settings": settings,
           "network": "encoder downsampling: stride-1 operations + 2x2 average pooling (symmetric edges)",
           "val_abs_rel": round(result["overall"]["abs_rel"], 4), "val_rmse": round(result["overall"]["rmse"], 4),
           "val_border": {k: round(v, 3) for k, v in border["ratios"].items()},
           "val_border_worst": round(max(border["ratios"].values()), 3),
           "val_abs_first_cols": round(float(columns[:3].mean()), 3),
           "val_abs_last_cols": round(float(columns[-3:].mean()), 3),
           "minutes": round(minutes, 2), "generator": synth.GENERATOR_VERSION}
    with open(args.log, "a") as f:
        f.write(json.dumps(row) + "\n")
    print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
