"""Several training runs on one device: separate processes or one process with stacked models?
``python benchmarks/bench_many.py [--device cpu] [--size 64] [--batch 4] [--runs 2]``.

On the same random images, with medians of repeats, it times one training step (DepthNet forward,
a mean-depth loss, backward, Adam step) of K models:

1. one model alone, in this process (the reference);
2. K models stepped one after another in this process (what one process without stacking does);
3. K models stacked (``torch.func.stack_module_state``) and stepped as one with ``torch.vmap``:
   batch norm then cannot keep running statistics (``replace_all_batch_norm_modules_``), so the
   stacked step is not the step ``train`` takes; only its speed is of interest;
4. K processes side by side, each stepping its own model (each with ``--threads`` threads).

It prints steps/s of all K models together and the speedup over (1). Each number is a median over
``--repeats`` timed rounds of ``--steps`` steps after one warm-up round.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def _timed(fn, dev: torch.device, steps: int, repeats: int) -> float:
    """Median seconds per step of ``fn`` (one step per call)."""
    fn()
    times = []
    for _ in range(repeats):
        _sync(dev)
        t0 = time.perf_counter()
        for _ in range(steps):
            fn()
        _sync(dev)
        times.append((time.perf_counter() - t0) / steps)
    return statistics.median(times)


def _models(k: int, dev: torch.device) -> list[torch.nn.Module]:
    from geodepth_lite.core.model import DepthNet

    out = []
    for seed in range(k):
        torch.manual_seed(seed)
        out.append(DepthNet().to(dev).train())
    return out


def _step_fn(model: torch.nn.Module, image: torch.Tensor):
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)

    def step():
        opt.zero_grad(set_to_none=True)
        model(image).mean().backward()
        opt.step()

    return step


def sequential(k: int, dev, image, steps: int, repeats: int) -> float:
    fns = [_step_fn(m, image) for m in _models(k, dev)]
    return _timed(lambda: [f() for f in fns], dev, steps, repeats)


def stacked(k: int, dev, image, steps: int, repeats: int) -> float:
    from torch.func import functional_call, replace_all_batch_norm_modules_, stack_module_state

    models = [replace_all_batch_norm_modules_(m) for m in _models(k, dev)]
    params, buffers = stack_module_state(models)
    base = copy.deepcopy(models[0]).to("meta")
    opt = torch.optim.Adam(list(params.values()), lr=1e-4)

    def one(p, b, x):
        return functional_call(base, (p, b), (x,))

    def step():
        opt.zero_grad(set_to_none=True)
        torch.vmap(one, in_dims=(0, 0, None))(params, buffers, image).mean().backward()
        opt.step()

    return _timed(step, dev, steps, repeats)


def _worker(a: argparse.Namespace) -> int:
    """One of the K processes (``--worker FOLDER``): warm up, say so, wait for the others, time."""
    torch.set_num_threads(a.threads)
    dev = torch.device(a.device)
    image = torch.rand(a.batch, 3, a.size, a.size, device=dev)
    fn = _step_fn(_models(1, dev)[0], image)
    fn()
    folder = Path(a.worker)
    (folder / f"ready-{os.getpid()}").touch()
    while not (folder / "go").exists():  # every process begins its timed rounds together
        time.sleep(0.01)
    print(json.dumps({"step_s": _timed(fn, dev, a.steps, a.repeats)}))
    return 0


def processes(k: int, a: argparse.Namespace) -> float:
    """Seconds per step of all K models: the slowest process's step time (they run side by side)."""
    with tempfile.TemporaryDirectory() as folder:
        argv = [sys.executable, __file__, "--worker", folder, "--device", a.device, "--size", str(a.size),
                "--batch", str(a.batch), "--threads", str(a.threads), "--steps", str(a.steps),
                "--repeats", str(a.repeats)]
        procs = [subprocess.Popen(argv, stdout=subprocess.PIPE, text=True) for _ in range(k)]
        while len(list(Path(folder).glob("ready-*"))) < k and all(p.poll() is None for p in procs):
            time.sleep(0.05)
        (Path(folder) / "go").touch()
        outs = [p.communicate()[0] for p in procs]
    if any(p.returncode for p in procs):
        raise RuntimeError(f"a worker process failed: exit codes {[p.returncode for p in procs]}")
    return max(json.loads(o.strip().splitlines()[-1])["step_s"] for o in outs)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--runs", type=int, default=2, help="K, the models trained together")
    ap.add_argument("--threads", type=int, default=1, help="threads of each process (CPU)")
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", default=None)
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        return _worker(a)
    dev, k = torch.device(a.device), a.runs
    image = torch.rand(a.batch, 3, a.size, a.size, device=dev)
    torch.set_num_threads(a.threads)
    one = _timed(_step_fn(_models(1, dev)[0], image), dev, a.steps, a.repeats)
    seq = sequential(k, dev, image, a.steps, a.repeats)
    torch.set_num_threads(a.threads * k)  # one process given the threads that K processes use together
    stack = stacked(k, dev, image, a.steps, a.repeats)
    torch.set_num_threads(a.threads)
    procs = processes(k, a)
    res = {"device": str(dev), "size": a.size, "batch": a.batch, "runs": k, "threads": a.threads,
           "one_step_s": one, "sequential_s": seq, "stacked_s": stack, "processes_s": procs}
    print(f"{k} runs, {a.size} px, batch {a.batch}, {dev}; steps/s of all runs together (speedup over one run):")
    for name, key in (("one run alone", "one_step_s"), ("one process, in turn", "sequential_s"),
                      (f"one process, stacked (vmap, {a.threads * k} threads)", "stacked_s"),
                      (f"{k} processes ({a.threads} thread each)", "processes_s")):
        runs = 1 if key == "one_step_s" else k
        print(f"  {name:42s} {runs / res[key]:7.2f} steps/s  ({runs * one / res[key]:.2f}x)")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
