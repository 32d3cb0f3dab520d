"""The class bundle: every trained model a profile's notebooks load, in one file to hand out.

After ``reproduce``, an instructor runs ``python -m geodepth_lite bundle`` to pack the complete
runs under ``runs/<profile>/checkpoints/`` into ``<profile>-models.zip``; each student runs
``python -m geodepth_lite unbundle <file>`` and can then execute every notebook without
training (the datasets regenerate byte-identically from the manifests, in seconds to minutes).

What goes in, per run folder: ``checkpoint.pt`` stripped to what prediction and the notebooks
need (weights, configuration, epochs, the per-epoch history: no optimizer, scaler, schedule or
random state, so it cannot be resumed), and its ``log.json`` / ``log.csv``. Beside them,
``bundle.json`` lists every file with its SHA-256, and a copy of each training manifest, so
that unpacking can tell a checkout whose dataset recipe differs from the one the weights were
trained on. Checkpoints stay data: they are read with ``torch.load(weights_only=True)``, and
unpacking refuses any member outside the run folders, a file whose checksum differs, and a
run folder that already holds a different checkpoint.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import zipfile
from pathlib import Path, PurePosixPath

import torch

from geodepth_lite import checkpoint, config, utils
from geodepth_lite import manifest as mf

BUNDLE_FORMAT = 1
INDEX = "bundle.json"
KEEP = ("model", "cfg", "epoch", "complete", "history", "world_size", "format")  # what a bundled checkpoint keeps
RUN_FILES = (checkpoint.CHECKPOINT_NAME, checkpoint.LOG_JSON, checkpoint.LOG_CSV)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def stripped(ckpt: dict) -> bytes:
    """A checkpoint's bytes without optimizer, scaler, schedule and random state."""
    buf = io.BytesIO()
    torch.save({k: v for k, v in ckpt.items() if k in KEEP}, buf)
    return buf.getvalue()


