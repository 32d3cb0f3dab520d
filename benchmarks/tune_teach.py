"""Tuning the teach recipe: train a run and score it, or score trained runs again; one JSON line per result.

Every result is appended to ``benchmarks/tuning_log.jsonl``, the record of every run behind the
recipe's evidence tables (``benchmarks/teach_recipe.json``, ``lambda_search.json``,
``view_evidence.json``; notebook 04 and docs/teach_recipe.md show them). Choices are made on the
validation split; the test split and the held-out close-ups (``heldout_closeup``) are recorded
beside it, never used to choose. The findings of finished experiments are written up in
``docs/experiments.md``.

train (the default command: the word ``train`` may be left out)

    python benchmarks/tune_teach.py [train] NAME [--case 1] [--seed 0] [--set KEY=VALUE ...]
                                    [--network FILE.py:NAME] [--border] [--closeups]

    Trains ``config.make_config("teach", case, seed, **settings)`` into ``runs/tune/NAME`` (an
    interrupted run continues) and logs {name, case, seed, settings, the metrics on the whole
    validation split, minutes}. ``--set`` values are JSON: ``--set image_size=96 --set
    lambdas=[1,0.1,0.1]``. ``--border`` adds the validation split's border band / centre error ratios
    (``border.border_error_map``); ``--closeups`` the model's and the shading prior's Abs Rel on
    ``heldout_closeup``. ``--network FILE.py:NAME`` (or ``package.module:NAME``) trains a variant
    instead of DepthNet (``train.fit(..., network=...)``): a class taking DepthNet's keyword arguments
    (``encoder_weights``, ``padding``, ``input_pad``; e.g. a DepthNet subclass) or a callable
    ``(cfg) -> nn.Module``. The configuration does not record the network: give each variant a run
    NAME of its own, and pass the same ``--network`` to the commands below to score its run.

closeups: the recorded sets for trained runs (no training)

    python benchmarks/tune_teach.py closeups RUN [RUN ...] [--network ...] [--input-pad P]

    One row ``<NAME>_closeups`` per run: Abs Rel on ``heldout_closeup`` beside the shading prior's,
    that set's worst border band / centre, and the test split's Abs Rel and border band ratios.

flips: test-time flips (``inference.FLIPS``), the evidence for a profile's ``predict_flips`` (no training)

    python benchmarks/tune_teach.py flips RUN [RUN ...] [--flips none h hv] [--tag TAG] [--network ...]
                                          [--input-pad P]

    One row ``<NAME>_flips_<flips>`` (``..._<TAG>`` with ``--tag``) per run and flips setting: the
    validation split's Abs Rel, RMSE and border bands, predicted at the frames' own size (what a
    choice is made on), and recorded beside them Abs Rel on ``heldout_closeup`` and the test split's
    Abs Rel, worst border band and frame count.

RUN is a ``runs/tune/NAME`` folder name or the path of a checkpoint.pt (named by its folder).
``--input-pad P`` scores a run whose network mirrored its input by P px without the setting in its
configuration (runs trained before ``input_pad`` was a setting).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import runpy
import sys
import time
from pathlib import Path

import numpy as np
import torch

from geodepth_lite import utils
from geodepth_lite.core.metrics import compute_depth_metrics
from geodepth_lite.data import datasets, synth
from geodepth_lite.data import manifest as mf
from geodepth_lite.evaluation import evaluate
from geodepth_lite.evaluation.border import border_error_map
from geodepth_lite.training import checkpoint, config, inference, train

LOG = Path(__file__).with_name("tuning_log.jsonl")
COMMANDS = ("train", "closeups", "flips")
SETTINGS_RECORDED = ("image_size", "threads", "border_weight", "input_pad")  # a scored run's row
CLOSEUPS_NOTE = "no training: run {name} scored on heldout_closeup and on the test split (recorded, not for choosing)"
FLIPS_NOTE = ("no training: {name} predicted with test-time flips '{flips}'; chosen on the val_* fields, "
              "closeup_* and test_* recorded")


# --------------------------------------------------------------------------- the command line


def parse_value(text: str):
    """A ``--set`` value: JSON when it parses (numbers, lists, null), else the text itself."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def load_network(spec: str | None):
    """The class or callable named by ``FILE.py:NAME`` or ``package.module:NAME`` (None: DepthNet)."""
    if not spec:
        return None
    where, _, name = spec.rpartition(":")
    if not where or not name:
        raise SystemExit(f"tune_teach: --network wants FILE.py:NAME or package.module:NAME, got {spec!r}")
    if where.endswith(".py"):
        if not Path(where).is_file():
            raise SystemExit(f"tune_teach: --network {spec}: no file {where}")
        namespace = runpy.run_path(where, run_name="tune_teach_network")
    else:
        namespace = vars(importlib.import_module(where))
    if not callable(namespace.get(name)):
        raise SystemExit(f"tune_teach: --network {spec}: {where} has no class or function {name}")
    return namespace[name]


