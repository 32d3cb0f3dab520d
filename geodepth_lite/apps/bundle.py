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
unpacking refuses any member outside the run folders, a member larger than its cap or packed like
a zip bomb, a file whose checksum differs, and a run folder that already holds a different
checkpoint or logs of its own; a refused bundle leaves nothing behind.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import os
import re
import tempfile
import zipfile
import zlib
from pathlib import Path, PurePosixPath

import torch

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.data import bounds
from geodepth_lite.data import manifest as mf
from geodepth_lite.training import checkpoint, config

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


def is_bundle(path: Path) -> bool:
    """Whether ``path`` is a regular file holding a class bundle (a zip with ``bundle.json``), read from
    its directory within the bundle's bounds."""
    if path.is_symlink() or not path.is_file():
        return False
    try:
        bounds.check_zip_directory(path, MEMBERS_MAX, "bundle")
        with zipfile.ZipFile(path) as zf:
            return INDEX in zf.namelist()
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, NotImplementedError, RuntimeError):
        return False


def _dataset_of(ckpt: dict, folder: Path) -> str:
    """The dataset a run's configuration names (a shipped manifest's name, or a path); a UserError naming
    the checkpoint when there is none."""
    name = ckpt["cfg"].get("dataset")
    if not isinstance(name, str) or not name:
        raise UserError(f"cannot pack {folder / checkpoint.CHECKPOINT_NAME}: its configuration names no dataset "
                        f"(dataset = {str(name)[:40]!r})")
    return name


def make_bundle(profile: str, out: str | Path | None = None) -> Path:
    """Pack every complete run of ``profile`` into a zip file (default ``<profile>-models.zip`` in
    the workspace); returns its path. Each checkpoint is read once; unfinished runs are left out. The
    folder it is written into is locked while it packs (one line naming the other writer): two bundles
    never write one folder at once."""
    config.get_profile(profile)
    target = Path(out) if out else utils.workspace() / f"{profile}-models.zip"
    with utils.FolderLock(target.parent, "folder of the bundle", remove_file=True):
        return _pack(profile, target)


def _pack(profile: str, target: Path) -> Path:
    if os.path.lexists(target) and not is_bundle(target):  # replaced only when it is an earlier bundle
        raise utils.FileProblem(f"cannot write {target}: it exists and is not a class bundle (bundle replaces only "
                                "a bundle it wrote); choose another --out", target)
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
                datasets.add(_dataset_of(ckpt, folder))
            if not runs:  # leave the block: its temporary file is removed, nothing is written
                raise _NothingToPack
            for name in sorted(datasets):
                if Path(name).is_dir():  # a dataset folder given by path: its own manifest.json travels with it
                    continue
                path = mf.manifest_path(name)
                mf.load_manifest(path)  # a manifest, within its bounds, before its bytes are packed
                add(f"manifests/{path.name}", path.read_bytes())
            zf.writestr(INDEX, json.dumps({"format": BUNDLE_FORMAT, "profile": profile, "runs": runs, "files": files},
                                          indent=1) + "\n")
    except _NothingToPack:
        raise FileNotFoundError(f"no complete run under {utils.runs_dir() / profile / 'checkpoints'}: "
                                f"run `python -m geodepth_lite reproduce --profile {profile}` first") from None
    return target


# What unpacking accepts, checked on the zip's central directory before a byte of a member is read.
INDEX_MAX = 4 * 2**20  # bundle.json: a few KB per run
MEMBER_MAX = {checkpoint.CHECKPOINT_NAME: 2**30, checkpoint.LOG_JSON: 64 * 2**20, checkpoint.LOG_CSV: 64 * 2**20,
              "manifest": 2**20}  # bytes, unpacked
MEMBERS_MAX = 10_000  # members in one bundle
RATIO_MAX = 200  # unpacked / packed size of a member over RATIO_FROM bytes (a zip bomb packs ~1000x)
RATIO_FROM = 2**20
RUN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+=-]{0,99}")  # a run folder's name: case4_seed0-<hash>, 100 at most
MANIFEST_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,99}\.json")  # names: fullmatch
CHUNK = 2**20
SUPPORTED = (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED)


def _refuse(path: Path, reason: str) -> UserError:
    return UserError(f"cannot unpack {path}: {reason}")


