"""Where and with what a training run was made: one record per training session in the run's
``log.json`` (key ``"provenance"``), written with every epoch's log.

A session is one call of ``train.fit`` that trained at least one epoch: a run resumed after an
interruption has one record per session. Each record holds the UTC start and the UTC time of its
last saved epoch (``end_utc``; the session's end once it finishes), the epochs it trained, the
code's git commit and whether the work tree was clean (None outside a checkout or without git),
the Python, torch and numpy versions, the CPU model and torch's thread count, the device, and
the configuration's hash (``config.config_hash``, the run folder's suffix).
"""

from __future__ import annotations

import datetime as dt
import platform
import subprocess
import sys
from pathlib import Path

import numpy
import torch

from geodepth_lite import utils
from geodepth_lite.training import config

FIELDS = ("start_utc", "end_utc", "first_epoch", "epochs_done", "git_commit", "git_clean", "python", "torch",
          "numpy", "cpu", "threads", "device", "config_hash")


def utc_now() -> str:
    """The current UTC time, ISO 8601 with seconds and a Z."""
    return dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo`` on Linux, else what ``platform`` says)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.partition(":")[2].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def _git(root: Path, *args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=20,
                              stdin=subprocess.DEVNULL)
    except (OSError, subprocess.SubprocessError):  # no git, or it hangs
        return None
    return done.stdout if done.returncode == 0 else None


def code_version() -> tuple[str | None, bool | None]:
    """(commit, whether the tracked files are unchanged) of the checkout the package runs from;
    (None, None) when it is not a git checkout or git is missing."""
    root = utils.project_root()
    if root is None or not (root / ".git").exists():
        return None, None
    commit = _git(root, "rev-parse", "HEAD")
    status = _git(root, "status", "--porcelain", "--untracked-files=no")
    return (commit.strip() if commit else None), (None if status is None else status.strip() == "")


def session(cfg: dict, device: torch.device | str, first_epoch: int) -> dict:
    """A new session's record, its end still open (``end_utc`` None, no epoch done)."""
    commit, clean = code_version()
    dev = torch.device(device)
    name = str(dev)
    if dev.type == "cuda" and torch.cuda.is_available():
        name += f" ({torch.cuda.get_device_name(dev)})"
    return {"start_utc": utc_now(), "end_utc": None, "first_epoch": int(first_epoch), "epochs_done": 0,
            "git_commit": commit, "git_clean": clean, "python": sys.version.split()[0], "torch": torch.__version__,
            "numpy": numpy.__version__, "cpu": cpu_model(), "threads": torch.get_num_threads(), "device": name,
            "config_hash": config.config_hash(cfg)}


def problems(record: dict, cfg: dict) -> list[str]:
    """What a session record lacks or gets wrong for ``cfg``: missing fields, an open end, an end before
    the start, a hash that is not the configuration's. [] for a sound record."""
    out = [f"no {k}" for k in FIELDS if k not in record]
    if out:
        return out
    if record["end_utc"] is None:
        out.append("its end is not recorded")
    elif record["end_utc"] < record["start_utc"]:
        out.append(f"it ends ({record['end_utc']}) before it starts ({record['start_utc']})")
    if record["config_hash"] != config.config_hash(cfg):
        out.append(f"config_hash {record['config_hash']} is not the run's {config.config_hash(cfg)}")
    if record["epochs_done"] < 1:
        out.append("no epoch recorded")
    return out


def earlier_sessions(log: dict | None) -> list[dict]:
    """The session records of an earlier ``log.json`` (read as a dict), those that are dicts."""
    found = (log or {}).get("provenance")
    return [r for r in found if isinstance(r, dict)] if isinstance(found, list) else []
