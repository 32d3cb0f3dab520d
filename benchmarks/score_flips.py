"""Test-time flips (``inference.FLIPS``) for trained runs: the evidence for a profile's ``predict_flips``.

    python benchmarks/score_flips.py RUN [RUN ...] [--input-pad P] [--flips none h hv] [--tag TAG]

RUN is a ``runs/tune/NAME`` folder name or the path of a checkpoint.pt (e.g. the teach ``predict``
model in ``runs/teach/checkpoints``). For each run and each flips setting one row named
``<NAME>_flips_<flips>`` (``..._<TAG>`` with ``--tag``) is appended to ``benchmarks/tuning_log.jsonl``:
the validation split's Abs Rel, RMSE and border band ratios (what a choice is made on), and, recorded
beside them, Abs Rel on the teach profile's ``heldout_closeup`` set and the test split's Abs Rel, worst
border band and frame count.
No weights change: the same network predicts each frame as the mean over the mirrorings.
``--input-pad`` is for runs of ``exp_padded_training.py``, whose network mirrors its input without
the setting in its configuration.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import network_experiment  # noqa: E402

from geodepth_lite import config, evaluate, inference, synth  # noqa: E402

RECORD_NOTE = ("no training: {name} predicted with test-time flips '{flips}'; chosen on the val_* fields, "
               "closeup_* and test_* recorded")


def score(net, cfg: dict, name: str, flips: str, closeups, test, tag: str = "") -> dict:
    start = time.perf_counter()
    row = {"name": f"{name}_flips_{flips}" + (f"_{tag}" if tag else ""), "case": cfg["case"], "seed": cfg["seed"],
           "flips": flips,
           "settings": {k: cfg[k] for k in ("image_size", "threads", "border_weight", "input_pad") if k in cfg}}
    row |= network_experiment.score_validation(net, cfg, flips)

    def predict(x):
        return inference.predict_depth(net, x, cfg["image_size"], flips)

    with torch.no_grad():
        close = evaluate.evaluate_predictor(predict, closeups, error_maps=0)
        t = evaluate.evaluate_predictor(predict, test, error_maps=0)
        test_border = evaluate.border_error_map(predict, test, n_boot=0)
    row |= {"closeup_abs_rel": round(close["overall"]["abs_rel"], 4),
            "test_abs_rel": round(t["overall"]["abs_rel"], 4),
            "test_border": {k: round(v, 3) for k, v in test_border["ratios"].items()},
            "test_border_worst": round(max(test_border["ratios"].values()), 3), "test_frames": len(test),
            "minutes": round((time.perf_counter() - start) / 60, 2),
            "generator": synth.GENERATOR_VERSION, "note": RECORD_NOTE.format(name=name, flips=flips)}
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", metavar="RUN")
    ap.add_argument("--input-pad", type=int, default=None,
                    help="the mirror padding of a run trained by exp_padded_training.py")
    ap.add_argument("--flips", nargs="+", choices=tuple(inference.FLIPS), default=list(inference.FLIPS))
    ap.add_argument("--tag", default="", help="appended to each row's name, e.g. to tell a new test split's rows apart")
    ap.add_argument("--log", default=str(network_experiment.LOG))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    prof = config.get_profile("teach")
    closeups = evaluate.open_eval_dataset(
        str(synth.ensure_dataset("heldout_closeup", overrides=prof["closeup_overrides"], progress=False)), split="test")
    for run in args.runs:
        net, cfg, name = network_experiment.load_tune_run(run, args.input_pad, "score_flips")
        test = evaluate.open_eval_dataset(cfg["dataset"], split="test")
        for flips in args.flips:
            network_experiment.append_row(score(net, cfg, name, flips, closeups, test, args.tag), args.log)
    return 0


if __name__ == "__main__":
    sys.exit(main())
