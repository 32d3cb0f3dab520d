"""Cached training runs: one run per configuration, reused when complete, continued when interrupted.

``ensure_checkpoint`` keeps one run per configuration under
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
from geodepth_lite.training.train import fit

# one thread, 64 x 64 input, one training frame forward + backward with every loss term plus its
# share of validation, two runs side by side on a 2-core laptop-class CPU: a teach ablation run
# (8 epochs x 600 frames) takes 2.6-3.0 min (docs/timings.md). Time grows with the pixel count
# of the padded input (the 96 px models with 16 px padding: about 10 min).
SECONDS_PER_FRAME_64 = 0.035


def estimated_minutes(cfg: dict) -> float:
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


def checkpoint_dir(profile: str, case: int = 4, seed: int = 0, **overrides: Any) -> Path:
    """Where ``ensure_checkpoint`` keeps the run: runs/<profile>/checkpoints/case<c>_seed<s>-<cfg hash>."""
    cfg = config.make_config(profile, case, seed, **overrides)
    return utils.runs_dir() / profile / "checkpoints" / f"case{case}_seed{seed}-{config.config_hash(cfg)}"


def is_complete(profile: str, case: int, seed: int, **overrides: Any) -> bool:
    """Whether the cached run of this configuration finished."""
    path = checkpoint_dir(profile, case, seed, **overrides) / checkpoint.CHECKPOINT_NAME
    if not path.exists():
        return False
    ckpt = checkpoint.read_checkpoint(path)
    return bool(ckpt.get("complete")) and config.config_identity(ckpt["cfg"]) == config.config_identity(
        config.make_config(profile, case, seed, **overrides))


def ensure_checkpoint(profile: str, case: int = 4, seed: int = 0, *, progress: bool = False,
                      announce: bool = True, **overrides: Any) -> Path:
    """The checkpoint of ``case``/``seed`` under ``profile``: reused when a run with the same
    configuration finished, continued when it was interrupted, trained otherwise (said first,
    with the expected minutes, unless ``announce`` is False)."""
    cfg = config.make_config(profile, case, seed, **overrides)
    run_dir = checkpoint_dir(profile, case, seed, **overrides)
    path = run_dir / checkpoint.CHECKPOINT_NAME
    if path.exists():
        ckpt = checkpoint.read_checkpoint(path)
        if ckpt.get("complete") and config.config_identity(ckpt["cfg"]) == config.config_identity(cfg):
            return path
    if announce:
        _announce(f"Case {case}, seed {seed} ({profile}, {cfg['image_size']} px)", estimated_minutes(cfg))
    return fit(cfg, run_dir, resume=True, progress=progress)


def predict_checkpoint(profile: str, case: int = 4, seed: int = 0, *, progress: bool = False) -> Path:
    """The checkpoint of the model that notebooks 04, 06, 07 and ``predict`` use: ``case``/``seed``
    trained at the profile's ``predict_image_size`` with its ``predict_overrides`` (the ablation's
    runs use ``image_size`` and the profile's own settings)."""
    return ensure_checkpoint(profile, case, seed, progress=progress, **predict_settings(profile))


def predict_settings(profile: str) -> dict:
    """The training settings that turn an ablation run of ``profile`` into its ``predict`` model."""
    prof = config.get_profile(profile)
    return {**prof.get("predict_overrides", {}), "image_size": prof["predict_image_size"]}


def real_checkpoint(profile: str, case: int = 4, seed: int = 0, *, progress: bool = False) -> Path:
    """The checkpoint of the model for real endoscope frames (notebook 07's zero-shot sections and
    gallery, ``predict`` on your frames): the ``predict`` model with the profile's ``real_overrides``
    (teach: random crops in training, which take away the lumen-in-the-middle prior that real
    close-ups expose; docs/teach_recipe.md). Where those are empty it is the ``predict`` model."""
    return ensure_checkpoint(profile, case, seed, progress=progress, **real_settings(profile))


def real_settings(profile: str) -> dict:
    """The training settings of ``profile``'s model for real frames: ``predict_settings`` and the
    profile's ``real_overrides``."""
    return {**predict_settings(profile), **config.get_profile(profile).get("real_overrides", {})}


