"""What a file from elsewhere may be, checked before it is read: images (pixels, from the header),
manifests and the files a dataset names (bytes, and inside the dataset's folder), ``.npy`` arrays
(plain numbers, the header's size; never unpickled). Every reader of the data wing and the commands
that read what a user gives (``predict``, the evaluation) hold a file to these bounds first; a file
over one is a :class:`~geodepth_lite.utils.FileProblem` naming it.
"""

from __future__ import annotations

import math
import os
import struct
import warnings
from pathlib import Path

import numpy as np
from PIL import Image

from geodepth_lite.core.errors import UserError
from geodepth_lite.utils import FileProblem, os_reason

MAX_PIXELS = 50_000_000  # an image (frame, mask, depth map) is refused above this many pixels, before decoding
# PIL warns on opening an image over 89 megapixels; every reader here refuses it first, in one line
warnings.filterwarnings("ignore", category=Image.DecompressionBombWarning)


def check_pixels(width: int, height: int, path: str | os.PathLike, what: str = "image",
                 max_pixels: int | None = None) -> None:
    """A :class:`FileProblem` naming ``path`` when ``width`` x ``height`` is over ``max_pixels``
    (default ``MAX_PIXELS``): decoding it would take more memory than an image should."""
    cap = MAX_PIXELS if max_pixels is None else int(max_pixels)
    if width * height > cap:
        raise FileProblem(f"cannot read {what} {path}: {width} x {height} pixels is over the limit of {cap} "
                          f"pixels ({cap / 1e6:g} megapixels), refused before decoding", path)


def image_header_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(width, height) from an image file's header, without decoding its pixels; None when PIL cannot
    identify it (its reader then says what is wrong). Images past PIL's own bomb limit are refused."""
    try:
        with Image.open(path) as im:
            return im.size
    except Image.DecompressionBombError as exc:
        raise FileProblem(f"cannot read {path}: {exc}", path) from exc
    except (OSError, ValueError, SyntaxError):  # not an image PIL knows, or a damaged header
        return None


def check_image_file(path: str | os.PathLike, what: str = "image", max_pixels: int | None = None) -> None:
    """:func:`check_pixels` from the file's header, before anything decodes it."""
    size = image_header_size(path)
    if size is not None:
        check_pixels(*size, path, what, max_pixels)


MAX_TEXT_BYTES = 64 * 2**20  # a text file of a public dataset (poses, a camera's calibration), at most


def read_text(path: str | os.PathLike, what: str = "file", limit: int | None = None) -> str:
    """The UTF-8 text of ``path``, read within ``limit`` bytes (default ``MAX_TEXT_BYTES``); a
    :class:`FileProblem` naming it (as ``what``) when it cannot be read, is larger or is not UTF-8 text."""
    limit = MAX_TEXT_BYTES if limit is None else limit
    try:
        with open(path, "rb") as f:
            raw = f.read(limit + 1)
    except OSError as exc:
        raise FileProblem(f"cannot read {what} {path}: {os_reason(exc)}", path) from exc
    if len(raw) > limit:
        raise FileProblem(f"cannot read {what} {path}: over the limit of {limit} bytes for this file", path)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FileProblem(f"cannot read {what} {path}: not a UTF-8 text file", path) from exc


def finite_numbers(values: list, where: str) -> list[float]:
    """``values`` (words of a text file, or numbers parsed from YAML/JSON) as floats, each finite; else a
    :class:`UserError` naming ``where`` (``file:line``, or the file and the field) and the first value that
    is not a finite number (a word, ``nan``, ``inf``, ``true``, a list, an integer too large for a float)."""
    numbers = []
    for value in values:
        number = math.nan
        if isinstance(value, (str, int, float)) and not isinstance(value, bool):
            try:
                number = float(value)
            except (ValueError, OverflowError):
                pass
        if not math.isfinite(number):
            shown = repr(value)
            raise UserError(f"{where}: {shown if len(shown) <= 40 else shown[:39] + '…'} is not a finite number")
        numbers.append(number)
    return numbers


