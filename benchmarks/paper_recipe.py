"""The paper's recipe at reduced size: train a run, score it beside the baselines, log it with its provenance.

One JSON line per run is appended to ``benchmarks/paper_recipe_log.jsonl`` (docs/paper_recipe.md
holds the table and the plan it follows).

    python benchmarks/paper_recipe.py NAME [--profile paper] [--case 1] [--seed 0] [--set KEY=VALUE ...]
                                      [--analytic] [--log FILE]

Trains ``config.make_config(profile, case, seed, **settings)`` into ``runs/paper_recipe/NAME`` (an
interrupted run continues), then scores the last epoch's weights on the whole validation split of
its dataset at the run's image size (Abs Rel and RMSE after per-frame median scaling, the
workbook's protocol), the shading prior and the constant depth on the same frames, and the
collapse diagnostics of :func:`collapse_stats`. ``--analytic`` trains on an analytic dataset
(``analytic.write_dataset``, 120/40 frames at 64 px) written once into ``data/analytic_diag``;
``--set analytic_mm=true`` writes it in millimetres (the former unit) into ``data/analytic_diag_mm``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from geodepth_lite import utils
from geodepth_lite.core import losses
from geodepth_lite.core.metrics import compute_depth_metrics
from geodepth_lite.data import analytic
from geodepth_lite.data.datasets import load_split, resolve_dataset
from geodepth_lite.evaluation import baselines
from geodepth_lite.training import checkpoint, config, train

LOG = Path(__file__).with_name("paper_recipe_log.jsonl")
ROOT = Path(__file__).resolve().parents[1]


def parse_value(text: str):
    """A ``--set`` value: JSON when it parses (numbers, lists, null, true), else the text itself."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("name", help="run name: runs/paper_recipe/NAME")
    p.add_argument("--profile", default="paper")
    p.add_argument("--case", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a make_config setting (JSON)")
    p.add_argument("--analytic", action="store_true", help="train on analytic frames (64 px, 120/40 frames)")
    p.add_argument("--log", default=str(LOG), help="the JSONL file the row is appended to")
    p.add_argument("--score-only", action="store_true",
                   help="no training: score the run's checkpoint as it stands (a run stopped early)")
    p.add_argument("--note", default="", help="a remark recorded in the row")
    args = p.parse_args(argv)
    args.settings = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            p.error(f"--set takes KEY=VALUE, got {item!r}")
        args.settings[key] = parse_value(value)
    return args


def provenance() -> dict:
    """Where and with what a run was made: git commit and whether the tree was clean, versions, CPU."""
    def git(*a):
        try:
            return subprocess.run(["git", "-C", str(ROOT), *a], capture_output=True, text=True, check=True).stdout
        except (OSError, subprocess.CalledProcessError):
            return ""
    cpu = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"git_commit": git("rev-parse", "HEAD").strip(), "git_clean": git("status", "--porcelain") == "",
            "torch": torch.__version__, "numpy": np.__version__, "python": platform.python_version(),
            "cpu": cpu, "cpu_count": os.cpu_count()}


def analytic_root(mm: bool) -> Path:
    """The analytic diagnostic dataset (written once): 120 train, 40 val frames at 64 px."""
    root = utils.data_dir() / ("analytic_diag_mm" if mm else "analytic_diag")
    if not (root / "checksums.sha256").is_file():
        unit = 1.0 if mm else analytic.MM_PER_SCENE_UNIT
        analytic.write_dataset(root, {"train": 120, "val": 40, "test": 2}, size=64, mm_per_unit=unit)
    return root


@torch.no_grad()
def predict_split(model, ds, batch: int = 20):
    """(prediction, ground truth, images) of every frame of ``ds``, N x H x W (and N x 3 x H x W)."""
    preds, gts, imgs = [], [], []
    for i in range(0, len(ds), batch):
        items = [ds[j] for j in range(i, min(i + batch, len(ds)))]
        x = torch.stack([it["image"] for it in items])
        preds.append(model(x)[:, 0])
        gts.append(torch.stack([it["depth"] for it in items])[:, 0])
        imgs.append(x)
    return torch.cat(preds).numpy(), torch.cat(gts).numpy(), torch.cat(imgs)


