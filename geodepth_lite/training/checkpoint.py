"""Checkpoints: atomic save and safe read, the run folder's lock, the per-epoch logs, loading a trained model.

A checkpoint (``checkpoint.pt``, written by ``train.fit`` once per epoch) holds "model",
"optimizer", "scaler", "schedule", "cfg", "epoch" (epochs done), "complete", "rng" (every
random state, so a resumed run ends bit-identical) and "history" (the per-epoch log rows).
Every read uses ``torch.load(weights_only=True)``: a checkpoint is data, never code.
``run_cache`` (cached runs, above the training loop) and ``train`` build on this module.
"""

from __future__ import annotations

import _compat_pickle
import contextlib
import csv
import filecmp
import functools
import io
import json
import multiprocessing
import os
import pickletools
import random
import re
import struct
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.data import bounds

try:
    import resource  # POSIX only: bounds the memory of the process that reads a first-format checkpoint
except ImportError:  # Windows
    resource = None
from geodepth_lite.core.model import PADDINGS, DepthNet

CHECKPOINT_NAME = "checkpoint.pt"
LOG_CSV = "log.csv"
LOG_JSON = "log.json"
RUN_MARK = ".run"  # a run folder's mark (utils.mark_folder): training writes there again


FORMAT = 2  # "format" entry: 2 = every entry a tensor or a plain type, so it loads with weights_only=True


def rng_state(loader_gen: torch.Generator) -> dict:
    """Every random state a training run draws from (torch, numpy, python, the DataLoader's, CUDA's),
    as tensors and plain types only, so a checkpoint loads with ``torch.load(weights_only=True)``."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {"kind": str(kind), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)), "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
        "python": {"version": int(version), "internal": list(internal), "gauss_next": gauss_next},
        "loader_generator": loader_gen.get_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict, loader_gen: torch.Generator) -> None:
    """Restore what :func:`rng_state` saved."""
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    p = state["python"]
    random.setstate((p["version"], tuple(p["internal"]), p["gauss_next"]))
    loader_gen.set_state(state["loader_generator"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: Path, payload: dict) -> None:
    """``torch.save`` to a temporary file, then rename: an interrupted save leaves the old file whole."""
    buf = io.BytesIO()
    torch.save({**payload, "format": FORMAT}, buf)
    utils.write_bytes_atomic(path, buf.getvalue())


class OldCheckpoint(UserError):
    """A checkpoint of the first format (numpy objects inside): loadable only through ``convert``."""


# --------------------------------------------------------------------------- bounds of a read
# A checkpoint is read only after its zip's central directory (declared sizes, compression) and its
# pickle (the globals it names) have been checked against what a checkpoint of the network can hold,
# and its tensors are used only after each is checked to view no more bytes than its storage holds.


@dataclass(frozen=True)
class Limits:
    """What one checkpoint may hold: ``record``, one tensor's storage in bytes; ``total``, all of them;
    ``members``, the records of its zip file."""

    record: int
    total: int
    members: int = 100_000


PICKLE_MAX_BYTES = 16 * 2**20  # data.pkl: every entry besides the tensors' data (a training run's: ~50 KB)
RECORD_SLACK_BYTES = 2**20  # a record besides the weights (the random states: a few KB each)
MEMBERS_SLACK = 200  # records besides the weights and the optimizer's two moments (a training run's: about 20)
TOTAL_SLACK_BYTES = 16 * 2**20
# a network given to train.fit in place of DepthNet: its size is not known before it is built
ANY_NETWORK = Limits(record=4 * 2**30, total=16 * 2**30)
SAFE_GLOBALS = frozenset({  # what torch.save writes for a checkpoint of tensors, dicts, lists and numbers
    "collections.OrderedDict", "torch._utils._rebuild_tensor_v2", "torch._utils._rebuild_parameter",
    "torch.Size", "torch.device", "builtins.set", "builtins.complex", "_codecs.encode"})


@functools.lru_cache(maxsize=None)
def network_sizes() -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
    """(shape, dtype) of every tensor of DepthNet's state dict, built on the meta device (no memory)."""
    with torch.device("meta"):
        state = DepthNet().state_dict()
    return {k: (tuple(v.shape), v.dtype) for k, v in state.items()}


def network_limits() -> Limits:
    """The bounds of a DepthNet checkpoint: one record, the largest weight tensor; all of them, the
    weights three times (the model and Adam's two moments), plus slack for the random states."""
    sizes = [int(np.prod(shape, dtype=np.int64)) * dt.itemsize for shape, dt in network_sizes().values()]
    return Limits(record=max(max(sizes), RECORD_SLACK_BYTES), total=3 * sum(sizes) + TOTAL_SLACK_BYTES,
                  members=3 * len(sizes) + MEMBERS_SLACK)


def _refused(path: Path, reason: str) -> UserError:
    return UserError(f"checkpoint {path} is refused: {reason}; nothing in it was read")


