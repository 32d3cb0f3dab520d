"""``python -m geodepth_lite gpu-check --out DIR``: one bounded check of the CUDA paths, and a
prediction of the paper profile's training time from a few measured epochs.

Needs only torch, numpy, scipy, Pillow, tqdm and PyYAML (no VTK, no matplotlib, no network): its
data are analytic lumen, wall and close-up views (:mod:`geodepth_lite.analytic`) written into a
temporary folder. Steps, each timed and recorded even when one fails:

1. the environment (torch, CUDA device, bf16);
2. the CUDA tests (``pytest -m cuda tests/test_cuda.py``) when pytest and the checkout's tests/
   are there (else recorded as not run);
3. the nearest-point search at the paper's scale (a batch of 20 depth maps of 320x320, the 32^3
   bounding-box grid): the batched device search per batch, its agreement with cKDTree, the SDF
   loss forward and backward, and DepthNet's forward and backward (autocast) at the same batch;
4. the paper profile (Case 4) for ``--epochs`` epochs on an analytic dataset of ``--frames``
   training frames, each epoch's time from the run's log; from these, the predicted time of 18
   epochs over the paper split (3600 training and 900 validation frames);
5. with ``--full``, the paper profile itself: Case 4, seed 0, its 18 epochs over an analytic split
   of the paper's size (3600 + 900 frames at 320 px), within ``--full-timeout`` seconds; every
   finished epoch is recorded even when the run is stopped at that limit.

It writes ``gpu_check.json`` and ``gpu_check.md`` into ``--out``, locked while it runs; it refuses
a non-empty folder it did not write (its marker ``.gpu-check`` says it did). ``--device cpu
--tiny`` is a dry run of the same steps at toy sizes (the test suite runs it).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy
import torch

from geodepth_lite import analytic, camera, inference, losses, sdf, utils
from geodepth_lite.model import DepthNet

MARKER = ".gpu-check"
PAPER_TRAIN, PAPER_VAL, PAPER_EPOCHS = 3600, 900, 18  # the paper split and epochs (config "paper")


def add_arguments_gpu_check(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help="folder for gpu_check.json and gpu_check.md (new or empty)")
    parser.add_argument("--device", default="cuda", help="cuda | cuda:N | cpu (default cuda)")
    parser.add_argument("--tiny", action="store_true", help="a dry run at toy sizes (with --device cpu: seconds)")
    parser.add_argument("--epochs", type=int, default=3, help="paper-profile epochs to time (default 3)")
    parser.add_argument("--frames", type=int, default=100, help="training frames of the timed runs (default 100)")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats of the benchmarks (default 5)")
    parser.add_argument("--no-pytest", action="store_true", help="skip the CUDA tests")
    parser.add_argument("--full", action="store_true",
                        help="also train the paper profile itself: 18 epochs over 3600 + 900 analytic frames")
    parser.add_argument("--full-timeout", type=int, default=420,
                        help="seconds allowed to the --full run, data included (default 420)")
    parser.add_argument("--step-timeout", type=int, default=200,
                        help="seconds allowed to the CUDA tests and to training, each (default 200: the whole "
                             "check stays within 10 minutes)")


def _sync(dev) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _median_time(fn, dev, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        _sync(dev)
        t0 = time.perf_counter()
        fn()
        _sync(dev)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def check_environment(dev) -> dict:
    import scipy  # heavy; only its version is read here

    env = {"python": platform.python_version(), "torch": torch.__version__, "numpy": numpy.__version__,
           "scipy": scipy.__version__, "cuda_available": torch.cuda.is_available(), "device": str(dev),
           "torch_threads": torch.get_num_threads(), "cpu_count": os.cpu_count()}
    if dev.type == "cuda":
        p = torch.cuda.get_device_properties(dev)
        env.update({"gpu": p.name, "gpu_memory_gib": round(p.total_memory / 2**30, 1),
                    "bf16": torch.cuda.is_bf16_supported(), "cuda": torch.version.cuda})
    return env


def run_cuda_tests(timeout: int) -> dict:
    tests = Path(__file__).resolve().parents[1] / "tests" / "test_cuda.py"
    try:
        import pytest  # noqa: F401 (optional: a GPU image may not have it)
    except ImportError:
        return {"status": "not run: pytest is not installed"}
    if not tests.is_file():
        return {"status": f"not run: {tests.name} is not beside the package (an installed copy, not a checkout)"}
    cmd = [sys.executable, "-m", "pytest", "-m", "cuda", "-p", "no:nbval", "-p", "no:cacheprovider", "-o", "addopts=",
           "-q", "-rs", str(tests)]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=tests.parents[1],
                              env=dict(os.environ, PYTHONPATH=str(tests.parents[1])))
    except subprocess.TimeoutExpired:
        return {"status": f"timed out after {timeout} s", "seconds": timeout}
    lines = [ln for ln in proc.stdout.strip().splitlines() if ln.strip()]
    return {"status": "passed" if proc.returncode == 0 else f"failed (exit {proc.returncode})",
            "summary": lines[-1] if lines else "", "tail": "\n".join(lines[-15:]),
            "seconds": round(time.perf_counter() - t0, 1)}


def bench_search(dev, batch: int, size: int, grid: int, repeats: int) -> dict:
    """The SDF search and loss at one batch, beside DepthNet's forward and backward."""
    K = torch.from_numpy(analytic.intrinsics(size)).float()
    depth = torch.stack([torch.from_numpy(analytic.depth_map(analytic.KINDS[i % 3], size, seed=i))[None]
                         for i in range(batch)]).to(dev)
    Kb = K.expand(batch, 3, 3).contiguous().to(dev)
    pts = camera.backproject(depth, Kb)
    pairs = [(p, sdf.grid_points(p.min(0).values, p.max(0).values, grid)) for p in pts]
    found = sdf.nearest_indices_many(pairs, "device")
    agree = sum(int((f.cpu() == sdf.nearest_indices_kdtree(p, q).cpu()).sum()) for f, (p, q) in zip(found, pairs))
    res = {"batch": batch, "size": size, "grid": grid, "queries": sum(len(q) for _, q in pairs), "agree": agree}
    res["search_batch_s"] = _median_time(lambda: sdf.nearest_indices_many(pairs, "device"), dev, repeats)
    pred0 = depth * 1.05

    def sdf_step():
        p = pred0.clone().requires_grad_()
        losses.sdf_loss(p, depth, Kb, grid, method="device", cache=None).backward()

    res["sdf_loss_batch_s"] = _median_time(sdf_step, dev, repeats)
    net = DepthNet().to(dev).train()
    image = torch.rand(batch, 3, size, size, device=dev)

    def net_step():
        with inference.autocast(dev):
            out = net(image)
        out.float().mean().backward()

    res["network_fwd_bwd_s"] = _median_time(net_step, dev, repeats)
    res["sdf_share_of_step"] = res["sdf_loss_batch_s"] / (res["sdf_loss_batch_s"] + res["network_fwd_bwd_s"])
    return res