def describe_network(spec: str, network) -> str:
    """The log row's ``network`` field: the spec and the first line of the network's docstring."""
    doc = (getattr(network, "__doc__", None) or "").strip().splitlines()
    return f"{spec}: {doc[0]}" if doc else spec


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 epilog="python benchmarks/tune_teach.py COMMAND --help: that command's options")
    commands = ap.add_subparsers(dest="command", required=True)
    tr = commands.add_parser("train", help="train a run, score it on the validation split")
    tr.add_argument("name")
    tr.add_argument("--case", type=int, default=1)
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a training setting (JSON value), e.g. lr=3e-4, lambdas=[1,0.1,0.1]")
    tr.add_argument("--border", action="store_true",
                    help="also the validation split's border error map: each border band's mean |log error| / "
                         "the centre's")
    tr.add_argument("--closeups", action="store_true", help="also score heldout_closeup (recorded, not for choosing)")
    cl = commands.add_parser("closeups", help="score trained runs on heldout_closeup and the test split")
    fl = commands.add_parser("flips", help="score trained runs with each test-time flips setting")
    for sub in (cl, fl):
        sub.add_argument("runs", nargs="+", metavar="RUN", help="a runs/tune/NAME folder name or a checkpoint.pt path")
        sub.add_argument("--input-pad", type=int, default=None,
                         help="the mirror padding of a run trained before input_pad was a setting")
    fl.add_argument("--flips", nargs="+", choices=tuple(inference.FLIPS), default=list(inference.FLIPS))
    fl.add_argument("--tag", default="", help="appended to each row's name, e.g. to tell a new test split's rows apart")
    for sub in (tr, cl, fl):
        sub.add_argument("--network", default="", metavar="FILE.py:NAME",
                         help="a network variant instead of DepthNet (a class or a callable (cfg) -> nn.Module)")
        sub.add_argument("--log", default=str(LOG))
    return ap


def parse_args(argv=None) -> argparse.Namespace:
    """The arguments, with ``train`` put in front when no command is named, and ``settings`` (a dict)
    parsed from the ``--set`` items of ``train``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] not in (*COMMANDS, "-h", "--help"):
        argv.insert(0, "train")
    args = build_parser().parse_args(argv)
    if args.command == "train":
        args.settings = {}
        for item in args.set:
            key, _, value = item.partition("=")
            args.settings[key] = parse_value(value)
    return args


def append_row(row: dict, log: str | Path = LOG) -> None:
    """Append ``row`` to the log as one JSON line, with the CPU kernel cap it ran under, if any
    (a cap changes the trained weights)."""
    env = {k: os.environ[k] for k in ("ONEDNN_MAX_CPU_ISA",) if k in os.environ}
    if env:
        row = {**row, "env": env}
    with open(log, "a") as f:
        f.write(json.dumps(row) + "\n")
    print(json.dumps(row))


# --------------------------------------------------------------------------- runs


def train_run(name: str, case: int, seed: int, settings: dict, network=None):
    """Train (or continue) the teach recipe with ``settings`` into ``runs/tune/NAME``.

    Returns (model in eval mode, cfg, minutes spent, run folder); the torch thread count is the run's.
    """
    cfg = config.make_config("teach", case, seed, **settings)
    run_dir = utils.runs_dir() / "tune" / name
    t0 = time.perf_counter()
    ckpt = train.fit(cfg, run_dir, resume=True, progress=False, network=network)
    minutes = (time.perf_counter() - t0) / 60
    net, _, _ = load_run(str(ckpt), network)
    torch.set_num_threads(cfg["threads"] or torch.get_num_threads())
    return net, cfg, minutes, run_dir


def load_run(run: str, network=None, input_pad: int | None = None, command: str = "tune_teach"):
    """(network in eval mode, cfg, name) of a trained run: a ``runs/tune/NAME`` folder name or a
    checkpoint.pt path. Its weights load into ``network`` (``train.build_network``; None: DepthNet).
    ``input_pad``: the mirror padding of a run trained before it was a setting; a run trained with
    another padding is refused."""
    path = Path(run)
    if path.suffix == ".pt":
        name = path.parent.name
    else:
        name, path = run, utils.runs_dir() / "tune" / run / checkpoint.CHECKPOINT_NAME
    if not path.is_file():
        raise SystemExit(f"{command}: no checkpoint at {path}; train the run first (tune_teach.py {name} ...)")
    state = checkpoint.read_checkpoint(path)
    cfg = dict(state["cfg"])
    if input_pad is not None and cfg.get("input_pad", 0) != input_pad:
        if cfg.get("input_pad", 0):
            raise SystemExit(f"{command}: {name} was trained with input_pad={cfg['input_pad']}, not {input_pad}")
        cfg["input_pad"] = input_pad
    net = train.build_network({**cfg, "encoder_weights": None, "padding": cfg.get("padding", "zeros"),
                               "input_pad": int(cfg.get("input_pad", 0))}, network)
    checkpoint.load_weights(net, state["model"], path)
    return net.eval(), cfg, name


def closeup_set():
    """The teach profile's ``heldout_closeup`` test frames (recorded beside choices, never used to make them)."""
    prof = config.get_profile("teach")
    root = synth.ensure_dataset("heldout_closeup", overrides=prof["closeup_overrides"], progress=False)
    return evaluate.open_eval_dataset(str(root), split="test")