def _checked_records(path: Path, zf: zipfile.ZipFile, limits: Limits) -> zipfile.ZipInfo | None:
    """Every record's declared size and packing against ``limits``; returns the pickle's entry (or None)."""
    total, pickle_info, names = 0, None, set()
    with open(path, "rb") as f:
        for info in zf.infolist():
            if info.filename in names:  # a reader takes one of the two, the check may have read the other
                raise _refused(path, f"its record {info.filename[:80]} is there twice; torch.save writes each once")
            names.add(info.filename)
            f.seek(info.header_offset)
            local = f.read(30)
            method = struct.unpack("<H", local[8:10])[0] if len(local) == 30 and local[:4] == b"PK\3\4" else -1
            if info.compress_type != zipfile.ZIP_STORED or method != 0 or info.file_size != info.compress_size:
                raise _refused(path, f"its record {info.filename[:80]} is compressed ({info.file_size} bytes "
                                     f"declared, {info.compress_size} stored); torch.save never compresses a record")
            is_pickle = info.filename.rpartition("/")[2] == "data.pkl"
            cap = PICKLE_MAX_BYTES if is_pickle else limits.record
            if info.file_size > cap:
                what = "the entries besides the tensors" if is_pickle else "the largest tensor of the network"
                raise _refused(path, f"its record {info.filename[:80]} declares {info.file_size} bytes, over the "
                                     f"{cap} bytes of {what}")
            total += info.file_size
            if is_pickle and pickle_info is not None:
                raise _refused(path, f"it holds two pickles ({pickle_info.filename[:80]}, {info.filename[:80]}); "
                                     "torch.save writes one")
            if is_pickle:
                pickle_info = info
    if total > limits.total + PICKLE_MAX_BYTES:
        raise _refused(path, f"its records declare {total} bytes, over the {limits.total} bytes a checkpoint of "
                             "the network holds (its weights and the optimizer's two moments)")
    return pickle_info


def _pickle_globals(data: bytes) -> list[str]:
    """Every global a pickle names (module.name), read opcode by opcode: nothing is built."""
    names: list[str] = []
    strings: list[str] = []
    for op, arg, _ in pickletools.genops(data):
        if op.name in ("GLOBAL", "INST"):  # protocol 2 names Python 2's modules, which pickle maps
            module, _, name = str(arg).partition(" ")
            module, name = _compat_pickle.NAME_MAPPING.get((module, name), (module, name))
            names.append(f"{_compat_pickle.IMPORT_MAPPING.get(module, module)}.{name}")
        elif op.name == "STACK_GLOBAL":
            names.append(".".join(strings[-2:]) if len(strings) >= 2 else "a global named on the stack")
        elif isinstance(arg, str) and op.name.endswith("UNICODE"):
            strings = [*strings[-1:], arg[:100]]
        if op.name == "STOP":
            break
    return names


def _safe_global(name: str) -> bool:
    if name in SAFE_GLOBALS:
        return True
    module, _, attr = name.rpartition(".")
    return module == "torch" and (re.fullmatch(r"[A-Za-z0-9]*Storage", attr) is not None
                                  or isinstance(getattr(torch, attr, None), torch.dtype))


def check_archive(path: Path, limits: Limits) -> list[str]:
    """Check ``path`` before torch reads any record of it: a zip file (torch.save's format) whose records
    are stored uncompressed within ``limits``; returns the globals its pickle names that
    ``SAFE_GLOBALS`` does not hold. ValueError naming the file otherwise."""
    size = path.stat().st_size
    if size > limits.total + 2 * PICKLE_MAX_BYTES:
        raise _refused(path, f"it is {size} bytes, over the {limits.total} bytes a checkpoint of the network holds")
    bounds.check_zip_directory(path, limits.members, "checkpoint")  # before zipfile reads the directory
    try:
        zf = zipfile.ZipFile(path)
    except zipfile.BadZipFile:
        zf = None
    except (ValueError, EOFError, NotImplementedError, RuntimeError, struct.error):
        raise UserError(f"checkpoint {path} is unreadable: a damaged checkpoint (its zip archive is broken or "
                         "cut short)") from None
    except OSError as exc:
        raise utils.FileProblem(f"cannot read {path}: {utils.os_reason(exc)}", path) from exc
    if zf is None:  # a plain pickle, or torch's legacy format (which allocates what its header declares)
        names = []
        with contextlib.suppress(Exception):
            names = [n for n in _pickle_globals(path.read_bytes()) if not _safe_global(n)]
        if names:
            raise _unsafe(path, names)
        raise UserError(f"checkpoint {path} is unreadable: not a checkpoint written by torch.save (not its zip "
                         "format: a damaged file, another kind of file, or torch's legacy format)")
    with zf:
        try:
            info = _checked_records(path, zf, limits)
            data = zf.read(info) if info is not None else None
        except (zipfile.BadZipFile, ValueError, EOFError, OSError, struct.error, NotImplementedError) as exc:
            if isinstance(exc, ValueError) and "is refused" in str(exc):
                raise
            raise UserError(f"checkpoint {path} is unreadable: a damaged checkpoint (its zip archive is broken "
                             "or cut short)") from None
    if data is None:
        return []  # no pickle: torch names what is missing
    try:
        return [n for n in _pickle_globals(data) if not _safe_global(n)]
    except Exception:  # noqa: BLE001 - a pickle that cannot be parsed cannot be loaded either
        raise UserError(f"checkpoint {path} is unreadable: a damaged checkpoint (its pickle cannot be "
                         "parsed)") from None


def _unsafe(path: Path, names: list[str]) -> UserError:
    return UserError(f"checkpoint {path} is refused: it holds more than tensors and plain values, which could "
                      f"run code or take any amount of memory when loaded ({names[0][:100]}); nothing in it was run")