def run_folders(profile: str) -> list[Path]:
    """The run folders of ``profile`` that hold a checkpoint, sorted by name."""
    root = utils.runs_dir() / profile / "checkpoints"
    folders = sorted(p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []
    return [f for f in folders if (f / checkpoint.CHECKPOINT_NAME).is_file()]


class _NothingToPack(Exception):
    """No complete run was found while packing (not an OSError, so the atomic write does not wrap it)."""


def make_bundle(profile: str, out: str | Path | None = None) -> Path:
    """Pack every complete run of ``profile`` into a zip file (default ``<profile>-models.zip`` in
    the workspace); returns its path. Each checkpoint is read once; unfinished runs are left out."""
    config.get_profile(profile)
    target = Path(out) if out else utils.workspace() / f"{profile}-models.zip"
    files: dict[str, str] = {}
    runs: list[str] = []
    datasets: set[str] = set()
    try:
        with utils.atomic_path(target) as tmp, zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            def add(name: str, data: bytes) -> None:  # one member at a time: the bundle never sits in memory whole
                zf.writestr(name, data)
                files[name] = _sha256(data)

            for folder in run_folders(profile):
                ckpt = checkpoint.read_checkpoint(folder / checkpoint.CHECKPOINT_NAME)
                if not ckpt.get("complete"):
                    continue
                runs.append(folder.name)
                add(f"checkpoints/{folder.name}/{checkpoint.CHECKPOINT_NAME}", stripped(ckpt))
                for name in RUN_FILES[1:]:
                    if (folder / name).is_file():
                        add(f"checkpoints/{folder.name}/{name}", (folder / name).read_bytes())
                datasets.add(str(ckpt["cfg"]["dataset"]))
            if not runs:  # leave the block: its temporary file is removed, nothing is written
                raise _NothingToPack
            for name in sorted(datasets):
                if Path(name).is_dir():  # a dataset folder given by path: its own manifest.json travels with it
                    continue
                path = mf.manifest_path(name)
                add(f"manifests/{path.name}", path.read_bytes())
            zf.writestr(INDEX, json.dumps({"format": BUNDLE_FORMAT, "profile": profile, "runs": runs, "files": files},
                                          indent=1) + "\n")
    except _NothingToPack:
        raise FileNotFoundError(f"no complete run under {utils.runs_dir() / profile / 'checkpoints'}: "
                                f"run `python -m geodepth_lite reproduce --profile {profile}` first") from None
    return target


def _read_index(zf: zipfile.ZipFile, path: Path) -> dict:
    try:
        index = json.loads(zf.read(INDEX))
    except KeyError:
        raise ValueError(f"{path} is not a geodepth-lite bundle: it has no {INDEX}") from None
    except ValueError as exc:
        raise ValueError(f"{path}: {INDEX} is not valid JSON ({exc})") from None
    if not isinstance(index, dict) or index.get("format") != BUNDLE_FORMAT or not isinstance(index.get("files"), dict):
        raise ValueError(f"{path}: {INDEX} is not a bundle index of format {BUNDLE_FORMAT}")
    config.get_profile(index.get("profile", ""))
    return index


def _member_target(name: str, path: Path) -> tuple[str, ...]:
    """The parts of a bundle member's name, refused unless it is checkpoints/<run>/<file> or manifests/<file>."""
    parts = PurePosixPath(name).parts
    ok = ((len(parts) == 3 and parts[0] == "checkpoints" and parts[2] in RUN_FILES)
          or (len(parts) == 2 and parts[0] == "manifests" and parts[1].endswith(".json")))
    if not ok or any(p in ("", ".", "..") or "\\" in p for p in parts):
        raise ValueError(f"{path}: refused member {name!r} (a bundle holds checkpoints/<run>/<file> and "
                         "manifests/<file> only)")
    return parts


def _verified_members(zf: zipfile.ZipFile, index: dict, path: Path) -> dict[str, bytes]:
    """Every member listed in the index, read and checked against its SHA-256."""
    listed = set(index["files"])
    extra = sorted(set(zf.namelist()) - listed - {INDEX})
    if extra:
        raise ValueError(f"{path}: member {extra[0]!r} is not listed in {INDEX}")
    data = {}
    for name, digest in index["files"].items():
        _member_target(name, path)
        try:
            blob = zf.read(name)
        except KeyError:
            raise ValueError(f"{path}: {name} is listed in {INDEX} but missing") from None
        if _sha256(blob) != digest:
            raise ValueError(f"{path}: {name} is damaged (its SHA-256 differs from {INDEX})")
        data[name] = blob
    return data


def _check_manifests(data: dict[str, bytes], path: Path) -> None:
    """Refuse a bundle whose weights were trained on a dataset recipe this checkout does not have."""
    for name, blob in data.items():
        parts = PurePosixPath(name).parts
        if parts[0] != "manifests":
            continue
        local = mf.manifest_path(parts[1].removesuffix(".json"))
        if json.loads(blob) != json.loads(local.read_text()):
            raise ValueError(f"{path}: its {parts[1]} differs from this checkout's {local}: the models were "
                             "trained on another dataset recipe (use the checkout the bundle was made from)")


def unpack_bundle(path: str | Path) -> list[Path]:
    """Unpack a bundle into ``runs/<profile>/checkpoints/``; returns the run folders written.

    Everything is checked before anything is written; a run folder that already holds the same
    checkpoint is left as it is, one that holds a different one is refused."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"bundle not found: {path}")
    try:
        zf = zipfile.ZipFile(path)
    except zipfile.BadZipFile:
        raise ValueError(f"{path} is not a zip file (a bundle is made by `python -m geodepth_lite bundle`)") from None
    with zf:
        index = _read_index(zf, path)
        data = _verified_members(zf, index, path)
    _check_manifests(data, path)
    root = utils.runs_dir() / index["profile"] / "checkpoints"
    todo = {}
    for name, blob in data.items():
        parts = PurePosixPath(name).parts
        if parts[0] != "checkpoints":
            continue
        target = root / parts[1] / parts[2]
        if target.is_file() and target.read_bytes() != blob and parts[2] == checkpoint.CHECKPOINT_NAME:
            raise FileExistsError(f"{target} holds a different checkpoint: move that run folder away to unpack "
                                  f"{path}")
        todo[target] = blob
    for target, blob in todo.items():
        utils.write_bytes_atomic(target, blob)
    for folder in sorted({t.parent for t in todo}):
        checkpoint.read_checkpoint(folder / checkpoint.CHECKPOINT_NAME)  # each one loads safely, or this names it
    return sorted({t.parent for t in todo})


# --------------------------------------------------------------------------- command line


def add_arguments_bundle(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", default="teach", help="whose trained runs to pack (default teach)")
    parser.add_argument("--out", default=None, help="the zip file to write (default <workspace>/<profile>-models.zip)")


def run_bundle(args: argparse.Namespace) -> int:
    path = make_bundle(args.profile, args.out)
    n = len(json.loads(zipfile.ZipFile(path).read(INDEX))["runs"])
    print(f"{path}: {n} trained runs, {path.stat().st_size / 2**20:.1f} MB "
          f"(unpack with `python -m geodepth_lite unbundle {path.name}`)")
    return 0


def add_arguments_unbundle(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="a bundle made by `python -m geodepth_lite bundle`")


def run_unbundle(args: argparse.Namespace) -> int:
    folders = unpack_bundle(args.file)
    print(f"{len(folders)} trained runs unpacked under {folders[0].parent if folders else utils.runs_dir()}: "
          "the notebooks now load them instead of training")
    return 0
