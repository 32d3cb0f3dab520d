"""Small shared helpers: seeding, atomic writes, where the workbook keeps its files."""

from __future__ import annotations

import contextlib
import json
import os
import random
import re
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch

from geodepth_lite.core.errors import UserError


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (CPU and CUDA); DataLoader workers use `worker_init`."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    if torch.cuda.is_available():
        torch.cuda.manual_seed_all(seed)


DEVICE_TYPES = ("cpu", "cuda", "mps")  # what a --device flag may name (cuda:N picks one GPU)


def parse_device(device: str | torch.device, flag: str = "--device") -> torch.device:
    """``device`` as a torch.device, or ValueError naming ``flag`` and what it accepts (one line,
    instead of torch's RuntimeError listing every backend it knows)."""
    if isinstance(device, torch.device):
        return device
    text = str(device)
    try:
        parsed = torch.device(text) if text == text.strip() else None
    except (RuntimeError, ValueError):
        parsed = None
    if parsed is None or parsed.type not in DEVICE_TYPES:
        raise UserError(f"{flag} {text[:40]!r} is not a device: cpu, cuda or cuda:N (N a GPU's index)")
    return parsed


def worker_init(worker_id: int, temp_dir: str | None = None) -> None:
    """DataLoader ``worker_init_fn``: derive numpy/python seeds from torch's per-worker seed.

    With ``temp_dir`` (a folder the main process owns, ``worker_temp_dir``) the worker's temporary
    files, its multiprocessing socket folder among them, go there: a worker that the loader has to
    kill (one slow to stop after an error) cannot remove its own, and the main process removes them.
    """
    seed = torch.initial_seed() % 2**32
    random.seed(seed)
    np.random.seed(seed)
    if temp_dir is not None:
        tempfile.tempdir = temp_dir


@contextlib.contextmanager
def worker_temp_dir(num_workers: int) -> Iterator[str | None]:
    """A folder of this process for the temporary files of its DataLoader workers (``worker_init``),
    removed with everything in it on leaving, however the block ends; None without workers."""
    if num_workers <= 0:
        yield None
        return
    folder = tempfile.mkdtemp(prefix="gd-")
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


# A DataLoader worker hands tensors to the main process over a Unix socket that multiprocessing
# makes at <temp folder>/gd-XXXXXXXX/pymp-XXXXXXXX/listener-XXXXXXXX (the middle folder:
# worker_temp_dir); Linux allows 107 bytes for its path.
SOCKET_PATH_MAX = 107
SOCKET_NAME_BYTES = len("/gd-12345678/pymp-12345678/listener-12345678")


def workers_fit_temp_dir(num_workers: int) -> int:
    """``num_workers``, or 0 where the temporary folder's path is too long for the workers' sockets.

    Too long a path (``TMPDIR``) makes each worker fail to send its batch, and the loader wait for
    it for ever; loading in the main process instead is slower, never stuck. Says so when it drops
    the workers.
    """
    folder = tempfile.gettempdir()
    if num_workers <= 0 or len(os.fsencode(folder)) + SOCKET_NAME_BYTES <= SOCKET_PATH_MAX:
        return num_workers
    print(f"the temporary folder {folder} is too long for data-loading worker processes (their sockets "
          f"allow {SOCKET_PATH_MAX - SOCKET_NAME_BYTES} characters): loading in the main process instead "
          f"of {num_workers} worker(s); set TMPDIR to a shorter folder to use them", flush=True)
    return 0


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


TEMP_PREFIX = ".geodepth-"  # every temporary file this project writes: .geodepth-<pid>-<name>.<random>.tmp
TEMP_GLOB = TEMP_PREFIX + "*.tmp"  # the names atomic_path's temporary files match (for removing stale ones)
_TEMP_NAME = re.compile(r"\.geodepth-(\d+)-.*\.tmp")  # whole names only: fullmatch
NAME_PART_MAX = 120  # characters of the final name kept in a temporary file's name (file names hold 255 bytes)


def temp_prefix(name: str = "") -> str:
    """The start of a temporary file's name that only this project makes: ``.geodepth-<pid>-<name>.``."""
    return f"{TEMP_PREFIX}{os.getpid()}-{name[:NAME_PART_MAX]}."


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (one of another user counts as alive)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # no such process; a number no process can have
        return False
    except OSError:  # PermissionError: it exists, under another user
        return True
    return True


