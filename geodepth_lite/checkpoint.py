"""Checkpoints: atomic save and safe read, the run folder's lock, the per-epoch logs, loading a trained model.

A checkpoint (``checkpoint.pt``, written by ``train.fit`` once per epoch) holds "model",
"optimizer", "scaler", "schedule", "cfg", "epoch" (epochs done), "complete", "rng" (every
random state, so a resumed run ends bit-identical) and "history" (the per-epoch log rows).
Every read uses ``torch.load(weights_only=True)``: a checkpoint is data, never code.
``run_cache`` (cached runs, above the training loop) and ``train`` build on this module.
"""

from __future__ import annotations

import contextlib
import csv
import importlib
import io
import json
import os
import random
import warnings
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch

from geodepth_lite import utils
from geodepth_lite.model import DepthNet

CHECKPOINT_NAME = "checkpoint.pt"
LOG_CSV = "log.csv"
LOG_JSON = "log.json"


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


class OldCheckpoint(ValueError):
    """A checkpoint of the first format (numpy objects inside): loadable only through ``convert``."""


def _load_safely(path: Path) -> Any:
    """``torch.load`` with ``weights_only=True``: tensors and plain types only, no code can run.

    A file that needs anything else is refused, naming the file. A checkpoint of the first
    format (its numpy RNG state pickled as numpy objects) is told apart, so the message can
    point at the one-time conversion instead.
    """
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols it reads all the same
            warnings.simplefilter("ignore", UserWarning)
            return torch.load(path, map_location="cpu", weights_only=True)
    except PermissionError as exc:
        raise utils.FileProblem(f"cannot read {path}: {utils.os_reason(exc)}", path) from exc
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad or unsafe file
        text = str(exc)
        if "numpy" in text and "weights_only" in text and _only_numpy_arrays(path):
            raise OldCheckpoint(
                f"checkpoint {path} has the first checkpoint format (numpy objects inside), which this "
                f"version does not unpickle; if you trust where it came from, convert it once with "
                f"`python -m geodepth_lite convert-checkpoint {path}`") from None
        if "weights_only" in text.lower() or "unsupported" in text.lower():
            what = next((ln.strip().rstrip(".") for ln in text.splitlines()
                         if "unsupported" in ln.lower() and "weights_only" not in ln), "")
            raise ValueError(f"checkpoint {path} is refused: it holds more than tensors and plain values, "
                             f"which could run code when loaded ({what or 'an unsupported object'}); "
                             f"nothing in it was run") from None
        raise ValueError(f"checkpoint {path} is unreadable: {text.splitlines()[0] if text else type(exc).__name__}"
                         ) from None


# what the first checkpoint format pickled besides tensors: numpy's RNG keys (an ndarray)
NUMPY_ARRAY_GLOBALS = ("numpy._core.multiarray._reconstruct", "numpy.core.multiarray._reconstruct",
                       "numpy.ndarray", "numpy.dtype", "numpy.dtypes.UInt32DType")


def _numpy_array_globals() -> list:
    """The objects behind ``NUMPY_ARRAY_GLOBALS`` that this numpy has: they rebuild an array, nothing else."""
    found = []
    for name in NUMPY_ARRAY_GLOBALS:
        module, _, attr = name.rpartition(".")
        try:
            found.append((getattr(importlib.import_module(module), attr), name))
        except (ImportError, AttributeError):
            continue
    return found


def _only_numpy_arrays(path: Path) -> bool:
    """Whether every global the pickle names is one that only rebuilds a numpy array."""
    try:
        names = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception:  # noqa: BLE001 - not a zip checkpoint: not the first format either
        return False
    return bool(names) and set(names) <= set(NUMPY_ARRAY_GLOBALS)