def _declared_size(info: zipfile.ZipInfo, cap: int, path: Path) -> None:
    """Refuse a member whose declared size, packing ratio, compression or flags could not be a bundle's."""
    if info.flag_bits & 0x1:
        raise _refuse(path, f"member {info.filename!r} is encrypted (a bundle never is)")
    if info.compress_type not in SUPPORTED:
        raise _refuse(path, f"member {info.filename!r} uses compression method {info.compress_type}, not stored "
                            "or deflated (what `bundle` writes)")
    if info.file_size > cap:
        raise _refuse(path, f"member {info.filename!r} declares {info.file_size / 2**20:.1f} MB unpacked, more than "
                            f"the {cap / 2**20:.0f} MB a bundle's {PurePosixPath(info.filename).name} may hold")
    if info.file_size > RATIO_FROM and info.file_size > RATIO_MAX * max(info.compress_size, 1):
        raise _refuse(path, f"member {info.filename!r} unpacks {info.file_size / max(info.compress_size, 1):.0f} "
                            f"times larger than it is packed (more than {RATIO_MAX}x: a zip bomb?)")


def _stream(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path, sink=None) -> str:
    """A member's SHA-256, read in chunks (never whole) and written to ``sink`` if given; a damaged
    member (bad CRC-32, broken deflate data, longer than declared) is a ValueError naming it."""
    digest, n = hashlib.sha256(), 0
    try:
        with zf.open(info) as f:
            while chunk := f.read(CHUNK):
                n += len(chunk)
                if n > info.file_size:
                    raise _refuse(path, f"member {info.filename!r} is longer than its declared size")
                digest.update(chunk)
                if sink is not None:
                    sink.write(chunk)
    except ValueError:
        raise
    except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, RuntimeError) as exc:
        raise _refuse(path, f"member {info.filename!r} is damaged ({exc})") from None
    except OSError as exc:
        raise utils.FileProblem(f"cannot read {path}: {utils.os_reason(exc)}", path) from exc
    return digest.hexdigest()


def _read_small(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path) -> bytes:
    """A small member's bytes (its size already capped), via :func:`_stream`."""
    buf = io.BytesIO()
    _stream(zf, info, path, buf)
    return buf.getvalue()


def _parse_json(blob: bytes, what: str, path: Path):
    try:
        return json.loads(blob)
    except (ValueError, RecursionError) as exc:  # RecursionError: nested thousands deep
        reason = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise _refuse(path, f"its {what} is not valid JSON ({reason})") from None


def _read_index(zf: zipfile.ZipFile, path: Path) -> dict:
    try:
        info = zf.getinfo(INDEX)
    except KeyError:
        raise UserError(f"{path} is not a geodepth-lite bundle: it has no {INDEX}") from None
    _declared_size(info, INDEX_MAX, path)
    index = _parse_json(_read_small(zf, info, path), INDEX, path)
    if not isinstance(index, dict) or index.get("format") != BUNDLE_FORMAT or not isinstance(index.get("files"), dict):
        raise UserError(f"{path}: {INDEX} is not a bundle index of format {BUNDLE_FORMAT}")
    profile, runs = index.get("profile"), index.get("runs")
    if not isinstance(profile, str):
        raise _refuse(path, f"{INDEX} names profile {profile!r}, not a profile name")
    if not isinstance(runs, list) or not all(isinstance(r, str) for r in runs):
        raise _refuse(path, f"{INDEX} has no list of run names")
    bad = [(k, v) for k, v in index["files"].items()
           if not isinstance(v, str) or len(v) != 64 or any(c not in "0123456789abcdef" for c in v)]
    if bad:
        raise _refuse(path, f"{INDEX} gives {bad[0][0]!r} no SHA-256 (64 hex digits)")
    config.get_profile(profile)
    return index


def _member_target(name: str, path: Path) -> tuple[str, ...]:
    """The parts of a bundle member's name, refused unless it is checkpoints/<run>/<file> or manifests/<file>."""
    parts = PurePosixPath(name).parts
    ok = ((len(parts) == 3 and parts[0] == "checkpoints" and parts[2] in RUN_FILES)
          or (len(parts) == 2 and parts[0] == "manifests" and parts[1].endswith(".json")))
    if not ok or any(p in ("", ".", "..") or "\\" in p for p in parts) or PurePosixPath(name).as_posix() != name:
        raise UserError(f"{path}: refused member {name!r} (a bundle holds checkpoints/<run>/<file> and "
                         "manifests/<file> only)")
    if parts[0] == "checkpoints" and not RUN_NAME.fullmatch(parts[1]):
        raise _refuse(path, f"member {name!r}: run name {parts[1][:40]!r}{'...' if len(parts[1]) > 40 else ''} "
                            f"({len(parts[1])} characters) is not a run folder's name (letters, digits, ._+=-, "
                            "100 characters at most)")
    if parts[0] == "manifests" and not MANIFEST_NAME.fullmatch(parts[1]):
        raise _refuse(path, f"member {name!r} is not a manifest's name (<name>.json, letters, digits, _ and -)")
    return parts


