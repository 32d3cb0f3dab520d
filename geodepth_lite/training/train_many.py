"""``python -m geodepth_lite train-many``: several training runs at once on one device.

Each run is a lone ``train`` command in a process of its own (``python -m geodepth_lite train
--run-dir OUT/case<c>_seed<s> ...`` with the same settings, through ``cli.main``), started by a scheduler that keeps at
most ``--concurrency`` of them running. A run folder therefore holds exactly what a lone ``train``
run writes (checkpoint.pt, log.csv, log.json; the same configuration and config hash), locked by
its process while it trains; where the profile fixes the thread count (smoke, teach) the weights
are the ones a lone run gives, bit for bit. Why processes and not one process with stacked models:
docs/training_and_evaluation.md ("Several runs at once", measured with benchmarks/bench_many.py).

OUT is new, empty, or one that train-many wrote before (its marker ``.train-many``), and locked for
the length of the command: a second command on it is refused, naming the process that holds it.
Each run's own output goes to ``OUT/logs/case<c>_seed<s>.txt``. A run folder that holds a
checkpoint is refused unless ``--resume``, which continues interrupted runs and skips finished
ones. Progress: a line when a run starts, after each of its epochs, and when it ends.

``--throughput K [K ...]`` measures instead: for each K, K runs (seeds 0..K-1 of the first
``--cases``) trained together under ``OUT/throughput/k<K>/``, and the aggregate steps/s against
one run's, written to ``OUT/throughput.json`` and ``OUT/throughput.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.data import integrity
from geodepth_lite.data.datasets import resolve_dataset
from geodepth_lite.training import checkpoint, config
from geodepth_lite.training.train_cli import SETTING_FLAGS, add_setting_arguments, setting_overrides

MARKER = ".train-many"
# a run's process: ``python -m geodepth_lite train ...``, with the parser of ``train`` alone
TRAIN_MAIN = "import sys; from geodepth_lite import cli; sys.exit(cli.main(sys.argv[1:], commands=('train',)))"
POLL_S = 0.5


def add_arguments_train_many(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", default="teach", help="smoke | teach | paper (default teach)")
    parser.add_argument("--cases", type=int, nargs="+", default=[4], help="ablation cases 1-4 (default 4)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="random seeds (default 0)")
    parser.add_argument("--out", required=True,
                        help="folder of the run folders case<c>_seed<s> (new, empty, or written by train-many)")
    parser.add_argument("--concurrency", type=int, default=None,
                        help="runs training at once (default: on CUDA every run, up to 8; on the CPU the "
                             "cores over the profile's threads per run)")
    parser.add_argument("--resume", action="store_true",
                        help="continue interrupted runs in --out and skip finished ones")
    parser.add_argument("--throughput", type=int, nargs="+", default=None, metavar="K",
                        help="measure instead: K runs together for each K (e.g. 1 2 4 8) against one run")
    parser.add_argument("--time-limit", type=float, default=None,
                        help="seconds: runs still training then are stopped, and no further K is started")
    add_setting_arguments(parser)


@dataclass
class Run:
    """One run of the group: its folder, its ``train`` command, its process while it trains."""

    case: int
    seed: int
    folder: Path
    argv: list[str]
    log_path: Path
    config_hash: str
    proc: subprocess.Popen | None = None
    started: float = 0.0
    ended: float = 0.0
    status: str = "waiting"
    started_at: float = 0.0  # wall-clock times (time.time()) of the start and end
    ended_at: float = 0.0
    rows: list[dict] = field(default_factory=list)

    @property
    def name(self) -> str:
        return f"case {self.case} seed {self.seed}"


def check_device(name: str | None) -> torch.device:
    """``--device`` as a torch device, or a one-line error naming the flag."""
    if name is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError):
        raise UserError(f"--device {name!r} is not a device: use cpu, cuda or cuda:N") from None
    if dev.type not in ("cpu", "cuda"):
        raise UserError(f"--device {name!r}: train-many trains on cpu, cuda or cuda:N")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise UserError(f"--device {name}: no CUDA device is available (use --device cpu)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise UserError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return dev


def default_concurrency(dev: torch.device, cfg: dict, n_runs: int) -> int:
    """On CUDA every run (up to 8); on the CPU as many runs as the cores hold at the profile's
    threads per run (a profile without a fixed thread count: one run at a time)."""
    if dev.type == "cuda":
        return max(1, min(n_runs, 8))
    threads = cfg.get("threads")
    return max(1, min(n_runs, (os.cpu_count() or 1) // threads)) if threads else 1


def settings_argv(args: argparse.Namespace) -> list[str]:
    """The shared settings as ``train`` arguments (a run's command line)."""
    out = []
    for flag, key in SETTING_FLAGS:
        value = getattr(args, key)
        if value is not None:
            out += [flag, repr(value) if isinstance(value, float) else str(value)]
    if args.device is not None:
        out += ["--device", args.device]
    if args.num_workers is not None:
        out += ["--num-workers", str(args.num_workers)]
    if args.no_cache:
        out.append("--no-cache")
    out += [flag for flag, on in (("--keep-best", args.keep_best), ("--channels-last", args.channels_last)) if on]
    return out


def plan_runs(args: argparse.Namespace, out: Path, pairs: list[tuple[int, int]]) -> tuple[list[Run], list[dict]]:
    """The runs to train and their configurations, checked before anything is written: bad settings,
    a run folder holding a checkpoint without ``--resume``, or one of another configuration."""
    runs, cfgs = [], []
    base = settings_argv(args)
    for case, seed in dict.fromkeys(pairs):  # one run per (case, seed), in the order given
        cfg = config.make_config(args.profile, case, seed, **setting_overrides(args))
        folder = out / f"case{case}_seed{seed}"
        ckpt = folder / checkpoint.CHECKPOINT_NAME
        resume = []
        if ckpt.exists():
            if not args.resume:
                raise FileExistsError(f"{ckpt} exists: pass --resume to continue interrupted runs (finished "
                                      "ones are skipped), or choose another --out")
            saved = config.validate_config(checkpoint.read_checkpoint(ckpt)["cfg"])
            if config.config_identity(saved) != config.config_identity(cfg):
                raise UserError(f"cannot resume {ckpt}: it was trained with other settings than these")
            resume = ["--resume"]
        argv = ["train", "--profile", args.profile, "--case", str(case), "--seed", str(seed),
                "--run-dir", str(folder), "--no-progress", "--no-verify", *resume, *base]
        runs.append(Run(case, seed, folder, argv, out / "logs" / f"case{case}_seed{seed}.txt",
                        config.config_hash(cfg)))
        cfgs.append(cfg)
    return runs, cfgs


def prepare_data(cfgs: list[dict], verify: bool, progress: bool) -> None:
    """Each distinct dataset found (or built) and checked once, before any run starts."""
    seen = set()
    for cfg in cfgs:
        key = (cfg["dataset"], json.dumps(cfg.get("dataset_overrides"), sort_keys=True))
        if key in seen:
            continue
        seen.add(key)
        root = resolve_dataset(cfg, progress=progress)
        if verify:
            integrity.check_dataset(root, ("train", "val"))


def child_env() -> dict:
    """The environment of a run's process: this package first on the import path."""
    pkg_root = str(utils.package_parent())
    return dict(os.environ, PYTHONPATH=pkg_root + os.pathsep + os.environ.get("PYTHONPATH", ""),
                PYTHONUNBUFFERED="1")


def _start(run: Run, say) -> None:
    utils.make_dir(run.log_path.parent)
    with open(run.log_path, "ab") as log:  # the child holds its own descriptor
        run.proc = subprocess.Popen([sys.executable, "-c", TRAIN_MAIN, *run.argv], stdout=log,
                                    stderr=subprocess.STDOUT, env=child_env(), start_new_session=True)
    run.started, run.started_at, run.status = time.perf_counter(), time.time(), "running"
    say(f"{run.name}: started (process {run.proc.pid}) -> {run.folder}")


def _read_rows(run: Run) -> list[dict]:
    path = run.folder / checkpoint.LOG_JSON
    try:
        return json.loads(path.read_text())["epochs"] if path.is_file() else []
    except (OSError, ValueError, KeyError):  # between two atomic writes, or not yet there
        return run.rows


def _poll(run: Run, say) -> bool:
    """Reports a run's new epochs; True once its process has ended (its status then set)."""
    rows = _read_rows(run)
    for r in rows[len(run.rows):]:
        metric = f", val Abs Rel {r['val_abs_rel']:.4f}" if "val_abs_rel" in r else ""
        say(f"{run.name}: epoch {r['epoch']} done in {r['epoch_s']:.1f} s{metric}")
    run.rows = rows
    code = run.proc.poll()
    if code is None:
        return False
    run.ended, run.ended_at = time.perf_counter(), time.time()
    if code == 0:
        run.status = "completed"
    else:
        lines = [ln for ln in run.log_path.read_text(errors="replace").splitlines() if ln.strip()]
        run.status = f"failed (exit {code}): {lines[-1] if lines else ''}"
    say(f"{run.name}: {run.status} after {run.ended - run.started:.1f} s")
    return True


def _stop(run: Run, why: str, say) -> None:
    """Stops a run this command started (its process group: the run and its data workers)."""
    if run.proc is not None and run.proc.poll() is None:
        try:
            os.killpg(run.proc.pid, signal.SIGTERM)
            run.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(run.proc.pid, signal.SIGKILL)
            run.proc.wait()
        except ProcessLookupError:
            pass
    run.rows = _read_rows(run)
    run.ended, run.ended_at, run.status = time.perf_counter(), time.time(), why
    say(f"{run.name}: {why}")


def run_group(runs: list[Run], concurrency: int, *, time_limit: float | None = None, say=print) -> float:
    """Trains ``runs``, at most ``concurrency`` at once, until all end or ``time_limit`` seconds
    pass (then the running ones are stopped, the waiting ones not started). Returns the wall time."""
    t0 = time.perf_counter()
    waiting, running = list(runs), []
    try:
        while waiting or running:
            over = time_limit is not None and time.perf_counter() - t0 > time_limit
            if over:
                for run in running:
                    _stop(run, f"stopped at the time limit of {time_limit:.0f} s", say)
                for run in waiting:
                    run.status = "not started (time limit)"
                break
            while waiting and len(running) < concurrency:
                run = waiting.pop(0)
                _start(run, say)
                running.append(run)
            time.sleep(POLL_S)
            running = [run for run in running if not _poll(run, say)]
    except BaseException:  # Ctrl-C, or an error here: no run is left training without its command
        for run in running:
            _stop(run, "stopped: the command was interrupted", say)
        raise
    return time.perf_counter() - t0


def run_summary(run: Run) -> dict:
    keep = ("epoch", "epoch_s", "train_frames_per_s", "data_wait_share", "train_total", "val_total", "val_rmse",
            "val_abs_rel")
    return {"case": run.case, "seed": run.seed, "folder": str(run.folder), "config_hash": run.config_hash,
            "status": run.status, "seconds": round(max(run.ended - run.started, 0.0), 2),
            "started_at": round(run.started_at, 2), "ended_at": round(run.ended_at, 2),
            "epochs": [{k: r[k] for k in keep if k in r} for r in run.rows]}


def _say(t0: float, on_line=None):
    def say(text: str) -> None:
        print(f"train-many [{time.perf_counter() - t0:7.1f} s] {text}", flush=True)
        if on_line is not None:
            on_line(text)

    return say


def _check_numbers(args: argparse.Namespace) -> None:
    if args.concurrency is not None and args.concurrency < 1:
        raise UserError(f"--concurrency must be >= 1, got {args.concurrency}")
    if args.time_limit is not None and not args.time_limit > 0:
        raise UserError(f"--time-limit must be > 0 seconds, got {args.time_limit}")
    if args.throughput is not None:
        if min(args.throughput) < 1:
            raise UserError(f"--throughput: each K must be >= 1, got {args.throughput}")
        if args.resume:
            raise UserError("--throughput measures fresh runs: it does not take --resume")


def run_train_many(args: argparse.Namespace, on_line=None) -> int:
    """The command; ``on_line``: also called with each progress line (``gpu-check`` records its run's
    epochs as they end)."""
    dev = check_device(args.device)
    _check_numbers(args)
    out = Path(args.out)
    utils.claim_folder(out, MARKER, "train-many")  # a file, or a folder of others' files: refused
    created = utils.missing_dirs(out)
    try:
        with utils.FolderLock(out, "train-many folder", remove_file=True):
            say = _say(time.perf_counter(), on_line)
            if args.throughput:
                record = throughput(args, out, dev, say)
            else:
                runs, cfgs = plan_runs(args, out, [(c, s) for c in args.cases for s in args.seeds])
                prepare_data(cfgs, not args.no_verify, not args.no_progress)
                utils.mark_folder(out, MARKER, "train-many")
                record = train_group(runs, cfgs, args, dev, say)
                utils.write_json_atomic(out / "train_many.json", record)
    except BaseException:
        utils.remove_empty_dirs(created)  # a refused command leaves no folder behind (a folder in use stays)
        raise
    if args.throughput:
        print(throughput_markdown(record))
        print(f"train-many: wrote {out / 'throughput.json'} and {out / 'throughput.md'}")
        return 0
    bad = [r for r in record["runs"] if r["status"] not in ("completed", "finished before")]
    print(f"train-many: {len(record['runs']) - len(bad)} of {len(record['runs'])} runs finished in "
          f"{record['wall_s']:.1f} s; record {out / 'train_many.json'}")
    return 1 if bad else 0


def train_group(runs: list[Run], cfgs: list[dict], args: argparse.Namespace, dev: torch.device, say) -> dict:
    """Trains the planned runs (finished ones skipped); the group's record."""
    for run in runs:
        ckpt = run.folder / checkpoint.CHECKPOINT_NAME
        if ckpt.exists() and checkpoint.read_checkpoint(ckpt).get("complete"):
            run.status, run.rows = "finished before", _read_rows(run)
            say(f"{run.name}: finished before, skipped")
    todo = [run for run in runs if run.status == "waiting"]
    k = args.concurrency or default_concurrency(dev, cfgs[0], len(todo))
    if todo:
        say(f"{len(todo)} run(s) of the {args.profile} profile on {dev}, {k} at a time")
    wall = run_group(todo, k, time_limit=args.time_limit, say=say)
    return {"profile": args.profile, "device": str(dev), "concurrency": k, "wall_s": round(wall, 2),
            "runs": [run_summary(r) for r in runs]}


def epoch_size(cfg: dict) -> tuple[int, int]:
    """(training frames, optimizer steps) of one epoch of ``cfg``: the split, or ``train_frames`` of
    it, and those frames over the batch size."""
    root = resolve_dataset(cfg)
    n = sum(1 for line in (root / "train" / "frames.jsonl").read_text().splitlines() if line.strip())
    if cfg.get("train_frames"):
        n = min(n, cfg["train_frames"])
    return n, math.ceil(n / cfg["batch_size"])


def level_row(k: int, runs: list[Run], wall: float, steps: int, frames: int) -> dict:
    """One K of the throughput table: steps/s of all K runs together, over the wall time from the
    first start to the last end (process start, data loading and validation included), and from
    the runs' logs (training time alone: frames over each epoch's training frames/s)."""
    done = sum(steps * len(r.rows) for r in runs)
    per_run = []
    for r in runs:
        train_s = sum(frames / max(row["train_frames_per_s"], 1e-12) for row in r.rows)
        if r.rows and train_s > 0:
            per_run.append(steps * len(r.rows) / train_s)
    return {"k": k, "wall_s": round(wall, 2), "steps": done, "steps_per_s_wall": done / wall if wall else 0.0,
            "steps_per_s_training": sum(per_run), "run_steps_per_s_median": statistics.median(per_run)
            if per_run else 0.0, "completed": sum(r.status == "completed" for r in runs),
            "status": sorted({r.status for r in runs}), "runs": [run_summary(r) for r in runs]}


def throughput(args: argparse.Namespace, out: Path, dev: torch.device, say) -> dict:
    """K runs together for each K of ``--throughput`` (seeds 0..K-1 of the first case), each K after
    the last has ended; a K is not started when the time left cannot hold it (the previous K's wall
    time times K over that K: as if no run overlapped another)."""
    ks = sorted(set(args.throughput) | {1})  # the speedups are over one run alone
    plans = {k: plan_runs(args, out / "throughput" / f"k{k}", [(args.cases[0], s) for s in range(k)]) for k in ks}
    cfg = plans[ks[-1]][1][0]
    prepare_data([cfg], not args.no_verify, not args.no_progress)
    frames, steps = epoch_size(cfg)
    utils.mark_folder(out, MARKER, "train-many")
    record = {"profile": args.profile, "case": args.cases[0], "device": str(dev), "cpu_count": os.cpu_count(),
              "epochs": cfg["epochs"], "steps_per_epoch": steps, "image_size": cfg["image_size"],
              "batch_size": cfg["batch_size"], "threads": cfg.get("threads"), "levels": []}
    t0 = time.perf_counter()
    for k in ks:
        left = None if args.time_limit is None else args.time_limit - (time.perf_counter() - t0)
        need = time_needed(record["levels"], k)
        if left is not None and (left <= 0 or need > left):
            record["levels"].append({"k": k, "status": [f"not run: about {need:.0f} s needed, {max(left, 0):.0f} s "
                                                        "left of the time limit"]})
            continue
        say(f"throughput: {k} run(s) together")
        runs = plans[k][0]
        wall = run_group(runs, k, time_limit=left, say=say)
        record["levels"].append(level_row(k, runs, wall, steps, frames))
        _speedups(record)
        utils.write_json_atomic(out / "throughput.json", record)
    utils.write_json_atomic(out / "throughput.json", record)
    utils.write_bytes_atomic(out / "throughput.md", throughput_markdown(record).encode())
    return record


def time_needed(levels: list[dict], k: int) -> float:
    """The wall time K runs together are expected to need: the last K that ran, its wall time times K
    over that K (as if no run overlapped another); 0 before any ran. A K that was not run is skipped."""
    ran = [lv for lv in levels if "wall_s" in lv]
    return ran[-1]["wall_s"] * k / ran[-1]["k"] if ran else 0.0


def _speedups(record: dict) -> None:
    """Each K's steps/s over one run's (K = 1), wall and training alike, and its wall time over one run's."""
    done = [lv for lv in record["levels"] if "wall_s" in lv]
    if not done or done[0]["k"] != 1:
        return
    base = done[0]
    for lv in done:
        for key in ("steps_per_s_wall", "steps_per_s_training"):
            lv[key.replace("steps_per_s", "speedup")] = lv[key] / base[key] if base[key] else 0.0
        lv["time_vs_one"] = lv["wall_s"] / base["wall_s"] if base["wall_s"] else 0.0


def throughput_markdown(record: dict) -> str:
    lines = [f"# train-many throughput: {record['profile']} profile, Case {record['case']}, on {record['device']}",
             "", f"{record['epochs']} epoch(s) of {record['steps_per_epoch']} steps per run, batch "
             f"{record['batch_size']}, {record['image_size']} px, {record['threads'] or 'default'} thread(s) per run; "
             f"{record['cpu_count']} CPU cores. Speedup: K runs' steps/s over one run's.", "",
             "| K runs together | wall s | x one run's time | steps/s, all runs (wall) | speedup | training steps/s, "
             "all runs (logs) | speedup | runs completed |", "|---|---|---|---|---|---|---|---|"]
    for lv in record["levels"]:
        if "wall_s" not in lv:
            lines.append(f"| {lv['k']} | - | - | - | - | - | - | {'; '.join(lv['status'])} |")
            continue
        lines.append(f"| {lv['k']} | {lv['wall_s']:.1f} | {lv.get('time_vs_one', 0):.2f} | "
                     f"{lv['steps_per_s_wall']:.2f} | {lv.get('speedup_wall', 0):.2f} | "
                     f"{lv['steps_per_s_training']:.2f} | {lv.get('speedup_training', 0):.2f} | "
                     f"{lv['completed']} of {lv['k']} |")
    return "\n".join(lines) + "\n"