def tensor_problem(obj: Any, limits: Limits) -> str | None:
    """Why the tensors in ``obj`` cannot be used, or None: each must be a dense CPU tensor viewing no more
    bytes than its storage holds (no expanded or overlapping view larger than its data), and all of them
    together within ``limits.total``. Only shapes are read: nothing is allocated."""
    seen: set[int] = set()
    todo, total = [obj], 0
    while todo:
        item = todo.pop()
        if id(item) in seen:
            continue
        seen.add(id(item))
        if isinstance(item, dict):
            todo += list(item.keys()) + list(item.values())
        elif isinstance(item, (list, tuple, set, frozenset)):
            todo += list(item)
        elif isinstance(item, torch.Tensor):
            if item.layout != torch.strided or item.device.type != "cpu" or item.is_quantized:
                return f"a {item.layout} tensor on {item.device} (a checkpoint holds dense CPU tensors)"
            need = item.numel() * item.element_size()
            held = item.untyped_storage().nbytes()
            if need > held:
                return (f"a tensor of shape {tuple(item.shape)} and strides {tuple(item.stride())} ({need} bytes) "
                        f"that views {held} bytes of data (an expanded or overlapping view)")
            total += need
            if total > limits.total:
                return f"tensors of over {limits.total} bytes together (views of the same data counted each time)"
    return None


def _load_safely(path: Path, limits: Limits | None = None) -> Any:
    """``torch.load`` with ``weights_only=True``: tensors and plain types only, no code can run.

    A file that needs anything else is refused, naming the file. A checkpoint of the first
    format (its numpy RNG state pickled as numpy objects) is told apart, so the message can
    point at the one-time conversion instead. Nothing is read before :func:`check_archive`
    passed, and no tensor is returned before :func:`tensor_problem` passed (``limits``:
    DepthNet's, ``network_limits()``, unless given).
    """
    limits = limits or network_limits()
    try:
        unsafe = check_archive(path, limits)
    except PermissionError as exc:
        raise utils.FileProblem(f"cannot read {path}: {utils.os_reason(exc)}", path) from exc
    if unsafe and set(unsafe) <= set(NUMPY_ARRAY_GLOBALS):
        problem = _old_format_problem(path, limits)
        if problem:
            raise UserError(f"checkpoint {path} is refused: {problem}; nothing in it was run") from None
        raise OldCheckpoint(
            f"checkpoint {path} has the first checkpoint format (numpy objects inside), which this "
            f"version does not unpickle; if you trust where it came from, convert it once with "
            f"`python -m geodepth_lite convert-checkpoint {path}`") from None
    if unsafe:
        raise _unsafe(path, unsafe)
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols it reads all the same
            warnings.simplefilter("ignore", UserWarning)
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except PermissionError as exc:
        raise utils.FileProblem(f"cannot read {path}: {utils.os_reason(exc)}", path) from exc
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad or unsafe file
        text = str(exc)
        if "weights_only" in text.lower() or "unsupported" in text.lower():
            what = next((ln.strip().rstrip(".") for ln in text.splitlines()
                         if "unsupported" in ln.lower() and "weights_only" not in ln), "")
            raise UserError(f"checkpoint {path} is refused: it holds more than tensors and plain values, "
                             f"which could run code when loaded ({what or 'an unsupported object'}); "
                             f"nothing in it was run") from None
        raise UserError(f"checkpoint {path} is unreadable: {_unreadable_reason(exc)}") from None
    problem = tensor_problem(ckpt, limits)
    if problem:
        raise UserError(f"checkpoint {path} is refused: it holds {problem}")
    return ckpt


# what the first checkpoint format pickled besides tensors: numpy's RNG keys (an ndarray); read
# only through the stand-ins of read_old_checkpoint, never numpy's own reconstruction
NUMPY_ARRAY_GLOBALS = ("numpy._core.multiarray._reconstruct", "numpy.core.multiarray._reconstruct",
                       "numpy.ndarray", "numpy.dtype")