def head_gradient_ratio(model, ds, cfg: dict, n: int = 20) -> float:
    """Mean |dL_depth / d logit| of the head over the nearest quarter of the valid pixels divided by that
    over the farthest quarter, on the first ``n`` frames: how much less the near pixels are pulled."""
    items = [ds[j] for j in range(min(n, len(ds)))]
    x = torch.stack([it["image"] for it in items])
    gt = torch.stack([it["depth"] for it in items])
    model.eval()
    feats = model.encode(x)
    logit = model.decoder.head(model.decoder(feats, return_features=True)[1][-1]).detach().requires_grad_(True)
    pred = model.depth_from_sigmoid(torch.sigmoid(logit))
    unit = float(cfg.get("depth_unit", 1.0))
    loss = losses.DEPTH_TERMS[cfg["depth_term"]](pred / unit, gt / unit)
    (g,) = torch.autograd.grad(loss, logit)
    g, d = g.abs().flatten(), gt.flatten()
    valid = d > 0
    g, d = g[valid], d[valid]
    lo, hi = torch.quantile(d, 0.25), torch.quantile(d, 0.75)
    return float(g[d <= lo].mean() / g[d >= hi].mean().clamp(min=1e-30))


def collapse_stats(pred: np.ndarray, gt: np.ndarray, floor: float) -> dict:
    """Shares of valid pixels predicted below 0.1x their true depth (before median scaling), and at the
    head's floor (below 1.5x ``floor``)."""
    v = gt > 0
    return {"below_0.1x": float(np.mean(pred[v] < 0.1 * gt[v])), "at_floor": float(np.mean(pred[v] < 1.5 * floor))}


def score(pred, gt, images) -> dict:
    """Abs Rel and RMSE (median scaling) of the model, the shading prior and the constant depth."""
    out = {}
    for name, p in (("model", pred), ("shading_prior", baselines.shading_prior(images)),
                    ("constant", baselines.constant_depth(images))):
        m = compute_depth_metrics(p, gt)
        out[f"{name}_abs_rel"] = round(float(m["abs_rel"]), 4)
        out[f"{name}_rmse"] = round(float(m["rmse"]), 4)
    return out


def utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def main(argv=None) -> int:
    args = parse_args(argv)
    settings = dict(args.settings)
    mm = bool(settings.pop("analytic_mm", False))
    if args.analytic:
        settings["dataset"] = str(analytic_root(mm))
    cfg = config.make_config(args.profile, args.case, args.seed, **settings)
    run_dir = utils.runs_dir() / "paper_recipe" / args.name
    start, prov, t0 = utc_now(), provenance(), time.perf_counter()
    ckpt = run_dir / checkpoint.CHECKPOINT_NAME
    if args.score_only:
        if not ckpt.is_file():
            raise SystemExit(f"paper_recipe: --score-only: no checkpoint at {ckpt}")
    else:
        ckpt = train.fit(cfg, run_dir, resume=True, progress=False)
    minutes = (time.perf_counter() - t0) / 60
    end = utc_now()
    model, cfg = checkpoint.load_model(ckpt)
    torch.set_num_threads(cfg["threads"] or torch.get_num_threads())
    ds = load_split(resolve_dataset(cfg), "val", cfg["image_size"])
    pred, gt, images = predict_split(model, ds)
    log = checkpoint.read_log(run_dir)
    row = {"name": args.name, "profile": args.profile, "case": args.case, "seed": args.seed,
           "settings": args.settings, "config_hash": config.config_hash(cfg), "epochs": cfg["epochs"],
           "epochs_done": len(log),
           "image_size": cfg["image_size"], "val_frames_scored": len(ds), **score(pred, gt, images),
           **collapse_stats(pred, gt, model.depth_range[0]),
           "head_grad_near_far": round(head_gradient_ratio(model, ds, cfg), 5),
           "val_abs_rel_by_epoch": [round(r.get("val_abs_rel", float("nan")), 4) for r in log],
           "epoch_s_median": round(float(np.median([r["epoch_s"] for r in log])), 1),
           "minutes_this_call": round(minutes, 2), "utc_start": start, "utc_end": end,
           "threads": cfg["threads"], "score_only": args.score_only, "note": args.note, **prov}
    with open(args.log, "a") as f:
        f.write(json.dumps(row) + "\n")
    print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
