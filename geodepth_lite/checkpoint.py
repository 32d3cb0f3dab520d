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
    from geodepth_lite.dataset import resolve_dataset

    runs = [(int(c), int(s)) for c, s in runs]
    todo = [r for r in runs if not is_complete(profile, *r, **overrides)]
    if todo:
        resolve_dataset(config.make_config(profile, *todo[0], **overrides))  # build it once, before any worker
        threads = config.make_config(profile, *todo[0], **overrides)["threads"]
        if workers is None:
            workers = max(1, (os.cpu_count() or 1) // threads) if threads else 1
        workers = max(1, min(workers, len(todo)))
        if workers == 1:
            for case, seed in todo:
                ensure_checkpoint(profile, case, seed, **overrides)
        else:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
                futures = [pool.submit(ensure_checkpoint, profile, case, seed, **overrides) for case, seed in todo]
                for f in futures:
                    f.result()
    return {(c, s): checkpoint_dir(profile, c, s, **overrides) / CHECKPOINT_NAME for c, s in runs}
