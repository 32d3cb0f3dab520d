"""Where a paper-profile run's first epoch goes: each training step's time, and each nearest-point
search's, through the first two epochs (the ground truth's fields searched in the first, cached after).

    python benchmarks/gpu/first_epoch.py --out OUT [--device cuda] [--train-frames 600] [--epochs 2]
        [--channels-last] [--data-dir DIR]

Makes the scenario frames with the torch renderer (as ``gpu-check --full``), trains Case 4 of the paper
profile on them in this process, waiting for the device after each step and each search (so the
times are the device's, a little slower than a run that does not wait), and writes
``OUT/first_epoch.json``: per step its seconds, its searches' seconds (the prediction's first, then
the ground truth's where it was not cached) and the median distance from the grid's queries to the
prediction's nearest point (the search prunes less the farther the prediction lies from the grid).
``--tiny`` is a dry run at toy sizes on any device.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from geodepth_lite import utils
from geodepth_lite.apps import gpu_check
from geodepth_lite.core import sdf
from geodepth_lite.training import config, train  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--train-frames", type=int, default=600)
    ap.add_argument("--epochs", type=int, default=2)
    ap.add_argument("--channels-last", action="store_true")
    ap.add_argument("--data-dir", default=None, help="make the frames here and keep them (default: a temporary folder)")
    ap.add_argument("--tiny", action="store_true")
    args = ap.parse_args(argv)
    dev = utils.parse_device(args.device)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    size = 32 if args.tiny else 320
    counts = {"train": 8 if args.tiny else args.train_frames, "val": 4 if args.tiny else 20, "test": 2}
    sync = (lambda: torch.cuda.synchronize(dev)) if dev.type == "cuda" else (lambda: None)
    steps: list[dict] = []
    searches: list[tuple[float, float]] = []
    search = sdf.nearest_indices_grid

    def timed_search(points, valid, queries, method="auto"):
        sync()
        t0 = time.perf_counter()
        idx = search(points, valid, queries, method)
        sync()
        near = torch.gather(points, 1, idx[..., None].expand(-1, -1, 3))
        searches.append((time.perf_counter() - t0, float((near - queries).detach().norm(dim=-1).median())))
        return idx

    process, step = train.Trainer.process_batch, train.Trainer.step

    def timed_process(self, batch):
        sync()
        searches.clear()
        self._t0 = time.perf_counter()
        return process(self, batch)

    def timed_step(self, loss):
        step(self, loss)
        sync()
        steps.append({"s": round(time.perf_counter() - self._t0, 5),
                      "searches_s": [round(s, 5) for s, _ in searches],
                      "pred_nearest_median": round(searches[0][1], 4) if searches else None})

    with tempfile.TemporaryDirectory(prefix="first-epoch-") as work:
        t0 = time.perf_counter()
        root = gpu_check._scenario_data(dev, Path(args.data_dir or Path(work) / "data"), counts, size, args.tiny)
        data_s = time.perf_counter() - t0
        cfg = config.make_config("paper", 4, 0, dataset=str(root), epochs=args.epochs,
                                 **({"image_size": size, "batch_size": 4} if args.tiny else {}))
        if args.tiny:
            cfg["sdf_grid"] = 6
        sdf.nearest_indices_grid = timed_search
        train.Trainer.process_batch, train.Trainer.step = timed_process, timed_step
        try:
            t0 = time.perf_counter()
            train.fit(cfg, Path(work) / "run", progress=False, device=str(dev), channels_last=args.channels_last)
            fit_s = time.perf_counter() - t0
        finally:
            sdf.nearest_indices_grid = search
            train.Trainer.process_batch, train.Trainer.step = process, step
    per_epoch = len(steps) // args.epochs
    summary = []
    for e in range(args.epochs):
        rows = steps[e * per_epoch:(e + 1) * per_epoch]
        summary.append({"epoch": e + 1, "steps": len(rows), "sum_s": round(sum(r["s"] for r in rows), 2),
                        "median_step_s": round(statistics.median(r["s"] for r in rows), 4),
                        "first_step_s": rows[0]["s"], "last_step_s": rows[-1]["s"],
                        "search_sum_s": round(sum(sum(r["searches_s"]) for r in rows), 2)})
    rec = {"device": str(dev), "gpu": torch.cuda.get_device_name(dev) if dev.type == "cuda" else None,
           "torch": torch.__version__, "train_frames": counts["train"], "size": size, "data_s": round(data_s, 1),
           "fit_s": round(fit_s, 1), "channels_last": args.channels_last, "epochs": summary, "steps": steps}
    rec["dataset"] = str(root) if args.data_dir else None
    utils.write_json_atomic(out / "first_epoch.json", rec)
    for s in summary:
        print(s)
    for i in (0, 1, 2, 3, 5, 10, 20, per_epoch - 1, per_epoch, per_epoch + 1, len(steps) - 1):
        if 0 <= i < len(steps):
            print(i + 1, steps[i])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
