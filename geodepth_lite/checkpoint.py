"""Checkpoints: atomic save and read, the per-epoch logs, cached runs, loading a trained model.

A checkpoint (``checkpoint.pt``, written by ``train.fit`` once per epoch) holds "model",
"optimizer", "scaler", "schedule", "cfg", "epoch" (epochs done), "complete", "rng" (every
random state, so a resumed run ends bit-identical) and "history" (the per-epoch log rows).
``ensure_checkpoint`` keeps one run per configuration under
``runs/<profile>/checkpoints/case<c>_seed<s>-<config hash>``: reused when complete,
continued when interrupted, trained otherwise. Notebooks 04-07 read their models this way.
"""

from __future__ import annotations

import csv
import io
import json
import os
import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

from geodepth_lite import config, utils

CHECKPOINT_NAME = "checkpoint.pt"
LOG_CSV = "log.csv"
LOG_JSON = "log.json"


def rng_state(loader_gen: torch.Generator) -> dict:
    """Every random state a training run draws from (torch, numpy, python, the DataLoader's, CUDA's)."""
    state = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
        "loader_generator": loader_gen.get_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict, loader_gen: torch.Generator) -> None:
    """Restore what :func:`rng_state` saved."""
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    loader_gen.set_state(state["loader_generator"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: Path, payload: dict) -> None:
    """``torch.save`` to a temporary file, then rename: an interrupted save leaves the old file whole."""
    buf = io.BytesIO()
    torch.save(payload, buf)
    utils.write_bytes_atomic(path, buf.getvalue())


def read_checkpoint(path: str | os.PathLike) -> dict:
    """A checkpoint dict; a clear error for a missing, unreadable or foreign file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except PermissionError as exc:
        raise utils.FileProblem(f"cannot read {path}: {utils.os_reason(exc)}", path) from exc
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad file
        raise ValueError(f"checkpoint {path} is unreadable: {exc}") from None
    if not isinstance(ckpt, dict) or "model" not in ckpt or "cfg" not in ckpt:
        raise ValueError(f"checkpoint {path} lacks 'model'/'cfg' entries: not a geodepth-lite checkpoint")
    bad = [k for k, v in ckpt["model"].items()
           if isinstance(v, torch.Tensor) and v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise ValueError(f"checkpoint {path} holds non-finite weights (NaN or inf) in {len(bad)} tensor(s), "
                         f"first {bad[0]}: the model is unusable (retrain it, or resume from an earlier copy)")
    return ckpt


def write_logs(run_dir: Path, cfg: dict, history: list[dict]) -> None:
    """log.json (config + one row per epoch) and log.csv (the same rows), both atomic."""
    utils.write_json_atomic(run_dir / LOG_JSON, {"cfg": cfg, "epochs": history})
    if not history:
        return
    fields = list(history[0])
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for row in history:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    utils.write_bytes_atomic(run_dir / LOG_CSV, buf.getvalue().encode())


def read_log(run_dir: str | os.PathLike) -> list[dict]:
    """The per-epoch rows of ``log.json`` in ``run_dir`` (or beside a checkpoint file)."""
    p = Path(run_dir)
    if p.is_file():
        p = p.parent
    return json.loads((p / LOG_JSON).read_text())["epochs"]


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu"):
    """(DepthNet in eval mode on ``device``, its training cfg) from a checkpoint file."""
    from geodepth_lite.model import DepthNet

    ckpt = read_checkpoint(path)
    model = DepthNet(padding=ckpt["cfg"].get("padding", "zeros"), input_pad=int(ckpt["cfg"].get("input_pad", 0)))
    model.load_state_dict(ckpt["model"])
    return model.to(device).eval(), dict(ckpt["cfg"])


# --------------------------------------------------------------------------- cached runs


def checkpoint_dir(profile: str, case: int = 4, seed: int = 0, **overrides: Any) -> Path:
    """Where ``ensure_checkpoint`` keeps the run: runs/<profile>/checkpoints/case<c>_seed<s>-<cfg hash>."""
    cfg = config.make_config(profile, case, seed, **overrides)
    return utils.runs_dir() / profile / "checkpoints" / f"case{case}_seed{seed}-{config.config_hash(cfg)}"


def is_complete(profile: str, case: int, seed: int, **overrides: Any) -> bool:
    """Whether the cached run of this configuration finished."""
    path = checkpoint_dir(profile, case, seed, **overrides) / CHECKPOINT_NAME
    if not path.exists():
        return False
    ckpt = read_checkpoint(path)
    return bool(ckpt.get("complete")) and config.config_identity(ckpt["cfg"]) == config.config_identity(
        config.make_config(profile, case, seed, **overrides))


def ensure_checkpoint(profile: str, case: int = 4, seed: int = 0, *, progress: bool = False,
                      **overrides: Any) -> Path:
    """The checkpoint of ``case``/``seed`` under ``profile``: reused when a run with the same
    configuration finished, continued when it was interrupted, trained otherwise."""
    from geodepth_lite.train import fit

    cfg = config.make_config(profile, case, seed, **overrides)
    run_dir = checkpoint_dir(profile, case, seed, **overrides)
    path = run_dir / CHECKPOINT_NAME
    if path.exists():
        ckpt = read_checkpoint(path)
        if ckpt.get("complete") and config.config_identity(ckpt["cfg"]) == config.config_identity(cfg):
            return path
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


def ensure_checkpoints(profile: str, runs: list[tuple[int, int]], *, workers: int | None = None,
                       **overrides: Any) -> dict[tuple[int, int], Path]:
    """``ensure_checkpoint`` for several (case, seed) runs, trained side by side in processes.

    With a fixed per-run thread count (``threads`` in the profile) each run gives the same
    weights whether it trains alone or beside others; ``workers`` defaults to
    cpu_count // threads. Returns {(case, seed): checkpoint path}.
    """
    runs = [(int(c), int(s)) for c, s in runs]
    paths = ensure_runs(profile, [(c, s, overrides) for c, s in runs], workers=workers)
    return dict(zip(runs, paths))


def ensure_runs(profile: str, runs: list[tuple[int, int, dict]], *, workers: int | None = None,
                progress: bool = False) -> list[Path]:
    """``ensure_checkpoint`` for several runs, each (case, seed, overrides), side by side in processes.

    Finished runs are reused and interrupted ones continued. The largest inputs start first (they
    train longest), so a long run overlaps the short ones instead of running alone at the end; the
    weights do not depend on the order, as each run has its own seed and thread count. ``workers``
    defaults to cpu_count // threads. Returns the checkpoint paths in the order of ``runs``.
    """
    from geodepth_lite.dataset import resolve_dataset

    runs = [(int(c), int(s), dict(o or {})) for c, s, o in runs]
    todo, folders = [], set()
    for c, s, o in runs:  # one job per run folder: two runs of one configuration are the same run
        folder = checkpoint_dir(profile, c, s, **o)
        if folder not in folders and not is_complete(profile, c, s, **o):
            todo.append((c, s, o))
        folders.add(folder)
    if todo:
        cfgs = [config.make_config(profile, c, s, **o) for c, s, o in todo]
        for cfg in cfgs:
            resolve_dataset(cfg, progress=progress)  # build (or find) each dataset before any worker starts
        threads = max(cfg["threads"] or 0 for cfg in cfgs)
        if workers is None:
            workers = max(1, (os.cpu_count() or 1) // threads) if threads else 1
        workers = max(1, min(workers, len(todo)))
        order = sorted(range(len(todo)), key=lambda i: -cfgs[i]["image_size"])
        if workers == 1:
            for i in order:
                c, s, o = todo[i]
                ensure_checkpoint(profile, c, s, progress=progress, **o)
        else:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor, as_completed

            from tqdm.auto import tqdm

            with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
                futures = [pool.submit(ensure_checkpoint, profile, *todo[i][:2], **todo[i][2]) for i in order]
                for f in tqdm(as_completed(futures), total=len(futures), disable=not progress,
                              desc=f"training {len(futures)} runs, {workers} side by side"):
                    f.result()
    return [checkpoint_dir(profile, c, s, **o) / CHECKPOINT_NAME for c, s, o in runs]
