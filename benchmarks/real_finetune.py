"""The runs of docs/real_finetune_plan.md: the model for real frames fine-tuned from the ``predict``
model for 2 and 3 epochs (candidates A and B), scored beside the model trained from scratch.

    GEODEPTH_LITE_HOME=WORKSPACE python benchmarks/real_finetune.py [--out benchmarks/real_finetune.json]

WORKSPACE holds the ``predict`` model and the reference under runs/teach/checkpoints/ (what
``reproduce`` trained); the candidates are trained there beside them (two side by side, one thread
each), then all three are scored: validation Abs Rel (120 frames) and the gallery's far blobs,
every prediction over the four mirrorings. The record holds each run's provenance.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

from geodepth_lite import utils
from geodepth_lite.evaluation import evaluate, gallery
from geodepth_lite.training import checkpoint, config, inference, provenance, run_cache

PROFILE, CASE, SEED, FLIPS = "teach", 4, 0, "hv"
CANDIDATES = {"A": 2, "B": 3}  # fine-tuning epochs
CLOSE = ("close-up", "wall")


def settings(epochs: int | None) -> dict:
    """The reference's settings (epochs None) or a candidate's: fine-tuned from the predict model."""
    prof = config.profile(PROFILE)
    real = prof.real_settings()
    if epochs is None:
        return {k: v for k, v in real.items() if k != "init_from"} | {"augment": "crop"}
    source = prof.predict_run(CASE, SEED).folder_name
    return {**prof.predict_settings(), "augment": "crop", "init_from": source, "epochs": epochs}


def score(path: Path) -> dict:
    model, cfg = checkpoint.load_model(path)
    val = evaluate.open_eval_dataset(cfg["dataset"], split="val")
    v = evaluate.evaluate_predictor(lambda im: inference.predict_depth(model, im, cfg["image_size"], FLIPS), val)
    rows = gallery.score_gallery(model, gallery.gallery_frames(), cfg["image_size"], FLIPS)
    close = [r for r in rows if r["view"] in CLOSE]
    return {"run": path.parent.name, "val_frames": v["n"], "val_abs_rel": round(float(v["overall"]["abs_rel"]), 4),
            "val_rmse": round(float(v["overall"]["rmse"]), 4),
            "close_frames": len(close), "close_blobs": sum(r["far_share"] > gallery.BLOB_LIMIT for r in close),
            "close_median_s": round(float(np.nanmedian([r["far_share"] for r in close])), 3),
            "close_median_r": round(float(np.nanmedian([r["r"] for r in close])), 3),
            "all_frames": len(rows), "all_blobs": sum(r["far_share"] > gallery.BLOB_LIMIT for r in rows),
            "train_s": round(sum(e["epoch_s"] for e in checkpoint.read_log_file(path.parent)["epochs"]), 1)}


def qualifies(c: dict, ref: dict) -> bool:
    """The plan's rule: all four conditions against the reference."""
    return (c["close_blobs"] <= ref["close_blobs"] and c["close_median_s"] <= ref["close_median_s"] + 0.05
            and c["all_blobs"] <= ref["all_blobs"] and c["val_abs_rel"] <= ref["val_abs_rel"] + 0.005)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/real_finetune.json")
    args = ap.parse_args()
    torch.set_num_threads(2)
    start = provenance.utc_now()
    t0 = time.perf_counter()
    prof = config.profile(PROFILE)
    runs = [prof.run(CASE, SEED, **settings(e)) for e in CANDIDATES.values()]
    paths = run_cache.ensure_runs(runs, workers=2, progress=True)
    train_wall = time.perf_counter() - t0
    ref_path = run_cache.checkpoint_dir(prof.run(CASE, SEED, **settings(None))) / checkpoint.CHECKPOINT_NAME
    ref = score(ref_path)
    cands = {name: score(p) for name, p in zip(CANDIDATES, paths)}
    ok = [n for n in CANDIDATES if qualifies(cands[n], ref)]
    commit, clean = provenance.code_version()
    record = {"plan": "docs/real_finetune_plan.md", "utc_start": start, "utc_end": provenance.utc_now(),
              "git_commit": commit, "git_clean": clean, "python": platform.python_version(),
              "torch": torch.__version__, "numpy": np.__version__, "device": "cpu", "cpu": provenance.cpu_model(),
              "candidates_wall_s": round(train_wall, 1), "reference": ref,
              "candidates": {n: {"epochs": CANDIDATES[n], **cands[n], "qualifies": n in ok} for n in CANDIDATES},
              "decision": ok[0] if ok else "reference (trained from scratch)"}
    utils.write_json_atomic(args.out, record)
    print(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
