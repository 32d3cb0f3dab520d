"""Cached training runs: one run per configuration, reused when complete, continued when interrupted.

``ensure_checkpoint`` takes a run's frozen configuration (``config.RunConfig``, made where the command,
``reproduce`` or the notebook starts) and keeps one run per configuration under
``runs/<profile>/checkpoints/case<c>_seed<s>-<config hash>``: reused when complete, continued
when interrupted, trained otherwise. Notebooks 04-07 and ``reproduce`` read their models
this way. This module sits above the training loop (``train.fit``), which sits above the
checkpoint file format (``checkpoint``).
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any, Callable

from tqdm.auto import tqdm

from geodepth_lite import utils
from geodepth_lite.data import manifest
from geodepth_lite.data.datasets import resolve_dataset
from geodepth_lite.training import checkpoint, config
from geodepth_lite.training.config import RunConfig
from geodepth_lite.training.train import fit

# one thread, 64 x 64 input, one training frame forward + backward with every loss term plus its
# share of validation, two runs side by side on a 2-core laptop-class CPU: a teach ablation run
# (8 epochs x 600 frames) takes 2.6-3.0 min (docs/timings.md). Time grows with the pixel count
# of the padded input (the 96 px models with 16 px padding: about 10 min).
SECONDS_PER_FRAME_64 = 0.035


def estimated_minutes(cfg: RunConfig | dict) -> float:
    """About how many minutes training ``cfg`` takes on one core of a laptop-class CPU."""
    m = manifest.load_manifest(cfg["dataset"], cfg.get("dataset_overrides"))
    frames = cfg.get("train_frames") or m["splits"]["train"]
    side = cfg["image_size"] + 2 * cfg.get("input_pad", 0)
    return cfg["epochs"] * frames * SECONDS_PER_FRAME_64 * (side / 64) ** 2 / 60


def _announce(what: str, minutes: float) -> None:
    """Say before a notebook starts training, so a reader knows the wait is expected."""
    when = "under a minute" if minutes < 1 else f"about {minutes:.0f} min"
    print(f"{what}: no finished run found, training it now ({when} on a 2-core laptop CPU; "
          "a class bundle or `reproduce` skips this)", flush=True)


def checkpoint_dir(run: RunConfig) -> Path:
    """Where ``ensure_checkpoint`` keeps the run: runs/<profile>/checkpoints/case<c>_seed<s>-<cfg hash>."""
    return utils.runs_dir() / run.profile / "checkpoints" / run.folder_name


def is_complete(run: RunConfig) -> bool:
    """Whether the cached run of this configuration finished."""
    path = checkpoint_dir(run) / checkpoint.CHECKPOINT_NAME
    if not path.exists():
        return False
    ckpt = checkpoint.read_checkpoint(path)
    return bool(ckpt.get("complete")) and config.config_identity(ckpt["cfg"]) == run.identity


def ensure_checkpoint(run: RunConfig, *, progress: bool = False, announce: bool = True) -> Path:
    """The checkpoint of ``run``: reused when a run with the same configuration finished, continued
    when it was interrupted, trained otherwise (said first, with the expected minutes, unless
    ``announce`` is False)."""
    path = checkpoint_dir(run) / checkpoint.CHECKPOINT_NAME
    if is_complete(run):
        return path
    if announce:
        _announce(f"Case {run.case}, seed {run.seed} ({run.profile}, {run['image_size']} px)",
                  estimated_minutes(run))
    return fit(run.as_dict(), checkpoint_dir(run), resume=True, progress=progress)


def ensure_runs(runs: list[RunConfig], *, workers: int | None = None, progress: bool = False,
                after: Callable[[Path], Any] | None = None) -> list[Path]:
    """``ensure_checkpoint`` for several runs side by side in processes.

    Finished runs are reused and interrupted ones continued. The largest inputs start first (they
    train longest), so a long run overlaps the short ones instead of running alone at the end; the
    weights do not depend on the order, as each run has its own seed and thread count. ``workers``
    defaults to cpu_count // threads. ``after`` (picklable: a module-level function or a
    ``functools.partial`` of one) is called with each checkpoint trained here, in the process that
    trained it, as soon as it is done (e.g. to score the run while the other runs still train).
    Returns the checkpoint paths in the order of ``runs``.
    """
    todo, folders = [], set()
    for run in runs:  # one job per run folder: two runs of one configuration are the same run
        folder = checkpoint_dir(run)
        if folder not in folders and not is_complete(run):
            todo.append(run)
        folders.add(folder)
    if todo:
        _train_all(todo, len(runs), workers, after, progress)
    return [checkpoint_dir(run) / checkpoint.CHECKPOINT_NAME for run in runs]


def _train_all(todo: list[RunConfig], n_runs: int, workers: int | None, after: Callable[[Path], Any] | None,
               progress: bool) -> None:
    """Train the unfinished runs ``todo`` (of ``n_runs`` asked for): datasets first, then the runs."""
    for run in todo:
        resolve_dataset(run.as_dict(), progress=progress)  # build (or find) each dataset before any worker starts
    threads = max(run["threads"] or 0 for run in todo)
    if workers is None:
        workers = max(1, (os.cpu_count() or 1) // threads) if threads else 1
    workers = max(1, min(workers, len(todo)))
    minutes = sorted((estimated_minutes(run) for run in todo), reverse=True)
    _announce(f"{len(todo)} of {n_runs} runs ({todo[0].profile}), {workers} side by side",
              max(minutes[0], sum(minutes) / workers))
    # a fine-tuning run waits for the run it starts from when that one trains here too
    training = {run.folder_name for run in todo}
    source = [run["init_from"] if run["init_from"] in training else None for run in todo]
    order = sorted(range(len(todo)), key=lambda i: (source[i] is not None, -todo[i]["image_size"]))
    if workers == 1:
        for i in order:
            train_run(todo[i], after=after, progress=progress)
    else:
        _train_side_by_side([todo[i] for i in order], [source[i] for i in order], workers, after, progress)


def _train_side_by_side(todo: list[RunConfig], source: list[str | None], workers: int,
                        after: Callable[[Path], Any] | None, progress: bool) -> None:
    """``train_run`` of each run in ``todo`` in ``workers`` processes; a run whose ``source`` (the run
    folder it fine-tunes) trains here too is started when that one is done."""
    names = [run.folder_name for run in todo]
    waiting = [i for i in range(len(todo)) if source[i] is not None]
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(train_run, todo[i], after=after): i for i in range(len(todo)) if source[i] is None}
        desc = f"training {len(todo)} runs, {workers} side by side"
        with tqdm(total=len(todo), disable=not progress, desc=desc) as bar:
            while futures:
                done, _ = wait(futures, return_when=FIRST_COMPLETED)
                for f in done:
                    finished = names[futures.pop(f)]
                    f.result()
                    bar.update()
                    for i in [i for i in waiting if source[i] == finished]:
                        waiting.remove(i)
                        futures[pool.submit(train_run, todo[i], after=after)] = i


def train_run(run: RunConfig, *, after: Callable[[Path], Any] | None = None, progress: bool = False) -> Path:
    """One job of ``ensure_runs``: ``ensure_checkpoint`` without its announcement, then ``after``
    on the checkpoint (when given); returns the checkpoint path."""
    path = ensure_checkpoint(run, progress=progress, announce=False)
    if after is not None:
        after(path)
    return path
