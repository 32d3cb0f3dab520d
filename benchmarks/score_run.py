"""Score trained tune runs on the sets that are recorded but never used to choose.

    python benchmarks/score_run.py NAME [NAME ...] [--input-pad P]

For each ``runs/tune/NAME`` (trained by ``tune_teach.py`` or an ``exp_*.py`` script) one row named
``NAME_closeups`` is appended to ``benchmarks/tuning_log.jsonl``: Abs Rel on the teach profile's
``heldout_closeup`` set beside the shading prior's, that set's worst border band / centre, and the
test split's Abs Rel and border band ratios (as notebook 06 computes them). Choices are made on the
validation split, in the training row; these numbers only say how a choice carries over.
``--input-pad`` is for runs of ``exp_padded_training.py``, whose network mirrors its input without
the setting in its configuration.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import network_experiment  # noqa: E402

from geodepth_lite import baselines, config, evaluate, inference, synth  # noqa: E402

RECORD_NOTE = "no training: run {name} scored on heldout_closeup and on the test split (recorded, not for choosing)"


def score(name: str, input_pad: int | None = None) -> dict:
    net, cfg, name = network_experiment.load_tune_run(name, input_pad, "score_run")
    prof = config.get_profile("teach")
    closeups = evaluate.open_eval_dataset(
        str(synth.ensure_dataset("heldout_closeup", overrides=prof["closeup_overrides"], progress=False)), split="test")
    test = evaluate.open_eval_dataset(cfg["dataset"], split="test")

    def predict(x):
        return inference.predict_depth(net, x, cfg["image_size"])

    row = {"name": f"{name}_closeups", "case": cfg["case"], "seed": cfg["seed"],
           "settings": {k: cfg[k] for k in ("image_size", "threads", "border_weight", "input_pad") if k in cfg}}
    with torch.no_grad():
        r = evaluate.evaluate_model(net, closeups, image_size=cfg["image_size"], error_maps=0)
        prior = baselines.evaluate_baselines(closeups, None, names=["shading_prior"])["shading_prior"]
        close_border = evaluate.border_error_map(predict, closeups)
        t = evaluate.evaluate_model(net, test, image_size=cfg["image_size"], error_maps=0)
        test_border = evaluate.border_error_map(predict, test)
    row |= {"closeup_abs_rel": round(r["overall"]["abs_rel"], 4),
            "closeup_shading_prior_abs_rel": round(prior["overall"]["abs_rel"], 4),
            "closeup_border_worst": round(max(close_border["ratios"].values()), 3),
            "test_abs_rel": round(t["overall"]["abs_rel"], 4),
            "test_border": {k: round(v, 3) for k, v in test_border["ratios"].items()},
            "test_border_worst": round(max(test_border["ratios"].values()), 3),
            "generator": synth.GENERATOR_VERSION, "note": RECORD_NOTE.format(name=name)}
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="+", metavar="NAME")
    ap.add_argument("--input-pad", type=int, default=None,
                    help="the mirror padding of a run trained by exp_padded_training.py")
    ap.add_argument("--log", default=str(network_experiment.LOG))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    for name in args.names:
        network_experiment.append_row(score(name, args.input_pad), args.log)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