def time_training(dev, work: Path, frames: int, epochs: int | None, size: int, tiny: bool, timeout: int,
                  n_val: int | None = None) -> dict:
    """Trains Case 4 (seed 0) of the paper profile on an analytic dataset; ``epochs`` None: the
    profile's own 18. The data are written in parallel, inside the time limit."""
    n_val = max(2, frames // 5) if n_val is None else n_val
    t0 = time.perf_counter()
    data = analytic.write_dataset(work / "data", {"train": frames, "val": n_val, "test": 2}, size=size,
                                  workers=os.cpu_count() or 1)
    data_s = time.perf_counter() - t0
    run = work / "run"
    cmd = [sys.executable, "-m", "geodepth_lite", "train", "--profile", "paper", "--case", "4", "--seed", "0",
           "--dataset", str(data), "--device", str(dev), "--run-dir", str(run), "--no-progress"]
    if epochs is not None:
        cmd += ["--epochs", str(epochs)]
    if tiny:
        cmd += ["--image-size", str(size), "--batch-size", "4"]
    pkg_root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=pkg_root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=max(1.0, timeout - data_s), env=env)
        status = ("completed" if proc.returncode == 0
                  else f"failed (exit {proc.returncode}): {proc.stderr.strip()[-300:]}")
    except subprocess.TimeoutExpired:
        status = f"timed out after {timeout} s"
    res = {"status": status, "train_frames": frames, "val_frames": n_val, "size": size,
           "epochs_asked": PAPER_EPOCHS if epochs is None else epochs, "data_s": round(data_s, 1),
           "seconds": round(time.perf_counter() - t0, 1)}
    log = run / "log.json"
    rows = json.loads(log.read_text())["epochs"] if log.is_file() else []
    res["epochs"] = [{k: r[k] for k in ("epoch", "epoch_s", "train_frames_per_s", "train_total", "val_rmse",
                                        "val_abs_rel") if k in r} for r in rows]
    if rows:
        res["prediction"] = predict_paper_time(rows, frames, n_val)
    return res