# --------------------------------------------------------------------------- scores


def validation_metrics(net, cfg: dict) -> dict:
    """The metrics of the train command's row: the whole validation split, resized to the network's
    input as in training, one pass per frame."""
    val = datasets.load_split(datasets.resolve_dataset(cfg), "val", cfg["image_size"])
    preds, gts = [], []
    with torch.no_grad():
        for i in range(0, len(val), 40):
            items = [val[j] for j in range(i, min(i + 40, len(val)))]
            preds.append(net(torch.stack([it["image"] for it in items]))[:, 0])
            gts.append(torch.stack([it["depth"] for it in items])[:, 0])
    m = compute_depth_metrics(torch.cat(preds).numpy(), torch.cat(gts).numpy())
    return {f"val_{k}": round(m[k], 4) for k in ("abs_rel", "rmse", "rmse_log", "a1")}


def border_scores(predict, frames) -> dict:
    """The border error map of ``predict`` on ``frames`` as log-row fields: band / centre ratios, the
    worst ratio, each band's mean |log error|, and the mean |log error| of the first and last 3 columns."""
    border = border_error_map(predict, frames, n_boot=0)
    columns = np.nanmean(border["abs"], axis=0)
    return {"val_border": {k: round(v, 3) for k, v in border["ratios"].items()},
            "val_border_worst": round(max(border["ratios"].values()), 3),
            "val_border_bands": {k: round(v, 4) for k, v in border["bands"].items()},
            "val_abs_first_cols": round(float(columns[:3].mean()), 3),
            "val_abs_last_cols": round(float(columns[-3:].mean()), 3)}


def score_validation(net, cfg: dict, flips: str = "none") -> dict:
    """Validation-split scores of ``net`` at the frames' own size, with test-time ``flips``
    (``inference.predict_depth``): Abs Rel, RMSE and ``border_scores``."""
    val = evaluate.open_eval_dataset(str(datasets.resolve_dataset(cfg)), split="val")

    def predict(x):
        return inference.predict_depth(net, x, cfg["image_size"], flips)

    with torch.no_grad():
        result = evaluate.evaluate_predictor(predict, val, error_maps=0)
        return {"val_abs_rel": round(result["overall"]["abs_rel"], 4),
                "val_rmse": round(result["overall"]["rmse"], 4)} | border_scores(predict, val)


def recorded_scores(predict, closeups, test) -> dict:
    """Abs Rel on the close-ups and on the test split, and the test split's border band ratios."""
    with torch.no_grad():
        close = evaluate.evaluate_predictor(predict, closeups, error_maps=0)
        t = evaluate.evaluate_predictor(predict, test, error_maps=0)
        test_border = border_error_map(predict, test, n_boot=0)
    return {"closeup_abs_rel": round(close["overall"]["abs_rel"], 4),
            "test_abs_rel": round(t["overall"]["abs_rel"], 4),
            "test_border": {k: round(v, 3) for k, v in test_border["ratios"].items()},
            "test_border_worst": round(max(test_border["ratios"].values()), 3)}


