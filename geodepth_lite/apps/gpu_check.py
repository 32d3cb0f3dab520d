"""``python -m geodepth_lite gpu-check --out DIR``: one bounded check of the CUDA paths, and a
prediction of the paper profile's training time from a few measured epochs.

Needs only torch, numpy, scipy, Pillow, tqdm and PyYAML (no VTK, no matplotlib, no network): its
data are analytic lumen, wall and close-up views (:mod:`geodepth_lite.data.analytic`) written into a
temporary folder. Steps, each timed and recorded even when one fails:

1. the environment (torch, CUDA device, bf16);
2. the CUDA tests (``pytest -m cuda tests/test_cuda.py``) when pytest and the checkout's tests/
   are there (else recorded as not run); with ``--full`` they run last;
3. the nearest-point search at the paper's scale (a batch of 20 depth maps of 320x320, the 32^3
   bounding-box grid): each exact batched search of the device per batch ("device"; "triton" on
   CUDA, after a sweep of its tile sizes that sets the fastest for the rest of the check), its
   agreement with cKDTree, the SDF loss forward and backward, and DepthNet's forward and backward
   (autocast) at the same batch;
4. the paper profile (Case 4) for ``--epochs`` epochs on an analytic dataset of ``--frames``
   training frames, each epoch's time from the run's log; from these, the predicted time of 18
   epochs over the paper split (3600 training and 900 validation frames); with ``--full`` this step
   gives way to the paper profile's own run, whose epochs give the prediction;
5. with ``--full``, the paper's recipe end to end (:func:`full_check`): the data of the paper
   manifest's split sizes (3600 / 900 / 300 frames at 320 px) rendered on the device by the torch
   renderer (:func:`_scenario_data`, no VTK: the scenario data, not analytic frames); one
   paper-profile run, Case 4, seed 0, its 18 epochs through
   ``train-many`` within ``--full-timeout`` seconds (every finished epoch recorded even when it is
   stopped at that limit); that run's TEST Abs Rel and RMSE beside the shading prior's and a
   constant depth's on the same test frames; its time per epoch; the SDF loss's share of a
   training step (a Case 4 step against a Case 2 step on the same batch, first epoch and later);
   then as many further runs as fit in ``--many-timeout`` seconds, trained together by
   ``train-many --throughput 1 2 4 8`` (one epoch of ``--many-frames`` frames each), with its
   table of K runs against one run's time.

The CUDA tests' status says "passed" only where some test ran and none failed; where every one
skipped (no CUDA device) it says "skipped (no CUDA)".

It writes ``gpu_check.json`` and ``gpu_check.md`` into ``--out`` after every step (so a step that
fails or times out is recorded, and the ones before it stay), locked while it runs; it refuses
a non-empty folder it did not write (its marker ``.gpu-check`` says it did). ``--device cpu
--tiny`` is a dry run of the same steps at toy sizes (the test suite runs it).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy
import torch

from geodepth_lite import utils
from geodepth_lite.core import camera, losses, nnsearch_triton, sdf
from geodepth_lite.core.errors import UserError
from geodepth_lite.core.model import DepthNet
from geodepth_lite.data import analytic, datasets, manifest, synth
from geodepth_lite.evaluation import evaluate
from geodepth_lite.training import checkpoint, config, inference, train, train_many

MARKER = ".gpu-check"
EPOCH_KEYS = ("epoch", "epoch_s", "train_frames_per_s", "data_wait_share", "train_total", "val_rmse", "val_abs_rel")
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
    parser.add_argument("--full-timeout", type=int, default=300,
                        help="seconds allowed to the --full run, data included (default 300)")
    parser.add_argument("--many-timeout", type=int, default=150,
                        help="seconds allowed to --full's further runs trained together (default 150; with the "
                             "defaults the whole check stays within 10 minutes)")
    parser.add_argument("--many-frames", type=int, default=400,
                        help="training frames of each further run of --full (one epoch; default 400)")
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


def _paired_medians(fns: list, dev, repeats: int) -> list[float]:
    """The median time of each of ``fns``, timed in turn within each repeat (so that a change of
    the machine's load falls on all of them alike), after one warm-up call of each."""
    for fn in fns:
        fn()
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        for fn, got in zip(fns, times):
            _sync(dev)
            t0 = time.perf_counter()
            fn()
            _sync(dev)
            got.append(time.perf_counter() - t0)
    return [statistics.median(t) for t in times]


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
    tests = utils.package_parent() / "tests" / "test_cuda.py"
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
                              env=dict(os.environ, PYTHONPATH=str(tests.parents[1]) + os.pathsep
                                       + os.environ.get("PYTHONPATH", "")))
    except subprocess.TimeoutExpired:
        return {"status": f"timed out after {timeout} s", "seconds": timeout}
    lines = [ln for ln in proc.stdout.strip().splitlines() if ln.strip()]
    summary = lines[-1] if lines else ""
    return {"status": cuda_test_status(proc.returncode, summary, torch.cuda.is_available()), "summary": summary,
            "tail": "\n".join(lines[-15:]), "seconds": round(time.perf_counter() - t0, 1)}


