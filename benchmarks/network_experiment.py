"""Shared by the network experiments in benchmarks/: train a variant of DepthNet with the teach
recipe and score it on the validation split (Abs Rel, RMSE, the border error map).

``run(network_class, description, argv)`` is the whole command line of such a script:

    python benchmarks/exp_<name>.py NAME [--set image_size=96] [--case 4] [--seed 0]

The model is trained into ``runs/tune/NAME`` and one row is appended to
``benchmarks/tuning_log.jsonl``. The package's network is not changed: the variant replaces
``model.DepthNet`` for this process only (``train.fit`` and ``checkpoint.load_model`` build the
network from there).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from geodepth_lite import checkpoint, config, dataset, evaluate, inference, model, synth, train, utils

LOG = Path(__file__).with_name("tuning_log.jsonl")


def border_scores(predict, val) -> dict:
    """The border error map of ``predict`` on ``val`` as log-row fields: band / centre ratios, the
    worst ratio, each band's mean |log error|, and the mean |log error| of the first and last 3 columns."""
    border = evaluate.border_error_map(predict, val)
    columns = np.nanmean(border["abs"], axis=0)
    return {"val_border": {k: round(v, 3) for k, v in border["ratios"].items()},
            "val_border_worst": round(max(border["ratios"].values()), 3),
            "val_border_bands": {k: round(v, 4) for k, v in border["bands"].items()},
            "val_abs_first_cols": round(float(columns[:3].mean()), 3),
            "val_abs_last_cols": round(float(columns[-3:].mean()), 3)}


def score_validation(net, cfg: dict, flips: str = "none") -> dict:
    """Validation-split scores of ``net`` at the frames' own size, with test-time ``flips``
    (``inference.predict_depth``): Abs Rel, RMSE and ``border_scores``."""
    val = evaluate.open_eval_dataset(str(dataset.resolve_dataset(cfg)), split="val")
    with torch.no_grad():
        def predict(x):
            return inference.predict_depth(net, x, cfg["image_size"], flips)

        result = evaluate.evaluate_predictor(predict, val, error_maps=0)
        return {"val_abs_rel": round(result["overall"]["abs_rel"], 4),
                "val_rmse": round(result["overall"]["rmse"], 4)} | border_scores(predict, val)


def train_tune_run(name: str, case: int, seed: int, settings: dict):
    """Train (or resume) the teach recipe with ``settings`` into ``runs/tune/NAME``.

    Returns (model in eval mode, cfg, minutes spent, run folder); the torch thread count is the run's.
    """
    cfg = config.make_config("teach", case, seed, **settings)
    run_dir = utils.runs_dir() / "tune" / name
    t0 = time.perf_counter()
    ckpt = train.fit(cfg, run_dir, resume=True, progress=False)
    minutes = (time.perf_counter() - t0) / 60
    net, _ = checkpoint.load_model(ckpt)
    torch.set_num_threads(cfg["threads"] or torch.get_num_threads())
    return net, cfg, minutes, run_dir


def load_tune_run(run: str, input_pad: int | None = None, script: str = "score"):
    """(network, cfg, name) of a trained run: a ``runs/tune/NAME`` folder name or a checkpoint.pt path
    (named by its folder). ``input_pad`` is for runs of ``exp_padded_training.py``, whose network mirrors
    its input without the setting in its configuration; a run trained with another padding is refused."""
    path = Path(run)
    if path.suffix == ".pt":
        name = path.parent.name
    else:
        name, path = run, utils.runs_dir() / "tune" / run / checkpoint.CHECKPOINT_NAME
    if not path.is_file():
        raise SystemExit(f"{script}: no checkpoint at {path}; train the run first (tune_teach.py {name} ...)")
    net, cfg = checkpoint.load_model(path)
    if input_pad is not None and cfg.get("input_pad", 0) != input_pad:
        if cfg.get("input_pad", 0):
            raise SystemExit(f"{script}: {name} was trained with input_pad={cfg['input_pad']}, not {input_pad}")
        cfg["input_pad"] = net.input_pad = input_pad
    return net, cfg, name


def append_row(row: dict, log: str | Path = LOG) -> None:
    """Append ``row`` to the log as one JSON line, with the CPU kernel cap it ran under, if any
    (a cap changes the trained weights)."""
    env = {k: os.environ[k] for k in ("ONEDNN_MAX_CPU_ISA",) if k in os.environ}
    if env:
        row = {**row, "env": env}
    with open(log, "a") as f:
        f.write(json.dumps(row) + "\n")
    print(json.dumps(row))


def run(network_class, description: str, argv=None, doc: str = "") -> int:
    ap = argparse.ArgumentParser(description=doc.splitlines()[0] if doc else description)
    ap.add_argument("name")
    ap.add_argument("--case", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a training setting (JSON value)")
    ap.add_argument("--log", default=str(LOG))
    args = ap.parse_args(argv)
    settings = {k: json.loads(v) for k, _, v in (s.partition("=") for s in args.set)}
    model.DepthNet = network_class
    net, cfg, minutes, _ = train_tune_run(args.name, args.case, args.seed, settings)
    row = {"name": args.name, "case": args.case, "seed": args.seed, "settings": settings, "network": description}
    row |= score_validation(net, cfg)
    row |= {"minutes": round(minutes, 2), "generator": synth.GENERATOR_VERSION}
    append_row(row, args.log)
    return 0