def ensure_checkpoints(profile: str, runs: list[tuple[int, int]], *, workers: int | None = None,
                       progress: bool = False, **overrides: Any) -> dict[tuple[int, int], Path]:
    """``ensure_checkpoint`` for several (case, seed) runs, trained side by side in processes.

    With a fixed per-run thread count (``threads`` in the profile) each run gives the same
    weights whether it trains alone or beside others; ``workers`` defaults to
    cpu_count // threads. Returns {(case, seed): checkpoint path}.
    """
    runs = [(int(c), int(s)) for c, s in runs]
    paths = ensure_runs(profile, [(c, s, overrides) for c, s in runs], workers=workers, progress=progress)
    return dict(zip(runs, paths))


def ensure_runs(profile: str, runs: list[tuple[int, int, dict]], *, workers: int | None = None,
                progress: bool = False, after: Callable[[Path], Any] | None = None) -> list[Path]:
    """``ensure_checkpoint`` for several runs, each (case, seed, overrides), side by side in processes.

    Finished runs are reused and interrupted ones continued. The largest inputs start first (they
    train longest), so a long run overlaps the short ones instead of running alone at the end; the
    weights do not depend on the order, as each run has its own seed and thread count. ``workers``
    defaults to cpu_count // threads. ``after`` (picklable: a module-level function or a
    ``functools.partial`` of one) is called with each checkpoint trained here, in the process that
    trained it, as soon as it is done (e.g. to score the run while the other runs still train).
    Returns the checkpoint paths in the order of ``runs``.
    """
    runs = [(int(c), int(s), dict(o or {})) for c, s, o in runs]
    todo, folders, training = [], set(), set()
    for c, s, o in runs:  # one job per run folder: two runs of one configuration are the same run
        folder = checkpoint_dir(profile, c, s, **o)
        if folder not in folders and not is_complete(profile, c, s, **o):
            todo.append((c, s, o))
            training.add(folder.name)
        folders.add(folder)
    if todo:
        cfgs = [config.make_config(profile, c, s, **o) for c, s, o in todo]
        for cfg in cfgs:
            resolve_dataset(cfg, progress=progress)  # build (or find) each dataset before any worker starts
        threads = max(cfg["threads"] or 0 for cfg in cfgs)
        if workers is None:
            workers = max(1, (os.cpu_count() or 1) // threads) if threads else 1
        workers = max(1, min(workers, len(todo)))
        minutes = sorted((estimated_minutes(cfg) for cfg in cfgs), reverse=True)
        _announce(f"{len(todo)} of {len(runs)} runs ({profile}), {workers} side by side",
                  max(minutes[0], sum(minutes) / workers))
        # a fine-tuning run waits for the run it starts from when that one trains here too
        source = [cfg["init_from"] if cfg["init_from"] in training else None for cfg in cfgs]
        order = sorted(range(len(todo)), key=lambda i: (source[i] is not None, -cfgs[i]["image_size"]))
        if workers == 1:
            for i in order:
                train_run(profile, *todo[i], after=after, progress=progress)
        else:
            _train_side_by_side(profile, [todo[i] for i in order], [source[i] for i in order], workers, after,
                                progress)
    return [checkpoint_dir(profile, c, s, **o) / checkpoint.CHECKPOINT_NAME for c, s, o in runs]


def _train_side_by_side(profile: str, todo: list[tuple[int, int, dict]], source: list[str | None], workers: int,
                        after: Callable[[Path], Any] | None, progress: bool) -> None:
    """``train_run`` of each run in ``todo`` in ``workers`` processes; a run whose ``source`` (the run
    folder it fine-tunes) trains here too is started when that one is done."""
    names = [checkpoint_dir(profile, c, s, **o).name for c, s, o in todo]
    waiting = [i for i in range(len(todo)) if source[i] is not None]
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(train_run, profile, *todo[i], after=after): i
                   for i in range(len(todo)) if source[i] is None}
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
                        futures[pool.submit(train_run, profile, *todo[i], after=after)] = i


def train_run(profile: str, case: int, seed: int, overrides: dict, *, after: Callable[[Path], Any] | None = None,
              progress: bool = False) -> Path:
    """One job of ``ensure_runs``: ``ensure_checkpoint`` without its announcement, then ``after``
    on the checkpoint (when given); returns the checkpoint path."""
    path = ensure_checkpoint(profile, case, seed, progress=progress, announce=False, **overrides)
    if after is not None:
        after(path)
    return path
