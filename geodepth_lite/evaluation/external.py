"""Depth-annotated frames from another simulator, scored beside the synthetic held-out sets (notebook 06).

The paper tests its network on data it never trained on (Section 4.2.2). Besides the synthetic
held-out groups, this module scores it on a small public sample from another renderer:

- ``data_manifests/external/<name>.json`` names the sample: where the files come from (repository,
  commit, folder), their licence, their depth encoding, and each file's SHA-256;
- ``sample_dataset(name, root)`` reads those files from a folder holding them (their own names,
  no sub-folders), checks every checksum first, and decodes them with the dataset's loader;
- ``score_sample`` scores a model and the three baselines on it, one row per method and frame;
- ``write_scores`` / ``read_scores``: those rows as CSV. The scores of the sample's frames are
  committed in ``notebooks/external/<name>.csv``, because the frames themselves are not shipped
  (their licence does not allow it here): notebook 06 reads that table, and scores the frames
  afresh when it is given a folder with them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from geodepth_lite import utils
from geodepth_lite.core import camera, metrics
from geodepth_lite.core.errors import UserError
from geodepth_lite.data.datasets import MemoryDataset, SimCol3DDataset
from geodepth_lite.data.images import read_rgb
from geodepth_lite.data.integrity import file_sha256
from geodepth_lite.evaluation import evaluate, tables
from geodepth_lite.training import inference

DECODERS = {"simcol3d": SimCol3DDataset.decode_depth}  # dataset -> depth PNG -> (depth, valid)


def sample_manifest_path(name: str) -> Path:
    return utils.checkout_path("data_manifests", "external") / f"{name}.json"


def load_sample_manifest(name: str) -> dict:
    """The sample's manifest (``data_manifests/external/<name>.json``), checked for its fields."""
    path = sample_manifest_path(name)
    if not path.is_file():
        known = sorted(p.stem for p in path.parent.glob("*.json"))
        raise FileNotFoundError(f"no external sample {name!r} (known: {', '.join(known) or 'none'})")
    m = json.loads(path.read_text())
    missing = [k for k in ("name", "dataset", "source", "licence", "files") if k not in m]
    if missing:
        raise UserError(f"{path}: missing field(s) {', '.join(missing)}")
    if m["dataset"] not in DECODERS:
        raise UserError(f"{path}: dataset {m['dataset']!r} has no decoder (known: {', '.join(DECODERS)})")
    for i, f in enumerate(m["files"]):
        if not {"rgb", "rgb_sha256", "depth", "depth_sha256"} <= set(f):
            raise UserError(f"{path}: files[{i}] needs rgb, rgb_sha256, depth, depth_sha256")
    return m


def check_copy(name: str, root: str | Path) -> list[str]:
    """What is wrong with the copy of sample ``name`` in ``root``, one line per file (none: all
    there and byte for byte the manifest's)."""
    root = Path(root)
    if not root.is_dir():
        return [f"{root}: not a folder"]
    problems = []
    for f in load_sample_manifest(name)["files"]:
        for kind in ("rgb", "depth"):
            p = root / f[kind]
            if not p.is_file():
                problems.append(f"{p}: missing")
            elif file_sha256(p) != f[f"{kind}_sha256"]:
                problems.append(f"{p}: not the file of the manifest (its SHA-256 differs)")
    return problems


def sample_dataset(name: str, root: str | Path) -> MemoryDataset:
    """The sample's frames from ``root`` (checked with ``check_copy`` first: a ValueError lists
    what is wrong), at their own size, as evaluation items (image, depth, valid, K, index)."""
    problems = check_copy(name, root)
    if problems:
        raise UserError(f"the {name} frames in {root} do not match data_manifests/external/{name}.json:\n"
                         + "\n".join(problems))
    m = load_sample_manifest(name)
    decode = DECODERS[m["dataset"]]
    items = []
    for i, f in enumerate(m["files"]):
        rgb = read_rgb(Path(root) / f["rgb"]).astype(np.float32) / 255.0
        depth, valid = decode(Path(root) / f["depth"])
        H, W = depth.shape
        if rgb.shape[:2] != (H, W):
            raise UserError(f"{Path(root) / f['rgb']}: {rgb.shape[1]}x{rgb.shape[0]}, its depth {W}x{H}")
        items.append({"image": torch.from_numpy(rgb).permute(2, 0, 1).contiguous(),
                      "depth": torch.from_numpy(depth)[None], "valid": torch.from_numpy(valid)[None],
                      "K": camera.intrinsics(W, H), "organ": "colon", "group": m["name"], "index": i})
    return MemoryDataset(items)


def score_sample(dataset, model, image_size: int, flips: str, mean_map: np.ndarray,
                 model_label: str = "model") -> list[dict]:
    """One row per method and frame: the model (``inference.predict_depth`` with ``flips``) and
    the three baselines (``evaluate.evaluate_baselines``), the seven metrics with the protocol's
    median scaling, and the scaling ratio."""
    def predict(images):
        return inference.predict_depth(model, images, image_size, flips)

    results = {model_label: evaluate.evaluate_predictor(predict, dataset)}
    results |= {f"baseline: {b}": r for b, r in evaluate.evaluate_baselines(dataset, mean_map).items()}
    return [{"method": method, "frame": f["index"], **{k: float(f[k]) for k in (*metrics.METRIC_NAMES, "ratio")}}
            for method, r in results.items() for f in r["frames"]]


def summary(rows: list[dict]) -> dict[str, dict]:
    """{method: {"frames": n, metric: mean over its frames}} (the protocol's mean over frames)."""
    out: dict[str, dict] = {}
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == method]
        out[method] = {"frames": len(mine), **{k: float(np.mean([r[k] for r in mine])) for k in metrics.METRIC_NAMES}}
    return out


def write_scores(path: str | Path, rows: list[dict]) -> Path:
    """The rows as CSV (numbers to 6 significant digits), written whole or not at all."""
    numbers = (*metrics.METRIC_NAMES, "ratio")
    text = tables.csv_bytes([{"method": r["method"], "frame": r["frame"], **{k: f"{r[k]:.6g}" for k in numbers}}
                             for r in rows])
    path = Path(path)
    utils.write_bytes_atomic(path, text)
    return path


def read_scores(path: str | Path) -> list[dict]:
    """Rows written by ``write_scores``, numbers as floats (frame as int)."""
    columns = (*metrics.METRIC_NAMES, "ratio")
    return [{"method": r["method"], "frame": int(r["frame"]), **{k: float(r[k]) for k in columns}}
            for r in tables.read_csv(path)]


def committed_scores(name: str) -> Path:
    """``notebooks/external/<name>.csv``: the committed scores of the sample's frames."""
    return sample_manifest_path(name).parents[2] / "notebooks" / "external" / f"{name}.csv"