def convert_checkpoint(path: str | os.PathLike, out: str | os.PathLike | None = None) -> Path:
    """Rewrite a first-format checkpoint (numpy RNG state as numpy objects) in the current format.

    Still never unpickles code, and never lets numpy rebuild an array from the file: the file is
    read by :func:`read_old_checkpoint` (a child process with bounded memory; numpy arrays only as
    plain numbers, checked against the bytes present). The result is checked to load with
    ``weights_only=True`` before anything is written. ``out``: a new file (never the input, never
    an existing file). Without ``out`` the input is kept whole as ``<name>.first-format``
    (``OLD_SUFFIX``; refused if that name exists) and the converted checkpoint takes its name.
    Returns the path written.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    if out is not None:
        target = Path(out)
        if target.resolve() == path.resolve():
            raise utils.FileProblem(f"cannot convert {path}: the output is the input itself; a conversion "
                                    "never rewrites its input (name another file)", path)
        if target.exists():
            raise utils.FileProblem(f"cannot convert {path}: {target} exists already and is left as it is "
                                    "(name a new file)", target)
    data = read_old_checkpoint(path)
    keep = path.with_name(path.name + OLD_SUFFIX)
    if out is None:
        if not _kept_already(path, keep):
            try:
                os.link(path, keep)  # the original, kept whole under its new name before anything is written
            except FileExistsError as exc:
                raise utils.FileProblem(f"cannot convert {path}: {keep} exists already", keep) from exc
            except OSError:
                utils.write_bytes_atomic(keep, path.read_bytes())
        target = path
    utils.write_bytes_atomic(target, data)
    return target


def _kept_already(path: Path, keep: Path) -> bool:
    """Whether ``keep`` holds the original of ``path`` already, byte for byte (what a conversion that failed
    after keeping it left); a different file there is refused, naming it; no file there: False."""
    if not os.path.lexists(keep):
        return False
    if keep.is_file() and not keep.is_symlink() and filecmp.cmp(path, keep, shallow=False):
        return True
    raise utils.FileProblem(f"cannot convert {path}: {keep}, where the original would be kept, exists already "
                            "and differs from it, so it is left as it is (move it away, or pass --out)", keep)


OLD_SUFFIX = ".first-format"  # the original of a checkpoint converted without --out, kept beside it
# Bounds of the first-format reader: the numpy arrays that format held are the RNG keys (624 uint32).
OLD_ARRAY_MAX_BYTES = 16 * 2**20  # one numpy array in a first-format checkpoint, at most
OLD_ARRAYS_MAX_BYTES = 64 * 2**20  # all its numpy arrays together
OLD_ARRAY_MAX_DIMS = 32  # numpy's own limit on dimensions
OLD_READ_MEMORY_BYTES = 4 * 2**30  # address space the reading child may add to its parent's
OLD_DTYPES = re.compile(r"[biufc][0-9]{1,2}")  # bool, signed, unsigned, float, complex: plain numbers


class _OldDtype:
    """Stands in for ``numpy.dtype`` while a first-format checkpoint is read: records its arguments and
    state, builds nothing."""

    def __init__(self, *args):
        self.args = args
        self.state = None

    def __setstate__(self, state):
        self.state = state


class _OldArray:
    """Stands in for ``numpy.ndarray``: records (shape, dtype, raw bytes) from ``__setstate__``; the
    array is built by :func:`_old_array` only after every check."""

    def __init__(self, *args):
        self.state = None

    def __setstate__(self, state):
        self.state = state


def _old_reconstruct(*args):
    """Stands in for numpy's ``_reconstruct``: an empty record, filled by ``__setstate__``."""
    return _OldArray()


_OLD_STAND_INS = [(_old_reconstruct, "numpy.core.multiarray._reconstruct"),
                  (_old_reconstruct, "numpy._core.multiarray._reconstruct"),
                  (_OldArray, "numpy.ndarray"), (_OldDtype, "numpy.dtype")]


def _old_dtype(d) -> np.dtype:
    """The plain numeric dtype a stand-in records, or ValueError saying why it is refused."""
    if not isinstance(d, _OldDtype) or not d.args or not isinstance(d.args[0], str):
        raise UserError("a numpy array without a readable dtype")
    name, st = d.args[0], d.state
    if not OLD_DTYPES.fullmatch(name):
        raise UserError(f"a numpy array of dtype {name[:20]!r}; only plain numbers (bool, int, uint, float, "
                         "complex) are read, never objects, raw bytes or records")
    order = "="
    if st is not None:
        if not isinstance(st, tuple) or len(st) < 5 or any(x is not None for x in st[2:5]):
            raise UserError(f"a numpy array of a structured or sub-array dtype ({name})")
        order = st[1] if st[1] in ("<", ">", "|", "=") else None
        if order is None:
            raise UserError(f"a numpy dtype {name} with an unknown byte order")
    try:
        dt = np.dtype(order + name if order != "|" else name)
    except TypeError:
        raise UserError(f"an unknown numpy dtype {name[:20]!r}") from None
    if dt.kind not in "biufc" or dt.fields is not None or dt.subdtype is not None:
        raise UserError(f"a numpy array of dtype {name!r}, not plain numbers")
    return dt


def _old_array(a: _OldArray, budget: list) -> np.ndarray:
    """The array a stand-in records, after checking its dtype, shape and byte count against the data."""
    st = a.state
    if not isinstance(st, tuple) or len(st) != 5:
        raise UserError("a numpy array without its data")
    _, shape, dtype, fortran, raw = st
    dt = _old_dtype(dtype)
    if (not isinstance(shape, tuple) or len(shape) > OLD_ARRAY_MAX_DIMS
            or not all(type(n) is int and n >= 0 for n in shape)):
        raise UserError(f"a numpy array of an impossible shape {str(shape)[:60]}")
    if not isinstance(raw, (bytes, bytearray)):
        raise UserError("a numpy array whose data is not raw numbers (a list of Python objects)")
    count = 1
    for n in shape:
        count *= n
    need = count * dt.itemsize
    if need != len(raw):
        raise UserError(f"a numpy array of shape {shape} and dtype {dt.str} ({need} bytes) whose data holds "
                         f"{len(raw)} bytes")
    if need > OLD_ARRAY_MAX_BYTES:
        raise UserError(f"a numpy array of {need} bytes, over the {OLD_ARRAY_MAX_BYTES} bytes a first-format "
                         "checkpoint's arrays ever held")
    budget[0] -= need
    if budget[0] < 0:
        raise UserError(f"numpy arrays of over {OLD_ARRAYS_MAX_BYTES} bytes together")
    return np.frombuffer(bytes(raw), dtype=dt).reshape(shape, order="F" if fortran is True else "C").copy()


