"""A trained run's scores kept in its run folder, so that no run is scored twice.

Scoring a run (``evaluate.evaluate_model`` on a few evaluation sets) takes seconds to minutes on a
CPU; a notebook that compares runs would otherwise repeat it on every execution. :func:`scores`
scores a checkpoint once and writes the result beside it, as ``scores.json`` in its run folder
(written atomically: whole or not at all), and later calls read that file instead.

The file is reused only when its key matches: a SHA-256 over the checkpoint file's bytes, every
evaluation set's name and content (its manifest, frame list and the checksums of its frame files),
the set whose per-frame rows are kept, and the scoring code (the sources of the modules that load,
run and score a model, and the torch version). A retrained run, another evaluation set or changed
scoring code gives another key, and the run is scored again. The file is data from disk: it is
read only up to :data:`MAX_SCORES_BYTES`, must be plain JSON of the shape :func:`scores` writes,
and one that is not (cut short, oversized, edited into another shape) is named in a warning and
scored again.

A model's predictions on a set are kept the same way (:func:`kept_predictor`): one ``.npy`` array of
depth maps in the run folder's ``predictions/``, keyed as the scores are (with the test-time flips),
beside the digest of each frame's image, so a notebook that evaluates the same model on the same
frames again (a second execution, nbval after ``reproduce``) predicts nothing again.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from geodepth_lite import utils
from geodepth_lite.core import metrics, model
from geodepth_lite.data import bounds, integrity
from geodepth_lite.evaluation import evaluate
from geodepth_lite.training import checkpoint, inference

SCORES_NAME = "scores.json"
CHECKSUMS_NAME = "checksums.sha256"  # a synthetic dataset's list of its files' SHA-256 (synth.py)
SCORES_FORMAT = 1
MAX_SCORES_BYTES = 8 * 2**20  # a run's scores with one set's frame rows: about 150 KB for 480 frames
FRAME_FIELDS = ("index", "organ", "group", *metrics.METRIC_NAMES, "ratio")
SCORING_MODULES = (checkpoint, evaluate, inference, metrics, model)  # their sources are part of the key
PREDICTIONS_DIR = "predictions"
DIGEST_BYTES = 20  # blake2b digest of one frame's image tensor (float32 bytes, shape and dtype)
NPY_HEADER_MAX = 16 * 2**10  # bytes a kept array's file may hold beyond its numbers


class ScoresFileError(ValueError):
    """A scores file that cannot be used: oversized, not JSON, or not the shape :func:`scores` writes."""


def code_fingerprint() -> str:
    """SHA-256 over the sources of the modules that load, run and score a model, this one and the torch version."""
    h = hashlib.sha256(torch.__version__.encode())
    for mod in SCORING_MODULES:
        h.update(Path(mod.__file__).read_bytes())
    h.update(Path(__file__).read_bytes())
    return h.hexdigest()


def set_fingerprint(dataset) -> str | None:
    """SHA-256 of an evaluation set's content as its files declare it: for each synthetic split it
    is made of (``torch.utils.data.ConcatDataset`` parts in order), the split's name, its
    ``manifest.json`` and ``frames.jsonl``, and the dataset's ``checksums.sha256`` (the SHA-256 of
    every frame file; "none" where synth has not written it). None for a dataset of another kind
    or one resized on reading (its scores are not kept)."""
    parts = dataset.datasets if isinstance(dataset, torch.utils.data.ConcatDataset) else [dataset]
    h = hashlib.sha256()
    for part in parts:
        root, split = getattr(part, "root", None), getattr(part, "split", None)
        if root is None or not isinstance(split, str) or getattr(part, "size", None) is not None:
            return None
        h.update(split.encode() + b"\0")
        for path in (Path(root) / "manifest.json", Path(root) / split / "frames.jsonl"):
            if not path.is_file():
                return None
            h.update(integrity.file_sha256(path).encode())
        sums = Path(root) / CHECKSUMS_NAME
        h.update(integrity.file_sha256(sums).encode() if sums.is_file() else b"none")
    return h.hexdigest()


def score_key(path: str | Path, sets: dict[str, Any], frames_of: str | None = None) -> str | None:
    """The key of ``path``'s scores on ``sets`` (with the frame rows of ``frames_of``), or None
    when a set's content cannot be fingerprinted (:func:`set_fingerprint`)."""
    prints = {name: set_fingerprint(ds) for name, ds in sets.items()}
    if any(v is None for v in prints.values()):
        return None
    payload = {"checkpoint": integrity.file_sha256(Path(path)), "sets": prints, "frames_of": frames_of,
               "code": code_fingerprint()}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def scores_path(path: str | Path) -> Path:
    """Where the scores of checkpoint ``path`` are kept: ``scores.json`` beside it."""
    return Path(path).parent / SCORES_NAME