def stale_temp(path: Path, locked: bool = False) -> bool:
    """Whether ``path`` is a temporary file of this project left by an interrupted writer: its name is
    ``.geodepth-<pid>-...tmp`` and its writer is gone (or, with ``locked`` -- the caller holds the
    folder's lock -- it is any process but this one). A file of any other name is never stale."""
    m = _TEMP_NAME.fullmatch(path.name)
    if not m:
        return False
    pid = int(m.group(1))
    if pid == os.getpid():
        return False
    return locked or not pid_alive(pid)


def remove_stale_temps(folder: str | os.PathLike, recursive: bool = False, locked: bool = False) -> int:
    """Delete half-written temporary files of this project (``TEMP_GLOB``, :func:`stale_temp`) that an
    interrupted writer left in ``folder``; they never carry a final name, so nothing complete is lost,
    and a file the project did not make (``.notes.tmp``) is never touched. Returns how many."""
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    found = folder.rglob(TEMP_GLOB) if recursive else folder.glob(TEMP_GLOB)
    stale = [p for p in found if p.is_file() and not p.is_symlink() and stale_temp(p, locked)]
    for p in stale:
        p.unlink(missing_ok=True)
    return len(stale)


def _temp_beside(path: Path) -> Path:
    """A new empty temporary file beside ``path`` (``temp_prefix``), with the permissions a plain
    ``open()`` would give (the umask applies); a :class:`FileProblem` naming ``path`` if it cannot be made."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path.name), suffix=".tmp", dir=path.parent)
        os.fchmod(fd, file_mode())  # mkstemp creates 0600 whatever the umask
        os.close(fd)
    except OSError as exc:
        raise FileProblem(f"cannot write {path}: {os_reason(exc)}", path) from exc
    return Path(tmp)


def _flush(tmp: Path) -> None:
    with open(tmp, "rb+") as f:
        os.fsync(f.fileno())


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
    tmp_path = _temp_beside(path)
    try:
        yield tmp_path
        _flush(tmp_path)
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


def write_files_atomic(files: dict[Path, bytes]) -> None:
    """Write several files as one set ({path: its bytes}), all or none.

    Every file is first written to a temporary file beside it and flushed (``atomic_path``'s way);
    only when all are on disk are they renamed onto their names, in the order given. A failure
    before the renames (a full disk, say) changes no file of the set. One during them removes every
    file of the set that can be removed, those an earlier writer left under these names too (they
    would no longer match the ones renamed), and no temporary file stays. Raises a
    :class:`FileProblem` naming the file that failed.
    """
    staged: list[tuple[Path, Path]] = []
    renaming = False
    try:
        for path, data in files.items():
            path = Path(path)
            tmp = _temp_beside(path)
            staged.append((tmp, path))
            try:
                tmp.write_bytes(data)
                _flush(tmp)
            except OSError as exc:
                raise FileProblem(f"cannot write {path}: {os_reason(exc)}", path) from exc
        renaming = True
        for tmp, path in staged:
            try:
                os.replace(tmp, path)
            except OSError as exc:
                raise FileProblem(f"cannot write {path}: {os_reason(exc)}", path) from exc
        for folder in dict.fromkeys(path.parent for _, path in staged):
            fsync_dir(folder)
    except BaseException:
        if renaming:
            for _, path in staged:
                with contextlib.suppress(OSError):
                    path.unlink(missing_ok=True)
        raise
    finally:
        for tmp, _ in staged:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)


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


def check_output_dir(path: str | os.PathLike, need_bytes: int = 0) -> Path:
    """``path`` as a folder that can be written, with ``need_bytes`` free, checked before any work.

    The folder is created (with its parents) if missing, then a small probe file is written
    and removed, and the free space is compared with ``need_bytes``. On failure a
    :class:`FileProblem` names the folder, and the folders this call created are removed again,
    so a refused command leaves nothing behind.
    """
    path = Path(path)
    missing = missing_dirs(path)
    try:
        make_dir(path)
        _probe_write(path, path)
        if need_bytes > 0:
            free = shutil.disk_usage(path).free
            if free < need_bytes:
                raise FileProblem(f"cannot write into {path}: no space left on device "
                                  f"({free / 2**20:.1f} MB free, {need_bytes / 2**20:.1f} MB needed)", path)
    except FileProblem:
        remove_empty_dirs(missing)
        raise
    return path


def check_can_create_dir(path: str | os.PathLike) -> Path:
    """``path`` checked as a folder that could be created and written, without creating anything.

    An existing ``path`` is probed as :func:`check_output_dir` does. A missing one is judged by its
    nearest existing parent: that must be a folder a probe file can be written into. Nothing is
    made or removed, so two processes checking the same new folder at once cannot disturb each
    other (one that creates and removes it again could pull it away under the other's probe).
    """
    path = Path(path)
    if path.exists():
        return check_output_dir(path)
    missing = missing_dirs(path)
    parent = (missing[-1] if missing else path.absolute()).parent
    if not parent.is_dir():
        raise FileProblem(f"cannot create folder {path}: {parent} is a file, not a folder", path)
    _probe_write(parent, path)
    return path


def _probe_write(folder: Path, named: Path) -> None:
    """Write and remove a small probe file in ``folder``; a :class:`FileProblem` naming ``named`` if
    that fails."""
    try:
        fd, probe = tempfile.mkstemp(prefix=temp_prefix("write-probe"), suffix=".tmp", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise FileProblem(f"cannot write into {named}: {os_reason(exc)}", named) from exc


def missing_dirs(path: str | os.PathLike) -> list[Path]:
    """The folders that creating ``path`` would make: ``path`` and its missing parents, innermost first."""
    path, out = Path(path).absolute(), []
    while not path.exists() and path != path.parent:
        out.append(path)
        path = path.parent
    return out


def remove_if_empty(path: str | os.PathLike) -> None:
    """Remove the folder ``path`` if it exists and holds nothing (a refused run's leftover)."""
    remove_empty_dirs([Path(path)])


def remove_empty_dirs(folders: list[Path]) -> None:
    """Remove each folder of ``folders`` (innermost first) that exists and holds nothing: what a
    refused command created is taken back; a folder with anything in it stays."""
    for p in folders:
        with contextlib.suppress(OSError):
            p.rmdir()


LOCK_NAME = ".lock"  # the lock file a writer holds in its run folder (see FolderLock)


def claim_folder(path: str | os.PathLike, marker: str, command: str, own_prefixes: tuple[str, ...] = (),
                 option: str = "--out") -> None:
    """Refuse to write into ``path`` unless it is missing, empty, or marked as ``command``'s (its file
    ``marker``, written by :func:`mark_folder`): a file of that name, or a folder holding anything else
    (a user's files, a checkout's tracked folder), is a :class:`FileProblem` and nothing is written.
    The lock file, this project's temporary files and names starting with ``own_prefixes`` (what a
    killed run of ``command`` may leave before it marks the folder) do not count. ``option``: the
    command's option that names the folder, for the message."""
    path = Path(path)
    if os.path.lexists(path) and not path.is_dir():
        raise FileProblem(f"cannot write into {path}: it is a file, not a folder", path)
    if not path.is_dir() or (path / marker).is_file():
        return
    theirs = sorted(p.name for p in path.iterdir()
                    if p.name != LOCK_NAME and not p.name.startswith((TEMP_PREFIX, *own_prefixes)))
    if theirs:
        raise FileProblem(f"cannot write into {path}: the folder holds files {command} did not write ({theirs[0]}"
                          f"{', ...' if len(theirs) > 1 else ''}); choose a new or empty {option}", path)


def mark_folder(path: str | os.PathLike, marker: str, command: str) -> None:
    """Mark ``path`` as written by ``command`` (:func:`claim_folder` then lets it write there again)."""
    write_bytes_atomic(Path(path) / marker, f"written by python -m geodepth_lite {command}\n".encode())


class FolderBusy(FileProblem):
    """Another process holds the folder's lock: one line naming the folder and the holder's PID
    (``holder``: that PID as written in the lock file, or "unknown")."""

    holder: str = "unknown"


class FolderLock:
    """One writer per folder: an OS lock (``fcntl.flock``) on ``<folder>/.lock`` for as long as it is held.

    The kernel frees the lock when its holder exits, however it exits (kill -9 included), so a
    crashed run never leaves the folder locked. A second writer is refused at once with
    :class:`FolderBusy`, naming the holder's PID (written into the lock file). The lock file
    stays after release, unless ``remove_file`` (a user's output folder): then it is unlinked while
    still held, and a writer that opened it meanwhile finds the name gone and tries again on a new
    file (the inode check in ``acquire``), so two writers never hold the same name's lock at once
    while either writes. Where ``fcntl`` is missing (Windows) the lock is a no-op.
    """

    def __init__(self, folder: str | os.PathLike, what: str = "run folder", *, remove_file: bool = False):
        self.folder, self.what = Path(folder), what
        self.path = self.folder / LOCK_NAME
        self.remove_file = remove_file  # an output folder of the user's: take the lock file away on release
        self._fd: int | None = None

    def acquire(self) -> FolderLock:
        try:
            import fcntl  # POSIX only: Windows has no fcntl
        except ImportError:  # pragma: no cover - Windows
            return self
        make_dir(self.folder)
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, file_mode())
            except OSError as exc:
                raise FileProblem(f"cannot write {self.path}: {os_reason(exc)}", self.path) from exc
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
                os.close(fd)
                busy = FolderBusy(f"cannot write into {self.folder}: the {self.what} is in use by process "
                                  f"{holder}; wait for it to finish, or choose another folder", self.folder)
                busy.holder = holder
                raise busy from None
            try:  # the file we locked must still be the one under the name (not unlinked meanwhile)
                if os.fstat(fd).st_ino == os.stat(self.path).st_ino:
                    break
            except FileNotFoundError:
                pass
            os.close(fd)
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            if self.remove_file:  # while still held: a writer that opened the old file retries (inode check)
                with contextlib.suppress(OSError):
                    self.path.unlink()
            os.close(self._fd)  # closing the descriptor frees the flock
            self._fd = None

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


LOCK_WAIT_ENV = "GEODEPTH_LOCK_WAIT"  # seconds a waiting command waits for a busy folder (wait_for_lock)
LOCK_WAIT_DEFAULT = 24 * 3600.0
LOCK_POLL_S = 2.0


def wait_for_lock(lock: FolderLock, waiting_for: str, max_wait: float | None = None, poll: float = LOCK_POLL_S
                  ) -> FolderLock:
    """``lock`` acquired, waiting while another process holds it: one line "waiting for <waiting_for>
    (PID n) holding <folder> ..." when it must wait, then a poll every ``poll`` seconds. After
    ``max_wait`` seconds (default ``$GEODEPTH_LOCK_WAIT``, else a day) the :class:`FolderBusy` is raised."""
    if max_wait is None:
        try:
            max_wait = float(os.environ.get(LOCK_WAIT_ENV, "") or LOCK_WAIT_DEFAULT)
        except ValueError:
            raise UserError(f"{LOCK_WAIT_ENV} must be a number of seconds, got "
                             f"{os.environ[LOCK_WAIT_ENV]!r}") from None
    deadline = time.monotonic() + max_wait
    told = None
    while True:
        try:
            return lock.acquire()
        except FolderBusy as exc:
            left = deadline - time.monotonic()
            if left <= 0:
                raise
            if exc.holder != told:
                print(f"waiting for {waiting_for} (PID {exc.holder}) holding {lock.folder} to finish ...",
                      flush=True)
                told = exc.holder
            time.sleep(min(poll, left))


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json_atomic(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> None:
    write_bytes_atomic(path, (json.dumps(obj, indent=indent, sort_keys=False) + "\n").encode())


def package_parent() -> Path:
    """The folder that holds the ``geodepth_lite`` package: a checkout's root, or where it is installed."""
    return Path(__file__).resolve().parent.parent


def project_root() -> Path | None:
    """The checkout this package runs from (has pyproject.toml), or None when installed elsewhere."""
    root = package_parent()
    return root if (root / "pyproject.toml").exists() and (root / "data_manifests").is_dir() else None


def checkout_path(*parts: str) -> Path:
    """The folder ``parts`` of the checkout (``checkout_path("notebooks", "gallery")``), or a
    FileNotFoundError saying that only a checkout of geodepth-lite has it."""
    root = project_root()
    if root is None:
        raise FileNotFoundError(f"{'/'.join(parts)}/ not found: run from a checkout of geodepth-lite")
    return root.joinpath(*parts)


def manifests_dir() -> Path:
    """The shipped manifests (``data_manifests/``)."""
    return checkout_path("data_manifests")


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