def _old_plain(obj: Any, budget: list, depth: int = 0) -> Any:
    """``obj`` with every stand-in replaced by its checked array, and numpy values turned into tensors."""
    if depth > 100:
        raise UserError("entries nested over 100 deep")
    if isinstance(obj, _OldArray):
        return torch.from_numpy(_old_array(obj, budget))
    if isinstance(obj, _OldDtype):
        raise UserError("a bare numpy dtype where a value belongs")
    if isinstance(obj, dict):
        return {k: _old_plain(v, budget, depth + 1) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_old_plain(v, budget, depth + 1) for v in obj)
    return obj


def _read_old_in_child(path: Path, limits: Limits | None = None) -> bytes:
    """Read a first-format checkpoint, check it, and return it in the current format (bytes of torch.save),
    at most ``limits.total`` plus ``PICKLE_MAX_BYTES``."""
    limits = limits or network_limits()
    unsafe = check_archive(path, limits)
    if not set(unsafe) <= set(NUMPY_ARRAY_GLOBALS):
        raise UserError(f"it holds {unsafe[0][:100]}, which is neither a tensor, a plain value nor a numpy array")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        with torch.serialization.safe_globals(_OLD_STAND_INS):
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(ckpt, dict) or "model" not in ckpt or "cfg" not in ckpt:
        raise UserError("it lacks 'model'/'cfg' entries: not a geodepth-lite checkpoint")
    problem = tensor_problem(ckpt, limits)
    if problem:
        raise UserError(f"it holds {problem}")
    ckpt = _old_plain(ckpt, [OLD_ARRAYS_MAX_BYTES])
    rng = ckpt.get("rng")
    if isinstance(rng, dict):
        if isinstance(rng.get("numpy"), tuple) and len(rng["numpy"]) == 5:
            kind, keys, pos, has_gauss, cached = rng["numpy"]
            if not isinstance(keys, torch.Tensor):
                raise UserError("its numpy random state has no key array")
            rng["numpy"] = {"kind": str(kind), "keys": keys.to(torch.int64), "pos": int(pos),
                            "has_gauss": int(has_gauss), "cached_gaussian": float(cached)}
        if isinstance(rng.get("python"), tuple) and len(rng["python"]) == 3:
            version, internal, gauss_next = rng["python"]
            rng["python"] = {"version": int(version), "internal": list(internal), "gauss_next": gauss_next}
    ckpt["format"] = FORMAT
    buf = io.BytesIO()
    torch.save(ckpt, buf)
    if buf.tell() > limits.total + PICKLE_MAX_BYTES:
        raise UserError(f"its conversion takes {buf.tell()} bytes, over the {limits.total + PICKLE_MAX_BYTES} "
                         "bytes a checkpoint of the network holds")
    return buf.getvalue()


def _address_space() -> int:
    """This process's virtual memory size in bytes (0 where /proc is not there)."""
    try:
        return int(Path("/proc/self/statm").read_text().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def _old_child(path: Path, conn, limits: Limits, parent_end=None) -> None:
    if parent_end is not None:
        parent_end.close()  # this process's copy of the reading end: the parent alone reads, or nobody does
    try:
        limit = _address_space() + OLD_READ_MEMORY_BYTES
        if resource is not None:
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    except (ValueError, OSError):
        pass
    try:
        data = _read_old_in_child(path, limits)
        conn.send(("ok", len(data)))
        conn.send_bytes(data)  # read by the parent with a bound on its length
    except MemoryError:
        conn.send(("error", f"reading it needs more than {OLD_READ_MEMORY_BYTES // 2**30} GiB of memory"))
    except BaseException as exc:  # noqa: BLE001 - every failure is reported as one line
        text = " ".join(str(exc).split()) or type(exc).__name__
        if "Weights only load failed" in text:
            text = _weights_only_reason(text)
        conn.send(("error", text[:300]))
    finally:
        conn.close()


def read_old_checkpoint(path: str | os.PathLike, limits: Limits | None = None) -> bytes:
    """A first-format checkpoint in the current format (the bytes to write), or ValueError naming
    the file and what is wrong. Its archive is checked first (``check_archive``), then it is read in
    a child process with bounded memory, so a hostile file can neither crash nor exhaust the caller;
    the converted bytes are received only up to ``limits.total`` plus ``PICKLE_MAX_BYTES``."""
    path = Path(path)
    limits = limits or network_limits()
    if "fork" not in multiprocessing.get_all_start_methods():  # Windows: in this process (stand-ins only)
        try:
            return _read_old_in_child(path, limits)
        except Exception as exc:  # noqa: BLE001 - every failure is reported as one line
            raise UserError(f"checkpoint {path} cannot be converted: {' '.join(str(exc).split())[:300]}") from None
    check_archive(path, limits)  # declared sizes and compression, before the child reads a record
    ctx = multiprocessing.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_old_child, args=(path, send, limits, recv), daemon=True)
    child.start()
    send.close()
    cap = limits.total + PICKLE_MAX_BYTES
    try:
        status, value = recv.recv()
        if status == "ok":
            try:
                value = recv.recv_bytes(cap)  # OSError past the cap: nothing more is read
            except OSError:
                status, value = "error", f"its conversion is over {cap} bytes, more than the network's checkpoint holds"
    except (EOFError, OSError):
        status, value = "error", None
    finally:
        recv.close()
        if status != "ok" and child.is_alive():
            child.kill()
        child.join()
    if status == "ok":
        try:
            _check_bytes_load(value)
        except Exception as exc:  # noqa: BLE001
            raise UserError(f"checkpoint {path} cannot be converted: its conversion does not load ({exc})") from None
        return value
    if value is None:
        code = child.exitcode
        value = (f"reading it stopped the reader (signal {-code})" if code is not None and code < 0
                 else f"reading it stopped the reader (exit status {code})")
    raise UserError(f"checkpoint {path} cannot be converted: {value}")