def _number(v) -> float | None:
    return float(v) if math.isfinite(v) else None  # plain JSON has no NaN: a skipped frame's metrics are null


def _metrics(d) -> bool:
    return isinstance(d, dict) and all(isinstance(d.get(m), (int, float)) and not isinstance(d.get(m), bool)
                                       for m in metrics.METRIC_NAMES)


def _check_shape(data, sets: dict[str, Any], frames_of: str | None) -> None:
    """ScoresFileError unless ``data`` has the shape :func:`scores` writes for ``sets``."""
    if not isinstance(data, dict) or data.get("format") != SCORES_FORMAT or not isinstance(data.get("key"), str):
        raise ScoresFileError(f"not a scores file of format {SCORES_FORMAT}")
    per_set = data.get("sets")
    if not isinstance(per_set, dict) or set(per_set) != set(sets):
        raise ScoresFileError("its evaluation sets are not the ones asked for")
    for name, r in per_set.items():
        if not isinstance(r, dict) or not isinstance(r.get("n"), int) or not _metrics(r.get("overall")):
            raise ScoresFileError(f"its scores on {name!r} are not a frame count and the seven metrics")
    rows = data.get("frames")
    if frames_of is None:
        if rows is not None:
            raise ScoresFileError("it holds frame rows no one asked for")
        return
    if not isinstance(rows, list) or not all(isinstance(f, dict) and set(f) == set(FRAME_FIELDS) for f in rows):
        raise ScoresFileError(f"its frame rows of {frames_of!r} are not one dict of {len(FRAME_FIELDS)} fields each")
    if len(rows) < per_set[frames_of]["n"]:
        raise ScoresFileError(f"it has {len(rows)} frame rows for {per_set[frames_of]['n']} scored frames")