def convert_checkpoint(path: str | os.PathLike, out: str | os.PathLike | None = None) -> Path:
    """Rewrite a first-format checkpoint (numpy RNG state as numpy objects) in the current format.

    Still never unpickles code: besides tensors and plain values, only numpy's array
    reconstruction is allowed (``NUMPY_ARRAY_GLOBALS``), and a file naming anything else is
    refused. Writes ``out`` (default: in place, atomically) and returns its path.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    allowed = _numpy_array_globals()
    try:
        named = set(torch.serialization.get_unsafe_globals_in_checkpoint(path))
    except Exception as exc:  # noqa: BLE001 - not a zip file written by torch.save
        raise ValueError(f"checkpoint {path} cannot be converted: not a file written by torch.save ({exc})") from None
    unsafe = named - {n for _, n in allowed}
    if unsafe:
        raise ValueError(f"checkpoint {path} is refused: it names {', '.join(sorted(unsafe))}, which a "
                         "geodepth-lite checkpoint never holds (it could run code when loaded)")
    with torch.serialization.safe_globals(allowed):
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(ckpt, dict) or "model" not in ckpt or "cfg" not in ckpt:
        raise ValueError(f"checkpoint {path} lacks 'model'/'cfg' entries: not a geodepth-lite checkpoint")
    rng = ckpt.get("rng")
    if isinstance(rng, dict):
        if isinstance(rng.get("numpy"), tuple):
            kind, keys, pos, has_gauss, cached = rng["numpy"]
            rng["numpy"] = {"kind": str(kind), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)),
                            "pos": int(pos), "has_gauss": int(has_gauss), "cached_gaussian": float(cached)}
        if isinstance(rng.get("python"), tuple):
            version, internal, gauss_next = rng["python"]
            rng["python"] = {"version": int(version), "internal": list(internal), "gauss_next": gauss_next}
    ckpt = _plain(ckpt)
    ckpt["format"] = FORMAT
    buf = io.BytesIO()
    torch.save(ckpt, buf)
    target = Path(out) if out is not None else path
    utils.write_bytes_atomic(target, buf.getvalue())
    _load_safely(target)  # the result loads with weights_only=True, or this raises
    return target


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


def read_checkpoint(path: str | os.PathLike, *, for_resume: bool = False) -> dict:
    """A checkpoint dict; a clear error for a missing, unreadable, foreign or unsafe file.

    The file is loaded with ``weights_only=True``: a crafted checkpoint cannot run code.
    for_resume: also require what continuing a run needs (``RESUME_KEYS``).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    ckpt = _load_safely(path)
    if not isinstance(ckpt, dict) or "model" not in ckpt or "cfg" not in ckpt:
        raise ValueError(f"checkpoint {path} lacks 'model'/'cfg' entries: not a geodepth-lite checkpoint")
    if not isinstance(ckpt["model"], dict) or not isinstance(ckpt["cfg"], dict):
        raise ValueError(f"checkpoint {path}: 'model' and 'cfg' must be dicts: not a geodepth-lite checkpoint")
    if for_resume:
        missing = [k for k in RESUME_KEYS if k not in ckpt]
        if missing:
            raise ValueError(f"checkpoint {path} cannot be resumed: it lacks {', '.join(missing)} "
                             "(written by something other than train?)")
    bad = [k for k, v in ckpt["model"].items()
           if isinstance(v, torch.Tensor) and v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise ValueError(f"checkpoint {path} holds non-finite weights (NaN or inf) in {len(bad)} tensor(s), "
                         f"first {bad[0]}: the model is unusable (retrain it, or resume from an earlier copy)")
    return ckpt


@contextlib.contextmanager
def run_folder(run_dir: str | os.PathLike) -> Iterator[Path]:
    """A training run's folder for the length of the block: checked writable before any work, and
    locked (``utils.FolderLock``) so that a second writer is refused, naming this process.

    If the block fails before a checkpoint exists in a folder this call created, the folder is
    removed again (with the lock file and logs), so a refused run leaves nothing behind.
    """
    run_dir = Path(run_dir)
    created = utils.missing_dirs(run_dir)
    utils.check_output_dir(run_dir)  # a file in the way, a read-only disk: named now, before any work
    lock = utils.FolderLock(run_dir).acquire()
    try:
        yield run_dir
    except BaseException:
        if created and not (run_dir / CHECKPOINT_NAME).exists():
            for name in (utils.LOCK_NAME, LOG_CSV, LOG_JSON):
                (run_dir / name).unlink(missing_ok=True)
            utils.remove_empty_dirs(created)
        raise
    finally:
        lock.release()


def checkpoint_bytes(model: torch.nn.Module) -> int:
    """About the size of one checkpoint of ``model``: its weights three times (the model and Adam's
    two moments), plus 1 MB for the rest."""
    return 3 * sum(t.numel() * t.element_size() for t in model.state_dict().values()) + 2**20


def write_logs(run_dir: Path, cfg: dict, history: list[dict]) -> None:
    """log.json (config + one row per epoch) and log.csv (the same rows), both atomic."""
    utils.write_json_atomic(run_dir / LOG_JSON, {"cfg": cfg, "epochs": history})
    if not history:
        return
    fields = list(history[0])
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for row in history:
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    utils.write_bytes_atomic(run_dir / LOG_CSV, buf.getvalue().encode())


def read_log(run_dir: str | os.PathLike) -> list[dict]:
    """The per-epoch rows of ``log.json`` in ``run_dir`` (or beside a checkpoint file)."""
    p = Path(run_dir)
    if p.is_file():
        p = p.parent
    return json.loads((p / LOG_JSON).read_text())["epochs"]


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu"):
    """(DepthNet in eval mode on ``device``, its training cfg) from a checkpoint file."""
    ckpt = read_checkpoint(path)
    model = DepthNet(padding=ckpt["cfg"].get("padding", "zeros"), input_pad=int(ckpt["cfg"].get("input_pad", 0)))
    load_weights(model, ckpt["model"], path)
    return model.to(device).eval(), dict(ckpt["cfg"])


def load_weights(model: torch.nn.Module, state: dict, path: str | os.PathLike) -> None:
    """``model.load_state_dict(state)``, with an error naming ``path`` and the first missing,
    unexpected or misshapen tensor instead of torch's multi-line report."""
    own = model.state_dict()
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    shapes = [k for k in own if k in state and getattr(state[k], "shape", None) != own[k].shape]
    problems = []
    if missing:
        problems.append(f"{len(missing)} missing tensor(s), first {missing[0]}")
    if unexpected:
        problems.append(f"{len(unexpected)} unexpected tensor(s), first {unexpected[0]}")
    if shapes:
        k = shapes[0]
        problems.append(f"{len(shapes)} tensor(s) of another shape, first {k} "
                        f"({tuple(getattr(state[k], 'shape', ()))} instead of {tuple(own[k].shape)})")
    if problems:
        raise ValueError(f"checkpoint {path} does not fit this network: {'; '.join(problems)}")
    model.load_state_dict(state)


# --------------------------------------------------------------------------- command line


def add_arguments_convert_checkpoint(parser) -> None:
    parser.description = (
        "Rewrite checkpoints written before the safe format (their numpy random state pickled as numpy "
        "objects) so that they load with torch.load(weights_only=True). Only numpy's array reconstruction "
        "is allowed while reading them; a file that names anything else is refused and left as it is.")
    parser.add_argument("paths", nargs="+", help="checkpoint files, or folders searched for checkpoint.pt")


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
    for f in files:
        try:
            _load_safely(f)
            print(f"already in the current format: {f}")
            continue
        except OldCheckpoint:
            pass
        if (f.parent / LOG_JSON).is_file():  # a training run's folder: not while a run writes there
            with utils.FolderLock(f.parent):
                convert_checkpoint(f)
        else:
            convert_checkpoint(f)
        print(f"converted: {f}")
    return 0