def _check_bytes_load(data: bytes) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        ckpt = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    if not isinstance(ckpt, dict) or "model" not in ckpt or "cfg" not in ckpt:
        raise UserError("no 'model'/'cfg' entries")


def _old_format_problem(path: Path, limits: Limits | None = None) -> str | None:
    """None when :func:`read_old_checkpoint` would convert ``path``; else what is wrong with it."""
    try:
        read_old_checkpoint(path, limits)
    except ValueError as exc:
        return str(exc).partition(": ")[2] or str(exc)
    return None


def _weights_only_reason(text: str) -> str:
    """The one useful line of torch's long weights-only refusal."""
    for ln in text.replace(". ", ".\n").splitlines():
        if "Unsupported" in ln or "unsupported" in ln or "Trying to" in ln:
            return ln.strip().rstrip(".")
    return "it holds more than tensors, plain values and numpy arrays of numbers"


def _unreadable_reason(exc: BaseException) -> str:
    """Why torch.load could not read a file, in words a user can act on."""
    text = str(exc)
    if "central directory" in text or "zip archive" in text:
        return "a damaged checkpoint (its zip archive is broken or cut short)"
    if "magic number" in text.lower() or isinstance(exc, (KeyError, EOFError)) or "pickle" in text.lower():
        return "not a checkpoint written by torch.save (a damaged file or another kind of file)"
    first = text.splitlines()[0] if text else ""
    return f"not a checkpoint written by torch.save ({type(exc).__name__}{': ' + first[:120] if first else ''})"


def _plain(obj: Any) -> Any:
    """``obj`` with numpy scalars and arrays turned into python numbers and tensors."""
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_plain(v) for v in obj)
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(np.array(obj))
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


RESUME_KEYS = ("optimizer", "scaler", "schedule", "epoch", "rng", "history")


def read_checkpoint(path: str | os.PathLike, *, for_resume: bool = False, limits: Limits | None = None) -> dict:
    """A checkpoint dict; a clear error for a missing, unreadable, foreign, unsafe or oversized file.

    The file is loaded with ``weights_only=True``: a crafted checkpoint cannot run code. Its declared
    sizes are checked against ``limits`` (DepthNet's, ``network_limits()``, unless given) before a
    record is read, and its tensors against their storage before any is used (``_load_safely``).
    for_resume: also require what continuing a run needs (``RESUME_KEYS``).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    ckpt = _load_safely(path, limits)
    if not isinstance(ckpt, dict) or "model" not in ckpt or "cfg" not in ckpt:
        raise UserError(f"checkpoint {path} lacks 'model'/'cfg' entries: not a geodepth-lite checkpoint")
    if not isinstance(ckpt["model"], dict) or not isinstance(ckpt["cfg"], dict):
        raise UserError(f"checkpoint {path}: 'model' and 'cfg' must be dicts: not a geodepth-lite checkpoint")
    check_checkpoint_cfg(ckpt["cfg"], path)
    if for_resume:
        missing = [k for k in RESUME_KEYS if k not in ckpt]
        if missing:
            raise UserError(f"checkpoint {path} cannot be resumed: it lacks {', '.join(missing)} "
                             "(written by something other than train?)")
    bad = [k for k, v in ckpt["model"].items()
           if isinstance(v, torch.Tensor) and v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise UserError(f"checkpoint {path} holds non-finite weights (NaN or inf) in {len(bad)} tensor(s), "
                         f"first {bad[0]}: the model is unusable (retrain it, or resume from an earlier copy)")
    return ckpt


def _is_count(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _is_number(value, finite: bool = True) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and (not finite or bool(np.isfinite(value))))


def training_state_problem(state: dict, params: list[torch.Tensor] | None = None) -> str | None:
    """What keeps a run from resuming from ``state`` (a checkpoint read ``for_resume``), in words, or None:
    its epoch a count, its history one record of numbers per epoch, its optimizer's parameter groups (finite
    ``lr``, ``eps``, ``weight_decay``, two ``betas``) and its Adam moments shaped like ``params`` (the model's,
    in order; not checked when None), its schedule's epoch a count and one finite base rate per group.
    torch's ``load_state_dict`` takes such entries as they are, and the run would stop at its first step."""
    epoch, history = state["epoch"], state["history"]
    if not _is_count(epoch):
        return f"its epoch is {str(epoch)[:40]!r}, not a count"
    if not isinstance(history, list) or len(history) != epoch or not all(
            isinstance(row, dict) and all(isinstance(k, str) and _is_number(v, finite=False) for k, v in row.items())
            for row in history):
        return f"its history is not one record of numbers per epoch for its {epoch} epoch(s)"
    opt = state["optimizer"]
    groups = opt.get("param_groups") if isinstance(opt, dict) else None
    if not isinstance(groups, list) or not groups or not all(isinstance(g, dict) for g in groups):
        return "its optimizer has no parameter groups"
    ids = []
    for g in groups:
        betas = g.get("betas")
        if not all(_is_number(g.get(k)) for k in ("lr", "eps", "weight_decay")) or not (
                isinstance(betas, (list, tuple)) and len(betas) == 2 and all(_is_number(b) for b in betas)):
            return "its optimizer's learning rate, eps, weight decay or betas are not finite numbers"
        ids += g.get("params") if isinstance(g.get("params"), list) else [None]
    schedule = state["schedule"]
    rates = schedule.get("base_lrs") if isinstance(schedule, dict) else None
    if not (isinstance(schedule, dict) and _is_count(schedule.get("last_epoch")) and isinstance(rates, list)
            and len(rates) == len(groups) and all(_is_number(r) for r in rates)):
        return "its learning-rate schedule's step or base rates are not counts and finite numbers"
    if params is None:
        return None
    if len(ids) != len(params) or not all(_is_count(i) for i in ids) or len(set(ids)) != len(ids):
        return f"its optimizer holds {len(ids)} parameter(s), the model {len(params)}"
    moments = opt.get("state")
    shapes = dict(zip(ids, (tuple(t.shape) for t in params)))
    if not isinstance(moments, dict) or not all(
            k in shapes and isinstance(v, dict) and all(not isinstance(t, torch.Tensor) or t.ndim == 0
                                                        or tuple(t.shape) == shapes[k] for t in v.values())
            for k, v in moments.items()):
        return "its optimizer's moments are not shaped like the model's parameters"
    return None