def _checked_infos(zf: zipfile.ZipFile, index: dict, path: Path) -> dict[str, zipfile.ZipInfo]:
    """Every member listed in the index, its name, size, packing and flags checked on the central
    directory (nothing read yet); a run listed must have its checkpoint, and only listed runs appear."""
    infos = zf.infolist()
    if len(infos) > MEMBERS_MAX:
        raise _refuse(path, f"{len(infos)} members, more than a bundle's {MEMBERS_MAX}")
    names = [i.filename for i in infos]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise _refuse(path, f"member {dup!r} appears twice")
    listed = set(index["files"])
    extra = sorted(set(names) - listed - {INDEX})
    if extra:
        raise UserError(f"{path}: member {extra[0]!r} is not listed in {INDEX}")
    by_name = {i.filename: i for i in infos}
    out = {}
    runs = set()
    for name in index["files"]:
        parts = _member_target(name, path)
        if name not in by_name:
            raise UserError(f"{path}: {name} is listed in {INDEX} but missing")
        _declared_size(by_name[name], MEMBER_MAX[parts[2] if parts[0] == "checkpoints" else "manifest"], path)
        out[name] = by_name[name]
        if parts[0] == "checkpoints":
            runs.add(parts[1])
    for run in sorted(runs):
        if f"checkpoints/{run}/{checkpoint.CHECKPOINT_NAME}" not in out:
            raise _refuse(path, f"run {run} has no {checkpoint.CHECKPOINT_NAME} (a bundle never carries logs "
                                "without their model)")
    if runs != set(index["runs"]):
        raise _refuse(path, f"{INDEX} lists runs {sorted(index['runs'])[:3]}, its members hold {sorted(runs)[:3]}")
    return out


def _check_manifests(zf: zipfile.ZipFile, infos: dict[str, zipfile.ZipInfo], index: dict, path: Path) -> None:
    """Refuse a bundle whose weights were trained on a dataset recipe this checkout does not have: each
    bundled manifest is compared with the one of that name in this checkout's data_manifests/ (only)."""
    for name, info in infos.items():
        parts = PurePosixPath(name).parts
        if parts[0] != "manifests":
            continue
        blob = _read_small(zf, info, path)
        if _sha256(blob) != index["files"][name]:
            raise UserError(f"{path}: {name} is damaged (its SHA-256 differs from {INDEX})")
        theirs = _parse_json(blob, f"member {name}", path)
        local = utils.manifests_dir() / parts[1]
        if not local.is_file():
            raise _refuse(path, f"its {name} names a manifest this checkout does not have ({local})")
        try:
            ours = json.loads(local.read_text())
        except (OSError, ValueError) as exc:
            raise utils.FileProblem(f"cannot read {local}: {utils.os_reason(exc)}", local) from exc
        if theirs != ours:
            raise UserError(f"{path}: its {parts[1]} differs from this checkout's {local}: the models were "
                             "trained on another dataset recipe (use the checkout the bundle was made from)")


def _file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


def _plan(root: Path, infos: dict[str, zipfile.ZipInfo], index: dict, path: Path) -> dict[str, dict[Path, str]]:
    """{run: {target file: member name}} of what to write. A run whose checkpoint is already there,
    byte for byte, is left as it is (its logs too); a run folder holding a different checkpoint, or a
    log of its own, is refused: unpacking never replaces a log or a checkpoint."""
    todo: dict[str, dict[Path, str]] = {}
    for name in infos:
        parts = PurePosixPath(name).parts
        if parts[0] == "checkpoints":
            todo.setdefault(parts[1], {})[root / parts[1] / parts[2]] = name
    for run in list(todo):
        ckpt = root / run / checkpoint.CHECKPOINT_NAME
        want = index["files"][f"checkpoints/{run}/{checkpoint.CHECKPOINT_NAME}"]
        if ckpt.is_file():
            if _file_sha256(ckpt) != want:
                raise FileExistsError(f"{ckpt} holds a different checkpoint: move that run folder away to unpack "
                                      f"{path}")
            del todo[run]  # the same model is there already: the run folder stays as it is
            continue
        for target in todo[run]:
            if os.path.lexists(target):
                raise FileExistsError(f"{target} exists without the bundle's checkpoint beside it: move that run "
                                      f"folder away to unpack {path} (unpacking never replaces a log)")
    return todo


def _remove_stale_staging(root: Path) -> None:
    """Temporary files a killed ``unbundle`` left in its run folders (``utils.remove_stale_temps``)."""
    if root.is_dir():
        for folder in root.iterdir():
            if folder.is_dir() and not folder.is_symlink():
                utils.remove_stale_temps(folder)


