"""The sandbox a student's notebook runs in while ``course autograde`` grades it.

nbgrader's autograde runs in the lecturer's process, outside the sandbox: it reads the gradebook,
puts the hidden tests back into the notebook and records the scores. Only the notebook's *kernel*,
where the student's code runs, is started inside bubblewrap (``bwrap``) by
:class:`geodepth_lite.workbook.sandbox_kernel.SandboxKernelManager`, which nbgrader's executor uses in place
of jupyter's kernel manager. The cells, hidden tests included, reach the kernel one by one over the
kernel protocol, never as a file the kernel could read ahead. Inside the sandbox the kernel sees:

- read-only: the system's programs and libraries (``/usr``), the Python environment
  (``sys.prefix``, ``sys.base_prefix``), the ``geodepth_lite`` package, and what the lessons read of
  the checkout (``data_manifests/``, ``benchmarks/``, ``pyproject.toml``, the folders of
  ``notebooks/`` such as ``study/``, but not the notebooks, which hold the solutions) and of the
  workspace (``data/``, ``runs/``); nothing else of the checkout (no ``tests/``, ``.git``, nor a
  course folder, a returned-notebooks folder or a grade table kept there), and the course folder
  hidden under an empty one where it lies inside a folder the kernel reads;
- read-write: an empty ``/tmp`` and, inside it, its working folder (:data:`WORK_INSIDE`), which holds
  a read-only copy of each of the submission's files but the notebooks (on the grader's disk, thrown
  away afterwards) and whatever the kernel writes there (in ``/tmp``, so bounded with it: a notebook cannot
  fill the grader's disk with files); that folder stays off ``sys.path`` (``PYTHONSAFEPATH``: a module
  the notebook writes there is never imported in place of an installed one); and the folder of its
  connection sockets;
- no network (a new network namespace: not even the host's loopback), no other process (a new PID
  namespace), the environment cleared but for a few variables, and no capability, even where the
  grader runs as root (:data:`NO_CAPABILITIES`): the kernel can neither remount what it reads as
  writable nor unmount the empty folder laid over the course; and the machine's settings
  (``/proc/sys``) are read-only (:data:`PROC_SETTINGS`), which root may otherwise write without any;
- bounded memory: each of its processes may hold at most ``memory_bytes`` of data (``RLIMIT_DATA``,
  :data:`KERNEL_MEMORY_GIB` GiB unless the lecturer says otherwise), its ``/tmp`` (held in memory) at most
  :data:`TMP_BYTES`, and no file it writes may grow past :data:`FILE_BYTES`. The limits are hard limits,
  set by a small program that then becomes the kernel (:func:`limited`): the student's code can lower
  them, never raise them. Its processes together may hold at most ``memory_bytes`` too, and be at most
  :data:`PROCESSES_MAX`: the grader watches that from outside (:func:`over_limits`) and stops the kernel
  past either.

The kernel talks to the executor through Unix sockets in a private folder (``transport = ipc``), so it
needs no network and never sees another kernel's connection file.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError

SCRATCH_ENV = "GEODEPTH_SANDBOX_SCRATCH"  # the per-submission scratch folder the grader made
HIDDEN_ENV = "GEODEPTH_SANDBOX_HIDE"  # os.pathsep-separated folders hidden inside the sandbox (the course)
REQUIRE_ENV = "GEODEPTH_REQUIRE_SANDBOX"  # "1": the tests fail, not skip, where no sandbox can be made
# what the kernel reads of the checkout (with each folder of notebooks/, never a notebook) and of the workspace
CHECKOUT_READS = ("geodepth_lite", "data_manifests", "benchmarks", "pyproject.toml")
WORKSPACE_READS = ("data", "runs")
KEPT_ENV = ("LANG", "LC_ALL", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "GEODEPTH_LITE_HOME", "MPLBACKEND")
MEMORY_ENV = "GEODEPTH_SANDBOX_MEMORY"  # bytes of data each process of the kernel's may hold (and all together)
KERNEL_MEMORY_GIB = 4.0  # the default of ``course autograde --kernel-memory``
KERNEL_MEMORY_BYTES = int(KERNEL_MEMORY_GIB * (1 << 30))  # the same, in bytes
TMP_BYTES = 1 << 30  # the sandbox's /tmp, a tmpfs: what is written there is held in memory
FILE_BYTES = 1 << 30  # the largest file the kernel may write (its copies of the submission's files are on disk)
WORK_INSIDE = Path("/tmp/work")  # the kernel's working folder, inside its /tmp
FILES_OPEN = 1024  # files one process may hold open (the grader reads them all: see memory_files_bytes)
# run as `python -c LIMITS DATA FSIZE CORE NOFILE ARGV...`: sets each as a hard limit (or keeps the machine's,
# where that is lower: no process without capabilities may raise one), then becomes ARGV
LIMITS = ("import os, resource, sys\n"
          "for name, value in zip(('RLIMIT_DATA', 'RLIMIT_FSIZE', 'RLIMIT_CORE', 'RLIMIT_NOFILE'), sys.argv[1:5]):\n"
          "    hard = resource.getrlimit(getattr(resource, name))[1]\n"
          "    value = int(value) if hard == resource.RLIM_INFINITY else min(int(value), hard)\n"
          "    resource.setrlimit(getattr(resource, name), (value, value))\n"
          "os.execv(sys.argv[5], sys.argv[5:])\n")


def _package_root() -> Path:
    return utils.package_parent()


def _inside(path: Path, folders) -> bool:
    return any(path == f or f in path.parents for f in folders)


def readable_paths(hidden: list[Path] = ()) -> list[Path]:
    """What the kernel may read: the Python environment, the package, the checkout's data the lessons
    read (:data:`CHECKOUT_READS`, and each folder of ``notebooks/`` but not its notebooks) and the
    workspace's ``data/`` and ``runs/``; none of ``hidden``; each path that exists, once, none under
    another."""
    hidden = [Path(h).resolve() for h in hidden]
    paths = [Path(sys.prefix), Path(sys.base_prefix), Path(sys.executable).resolve().parent.parent]
    root = utils.project_root()
    if root is not None:
        paths += [root / name for name in CHECKOUT_READS]
        paths += [d for d in sorted((root / "notebooks").glob("*/")) if not d.name.startswith(".")]
    else:
        paths.append(_package_root() / "geodepth_lite")
    paths += [utils.workspace() / name for name in WORKSPACE_READS]
    out: list[Path] = []
    for p in (p.resolve() for p in paths if p.exists() and not p.is_symlink()):
        if p != Path("/") and not _inside(p, out) and not _inside(p, hidden):
            out = [q for q in out if p not in q.parents] + [p]
    return out


# bubblewrap keeps every capability of a grader run as root (a container, a CI runner): with CAP_SYS_ADMIN
# the kernel could remount what it reads read-only as writable, or unmount the empty folder over the course
NO_CAPABILITIES = ("--cap-drop", "ALL")
# the machine's settings (/proc/sys), read-only: a process whose user is root may write them with no capability
# (the kernel's core_pattern, which names a program the machine runs as root when a process crashes, among them)
PROC_SETTINGS = ("--ro-bind", "/proc/sys", "/proc/sys")
# bubblewrap's /dev is a tmpfs of half the machine's memory, /dev/shm in it: written files there are held in
# memory and counted in no process. /dev/shm gets a small tmpfs of its own (semaphores, shared tensors), the
# rest of /dev is read-only (its devices still open for writing, /dev/null among them)
SHM_BYTES = 64 << 20
DEVICES = ("--size", str(SHM_BYTES), "--tmpfs", "/dev/shm", "--remount-ro", "/dev")


def _system_binds(tmp_bytes: int | None = None) -> list[str]:
    size = ["--size", str(tmp_bytes)] if tmp_bytes else []
    cmd = ["--ro-bind", "/usr", "/usr", "--proc", "/proc", *PROC_SETTINGS, "--dev", "/dev", *DEVICES,
           *size, "--tmpfs", "/tmp"]
    for name in ("bin", "lib", "lib64", "sbin"):
        link = Path("/") / name
        if link.is_symlink():
            cmd += ["--symlink", os.readlink(link), str(link)]
        elif link.is_dir():
            cmd += ["--ro-bind", str(link), str(link)]
    return cmd


def memory_bytes(gib: float) -> int:
    """``gib`` GiB in bytes, for ``course autograde --kernel-memory``; a user's error below 0.5 GiB, where
    Python and the package no longer start, above 65,536 GiB, or where it is not a number."""
    if not (isinstance(gib, (int, float)) and math.isfinite(gib) and 0.5 <= gib <= 65536):
        raise UserError(f"--kernel-memory {gib}: give the GiB a student's kernel may hold, its processes together, "
                        f"from 0.5 to 65536 (default {KERNEL_MEMORY_GIB:g})")
    return int(gib * (1 << 30))


def limited(argv: list[str], memory: int) -> list[str]:
    """``argv`` run with the sandbox's hard limits (see the module docstring): ``memory`` bytes of data per
    process, files up to :data:`FILE_BYTES`, no core dump, at most :data:`FILES_OPEN` files open. The limits
    are set before the kernel starts, and a process without ``CAP_SYS_RESOURCE`` (the sandbox holds none:
    :data:`NO_CAPABILITIES`) cannot raise a hard limit."""
    exe = shutil.which(argv[0]) or argv[0]
    return [sys.executable, "-c", LIMITS, str(int(memory)), str(FILE_BYTES), "0", str(FILES_OPEN), exe, *argv[1:]]


def bwrap_command(argv: list[str], scratch: Path, hidden: list[Path],
                  memory: int = KERNEL_MEMORY_BYTES) -> list[str]:
    """``argv`` (a kernel's command) run inside bubblewrap, ``memory`` bytes of data per process: see the
    module docstring."""
    cmd = ["bwrap", "--die-with-parent", "--new-session", "--unshare-all", "--clearenv", *NO_CAPABILITIES,
           *_system_binds(tmp_bytes=TMP_BYTES)]
    for etc in ("/etc/ld.so.cache", "/etc/localtime", "/etc/nsswitch.conf", "/etc/passwd", "/etc/group", "/etc/fonts"):
        if Path(etc).exists():
            cmd += ["--ro-bind", etc, etc]
    readable = readable_paths(hidden)
    for path in readable:
        if not _inside(path, [Path("/usr")]):
            cmd += ["--ro-bind", str(path), str(path)]
    for path in (Path(h).resolve() for h in hidden):  # the course folder, where it lies under a readable one
        if _inside(path, readable):
            cmd += ["--tmpfs", str(path)]
    work, sockets = scratch / "work", scratch / "kernel"
    cmd += ["--dir", str(WORK_INSIDE)]  # in its bounded /tmp: a file it writes there counts in TMP_BYTES, not on disk
    for item in sorted(work.iterdir()) if work.is_dir() else []:  # the submission's own files, at their names,
        cmd += ["--ro-bind", str(item), str(WORK_INSIDE / item.name)]  # read-only: they lie on the grader's disk
    cmd += ["--bind", str(sockets), str(sockets), "--chdir", str(WORK_INSIDE),
            "--setenv", "HOME", "/tmp", "--setenv", "PATH", f"{Path(sys.executable).parent}:/usr/bin:/bin",
            "--setenv", "PYTHONPATH", str(_package_root()), "--setenv", "MPLBACKEND", "Agg",
            "--setenv", "PYTHONSAFEPATH", "1"]  # its working folder stays off sys.path: no module written there runs
    for key in KEPT_ENV:
        if key in os.environ and key != "MPLBACKEND":
            cmd += ["--setenv", key, os.environ[key]]
    return cmd + ["--", *limited(argv, memory)]


def unavailable() -> str | None:
    """Why no sandbox can be made here (one line), or None when bubblewrap runs a program in one."""
    if shutil.which("bwrap") is None:
        return "bubblewrap (bwrap) is not installed"
    probe = ["bwrap", "--die-with-parent", "--unshare-all", *NO_CAPABILITIES, *_system_binds(tmp_bytes=TMP_BYTES)]
    try:
        done = subprocess.run([*probe, "true"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"bubblewrap cannot start ({exc})"
    if done.returncode != 0:
        lines = (done.stderr or done.stdout).strip().splitlines()
        return f"bubblewrap cannot make a sandbox here ({lines[-1] if lines else f'exit {done.returncode}'})"
    return None


# ----------------------------------------------------------------------------------------- its processes together
# RLIMIT_DATA bounds each process; what a kernel's processes hold together is watched from outside the sandbox
# by the grader (:class:`geodepth_lite.workbook.autograde.KernelWatch`), which stops the kernel past these
PROCESSES_MAX = 64  # processes of one kernel at once, bubblewrap's included
WATCH_S = 0.2  # how often the grader adds up what they hold
_PSS = re.compile(rb"^Pss:\s+(\d+) kB", re.M)


def _parents() -> dict[int, int]:
    """pid -> parent pid of every process this machine shows in /proc."""
    out = {}
    for entry in os.scandir("/proc"):
        if entry.name.isdigit():
            try:
                with open(f"/proc/{entry.name}/stat", "rb") as f:
                    stat = f.read(4096)
                # "pid (name) state ppid ...": a name may hold spaces and parentheses, so read after the last ")"
                out[int(entry.name)] = int(stat[stat.rindex(b")") + 2:].split()[1])
            except (OSError, ValueError, IndexError):
                continue  # ended while it was read
    return out


def descendants(root: int) -> list[int]:
    """Every living process descended from ``root`` (``root`` not among them), parents before children. In
    the sandbox's PID namespace an orphan goes to the namespace's first process, so none leaves the tree."""
    children: dict[int, list[int]] = {}
    for pid, ppid in _parents().items():
        children.setdefault(ppid, []).append(pid)
    out, todo = [], list(children.get(root, []))
    while todo:
        pid = todo.pop(0)
        out.append(pid)
        todo.extend(children.get(pid, []))
    return out


def resident_bytes(pid: int) -> int:
    """What ``pid`` has in memory (its resident size; 0 once it has ended). Pages it shares with another
    process (a forked worker's, a library's) count in both."""
    try:
        with open(f"/proc/{pid}/statm", "rb") as f:
            return int(f.read(4096).split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def held_bytes(pid: int) -> int:
    """``pid``'s share of memory (its proportional set size: a page shared by n processes counts 1/n in each),
    or its resident size where that cannot be read; 0 once it has ended."""
    try:
        with open(f"/proc/{pid}/smaps_rollup", "rb") as f:
            found = _PSS.search(f.read(1 << 16))
        if found:
            return int(found.group(1)) * 1024
    except OSError:
        pass
    return resident_bytes(pid)


# the folder of the kernel's connection sockets lies on the grader's disk, where the kernel may write (it makes
# its sockets there): what it holds is watched too. Its sockets and connection file take a few hundred bytes
SOCKETS_BYTES = 1 << 20
SOCKETS_ENTRIES = 64


def folder_use(folder: Path, entries_max: int = SOCKETS_ENTRIES) -> tuple[int, int]:
    """(entries, bytes of files on disk) under ``folder``, counting no further than ``entries_max`` + 1 entries (so a
    folder of a million files costs no more to read than one of 65); (0, 0) where it cannot be read."""
    entries, size, todo = 0, 0, [folder]
    while todo and entries <= entries_max:
        try:
            with os.scandir(todo.pop()) as it:
                for entry in it:
                    entries += 1
                    if entries > entries_max:
                        break
                    if entry.is_dir(follow_symlinks=False):
                        todo.append(entry.path)
                    elif entry.is_file(follow_symlinks=False):  # its length, or its blocks where more
                        st = entry.stat(follow_symlinks=False)  # (space kept past its end: fallocate's KEEP_SIZE)
                        size += max(st.st_size, st.st_blocks * 512)
        except OSError:
            continue  # removed while it was read
    return entries, size


def sockets_over(folder: Path) -> str | None:
    """Why the kernel's sockets folder ``folder`` holds too much, in words, or None."""
    entries, size = folder_use(folder)
    if entries > SOCKETS_ENTRIES or size > SOCKETS_BYTES:
        what = f"more than {SOCKETS_ENTRIES} files" if entries > SOCKETS_ENTRIES else f"{size / (1 << 20):.1f} MiB"
        return (f"it wrote {what} into the folder of its connection sockets, on the grader's disk (at most "
                f"{SOCKETS_ENTRIES} files, {SOCKETS_BYTES >> 20} MiB)")
    return None


def memory_files_bytes(pids: list[int]) -> int:
    """The memory that the in-memory files (``os.memfd_create``'s) the processes ``pids`` hold open take, each
    file counted once: what is written there shows in no process's resident size until it is mapped."""
    seen, pages = set(), 0
    for pid in pids:
        try:
            fds = os.listdir(f"/proc/{pid}/fd")  # at most FILES_OPEN: a hard limit in the sandbox
        except OSError:
            continue  # ended
        for fd in fds:
            link = f"/proc/{pid}/fd/{fd}"
            try:
                if not os.readlink(link).startswith("/memfd:"):
                    continue
                st = os.stat(link)
            except OSError:
                continue  # closed while it was read
            if (st.st_dev, st.st_ino) not in seen:
                seen.add((st.st_dev, st.st_ino))
                pages += st.st_blocks * 512  # its pages, not its length (a length alone holds no memory)
    return pages


def over_limits(pids: list[int], memory: int, processes: int = PROCESSES_MAX) -> str | None:
    """Why the processes ``pids`` (a kernel's) are past their limits together, in words, or None: more than
    ``processes`` of them, or more than ``memory`` bytes held (their resident sizes are added first, which is
    cheap; their shares only where that sum is over, shared pages then counted once; and to each, the
    in-memory files they hold open)."""
    if len(pids) > processes:
        return f"it started more than {processes} processes at once"
    files = memory_files_bytes(pids)
    if files + sum(resident_bytes(p) for p in pids) <= memory:
        return None
    held = files + sum(held_bytes(p) for p in pids)
    if held <= memory:
        return None
    return (f"its processes held {held / (1 << 30):.2f} GiB together, over the limit of "
            f"{memory / (1 << 30):g} GiB (--kernel-memory)")


# ----------------------------------------------------------------------------------------- what the kernel sends
# The kernel's messages reach nbgrader's process (the lecturer's), which keeps every output in the notebook it
# writes: 600 MB printed took it to 2,700 MB. These bound what it receives and keeps of one kernel.
# one part of a message, at most: zmq drops a larger one unread (MAXMSGSIZE), and what the kernel sends
# next until it reconnects, so the cell waits for its end in vain and the submission could not run
FRAME_BYTES = 32 << 20
CELL_OUTPUT_BYTES = 16 << 20  # the outputs kept of one cell (the lessons' largest: about 3 MB)
NOTEBOOK_OUTPUT_BYTES = 48 << 20  # of one notebook's cells together
DECIDING_BYTES = 4096  # an output past the budget that decides a grade is kept, cut to this many characters
DECIDING_KEPT = 8  # such outputs per cell
OUTPUT_CUT = "[output cut: over the grader's limit of {limit} MiB; what decides the grade is kept]\n"
_BUDGETED = ("stream", "display_data", "execute_result", "error", "update_display_data", "comm_open", "comm_msg")


def message_bytes(content) -> int:
    """About how many bytes ``content`` (a kernel message's, decoded) holds: its text and numbers, walked
    without recursion, so that a deeply nested message costs no stack."""
    counted, todo = 0, [content]
    while todo:
        item = todo.pop()
        if isinstance(item, (str, bytes, bytearray, memoryview)):
            counted += len(item)
        elif isinstance(item, dict):
            todo.extend(item.keys())
            todo.extend(item.values())
            counted += 2
        elif isinstance(item, (list, tuple)):
            todo.extend(item)
            counted += 2
        else:
            counted += 8
    return counted


def deciding(msg: dict) -> bool:
    """Whether nbgrader reads ``msg``'s output to grade a cell: an error, a standard-error stream (both give
    0 points), an execute result (partial credit)."""
    kind, content = msg.get("msg_type"), msg.get("content") or {}
    return kind in ("error", "execute_result") or (kind == "stream" and content.get("name") == "stderr")


def _cut(value, keep: int):
    if isinstance(value, str):
        return value[:keep]
    if isinstance(value, list):
        return [_cut(v, keep) for v in value[:20]]
    if isinstance(value, dict):
        return {k: _cut(v, keep) for k, v in list(value.items())[:20] if isinstance(k, str)}
    return value


class OutputBudget:
    """What nbgrader's process keeps of one kernel's output messages (:meth:`admit`): a cell's outputs up
    to :data:`CELL_OUTPUT_BYTES`, the notebook's up to :data:`NOTEBOOK_OUTPUT_BYTES`. Past either, a cell
    gets one line saying its output was cut, and only the outputs that decide its grade (:func:`deciding`,
    the first :data:`DECIDING_KEPT`, each cut to :data:`DECIDING_BYTES`) are kept, so that the grade is the
    one the whole output would give: nbgrader grades a cell by its first error, standard-error stream or
    execute result."""

    def __init__(self, cell_bytes: int = CELL_OUTPUT_BYTES, notebook_bytes: int = NOTEBOOK_OUTPUT_BYTES):
        self.cell_bytes, self.notebook_bytes = cell_bytes, notebook_bytes
        self.total = 0
        self.cells: dict[str, int] = {}
        self.kept: dict[str, int] = {}  # deciding outputs kept past the budget, per cell

    def admit(self, msg: dict) -> dict | None:
        """``msg`` as nbgrader's process may keep it, a shorter copy, a note that the cell's output was cut,
        or None: dropped."""
        if msg.get("msg_type") not in _BUDGETED:
            return msg
        cell = str((msg.get("parent_header") or {}).get("msg_id"))
        size = message_bytes(msg.get("content")) + message_bytes(msg.get("buffers") or [])
        used = self.cells.get(cell, 0)
        if used >= 0 and used + size <= self.cell_bytes and self.total + size <= self.notebook_bytes:
            self.cells[cell] = used + size
            self.total += size
            return msg
        if used >= 0:  # the first message past the budget: the cell's note, then only what decides
            self.cells[cell] = -1
            if deciding(msg):
                self.kept[cell] = 1
                return dict(msg, content=_cut(msg["content"], DECIDING_BYTES), buffers=[])
            limit = min(self.cell_bytes, self.notebook_bytes) >> 20
            return dict(msg, msg_type="stream", header=dict(msg.get("header") or {}, msg_type="stream"),
                        content={"name": "stdout", "text": OUTPUT_CUT.format(limit=limit)}, buffers=[])
        if deciding(msg) and self.kept.get(cell, 0) < DECIDING_KEPT:
            self.kept[cell] = self.kept.get(cell, 0) + 1
            return dict(msg, content=_cut(msg["content"], DECIDING_BYTES), buffers=[])
        return None
