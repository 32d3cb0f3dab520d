"""One tuning run of the teach recipe, scored on the validation split, logged as one JSON line.

    python benchmarks/tune_teach.py NAME --case 1 --seed 0 --set epochs=10 --set weight_decay=0 ...

Trains ``config.make_config("teach", case, seed, **settings)`` into ``runs/tune/NAME`` and appends
{name, case, seed, settings, val metrics on the whole validation split, minutes} to
``benchmarks/tuning_log.jsonl``. The test split is never read here: choices are made on
validation (the tables in ``config.TEACH_EVIDENCE`` and notebook 04 come from this log).
With ``--border`` it holds the validation split's border/centre error ratios
(``evaluate.border_error_map``). With ``--closeups`` the row also holds the model's and the shading prior's
Abs Rel on the teach profile's ``heldout_closeup`` set, for the record only (never used to choose).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import network_experiment  # noqa: E402

from geodepth_lite import baselines, checkpoint, config, dataset, evaluate, inference, synth
from geodepth_lite.metrics import compute_depth_metrics

LOG = network_experiment.LOG


def parse_value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("name")
    ap.add_argument("--case", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a training setting (JSON value), e.g. lr=3e-4, lambdas=[1,0.1,0.1]")
    ap.add_argument("--log", default=str(LOG))
    ap.add_argument("--closeups", action="store_true", help="also score heldout_closeup (recorded, not for choosing)")
    ap.add_argument("--border", action="store_true",
                    help="also the validation split's border error map: "
                         "each border band's mean |log error| / the centre's")
    args = ap.parse_args(argv)
    settings = {}
    for item in args.set:
        key, _, value = item.partition("=")
        settings[key] = parse_value(value)
    model, cfg, minutes, run_dir = network_experiment.train_tune_run(args.name, args.case, args.seed, settings)
    root = dataset.resolve_dataset(cfg)
    val = dataset.load_split(root, "val", cfg["image_size"])  # the whole validation split
    preds, gts = [], []
    with torch.no_grad():
        for i in range(0, len(val), 40):
            items = [val[j] for j in range(i, min(i + 40, len(val)))]
            x = torch.stack([it["image"] for it in items])
            preds.append(model(x)[:, 0])
            gts.append(torch.stack([it["depth"] for it in items])[:, 0])
    m = compute_depth_metrics(torch.cat(preds).numpy(), torch.cat(gts).numpy())
    hist = checkpoint.read_log(run_dir)
    row = {"name": args.name, "case": args.case, "seed": args.seed, "settings": settings,
           "val_abs_rel": round(m["abs_rel"], 4), "val_rmse": round(m["rmse"], 4),
           "val_rmse_log": round(m["rmse_log"], 4), "val_a1": round(m["a1"], 4),
           "train_depth_last": round(hist[-1]["train_depth"], 4), "minutes": round(minutes, 2),
           "frames_per_s": round(hist[-1]["train_frames_per_s"], 1)}
    row["generator"] = synth.GENERATOR_VERSION
    if args.border:
        ds = evaluate.open_eval_dataset(str(root), split="val")
        with torch.no_grad():
            row |= network_experiment.border_scores(lambda x: inference.predict_depth(model, x, cfg["image_size"]), ds)
    if args.closeups:
        prof = config.get_profile("teach")
        ds = evaluate.open_eval_dataset(str(synth.ensure_dataset("heldout_closeup", overrides=prof["closeup_overrides"],
                                                                  progress=False)), split="test")
        r = evaluate.evaluate_model(model, ds, image_size=cfg["image_size"], error_maps=0)
        b = baselines.evaluate_baselines(ds, None, names=["shading_prior"])["shading_prior"]
        row["closeup_abs_rel"] = round(r["overall"]["abs_rel"], 4)
        row["closeup_shading_prior_abs_rel"] = round(b["overall"]["abs_rel"], 4)
    network_experiment.append_row(row, args.log)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