# What a checkpoint's config may ask of the network: an input side of at most MAX_INPUT_SIDE pixels
# (image_size plus twice input_pad), so one frame's forward pass stays within a few GiB.
MAX_INPUT_SIDE = 2048
FORWARD_BYTES_PER_PIXEL = 1200  # about what DepthNet's forward pass holds per input pixel (float32, no grad)


def check_checkpoint_cfg(cfg: dict, path: str | os.PathLike) -> None:
    """A ValueError naming ``path`` and the field when a checkpoint's config holds a number the network
    cannot serve: ``image_size`` a positive multiple of 32, ``input_pad`` a non-negative multiple of 16,
    the input side (``image_size + 2 input_pad``) at most ``MAX_INPUT_SIDE``, ``padding`` one of
    ``model.PADDINGS``, and every number finite."""
    def bad(field: str, want: str, value) -> UserError:
        return UserError(f"checkpoint {path}: its config field '{field}' must be {want}, got {str(value)[:60]}")

    for key, value in cfg.items():
        if isinstance(value, float) and not np.isfinite(value):
            raise bad(key, "a finite number", value)
    size = cfg.get("image_size")
    if isinstance(size, bool) or not isinstance(size, int) or size <= 0 or size % 32:
        raise bad("image_size", "a positive multiple of 32 (pixels)", size)
    pad = cfg.get("input_pad", 0)
    if isinstance(pad, bool) or not isinstance(pad, int) or pad < 0 or pad % 16:
        raise bad("input_pad", "a non-negative multiple of 16 (pixels)", pad)
    side = size + 2 * pad
    if side > MAX_INPUT_SIDE:
        need = side * side * FORWARD_BYTES_PER_PIXEL
        raise UserError(f"checkpoint {path}: its config field 'image_size' ({size}, with input_pad {pad}) asks for "
                         f"a {side} x {side} network input, about {need / 2**30:.3g} GiB for one frame; the limit "
                         f"is {MAX_INPUT_SIDE} pixels a side")
    if cfg.get("padding", "zeros") not in PADDINGS:
        raise bad("padding", f"one of {', '.join(PADDINGS)}", cfg.get("padding"))


@contextlib.contextmanager
def run_folder(run_dir: str | os.PathLike) -> Iterator[Path]:
    """A training run's folder for the length of the block: checked writable before any work, and
    locked (``utils.FolderLock``) so that a second writer is refused, naming this process.

    A folder is a run's when it is new or empty, holds a checkpoint, or carries :data:`RUN_MARK`
    (written here, under the lock, before any other file): any other folder holds someone else's files
    (a ``log.csv`` of their own, a checkout's tracked folder), which the run's logs would replace, and is
    refused in one line before anything is written.

    If the block fails before a checkpoint exists in a folder this call created, the folder is
    removed again (with the lock file, the mark and logs), so a refused run leaves nothing behind.
    """
    run_dir = Path(run_dir)
    created = utils.missing_dirs(run_dir)
    if not (run_dir / CHECKPOINT_NAME).is_file():
        utils.claim_folder(run_dir, RUN_MARK, "train", option="--run-dir")
    utils.check_output_dir(run_dir)  # a file in the way, a read-only disk: named now, before any work
    lock = utils.FolderLock(run_dir).acquire()
    try:
        if not (run_dir / RUN_MARK).is_file():
            utils.mark_folder(run_dir, RUN_MARK, "train")
        yield run_dir
    except BaseException:
        if created and not (run_dir / CHECKPOINT_NAME).exists():
            for name in (utils.LOCK_NAME, RUN_MARK, LOG_CSV, LOG_JSON):
                (run_dir / name).unlink(missing_ok=True)
            utils.remove_empty_dirs(created)
        raise
    finally:
        lock.release()


def checkpoint_bytes(model: torch.nn.Module) -> int:
    """About the size of one checkpoint of ``model``: its weights three times (the model and Adam's
    two moments), plus 1 MB for the rest."""
    return 3 * sum(t.numel() * t.element_size() for t in model.state_dict().values()) + 2**20