def cuda_test_status(returncode: int, summary: str, cuda_available: bool) -> str:
    """What pytest's exit status and last line say: "passed" only where some test passed and none
    failed; every test skipped is "skipped (no CUDA)" (or "skipped", with a device), not a pass."""
    counts = {word: int(n) for n, word in re.findall(r"(\d+) (passed|failed|skipped|errors?|deselected)", summary)}
    failed = counts.get("failed", 0) + counts.get("error", 0) + counts.get("errors", 0)
    if returncode not in (0, 5) or failed:
        return f"failed (exit {returncode})"
    if counts.get("passed", 0):
        return "passed"
    if counts.get("skipped", 0):
        return "skipped (no CUDA)" if not cuda_available else "skipped (every test; see the summary)"
    return "not run: no test was collected"


TILES = ("16,32,32,2", "16,32,32,2,1", "8,32,32,1", "8,32,32,1,1", "16,16,32,2,1", "32,32,32,4,1")


def _search_batch(dev, batch: int, size: int, grid: int):
    """A batch of analytic depth maps as the SDF loss searches them: (depth B x 1 x S x S, K B x 3 x 3,
    points B x N x 3, valid B x N, queries B x M x 3: each image's bounding-box grid)."""
    K = torch.from_numpy(analytic.intrinsics(size)).float()
    depth = torch.stack([torch.from_numpy(analytic.depth_map(analytic.KINDS[i % 3], size, seed=i))[None]
                         for i in range(batch)]).to(dev)
    Kb = K.expand(batch, 3, 3).contiguous().to(dev)
    pts = camera.backproject(depth, Kb)
    q = torch.stack([sdf.grid_points(p.min(0).values, p.max(0).values, grid) for p in pts])
    return depth, Kb, pts, torch.ones(pts.shape[:2], dtype=torch.bool, device=dev), q


def tile_sweep(dev, pts, valid, q, repeats: int) -> dict:
    """The Triton search's time per batch for each of :data:`TILES`; the fastest (least median, the
    first listed among equal ones) is set for this process and the runs it starts
    (``nnsearch_triton.TILE_ENV``)."""
    times = {}
    for tile in TILES:
        (nnsearch_triton.BQ, nnsearch_triton.BP, nnsearch_triton.CB, nnsearch_triton.NUM_WARPS,
         nnsearch_triton.MODE) = nnsearch_triton.parse_tile(tile)
        times[tile] = _median_time(lambda: sdf.nearest_indices_grid(pts, valid, q, "triton"), dev, repeats)
    best = min(TILES, key=lambda t: (times[t], TILES.index(t)))
    (nnsearch_triton.BQ, nnsearch_triton.BP, nnsearch_triton.CB, nnsearch_triton.NUM_WARPS,
     nnsearch_triton.MODE) = nnsearch_triton.parse_tile(best)
    os.environ[nnsearch_triton.TILE_ENV] = best
    return {"tiles_s": times, "chosen": best}