ZIP_ENTRY_BYTES = 1024  # the central directory may hold this many bytes per member it may declare


def zip_directory(path: str | os.PathLike) -> tuple[int, int] | None:
    """(members, bytes) that a zip file's central directory declares, read from its end record (and
    the ZIP64 one where there is one) without parsing the directory; None when there is no end record."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        f.seek(max(size - 22 - 65535, 0))  # the end record: 22 bytes and a comment of up to 65535
        tail = f.read()
        at = tail.rfind(b"PK\x05\x06")
        if at < 0 or len(tail) - at < 22:
            return None
        entries, directory = struct.unpack("<HL", tail[at + 10:at + 16])
        if at >= 20 and tail[at - 20:at - 16] == b"PK\x06\x07":  # ZIP64: the counts are in its own end record
            f.seek(struct.unpack("<Q", tail[at - 12:at - 4])[0])
            record = f.read(56)
            if len(record) == 56 and record[:4] == b"PK\x06\x06":
                entries, directory = struct.unpack("<QQ", record[32:48])
    return entries, directory


def check_zip_directory(path: str | os.PathLike, max_members: int, what: str) -> None:
    """A :class:`UserError` naming ``path`` when its zip directory declares more than ``max_members`` members
    or more than ``ZIP_ENTRY_BYTES`` a member: reading it would take memory a ``what`` never needs."""
    try:
        declared = zip_directory(path)
    except OSError as exc:
        raise FileProblem(f"cannot read {what} {path}: {os_reason(exc)}", path) from exc
    if declared is None:
        return  # not a zip: its reader says so
    entries, directory = declared
    if entries > max_members or directory > max_members * ZIP_ENTRY_BYTES:
        raise UserError(f"{what} {path} is refused: its zip directory declares {entries} members in {directory} "
                        f"bytes, over the {max_members} members a {what} holds; nothing in it was read")


MAX_MANIFEST_BYTES = 4 * 2**20  # a manifest file (data_manifests/*.json, a dataset's manifest.json), at most
MAX_DATASET_FILE_BYTES = 2**30  # a file a dataset names (frame, depth map, frames.jsonl, checksummed file)
# a depth map's finite values, at most (in its own unit): no endoscope sees a million millimetres, and a
# value such as 2^63 trains on a loss of 10^18 (NaN and inf are kept: they mark pixels without depth)
MAX_DEPTH_VALUE = 1e6


def inside_folder(root: str | os.PathLike, rel: str) -> Path | None:
    """``root / rel`` when ``rel`` is a relative path that stays inside ``root`` (no absolute path,
    no ``..``, no symbolic link leading out) and names a regular file; else None."""
    if not isinstance(rel, str) or not rel or "\0" in rel:
        return None
    parts = Path(rel).parts
    if Path(rel).is_absolute() or ".." in parts or rel.startswith(("/", "\\")):
        return None
    base = Path(root).resolve()
    try:
        target = (base / rel).resolve()
    except (OSError, RuntimeError):  # a symlink loop
        return None
    if target != base and base not in target.parents:
        return None
    return Path(root) / rel if target.is_file() else None


def dataset_file(root: str | os.PathLike, rel: str, what: str, source: str | os.PathLike) -> Path:
    """The file ``rel`` that ``source`` (a file of dataset folder ``root``) names, checked to be a
    regular file inside ``root`` of at most ``MAX_DATASET_FILE_BYTES``; a FileProblem naming both otherwise."""
    path = inside_folder(root, rel)
    if path is None:
        shown = rel if isinstance(rel, str) else repr(rel)
        if not isinstance(rel, str) or not rel:
            reason = f"its {what} path is {shown!s}, not a file name"
        elif Path(rel).is_absolute() or ".." in Path(rel).parts:
            reason = f"its {what} path {shown} leads outside the dataset folder {root}"
        elif (Path(root) / rel).exists() and not (Path(root) / rel).resolve().is_relative_to(Path(root).resolve()):
            reason = f"its {what} path {shown} is a link leading outside the dataset folder {root}"
        elif (Path(root) / rel).exists():
            reason = f"its {what} path {shown} is not a regular file"
        else:
            raise FileNotFoundError(f"{what} file named by {source} not found: {Path(root) / rel}")
        raise FileProblem(f"cannot use {source}: {reason}", source)
    size = path.stat().st_size
    if size > MAX_DATASET_FILE_BYTES:
        raise FileProblem(f"cannot read {path}: {size} bytes, over the limit of {MAX_DATASET_FILE_BYTES} bytes "
                          "for one file of a dataset", path)
    return path


def check_npy_header(f, path: str | os.PathLike) -> None:
    """From an open ``.npy`` file (at its start), check the header before any array is read: plain
    numbers, and as many bytes as its shape and dtype say, at most ``MAX_DATASET_FILE_BYTES``."""
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f, max_header_size=10_000)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(f, max_header_size=10_000)
    except (ValueError, OSError, SyntaxError, TypeError) as exc:
        raise FileProblem(f"cannot read {path}: damaged .npy header ({' '.join(str(exc).split())[:120]})",
                          path) from exc
    if dtype.hasobject:
        raise FileProblem(f"cannot read {path}: it holds pickled Python objects, never loaded (a depth file holds "
                          "numbers only)", path)
    if dtype.kind not in "fiub":
        raise FileProblem(f"cannot read {path}: its dtype is {dtype}, not plain numbers", path)
    count = 1
    for n in shape:
        count *= int(n)
    need = count * dtype.itemsize
    have = os.fstat(f.fileno()).st_size - f.tell()
    if need > MAX_DATASET_FILE_BYTES:
        raise FileProblem(f"cannot read {path}: its header claims {need} bytes of data (shape {shape}), over the "
                          f"limit of {MAX_DATASET_FILE_BYTES} bytes for one file of a dataset", path)
    if need != have:
        raise FileProblem(f"cannot read {path}: its header claims {need} bytes of data (shape {shape}) but "
                          f"{have} follow (a damaged or cut-short file)", path)


def read_npy(path: str | os.PathLike) -> np.ndarray:
    """A numeric array from a ``.npy`` file (never unpickled); a :class:`FileProblem` naming the file otherwise."""
    try:
        with open(path, "rb") as f:
            if f.read(6) != b"\x93NUMPY":
                raise FileProblem(f"cannot read {path}: not a .npy file (no NumPy header)", path)
            f.seek(0)
            check_npy_header(f, path)  # bounded before the array is read
        a = np.load(path, allow_pickle=False)
    except FileProblem:
        raise
    except (OSError, ValueError, EOFError) as exc:  # missing, truncated, or pickled objects
        if isinstance(exc, OSError):
            reason = os_reason(exc)
        elif "allow_pickle" in str(exc) or "pickle" in str(exc).lower():
            reason = "it holds pickled Python objects, never loaded (a depth file holds numbers only)"
        else:
            reason = f"damaged .npy file ({exc})"
        raise FileProblem(f"cannot read {path}: {reason}", path) from exc
    if not isinstance(a, np.ndarray) or a.dtype.kind not in "fiub":
        raise FileProblem(f"cannot read {path}: not a numeric array", path)
    return a


def read_depth_npy(path: str | os.PathLike) -> np.ndarray:
    """A depth map from a ``.npy`` file (:func:`read_npy`) whose finite values lie within
    +-``MAX_DEPTH_VALUE``; NaN and inf pass (they mark pixels without depth). A :class:`FileProblem`
    naming the file otherwise."""
    depth = read_npy(path)
    finite = depth[np.isfinite(depth)] if depth.dtype.kind == "f" else depth
    if finite.size:
        lo, hi = float(finite.min()), float(finite.max())
        if max(hi, -lo) > MAX_DEPTH_VALUE:
            raise FileProblem(f"cannot use {path}: it holds the depth {hi if hi > -lo else lo:.4g}, beyond the "
                              f"{MAX_DEPTH_VALUE:.0e} a depth map may hold (NaN or inf mark a pixel without depth)",
                              path)
    return depth