def predict_paper_time(rows: list[dict], n_train: int, n_val: int) -> dict:
    """The paper profile's time from measured epochs: training per frame from the log's frames/s,
    validation the rest of each epoch per validation frame, scaled to 3600 + 900 frames. The first
    epoch (every ground-truth field searched) and later ones (cached) are scaled separately."""
    def epoch_time(r):
        train_s = n_train / max(r["train_frames_per_s"], 1e-9)
        val_s = max(r["epoch_s"] - train_s, 0.0)
        return PAPER_TRAIN * train_s / n_train + PAPER_VAL * val_s / n_val

    first = epoch_time(rows[0])
    later = statistics.median(epoch_time(r) for r in rows[1:]) if len(rows) > 1 else first
    total = first + (PAPER_EPOCHS - 1) * later
    return {"first_epoch_s": round(first, 1), "later_epoch_s": round(later, 1), "total_s": round(total, 1),
            "total_min": round(total / 60, 1), "basis": f"{len(rows)} measured epoch(s) of {n_train} frames"}


def markdown(report: dict) -> str:
    env, lines = report["environment"], []
    lines += [f"# gpu-check on {env.get('gpu', env['device'])}", "",
              f"torch {env['torch']}, numpy {env['numpy']}, scipy {env['scipy']}, {env['cpu_count']} CPU cores"
              + (" (dry run at toy sizes)" if report["tiny"] else ""), "", "| what | figure |", "|---|---|"]
    t = report.get("cuda_tests", {})
    lines.append(f"| CUDA tests | {t.get('status', '-')} {t.get('summary', '')} |")
    b = report.get("search", {})
    if "search_batch_s" in b:
        lines += [f"| nearest-point search, batch {b['batch']}, {b['size']}x{b['size']}, {b['grid']}^3 grid | "
                  f"{1e3 * b['search_batch_s']:.1f} ms per batch ({1e3 * b['search_batch_s'] / b['batch']:.2f} ms "
                  f"per field); agrees with cKDTree on {b['agree']} of {b['queries']} queries |",
                  f"| SDF loss forward + backward, same batch | {1e3 * b['sdf_loss_batch_s']:.1f} ms |",
                  f"| DepthNet forward + backward (autocast), same batch | {1e3 * b['network_fwd_bwd_s']:.1f} ms |",
                  f"| SDF share of a step (uncached) | {100 * b['sdf_share_of_step']:.1f} % |"]
    elif b:
        lines.append(f"| nearest-point search | {b.get('status', '')} |")
    tr = report.get("training", {})
    for r in tr.get("epochs", []):
        lines.append(f"| paper profile epoch {r['epoch']} ({tr['train_frames']} frames) | {r['epoch_s']:.1f} s, "
                     f"{r['train_frames_per_s']:.1f} frames/s |")
    if "prediction" in tr:
        p = tr["prediction"]
        lines.append(f"| predicted paper profile (18 epochs, 3600 + 900 frames) | {p['total_min']} min "
                     f"(first epoch {p['first_epoch_s']} s, later {p['later_epoch_s']} s; {p['basis']}) |")
    if tr.get("status", "completed") != "completed":
        lines.append(f"| training | {tr['status']} |")
    full = report.get("paper_run")
    if full:
        done = full.get("epochs", [])
        train_s = sum(r["epoch_s"] for r in done)
        lines.append(f"| paper profile run, Case 4 seed 0, {full['train_frames']} + {full['val_frames']} frames | "
                     f"{len(done)} of {full['epochs_asked']} epochs in {train_s:.0f} s ({train_s / 60:.1f} min; "
                     f"data written in {full['data_s']:.0f} s); {full['status']} |")
        if done:
            last = done[-1]
            lines.append(f"| paper profile run, last epoch | {last['epoch_s']:.1f} s, {last['train_frames_per_s']:.1f} "
                         f"frames/s; val RMSE {last.get('val_rmse', float('nan')):.3f}, Abs Rel "
                         f"{last.get('val_abs_rel', float('nan')):.4f} |")
    lines += ["", f"Total {report['seconds']:.0f} s."]
    return "\n".join(lines) + "\n"