def row_head(name: str, cfg: dict) -> dict:
    """The first fields of a scored run's row."""
    return {"name": name, "case": cfg["case"], "seed": cfg["seed"],
            "settings": {k: cfg[k] for k in SETTINGS_RECORDED if k in cfg}}


def closeups_row(net, cfg: dict, name: str, closeups) -> dict:
    def predict(x):
        return inference.predict_depth(net, x, cfg["image_size"])

    test = evaluate.open_eval_dataset(cfg["dataset"], split="test")
    recorded = recorded_scores(predict, closeups, test)
    with torch.no_grad():
        prior = evaluate.evaluate_baselines(closeups, None, names=["shading_prior"])["shading_prior"]
        close_border = border_error_map(predict, closeups, n_boot=0)
    row = row_head(f"{name}_closeups", cfg) | {
        "closeup_abs_rel": recorded.pop("closeup_abs_rel"),
        "closeup_shading_prior_abs_rel": round(prior["overall"]["abs_rel"], 4),
        "closeup_border_worst": round(max(close_border["ratios"].values()), 3)}
    return row | recorded | {"generator": mf.GENERATOR_VERSION, "note": CLOSEUPS_NOTE.format(name=name)}


def flips_row(net, cfg: dict, name: str, flips: str, closeups, test, tag: str = "") -> dict:
    start = time.perf_counter()

    def predict(x):
        return inference.predict_depth(net, x, cfg["image_size"], flips)

    row = row_head(f"{name}_flips_{flips}" + (f"_{tag}" if tag else ""), cfg) | {"flips": flips}
    row |= score_validation(net, cfg, flips) | recorded_scores(predict, closeups, test)
    return row | {"test_frames": len(test), "minutes": round((time.perf_counter() - start) / 60, 2),
                  "generator": mf.GENERATOR_VERSION, "note": FLIPS_NOTE.format(name=name, flips=flips)}


# --------------------------------------------------------------------------- the commands


def run_train(args, network) -> None:
    net, cfg, minutes, run_dir = train_run(args.name, args.case, args.seed, args.settings, network)
    hist = checkpoint.read_log(run_dir)
    row = {"name": args.name, "case": args.case, "seed": args.seed, "settings": args.settings}
    if network is not None:
        row["network"] = describe_network(args.network, network)
    row |= validation_metrics(net, cfg)
    row |= {"train_depth_last": round(hist[-1]["train_depth"], 4), "minutes": round(minutes, 2),
            "frames_per_s": round(hist[-1]["train_frames_per_s"], 1), "generator": mf.GENERATOR_VERSION}
    if args.border:
        val = evaluate.open_eval_dataset(str(datasets.resolve_dataset(cfg)), split="val")
        with torch.no_grad():
            row |= border_scores(lambda x: inference.predict_depth(net, x, cfg["image_size"]), val)
    if args.closeups:
        closeups = closeup_set()
        with torch.no_grad():
            r = evaluate.evaluate_model(net, closeups, image_size=cfg["image_size"], error_maps=0)
            prior = evaluate.evaluate_baselines(closeups, None, names=["shading_prior"])["shading_prior"]
        row["closeup_abs_rel"] = round(r["overall"]["abs_rel"], 4)
        row["closeup_shading_prior_abs_rel"] = round(prior["overall"]["abs_rel"], 4)
    append_row(row, args.log)


def main(argv=None) -> int:
    args = parse_args(argv)
    network = load_network(args.network)
    if args.command == "train":
        run_train(args, network)
        return 0
    torch.set_num_threads(1)
    closeups = closeup_set()
    for run in args.runs:
        net, cfg, name = load_run(run, network, args.input_pad, f"tune_teach {args.command}")
        if args.command == "closeups":
            append_row(closeups_row(net, cfg, name, closeups), args.log)
            continue
        test = evaluate.open_eval_dataset(cfg["dataset"], split="test")
        for flips in args.flips:
            append_row(flips_row(net, cfg, name, flips, closeups, test, args.tag), args.log)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
