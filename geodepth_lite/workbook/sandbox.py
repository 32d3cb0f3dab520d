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
- read-write: its own scratch folder (a copy of the submission's files but the notebooks, thrown away
  afterwards),
  an empty ``/tmp`` and the folder of its connection sockets;
- no network (a new network namespace: not even the host's loopback), no other process (a new PID
  namespace), the environment cleared but for a few variables;
- bounded memory: each of its processes may hold at most ``memory_bytes`` of data (``RLIMIT_DATA``,
  :data:`KERNEL_MEMORY_GIB` GiB unless the lecturer says otherwise), its ``/tmp`` (held in memory) at most
  :data:`TMP_BYTES`, and no file it writes may grow past :data:`FILE_BYTES`. The limits are hard limits,
  set by a small program that then becomes the kernel (:func:`limited`): the student's code can lower
  them, never raise them.

The kernel talks to the executor through Unix sockets in a private folder (``transport = ipc``), so it
needs no network and never sees another kernel's connection file.
"""

from __future__ import annotations

import math
import os
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
MEMORY_ENV = "GEODEPTH_SANDBOX_MEMORY"  # bytes of data each process of the kernel's may hold
KERNEL_MEMORY_GIB = 4.0  # the default of ``course autograde --kernel-memory``
TMP_BYTES = 1 << 30  # the sandbox's /tmp, a tmpfs: what is written there is held in memory
FILE_BYTES = 1 << 30  # the largest file the kernel may write (its scratch folder is on the grader's disk)
# run as `python -c LIMITS DATA FSIZE CORE ARGV...`: sets each as a hard limit, then becomes ARGV
LIMITS = ("import os, resource, sys\n"
          "for name, value in zip(('RLIMIT_DATA', 'RLIMIT_FSIZE', 'RLIMIT_CORE'), sys.argv[1:4]):\n"
          "    resource.setrlimit(getattr(resource, name), (int(value), int(value)))\n"
          "os.execv(sys.argv[4], sys.argv[4:])\n")


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


def _system_binds(tmp_bytes: int | None = None) -> list[str]:
    size = ["--size", str(tmp_bytes)] if tmp_bytes else []
    cmd = ["--ro-bind", "/usr", "/usr", "--proc", "/proc", "--dev", "/dev", *size, "--tmpfs", "/tmp"]
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
        raise UserError(f"--kernel-memory {gib}: give the GiB each process of a student's kernel may hold, "
                        f"from 0.5 to 65536 (default {KERNEL_MEMORY_GIB:g})")
    return int(gib * (1 << 30))


def limited(argv: list[str], memory: int) -> list[str]:
    """``argv`` run with the sandbox's hard limits (see the module docstring): ``memory`` bytes of data per
    process, files up to :data:`FILE_BYTES`, no core dump. The limits are set before the kernel starts, and a
    process without ``CAP_SYS_RESOURCE`` (bubblewrap drops every capability) cannot raise a hard limit."""
    exe = shutil.which(argv[0]) or argv[0]
    return [sys.executable, "-c", LIMITS, str(int(memory)), str(FILE_BYTES), "0", exe, *argv[1:]]


def bwrap_command(argv: list[str], scratch: Path, hidden: list[Path],
                  memory: int = int(KERNEL_MEMORY_GIB * (1 << 30))) -> list[str]:
    """``argv`` (a kernel's command) run inside bubblewrap, ``memory`` bytes of data per process: see the
    module docstring."""
    cmd = ["bwrap", "--die-with-parent", "--new-session", "--unshare-all", "--clearenv",
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
    cmd += ["--bind", str(work), str(work), "--bind", str(sockets), str(sockets), "--chdir", str(work),
            "--setenv", "HOME", "/tmp", "--setenv", "PATH", f"{Path(sys.executable).parent}:/usr/bin:/bin",
            "--setenv", "PYTHONPATH", str(_package_root()), "--setenv", "MPLBACKEND", "Agg"]
    for key in KEPT_ENV:
        if key in os.environ and key != "MPLBACKEND":
            cmd += ["--setenv", key, os.environ[key]]
    return cmd + ["--", *limited(argv, memory)]


def unavailable() -> str | None:
    """Why no sandbox can be made here (one line), or None when bubblewrap runs a program in one."""
    if shutil.which("bwrap") is None:
        return "bubblewrap (bwrap) is not installed"
    probe = ["bwrap", "--die-with-parent", "--unshare-all", *_system_binds(tmp_bytes=TMP_BYTES)]
    try:
        done = subprocess.run([*probe, "true"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"bubblewrap cannot start ({exc})"
    if done.returncode != 0:
        lines = (done.stderr or done.stdout).strip().splitlines()
        return f"bubblewrap cannot make a sandbox here ({lines[-1] if lines else f'exit {done.returncode}'})"
    return None
