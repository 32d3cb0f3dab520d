"""Small shared helpers: seeding, atomic writes, where the workbook keeps its files."""

from __future__ import annotations

import contextlib
import json
import os
import random
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (CPU and CUDA); DataLoader workers use `worker_init`."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    try:
        import torch
    except ImportError:  # pragma: no cover - torch is a hard dependency
        return
    torch.manual_seed(seed)
    if torch.cuda.is_available():
        torch.cuda.manual_seed_all(seed)


def worker_init(worker_id: int) -> None:
    """DataLoader ``worker_init_fn``: derive numpy/python seeds from torch's per-worker seed."""
    import torch

    seed = torch.initial_seed() % 2**32
    random.seed(seed)
    np.random.seed(seed)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds.

    An interrupted writer therefore never leaves a half file under the final name.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json_atomic(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> None:
    write_bytes_atomic(path, (json.dumps(obj, indent=indent, sort_keys=False) + "\n").encode())


def project_root() -> Path | None:
    """The checkout this package runs from (has pyproject.toml), or None when installed elsewhere."""
    root = Path(__file__).resolve().parent.parent
    return root if (root / "pyproject.toml").exists() and (root / "data_manifests").is_dir() else None


def manifests_dir() -> Path:
    """The shipped manifests (``data_manifests/``)."""
    root = project_root()
    if root is None:
        raise FileNotFoundError("data_manifests/ not found: run from a checkout of geodepth-lite")
    return root / "data_manifests"


def workspace() -> Path:
    """Where generated datasets, checkpoints and runs go.

    ``$GEODEPTH_LITE_HOME`` if set; else the checkout's root (``data/`` and ``runs/``
    there are git-ignored); else ``~/.cache/geodepth_lite``.
    """
    env = os.environ.get("GEODEPTH_LITE_HOME")
    if env:
        return Path(env).expanduser().resolve()
    root = project_root()
    return root if root is not None else Path.home() / ".cache" / "geodepth_lite"


def data_dir() -> Path:
    return workspace() / "data"


def runs_dir() -> Path:
    return workspace() / "runs"