def bench_search(dev, batch: int, size: int, grid: int, repeats: int) -> dict:
    """The SDF search and loss at one batch, beside DepthNet's forward and backward: each exact search
    this device runs ("device"; "triton" on CUDA with Triton), its agreement with cKDTree (exact, the
    CPU reference), and the SDF loss forward and backward with the search training uses ("auto")."""
    depth, Kb, pts, valid, q = _search_batch(dev, batch, size, grid)
    ref = sdf.nearest_indices_grid(pts.cpu(), valid.cpu(), q.cpu(), "kdtree")
    res = {"batch": batch, "size": size, "grid": grid, "queries": int(q.shape[0] * q.shape[1]), "methods": {}}
    if nnsearch_triton.usable(dev) and dev.type == "cuda":
        res["tile_sweep"] = tile_sweep(dev, pts, valid, q, repeats)
    for method in ("device", "triton"):
        if method == "triton" and "tile_sweep" not in res:
            continue
        found = sdf.nearest_indices_grid(pts, valid, q, method).cpu()
        res["methods"][method] = {
            "agree": int((found == ref).sum()),
            "batch_s": _median_time(lambda m=method: sdf.nearest_indices_grid(pts, valid, q, m), dev, repeats)}
    res["auto"] = sdf.resolve_method("auto", dev)
    res["timed"] = res["auto"] if res["auto"] in res["methods"] else "device"  # CPU: kdtree, not timed here
    res["search_batch_s"] = res["methods"][res["timed"]]["batch_s"]
    res["agree"] = res["methods"][res["timed"]]["agree"]
    pred0 = depth * 1.05

    def sdf_step():
        p = pred0.clone().requires_grad_()
        losses.sdf_loss(p, depth, Kb, sdf.SDFOptions(grid=grid, cache=None)).backward()

    res["sdf_loss_batch_s"] = _median_time(sdf_step, dev, repeats)
    net = DepthNet().to(dev).train()
    net_cl = DepthNet().to(dev).train().to(memory_format=torch.channels_last)
    image = torch.rand(batch, 3, size, size, device=dev)
    image_cl = image.contiguous(memory_format=torch.channels_last)

    def net_step(net=net, image=image):
        with inference.autocast(dev):
            out = net(image)
        out.float().mean().backward()

    nchw, nhwc = _paired_medians([net_step, lambda: net_step(net_cl, image_cl)], dev, repeats)
    # the layout the paper runs train in: channels_last where its median is less (ties: the default layout)
    res.update(network_fwd_bwd_nchw_s=nchw, network_fwd_bwd_channels_last_s=nhwc, channels_last=nhwc < nchw)
    res["network_fwd_bwd_s"] = min(nchw, nhwc)
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
    pkg_root = str(utils.package_parent())
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
    res["epochs"] = [{k: r[k] for k in EPOCH_KEYS if k in r} for r in rows]
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
        for m, r in b.get("methods", {}).items():
            lines.append(f"| nearest-point search \"{m}\", batch {b['batch']}, {b['size']}x{b['size']}, "
                         f"{b['grid']}^3 grid | {1e3 * r['batch_s']:.2f} ms per batch; agrees with cKDTree on "
                         f"{r['agree']} of {b['queries']} queries |")
        if "tile_sweep" in b:
            sw = b["tile_sweep"]
            lines.append("| Triton tile (queries, points, blocks per chunk, warps[, bound per chunk]): ms per batch | "
                         + ", ".join(f"{t} {1e3 * v:.2f}" for t, v in sw["tiles_s"].items())
                         + f"; chosen {sw['chosen']} |")
        timed = b.get("timed", "device")
        lines += [f"| search \"{timed}\"" + (f" (training here uses \"{b['auto']}\")" if b.get("auto", timed) != timed
                                               else " (the one training uses)") + " | "
                  f"{1e3 * b['search_batch_s']:.1f} ms per batch ({1e3 * b['search_batch_s'] / b['batch']:.2f} ms "
                  f"per field); agrees with cKDTree on {b['agree']} of {b['queries']} queries |",
                  f"| SDF loss forward + backward, same batch | {1e3 * b['sdf_loss_batch_s']:.1f} ms |",
                  "| DepthNet forward + backward (autocast), same batch | " + _layout_words(b) + " |",
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
    lines += _full_lines(report)
    lines += ["", f"Total {report['seconds']:.0f} s."]
    return "\n".join(lines) + "\n"


def _layout_words(b: dict) -> str:
    """DepthNet's step in the two memory formats and the one the paper runs use (records before both were
    timed hold one figure)."""
    if "network_fwd_bwd_nchw_s" not in b:
        return f"{1e3 * b['network_fwd_bwd_s']:.1f} ms"
    return (f"{1e3 * b['network_fwd_bwd_nchw_s']:.1f} ms (NCHW), {1e3 * b['network_fwd_bwd_channels_last_s']:.1f} ms "
            f"(channels_last); the runs train in {'channels_last' if b['channels_last'] else 'NCHW'}")


def _full_lines(report: dict) -> list[str]:
    """The rows of ``--full``: the paper run, its test scores, the SDF share, the runs together."""
    full, lines = report.get("paper_run"), []
    if not full:
        return lines
    done = full.get("epochs", [])
    train_s = sum(r["epoch_s"] for r in done)
    lines.append(f"| paper profile run, Case 4 seed 0, {full['train_frames']} + {full['val_frames']} frames | "
                 f"{len(done)} of {full['epochs_asked']} epochs in {train_s:.0f} s ({train_s / 60:.1f} min; "
                 f"data made in {full.get('data_s', 0):.0f} s); {full['status']} |")
    if done:
        per = statistics.median(r["epoch_s"] for r in done[1:]) if len(done) > 1 else done[0]["epoch_s"]
        last = done[-1]
        lines.append(f"| paper profile run, time per epoch | first {done[0]['epoch_s']:.1f} s, later {per:.1f} s "
                     f"(median); last {last['train_frames_per_s']:.1f} frames/s; val RMSE "
                     f"{last.get('val_rmse', float('nan')):.3f}, Abs Rel {last.get('val_abs_rel', float('nan')):.4f} |")
    if "run_s" in full:
        lines.append(f"| paper profile run end to end (process start to exit: data onto the device, every epoch, "
                     f"every checkpoint) | {full['run_s']:.1f} s ({full['run_s'] / 60:.2f} min); data on the device: "
                     f"{full.get('device_data')} (read in {full.get('load_data_s', float('nan')):.1f} s), "
                     f"channels_last: {full.get('channels_last')} |")
    if "prediction" in full:
        p = full["prediction"]
        lines.append(f"| paper profile, 18 epochs at the run's pace (3600 + 900 frames) | {p['total_min']} min "
                     f"(first epoch {p['first_epoch_s']} s, later {p['later_epoch_s']} s; {p['basis']}) |")
    t = report.get("paper_test", {})
    if "model" in t:
        lines.append(f"| TEST split, {t['frames']} frames (model after epoch {t['model_epoch']}): Abs Rel / RMSE | "
                     + "; ".join(f"{name.replace('_', ' ')} {t[name]['abs_rel']:.4f} / {t[name]['rmse']:.3f}"
                                 for name in ("model", "shading_prior", "constant")) + " |")
    elif t:
        lines.append(f"| TEST split scores | {t['status']} |")
    if "best" in t:
        bt = t["best"]
        lines.append(f"| TEST split, the model of the least validation Abs Rel (epoch {bt['epoch']}, val Abs Rel "
                     f"{bt['val_abs_rel']:.4f}): Abs Rel / RMSE | {bt['abs_rel']:.4f} / {bt['rmse']:.3f} |")
    sh = report.get("sdf_share", {})
    if "share_first" in sh:
        lines.append(f"| SDF loss share of a training step (batch {sh['batch']}, {sh['size']} px, {sh['grid']}^3) | "
                     f"first epoch {share_words(sh, 'first')}, later {share_words(sh, 'later')} |")
    elif sh:
        lines.append(f"| SDF loss share of a training step | {sh['status']} |")
    many = report.get("many_runs", {})
    if "levels" in many:
        lines += ["", *train_many.throughput_markdown(many).strip().splitlines()[2:]]
    elif many:
        lines.append(f"| further runs together | {many['status']} |")
    return lines


def _claim_out(out: Path) -> None:
    """The output folder: new, empty, or one this command wrote before (its marker)."""
    utils.claim_folder(out, MARKER, "gpu-check")
    utils.make_dir(out)
    utils.mark_folder(out, MARKER, "gpu-check")


def _step(report: dict, key: str, fn, save) -> dict:
    """``report[key] = fn()``, or the failure as its status; recorded (``save``) either way."""
    t0 = time.perf_counter()
    try:
        report[key] = fn()
    except Exception as exc:  # recorded, and the next step still runs
        report[key] = {**report.get(key, {}), "status": f"failed: {type(exc).__name__}: {exc}"}
    report.setdefault("step_s", {})[key] = round(time.perf_counter() - t0, 1)
    save()
    return report[key]


def run_gpu_check(args: argparse.Namespace) -> int:
    for name in ("epochs", "frames", "repeats", "step_timeout", "full_timeout", "many_timeout", "many_frames"):
        if getattr(args, name) < 1:
            raise UserError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    dev = utils.parse_device(args.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError("gpu-check --device cuda: no CUDA device is available (a dry run: --device cpu --tiny)")
    out = Path(args.out)
    _claim_out(out)
    with utils.FolderLock(out, "gpu-check folder"):
        t0 = time.perf_counter()
        report = {"tiny": bool(args.tiny), "environment": check_environment(dev)}

        def save():
            report["seconds"] = round(time.perf_counter() - t0, 1)
            utils.write_json_atomic(out / "gpu_check.json", report)
            utils.write_bytes_atomic(out / "gpu_check.md", markdown(report).encode())

        size, batch, grid = (32, 2, 6) if args.tiny else (320, 20, 32)
        frames = min(args.frames, 8) if args.tiny else args.frames
        def cuda_tests():
            _step(report, "cuda_tests", lambda: {"status": "skipped (--no-pytest)"} if args.no_pytest
                  else run_cuda_tests(args.step_timeout), save)
            print(f"gpu-check: CUDA tests {report['cuda_tests']['status']}", flush=True)

        if not args.full:  # --full runs them last: the paper run's time first
            cuda_tests()
        b = _step(report, "search", lambda: bench_search(dev, batch, size, grid, 1 if args.tiny else args.repeats),
                  save)
        print(f"gpu-check: search {b.get('search_batch_s', b.get('status'))}", flush=True)
        if not args.full:  # --full trains the paper profile itself, and predicts from its epochs
            with tempfile.TemporaryDirectory(prefix="gpu-check-") as work:
                _step(report, "training", lambda: time_training(dev, Path(work), frames, 2 if args.tiny
                                                                else args.epochs, size, args.tiny, args.step_timeout),
                      save)
            print(f"gpu-check: training {report['training']['status']}", flush=True)
        else:
            with tempfile.TemporaryDirectory(prefix="gpu-check-full-") as work:
                full_check(dev, Path(work), args, report, save)
            cuda_tests()
        save()
    print(markdown(report))
    print(f"gpu-check: wrote {out / 'gpu_check.json'} and {out / 'gpu_check.md'}")
    return 0


# --------------------------------------------------------------------------- --full


def _scenario_data(dev, work: Path, counts: dict, size: int, tiny: bool) -> Path:
    """The data of ``--full``: the paper manifest's scenario frames, its splits (``counts``) at
    ``size`` px, rendered into ``work`` by the torch renderer on ``dev`` (no VTK); returns the dataset
    folder. Scene building runs in one worker process per CPU core, except in the dry run (``tiny``)."""
    overrides = {"splits": dict(counts)}
    if tiny:
        overrides["camera"] = {"width": size, "height": size}
    m = manifest.load_manifest("scenario_paper", overrides)
    return synth.generate(m, work, progress=False, renderer="torch", device=str(dev),
                          processes=0 if tiny else (os.cpu_count() or 1))


def _paper_counts(tiny: bool) -> dict:
    if tiny:
        return {"train": 12, "val": 4, "test": 4}
    return {k: int(v) for k, v in manifest.load_manifest("scenario_paper")["splits"].items()}


def _train_many(argv: list[str], on_line=None) -> int:
    """``python -m geodepth_lite train-many`` with ``argv``, in this process (its runs in their own)."""
    parser = argparse.ArgumentParser(prog="train-many")
    train_many.add_arguments_train_many(parser)
    return train_many.run_train_many(parser.parse_args(argv), on_line)


def full_check(dev, work: Path, args: argparse.Namespace, report: dict, save) -> None:
    """The paper's recipe end to end (module docstring, step 5); each part recorded as it ends."""
    tiny, size = args.tiny, 32 if args.tiny else 320
    counts = _paper_counts(tiny)
    run = report["paper_run"] = {"status": "making the data", "train_frames": counts["train"],
                                 "val_frames": counts["val"], "test_frames": counts.get("test", 0),
                                 "epochs_asked": 2 if tiny else PAPER_EPOCHS, "epochs": []}
    t0 = time.perf_counter()
    root = _step(report, "paper_data", lambda: {"root": str(_scenario_data(dev, work / "data", counts, size, tiny)),
                                                "seconds": round(time.perf_counter() - t0, 1)}, save)
    run["data_s"] = root.get("seconds", round(time.perf_counter() - t0, 1))
    if "root" not in root:
        run["status"] = f"not run: {root['status']}"
        return save()
    root = Path(root["root"])
    sizes = ["--image-size", "32", "--batch-size", "4", "--epochs", "2"] if tiny else []
    common = ["--profile", "paper", "--cases", "4", "--dataset", str(root), "--device", str(dev), "--no-progress",
              "--keep-best"] + (["--channels-last"] if report.get("search", {}).get("channels_last") else [])
    left = args.full_timeout - run["data_s"]
    run = _step(report, "paper_run", lambda: paper_run(work / "full", common + sizes, left, run, save), save)
    print(f"gpu-check: paper profile run {run['status']}, {len(run.get('epochs', []))} epochs", flush=True)
    ckpt = work / "full" / "case4_seed0" / checkpoint.CHECKPOINT_NAME
    _step(report, "paper_test", lambda: test_split_scores(ckpt, root, dev), save)
    _step(report, "sdf_share", lambda: sdf_step_share(dev, root, size, 2 if tiny else 20, 6 if tiny else 32,
                                                      1 if tiny else args.repeats, "--channels-last" in common), save)
    ks = ["1", "2"] if tiny else ["1", "2", "4", "8"]
    frames = ["--train-frames", "8", "--val-frames", "2"] if tiny else [
        "--train-frames", str(args.many_frames), "--val-frames", "20"]
    _step(report, "many_runs", lambda: many_runs(work / "many", common + sizes[:4] + ["--epochs", "1"] + frames,
                                                 ks, args.many_timeout), save)


def paper_run(out: Path, argv: list[str], seconds: float, run: dict, save) -> dict:
    """Case 4, seed 0 of the paper profile through ``train-many``, stopped after ``seconds``."""
    if seconds < 1:
        return {**run, "status": f"not run: the data took the whole --full-timeout ({run['data_s']:.0f} s)"}
    t0 = time.perf_counter()
    def on_line(text: str) -> None:  # each finished epoch recorded at once (the check may be cut off)
        if ": epoch " in text:
            try:
                rows = checkpoint.read_log(folder)
            except (OSError, ValueError):  # the next epoch's line tries again
                return
            run.update(status="training", epochs=[{k: r[k] for k in EPOCH_KEYS if k in r} for r in rows])
            save()

    folder = out / "case4_seed0"
    code = _train_many([*argv, "--seeds", "0", "--out", str(out), "--time-limit", str(seconds)], on_line)
    group = json.loads((out / "train_many.json").read_text())
    one = group["runs"][0]
    res = {**run, "status": one["status"], "exit": code, "seconds": round(time.perf_counter() - t0, 1),
           "epochs": one["epochs"], "config_hash": one["config_hash"], "run_s": one["seconds"]}
    sessions = (checkpoint.read_log_file(folder) or {}).get("provenance") or [{}]
    res.update({k: sessions[-1][k] for k in ("device_data", "load_data_s", "channels_last") if k in sessions[-1]})
    if one["epochs"]:
        res["prediction"] = predict_paper_time(one["epochs"], run["train_frames"], run["val_frames"])
    return res


def test_split_scores(ckpt: Path, root: Path, dev) -> dict:
    """The trained model's Abs Rel and RMSE on the TEST split, beside the shading prior's and a
    constant depth's on the same frames (``evaluate``'s metrics, median scaling)."""
    if not ckpt.is_file():
        return {"status": "not run: the run wrote no checkpoint (no epoch finished)"}
    ds = evaluate.open_eval_dataset(str(root), split="test")
    base = evaluate.evaluate_baselines(ds, None, names=["shading_prior", "constant"])
    model, cfg = checkpoint.load_model(ckpt, dev)
    res = evaluate.evaluate_model(model, ds, image_size=cfg["image_size"], error_maps=0)
    rows = {"model": res["overall"], **{name: b["overall"] for name, b in base.items()}}
    epoch = int(checkpoint.read_checkpoint(ckpt)["epoch"])
    out = {"status": "completed", "frames": res["n"], "model_epoch": epoch,
           **{name: {"abs_rel": r["abs_rel"], "rmse": r["rmse"]} for name, r in rows.items()}}
    best = ckpt.parent / train.BEST_NAME
    if best.is_file():  # the model chosen on the validation split (train --keep-best), beside the last epoch's
        state = checkpoint.read_checkpoint(best)
        model, cfg = checkpoint.load_model(best, dev)
        r = evaluate.evaluate_model(model, ds, image_size=cfg["image_size"], error_maps=0)["overall"]
        e = int(state["epoch"])
        out["best"] = {"epoch": e, "val_abs_rel": float(state["history"][e - 1]["val_abs_rel"]),
                       "abs_rel": r["abs_rel"], "rmse": r["rmse"]}
    return out


def share_words(sh: dict, when: str) -> str:
    """The SDF share of :func:`sdf_step_share` at ``when`` ("first", "later") in words: a Case 4 step
    timed faster than a Case 2 step (possible at toy sizes) is timing noise, not a negative share."""
    c4, c2 = sh[f"case4_{when}_s"], sh[f"case2_{when}_s"]
    if c4 < c2:
        return f"below the timing noise (Case 4 step {1e3 * c4:.1f} ms, Case 2 step {1e3 * c2:.1f} ms)"
    return f"{100 * sh[f'share_{when}']:.1f} % ({1e3 * c4:.1f} ms a step)"


def sdf_step_share(dev, root: Path, size: int, batch: int, grid: int, repeats: int,
                   channels_last: bool = False) -> dict:
    """The SDF loss's share of a paper-profile training step (forward, every loss term, backward,
    Adam step) on one batch of the training frames: 1 - (Case 2 step) / (Case 4 step), Case 2 being
    Case 4 without the SDF term; with the ground-truth fields searched anew (the first epoch) and
    taken from the cache by frame id (every later epoch), as training does; in the runs' memory format."""
    ds = datasets.load_split(root, "train", size, limit=batch)
    data = inference.to_device(inference.collate([ds[i] for i in range(len(ds))]), dev)
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    image = data["image"].contiguous(memory_format=fmt)
    steps = {}
    ids = [("train", i) for i in range(len(ds))]  # the ground truth's fields keyed by frame, as training keys them
    for case in (4, 2):
        cfg = config.make_config("paper", case, 0, image_size=size, batch_size=batch)
        cfg["sdf_grid"] = grid
        torch.manual_seed(0)
        net = DepthNet().to(dev).train().to(memory_format=fmt)
        opt = torch.optim.Adam(net.parameters(), lr=cfg["lr"])

        def step(cfg=cfg, net=net, opt=opt):
            opt.zero_grad(set_to_none=True)
            with inference.autocast(dev):
                pred = net(image)
            train.compute_losses(pred, data, cfg, frame_ids=ids)[0].backward()
            opt.step()

        steps[case] = step
    cache = sdf.GT_FIELD_CACHE
    saved, cache.max_bytes = cache.max_bytes, 0  # every field searched anew: the first epoch
    try:
        first = _paired_medians([steps[4], steps[2]], dev, repeats)
    finally:
        cache.max_bytes = saved
    later = _paired_medians([steps[4], steps[2]], dev, repeats)  # the warm-up fills the cache
    times = {"case4_first_s": first[0], "case2_first_s": first[1], "case4_later_s": later[0],
             "case2_later_s": later[1]}
    return {"status": "completed", "batch": len(ds), "size": size, "grid": grid, "channels_last": channels_last,
            **times,
            "share_first": 1 - times["case2_first_s"] / times["case4_first_s"],
            "share_later": 1 - times["case2_later_s"] / times["case4_later_s"]}


def many_runs(out: Path, argv: list[str], ks: list[str], seconds: float) -> dict:
    """Further runs of the paper profile trained together (``train-many --throughput``), as many K
    as fit in ``seconds``; its table is the record."""
    _train_many([*argv, "--out", str(out), "--throughput", *ks, "--time-limit", str(seconds)])
    return {"status": "completed", **json.loads((out / "throughput.json").read_text())}