def read_kept_scores(path: str | Path, key: str, sets: dict[str, Any], frames_of: str | None = None) -> dict | None:
    """The scores kept beside checkpoint ``path`` when their key is ``key``; None when there are
    none or they were made for another key (another checkpoint, set or scoring code).
    ScoresFileError naming the file when it is over :data:`MAX_SCORES_BYTES`, not JSON, or not
    the shape :func:`scores` writes."""
    file = scores_path(path)
    try:
        with open(file, "rb") as f:
            raw = f.read(MAX_SCORES_BYTES + 1)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise ScoresFileError(f"{file}: cannot be read ({utils.os_reason(exc)})") from None
    if len(raw) > MAX_SCORES_BYTES:
        raise ScoresFileError(f"{file}: over {MAX_SCORES_BYTES} bytes, more than a run's scores take")
    try:
        data = json.loads(raw.decode("utf-8"), parse_constant=_refuse_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise ScoresFileError(f"{file}: not plain JSON ({str(exc)[:80]})") from None
    if isinstance(data, dict) and data.get("key") != key and data.get("format") == SCORES_FORMAT:
        return None
    try:
        _check_shape(data, sets, frames_of)
    except ScoresFileError as exc:
        raise ScoresFileError(f"{file}: {exc}") from None
    return data


def _refuse_constant(name: str):
    raise ValueError(f"{name} is not plain JSON")


def compute_scores(path: str | Path, sets: dict[str, Any], frames_of: str | None = None) -> dict:
    """Score checkpoint ``path`` on every set: {"sets": {name: {"n", "overall"}}, "frames": the
    per-frame rows of ``frames_of`` (None: no rows)}, numbers as floats (None for a skipped frame's)."""
    net, cfg = checkpoint.load_model(path)
    out: dict[str, Any] = {"sets": {}, "frames": None}
    for name, ds in sets.items():
        r = evaluate.evaluate_model(net, ds, image_size=cfg["image_size"])
        out["sets"][name] = {"n": int(r["n"]), "overall": {m: float(r["overall"][m]) for m in metrics.METRIC_NAMES}}
        if name == frames_of:
            out["frames"] = [{k: (f[k] if k in ("index", "organ", "group") else _number(f[k])) for k in FRAME_FIELDS}
                             for f in r["frames"]]
    return out


def scores(path: str | Path, sets: dict[str, Any], frames_of: str | None = None) -> dict:
    """The scores of checkpoint ``path`` on ``sets`` (:func:`compute_scores`' shape), read from
    its run folder when kept there under the same key, else computed and kept there. A kept file
    that cannot be used is named in a warning and replaced."""
    if frames_of is not None and frames_of not in sets:
        raise ValueError(f"frames_of={frames_of!r} is not one of the sets {sorted(sets)}")
    key = score_key(path, sets, frames_of)
    if key is None:
        return compute_scores(path, sets, frames_of)
    try:
        kept = read_kept_scores(path, key, sets, frames_of)
    except ScoresFileError as exc:
        warnings.warn(f"{exc}; scoring the run again", stacklevel=2)
        kept = None
    if kept is not None:
        return {"sets": kept["sets"], "frames": kept["frames"]}
    fresh = compute_scores(path, sets, frames_of)
    utils.write_bytes_atomic(scores_path(path), (json.dumps({"format": SCORES_FORMAT, "key": key, **fresh},
                                                            allow_nan=False) + "\n").encode())
    return fresh


# --------------------------------------------------------------------------- kept predictions


def image_digest(image: torch.Tensor) -> bytes:
    """The blake2b digest of one image tensor (its float32 bytes, shape and dtype)."""
    a = image.detach().cpu().contiguous().numpy()
    return hashlib.blake2b(a.tobytes() + repr((a.shape, a.dtype.str)).encode(), digest_size=DIGEST_BYTES).digest()


def prediction_key(path: str | Path, dataset, flips: str) -> str | None:
    """The key of checkpoint ``path``'s predictions (test-time ``flips``) on ``dataset``; None
    when the set's content cannot be fingerprinted (:func:`set_fingerprint`)."""
    fingerprint = set_fingerprint(dataset)
    if fingerprint is None:
        return None
    payload = {"kind": "predictions", "checkpoint": integrity.file_sha256(Path(path)), "set": fingerprint,
               "flips": flips, "code": code_fingerprint()}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()


def predictions_paths(path: str | Path, key: str) -> tuple[Path, Path]:
    """(depth maps, frame digests): the two files that keep checkpoint ``path``'s predictions under ``key``."""
    folder = Path(path).parent / PREDICTIONS_DIR
    return folder / f"{key}.npy", folder / f"{key}.frames.npy"


def _read_bounded(file: Path, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    """The array in ``file`` when it is exactly ``shape`` of ``dtype``; ScoresFileError naming it otherwise
    (its size is checked before a byte of the array is read)."""
    need = int(np.prod(shape)) * np.dtype(dtype).itemsize
    try:
        size = file.stat().st_size
    except OSError as exc:
        raise ScoresFileError(f"{file}: cannot be read ({utils.os_reason(exc)})") from None
    if size > need + NPY_HEADER_MAX:
        raise ScoresFileError(f"{file}: {size} bytes, more than {shape} {np.dtype(dtype)} take")
    try:
        a = bounds.read_npy(file)
    except utils.FileProblem as exc:
        raise ScoresFileError(str(exc)) from None
    if a.shape != shape or a.dtype != np.dtype(dtype):
        raise ScoresFileError(f"{file}: holds {a.dtype} {a.shape}, not {np.dtype(dtype)} {shape}")
    return a


def read_kept_predictions(path: str | Path, key: str, n: int, size: tuple[int, int]
                          ) -> tuple[np.ndarray, np.ndarray] | None:
    """(digests N x DIGEST_BYTES uint8, depth N x H x W float32) kept under ``key`` beside checkpoint
    ``path`` for ``n`` frames of ``size``; None when none are kept; ScoresFileError naming a file
    that is not what :func:`kept_predictor` writes (checked for size before it is read)."""
    depth_file, digest_file = predictions_paths(path, key)
    if not (depth_file.is_file() and digest_file.is_file()):
        return None
    digests = _read_bounded(digest_file, (n, DIGEST_BYTES), np.uint8)
    depth = _read_bounded(depth_file, (n, *size), np.float32)
    if not np.isfinite(depth).all():
        raise ScoresFileError(f"{depth_file}: holds non-finite depth")
    return digests, depth


def predict_set(predict_fn, dataset, *, batch_size: int = 8, progress: bool = False
                ) -> tuple[np.ndarray, np.ndarray]:
    """(digests, depth) of every frame of ``dataset`` by ``predict_fn``, in the batches evaluation uses."""
    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=False, collate_fn=inference.collate)
    digests, depth = [], []
    for batch in tqdm(loader, desc="predict", disable=not progress, leave=False):
        digests += [np.frombuffer(image_digest(im), dtype=np.uint8) for im in batch["image"]]
        depth.append(evaluate.as_depth_batch(predict_fn(batch["image"])))
    return np.stack(digests), np.concatenate(depth)


def _write_kept(path: Path, a: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    utils.write_bytes_atomic(path, buf.getvalue())


def kept_predictor(path: str | Path, dataset, flips: str = "none", *, loaded: tuple | None = None,
                   batch_size: int = 8, progress: bool = False):
    """A predictor (images B x 3 x H x W -> depth B x H x W, as ``evaluate.evaluate_predictor`` takes)
    for the frames of ``dataset``: checkpoint ``path``'s network with test-time ``flips``
    (``inference.predict_depth``), its predictions on every frame computed once, in evaluation's
    batches, and kept in the run folder (:func:`prediction_key`). Each image asked for is found by
    its digest; an image of no kept frame is predicted afresh (``misses`` counts those batches).

    loaded: the (model, cfg) of ``checkpoint.load_model(path)`` when the caller holds them already.
    A kept file that cannot be used is named in a warning and replaced; a set that cannot be
    fingerprinted is predicted afresh (nothing kept).
    """
    inference.check_flips(flips)
    net, cfg = loaded if loaded is not None else checkpoint.load_model(path)

    def predict(images: torch.Tensor) -> torch.Tensor:
        return inference.predict_depth(net, images, cfg["image_size"], flips)

    key = prediction_key(path, dataset, flips)
    kept = None
    if key is not None and len(dataset):
        size = tuple(dataset[0]["depth"].shape[-2:])
        try:
            kept = read_kept_predictions(path, key, len(dataset), size)
        except ScoresFileError as exc:
            warnings.warn(f"{exc}; predicting again", stacklevel=2)
    if kept is None:
        kept = predict_set(predict, dataset, batch_size=batch_size, progress=progress)
        if key is not None:
            depth_file, digest_file = predictions_paths(path, key)
            _write_kept(digest_file, kept[0])
            _write_kept(depth_file, kept[1])
    digests, depth = kept
    rows = {d.tobytes(): i for i, d in enumerate(digests)}

    def served(images: torch.Tensor) -> np.ndarray:
        found = [rows.get(image_digest(im)) for im in images]
        if None not in found:
            return depth[found].copy()
        served.misses += 1
        return evaluate.as_depth_batch(predict(images))

    served.misses = 0
    return served