def unpack_bundle(path: str | Path) -> list[Path]:
    """Unpack a bundle into ``runs/<profile>/checkpoints/``; returns the run folders written.

    Everything is checked before anything is written: the index (size-capped), every member's name,
    declared size, packing ratio, compression and flags on the zip's central directory, then every
    member's SHA-256 read in chunks (nothing is held whole in memory), and the manifests against this
    checkout's. Each run folder written is locked as ``train`` locks it (``checkpoint.run_folder``); its
    files are streamed to temporary files there, each checkpoint is loaded safely from its temporary
    file, and only then are they renamed into place. A run folder that already holds the same
    checkpoint is left as it is; one that holds a different checkpoint, or logs without it, is refused.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"bundle not found: {path}")
    bounds.check_zip_directory(path, MEMBERS_MAX, "bundle")  # before zipfile reads the directory
    try:
        zf = zipfile.ZipFile(path)
    except zipfile.BadZipFile:
        raise UserError(f"{path} is not a zip file (a bundle is made by `python -m geodepth_lite bundle`)") from None
    except (ValueError, EOFError, NotImplementedError, RuntimeError) as exc:
        raise _refuse(path, f"damaged zip file ({exc})") from None
    except OSError as exc:
        raise utils.FileProblem(f"cannot read {path}: {utils.os_reason(exc)}", path) from exc
    with zf:
        index = _read_index(zf, path)
        infos = _checked_infos(zf, index, path)
        _check_manifests(zf, infos, index, path)
        for name, info in infos.items():  # every checksum, before the first write
            if PurePosixPath(name).parts[0] == "checkpoints" and _stream(zf, info, path) != index["files"][name]:
                raise UserError(f"{path}: {name} is damaged (its SHA-256 differs from {INDEX})")
        root = utils.runs_dir() / index["profile"] / "checkpoints"
        _remove_stale_staging(root)  # what a killed unbundle left: writers that are gone
        if not _plan(root, infos, index, path):
            return []
        with contextlib.ExitStack() as stack:
            for run in sorted(_plan(root, infos, index, path)):  # each run folder locked, as train locks it
                stack.enter_context(checkpoint.run_folder(root / run))
            todo = _plan(root, infos, index, path)  # again, under the locks
            for run in todo:
                utils.remove_stale_temps(root / run, locked=True)
            _write_runs(zf, infos, index, todo, path)
        return sorted(root / run for run in todo)


def _write_runs(zf: zipfile.ZipFile, infos: dict[str, zipfile.ZipInfo], index: dict,
                todo: dict[str, dict[Path, str]], path: Path) -> None:
    """Stream every file of ``todo`` to a temporary file beside its target, checking its SHA-256 again
    and loading each checkpoint safely; rename them all into place only when every one passed."""
    temps: dict[Path, Path] = {}
    try:
        for files in todo.values():
            for target, name in files.items():
                fd, tmp = tempfile.mkstemp(prefix=utils.temp_prefix(target.name), suffix=".tmp", dir=target.parent)
                temps[target] = Path(tmp)
                try:
                    with os.fdopen(fd, "wb") as f:
                        digest = _stream(zf, infos[name], path, f)
                        f.flush()
                        os.fsync(f.fileno())
                    os.chmod(tmp, utils.file_mode())
                except OSError as exc:
                    if isinstance(exc, utils.FileProblem):
                        raise
                    raise utils.FileProblem(f"cannot write {target}: {utils.os_reason(exc)}", target) from exc
                if digest != index["files"][name]:
                    raise UserError(f"{path}: {name} is damaged (its SHA-256 differs from {INDEX})")
            ckpt = next(t for t in files if t.name == checkpoint.CHECKPOINT_NAME)
            try:
                state = checkpoint.read_checkpoint(temps[ckpt])  # loads safely, or is refused before it is in place
                checkpoint.check_fits(None, state["model"], temps[ckpt])  # and fits the network the notebooks build
            except ValueError as exc:
                reason = str(exc).replace(str(temps[ckpt]), "").strip()
                raise _refuse(path, f"its {files[ckpt]} is refused ({reason})") from None
        # checkpoints first: a rename failing after one leaves a run that a rerun finds complete and keeps
        for target, tmp in sorted(temps.items(), key=lambda t: t[0].name != checkpoint.CHECKPOINT_NAME):
            try:
                os.replace(tmp, target)
            except OSError as exc:
                raise utils.FileProblem(f"cannot write {target}: {utils.os_reason(exc)}", target) from exc
        for folder in {t.parent for t in temps}:
            utils.fsync_dir(folder)
    finally:
        for tmp in temps.values():
            with contextlib.suppress(OSError):
                tmp.unlink()


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
    if not folders:
        print(f"every trained run of {args.file} is already in place: nothing to unpack")
        return 0
    print(f"{len(folders)} trained runs unpacked under {folders[0].parent}: "
          "the notebooks now load them instead of training")
    return 0
