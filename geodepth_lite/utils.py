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


class FileProblem(OSError):
    """A file that cannot be read or written, as one line: ``cannot <action> <path>: <reason>``.

    The command line prints it as ``error: ...`` with exit status 2 (``cli.main``). It is an
    OSError, so code that handles OSError keeps working; ``path`` names the file.
    """

    def __init__(self, message: str, path: str | os.PathLike | None = None):
        super().__init__(message)
        self.path = None if path is None else Path(path)

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


def os_reason(exc: BaseException) -> str:
    """The reason of an OSError in plain words ("no space left on device"), else its message."""
    if isinstance(exc, OSError) and not isinstance(exc, FileProblem) and exc.strerror:
        return exc.strerror[0].lower() + exc.strerror[1:]
    return str(exc) or type(exc).__name__


def file_mode() -> int:
    """The permissions ``open()`` gives a new file: 0o666 less the process's umask (0o644 under 022)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def fsync_dir(path: str | os.PathLike) -> None:
    """Flush a directory's entries to disk (after a rename), where the platform allows it."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # e.g. Windows: directories cannot be opened
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


TEMP_GLOB = ".*.tmp"  # the names atomic_path's temporary files match (for removing stale ones)


def remove_stale_temps(folder: str | os.PathLike, recursive: bool = False) -> int:
    """Delete half-written temporary files (``TEMP_GLOB``) that an interrupted writer left in
    ``folder``; they never carry a final name, so nothing complete is lost. Returns how many."""
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    stale = [p for p in (folder.rglob(TEMP_GLOB) if recursive else folder.glob(TEMP_GLOB)) if p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    return len(stale)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds.

    An interrupted writer therefore never leaves a half file under the final name. The data is
    flushed to disk (fsync) before the rename and the directory after it, so a power loss
    leaves the old file or the new one, never an empty one. The file gets the permissions a
    plain ``open()`` would (the umask applies). Any OSError becomes a :class:`FileProblem`
    naming ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.fchmod(fd, file_mode())  # mkstemp creates 0600 whatever the umask
        os.close(fd)
    except OSError as exc:
        raise FileProblem(f"cannot write {path}: {os_reason(exc)}", path) from exc
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp_path, path)
        fsync_dir(path.parent)
    except FileProblem:
        raise
    except OSError as exc:
        raise FileProblem(f"cannot write {path}: {os_reason(exc)}", path) from exc
    finally:
        with contextlib.suppress(OSError):
            if tmp_path.exists():
                tmp_path.unlink()


def make_dir(path: str | os.PathLike) -> Path:
    """``path`` as an existing folder (created with its parents); a :class:`FileProblem` if it cannot be."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise FileProblem(f"cannot create folder {path}: a file of that name exists", path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FileProblem(f"cannot create folder {path}: {os_reason(exc)}", path) from exc
    return path


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json_atomic(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> None:
    write_bytes_atomic(path, (json.dumps(obj, indent=indent, sort_keys=False) + "\n").encode())


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """H x W x 3 uint8 from an image file; a :class:`FileProblem` naming the file if it cannot be decoded."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return np.array(im.convert("RGB"))
    except Image.UnidentifiedImageError as exc:
        raise FileProblem(f"cannot read {path}: not an image file, or a damaged one", path) from exc
    except OSError as exc:  # missing, unreadable, truncated ("image file is truncated")
        raise FileProblem(f"cannot read {path}: {os_reason(exc)}", path) from exc


def read_npy(path: str | os.PathLike) -> np.ndarray:
    """A numeric array from a ``.npy`` file (never unpickled); a :class:`FileProblem` naming the file otherwise."""
    try:
        with open(path, "rb") as f:
            if f.read(6) != b"\x93NUMPY":
                raise FileProblem(f"cannot read {path}: not a .npy file (no NumPy header)", path)
        a = np.load(path, allow_pickle=False)
    except FileProblem:
        raise
    except (OSError, ValueError, EOFError) as exc:  # missing, truncated, or pickled objects
        reason = os_reason(exc) if isinstance(exc, OSError) else f"damaged .npy file ({exc})"
        raise FileProblem(f"cannot read {path}: {reason}", path) from exc
    if not isinstance(a, np.ndarray) or a.dtype.kind not in "fiub":
        raise FileProblem(f"cannot read {path}: not a numeric array", path)
    return a


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