def _claim_out(out: Path) -> None:
    """The output folder: new, empty, or one this command wrote before (its marker)."""
    if out.exists() and not out.is_dir():
        raise utils.FileProblem(f"cannot write into {out}: it is a file, not a folder", out)
    if out.is_dir():
        entries = {p.name for p in out.iterdir()} - {utils.LOCK_NAME}
        if entries and MARKER not in entries:
            raise utils.FileProblem(f"cannot write into {out}: the folder holds files gpu-check did not write; "
                                    "choose a new or empty folder", out)
    utils.make_dir(out)
    (out / MARKER).write_text("written by python -m geodepth_lite gpu-check\n")


def run_gpu_check(args: argparse.Namespace) -> int:
    for name in ("epochs", "frames", "repeats", "step_timeout", "full_timeout"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    dev = utils.parse_device(args.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("gpu-check --device cuda: no CUDA device is available (a dry run: --device cpu --tiny)")
    out = Path(args.out)
    _claim_out(out)
    with utils.FolderLock(out, "gpu-check folder"):
        t0 = time.perf_counter()
        report = {"tiny": bool(args.tiny), "environment": check_environment(dev)}
        size, batch, grid = (32, 2, 6) if args.tiny else (320, 20, 32)
        frames = min(args.frames, 8) if args.tiny else args.frames
        report["cuda_tests"] = {"status": "skipped (--no-pytest)"} if args.no_pytest else run_cuda_tests(
            args.step_timeout)
        print(f"gpu-check: CUDA tests {report['cuda_tests']['status']}", flush=True)
        try:
            report["search"] = bench_search(dev, batch, size, grid, 1 if args.tiny else args.repeats)
        except Exception as exc:  # recorded, and the next step still runs
            report["search"] = {"status": f"failed: {type(exc).__name__}: {exc}"}
        print(f"gpu-check: search {report['search'].get('search_batch_s', report['search'].get('status'))}",
              flush=True)
        work = Path(tempfile.mkdtemp(prefix="gpu-check-"))
        try:
            report["training"] = time_training(dev, work, frames, 2 if args.tiny else args.epochs, size, args.tiny,
                                               args.step_timeout)
        finally:
            shutil.rmtree(work, ignore_errors=True)
        print(f"gpu-check: training {report['training']['status']}", flush=True)
        if args.full:
            work = Path(tempfile.mkdtemp(prefix="gpu-check-full-"))
            try:
                n_train, n_val = (12, 4) if args.tiny else (PAPER_TRAIN, PAPER_VAL)
                report["paper_run"] = time_training(dev, work, n_train, 2 if args.tiny else None, size, args.tiny,
                                                    args.full_timeout, n_val=n_val)
            finally:
                shutil.rmtree(work, ignore_errors=True)
            print(f"gpu-check: paper profile run {report['paper_run']['status']}, "
                  f"{len(report['paper_run']['epochs'])} epochs", flush=True)
        report["seconds"] = round(time.perf_counter() - t0, 1)
        utils.write_json_atomic(out / "gpu_check.json", report)
        utils.write_bytes_atomic(out / "gpu_check.md", markdown(report).encode())
    print(markdown(report))
    print(f"gpu-check: wrote {out / 'gpu_check.json'} and {out / 'gpu_check.md'}")
    return 0