def write_logs(run_dir: Path, cfg: dict, history: list[dict], sessions: list[dict] | None = None) -> None:
    """log.json (config + one row per epoch, and with ``sessions`` the training sessions' provenance,
    :mod:`geodepth_lite.training.provenance`) and log.csv (the same rows), both atomic."""
    log = {"cfg": cfg, "epochs": history}
    if sessions is not None:
        log["provenance"] = sessions
    utils.write_json_atomic(run_dir / LOG_JSON, log)
    if not history:
        return
    fields = list(history[0])
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for row in history:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    utils.write_bytes_atomic(run_dir / LOG_CSV, buf.getvalue().encode())


def read_log_file(run_dir: str | os.PathLike) -> dict | None:
    """The whole ``log.json`` of ``run_dir`` as a dict, or None when it is missing, oversized or not one."""
    path = Path(run_dir) / LOG_JSON
    try:
        if not path.is_file() or path.stat().st_size > 64 * 2**20:
            return None
        log = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError):
        return None
    return log if isinstance(log, dict) else None


def read_log(run_dir: str | os.PathLike) -> list[dict]:
    """The per-epoch rows of ``log.json`` in ``run_dir`` (or beside a checkpoint file)."""
    p = Path(run_dir)
    if p.is_file():
        p = p.parent
    return json.loads((p / LOG_JSON).read_text())["epochs"]


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu"):
    """(DepthNet in eval mode on ``device``, its training cfg) from a checkpoint file."""
    ckpt = read_checkpoint(path)
    model = DepthNet(padding=ckpt["cfg"].get("padding", "zeros"), input_pad=int(ckpt["cfg"].get("input_pad", 0)),
                     depth_range=ckpt["cfg"].get("head_range"))
    load_weights(model, ckpt["model"], path)
    return model.to(device).eval(), dict(ckpt["cfg"])


def load_weights(model: torch.nn.Module, state: dict, path: str | os.PathLike) -> None:
    """``model.load_state_dict(state)``, with an error naming ``path`` and the first missing,
    unexpected or misshapen tensor instead of torch's multi-line report."""
    check_fits({k: tuple(v.shape) for k, v in model.state_dict().items()}, state, path)
    model.load_state_dict(state)


def check_fits(own: dict[str, tuple[int, ...]] | None, state: dict, path: str | os.PathLike) -> None:
    """ValueError naming ``path`` and the first missing, unexpected or misshapen tensor when ``state``
    does not fit a network whose tensors have the shapes ``own`` (None: DepthNet's, ``network_sizes()``)."""
    if own is None:
        own = {k: shape for k, (shape, _) in network_sizes().items()}
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    shapes = [k for k in own if k in state and tuple(getattr(state[k], "shape", (None,))) != tuple(own[k])]
    problems = []
    if missing:
        problems.append(f"{len(missing)} missing tensor(s), first {missing[0]}")
    if unexpected:
        problems.append(f"{len(unexpected)} unexpected tensor(s), first {unexpected[0]}")
    if shapes:
        k = shapes[0]
        problems.append(f"{len(shapes)} tensor(s) of another shape, first {k} "
                        f"({tuple(getattr(state[k], 'shape', ()))} instead of {tuple(own[k])})")
    if problems:
        raise UserError(f"checkpoint {path} does not fit this network: {'; '.join(problems)}")


# --------------------------------------------------------------------------- command line


def add_arguments_convert_checkpoint(parser) -> None:
    parser.description = (
        "Rewrite checkpoints written before the safe format (their numpy random state pickled as numpy "
        "objects) so that they load with torch.load(weights_only=True). Their numpy arrays are read as plain "
        "numbers only (checked against the bytes present, in a child process with bounded memory); a file "
        "that holds anything else is refused and left as it is. The original is never rewritten.")
    parser.add_argument("paths", nargs="+", help="checkpoint files, or folders searched for checkpoint.pt")
    parser.add_argument("--out", default=None,
                        help="write the converted checkpoint to this new file (one input file only); without it "
                             f"the original is kept beside it as <name>{OLD_SUFFIX} and the converted file takes "
                             "its name")


def run_convert_checkpoint(args) -> int:
    files: list[Path] = []
    for p in map(Path, args.paths):
        if p.is_dir():
            files += sorted(p.rglob(CHECKPOINT_NAME))
        elif p.is_file():
            files.append(p)
        else:
            raise FileNotFoundError(f"checkpoint not found: {p}")
    if not files:
        raise FileNotFoundError(f"no {CHECKPOINT_NAME} under {', '.join(args.paths)}")
    out = getattr(args, "out", None)
    if out is not None and len(files) != 1:
        raise UserError(f"--out names one file, but {len(files)} checkpoints were found: convert them one at a time")
    for f in files:
        try:
            _load_safely(f)
            print(f"already in the current format: {f}")
            continue
        except OldCheckpoint:
            pass
        if (f.parent / LOG_JSON).is_file():  # a training run's folder: not while a run writes there
            with utils.FolderLock(f.parent):
                written = convert_checkpoint(f, out)
        else:
            written = convert_checkpoint(f, out)
        kept = f if out is not None else f.with_name(f.name + OLD_SUFFIX)
        print(f"converted: {f} -> {written} (the original kept as {kept})")
    return 0
