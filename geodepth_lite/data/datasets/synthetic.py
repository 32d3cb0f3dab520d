"""The synthetic RGB-depth dataset as a torch ``Dataset`` (layout: see ``synth.py``).

Each item is a dict::

    image  float32 3 x H x W in [0, 1]
    depth  float32 1 x H x W z-depth (scene units; 0 = invalid)
    K      float32 3 x 3 intrinsics (pixels) of the returned size
    organ  str   ("colon", "small_intestine", "stomach", ...)
    group  str   texture x lighting group, e.g. "pink-warm_single"
    index  int   frame index within the split

``image_size`` (an int or (H, W)) resizes on the fly: the image by bilinear
interpolation with antialiasing (area-like when shrinking); the depth by
pixel-centre nearest neighbour ("nearest-exact"), so every returned depth is a
depth that was rendered (no blending across fold edges into depths that exist
nowhere) and invalid zeros stay zeros; K by ``camera.scale_intrinsics``.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from geodepth_lite.data import synth
from geodepth_lite.core import camera as cam
from geodepth_lite.core.errors import UserError
from geodepth_lite.data.images import read_rgb
from geodepth_lite.data.integrity import read_frames
from geodepth_lite.data.bounds import read_depth_npy
from geodepth_lite.utils import FileProblem


def resize_image(image: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Images (... x 3 x H x W in [0, 1]) to ``size`` = (h, w): bilinear with antialiasing, so that
    training, evaluation and prediction all see the network's input made the same way."""
    batched = image.dim() == 4
    x = image if batched else image[None]
    if tuple(x.shape[-2:]) != tuple(size):
        x = F.interpolate(x, size=tuple(size), mode="bilinear", align_corners=False, antialias=True).clamp_(0, 1)
    return x if batched else x[0]


def resize_frame(image: torch.Tensor, depth: torch.Tensor, K: np.ndarray, size: tuple[int, int],
                 valid: torch.Tensor | None = None):
    """One frame (image 3 x H x W, depth 1 x H x W, K 3x3, optional valid mask 1 x H x W) resized to
    ``size`` = (h, w): image by :func:`resize_image`, depth and mask by nearest-exact sampling (no
    depth is invented across an edge), K by :func:`camera.scale_intrinsics`.
    Returns (image, depth, K) or (image, depth, K, valid)."""
    h0, w0 = depth.shape[-2:]
    h, w = size
    image = resize_image(image, (h, w))
    depth = F.interpolate(depth[None], size=(h, w), mode="nearest-exact")[0]
    K = cam.scale_intrinsics(K, w / w0, h / h0)
    if valid is None:
        return image, depth, K
    valid = F.interpolate(valid[None].float(), size=(h, w), mode="nearest-exact")[0] > 0.5
    return image, depth, K, valid


def _size(image_size) -> tuple[int, int] | None:
    if image_size is None:
        return None
    if isinstance(image_size, int):
        h = w = image_size
    else:
        h, w = (int(v) for v in image_size)
    if h <= 0 or w <= 0:
        raise UserError(f"image_size must be positive, got {image_size!r}")
    return h, w


class SyntheticDepthDataset(torch.utils.data.Dataset):
    """Frames of one split of a generated dataset; see the module docstring for the item dict."""

    def __init__(self, root: str | Path, split: str, image_size=None):
        self.root = Path(root)
        self.split = split
        self.frames = read_frames(self.root, split)
        self.size = _size(image_size)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> dict:
        rec = self.frames[i]
        rgb = read_rgb(self.root / rec["rgb"])  # a damaged file is named (utils.FileProblem)
        depth_path = self.root / rec["depth"]
        depth = read_depth_npy(depth_path)
        if depth.ndim != 2 or depth.shape != rgb.shape[:2]:
            raise FileProblem(f"cannot use {depth_path}: a depth map of shape {depth.shape} for an image of "
                              f"{rgb.shape[1]} x {rgb.shape[0]} pixels (it must be H x W, the image's size)",
                              depth_path)
        image = torch.from_numpy(rgb.copy()).permute(2, 0, 1).float() / 255.0
        depth_t = torch.from_numpy(depth.astype(np.float32, copy=False))[None]
        K = np.asarray(rec["K"], dtype=np.float64)
        if self.size is not None and self.size != tuple(depth.shape):
            image, depth_t, K = resize_frame(image, depth_t, K, self.size)
        return {"image": image, "depth": depth_t, "K": torch.from_numpy(K.astype(np.float32)),
                "organ": rec["organ"], "group": rec["group"], "index": int(rec["index"])}


# --------------------------------------------------------------------------- training splits
# Datasets decoded at the network size stay in memory below this many bytes (per process).
CACHE_LIMIT_BYTES = 2 * 1024**3


def resolve_dataset(cfg: dict, progress: bool = False) -> Path:
    """The dataset directory of ``cfg``: an existing directory as is, else a manifest built on demand."""
    path = Path(cfg["dataset"]).expanduser()
    if path.is_dir() and (path / "manifest.json").exists():
        return path
    return Path(synth.ensure_dataset(cfg["dataset"], overrides=cfg.get("dataset_overrides"), progress=progress))


class MemoryDataset(torch.utils.data.Dataset):
    """A split decoded and resized once: tensors in memory, the same item dicts as the source."""

    def __init__(self, items: list[dict]):
        self.image = torch.stack([it["image"] for it in items])
        self.depth = torch.stack([it["depth"] for it in items])
        self.K = torch.stack([torch.as_tensor(it["K"], dtype=torch.float32) for it in items])
        self.valid = torch.stack([it["valid"] for it in items]) if items and "valid" in items[0] else None
        self.organ = [it.get("organ", "") for it in items]
        self.group = [it.get("group", "") for it in items]
        self.index = [int(it.get("index", i)) for i, it in enumerate(items)]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict:
        item = {"image": self.image[i], "depth": self.depth[i], "K": self.K[i],
                "organ": self.organ[i], "group": self.group[i], "index": self.index[i]}
        if self.valid is not None:
            item["valid"] = self.valid[i]
        return item


MEMORY_CACHE: dict[tuple, MemoryDataset] = {}


class DeviceSplit:
    """A split decoded once into tensors on one device (a CUDA run's data, where they fit in its memory):
    each batch is gathered there, with no decoding, collating, pinning or host-to-device copy per step.

    ``batch(indices)`` is the dict ``inference.collate`` makes of ``ds[i] for i in indices`` (the same
    keys, values and order), its tensors on ``device`` except "index", which stays on the host (frame ids
    are read from it). Frames are decoded ``chunk`` at a time by ``threads`` threads (image reading lets
    other threads run), so the host holds one chunk, not the split."""

    def __init__(self, ds, device: torch.device | str, *, threads: int | None = None, chunk: int = 256):
        self.device = torch.device(device)
        n = len(ds)
        self.organ: list[str] = []
        self.group: list[str] = []
        self.index: list[int] = []
        self.tensors: dict[str, torch.Tensor] = {}
        with ThreadPoolExecutor(max_workers=threads or min(16, os.cpu_count() or 1)) as pool:
            for start in range(0, n, chunk):
                items = list(pool.map(ds.__getitem__, range(start, min(n, start + chunk))))
                for key in ("image", "depth", "K", "valid"):
                    if key not in items[0]:
                        continue
                    part = torch.stack([torch.as_tensor(it[key]) for it in items])
                    if key not in self.tensors:
                        self.tensors[key] = torch.empty((n, *part.shape[1:]), dtype=part.dtype, device=self.device)
                    self.tensors[key][start:start + len(items)] = part.to(self.device)
                self.organ += [it.get("organ", "") for it in items]
                self.group += [it.get("group", "") for it in items]
                self.index += [int(it.get("index", start + j)) for j, it in enumerate(items)]

    def __len__(self) -> int:
        return len(self.index)

    def batch(self, indices) -> dict:
        """The frames ``indices`` (host ints) as one batch (class docstring)."""
        idx = [int(i) for i in indices]
        at = torch.tensor(idx, dtype=torch.long).to(self.device)
        out = {key: self.tensors[key].index_select(0, at) for key in ("image", "depth", "K")}
        out.update(organ=[self.organ[i] for i in idx], group=[self.group[i] for i in idx],
                   index=torch.tensor([self.index[i] for i in idx]))
        if "valid" in self.tensors:
            out["valid"] = self.tensors["valid"].index_select(0, at)
        return out

    def batches(self, batch_size: int):
        """Every frame in order, ``batch_size`` at a time (the last batch may be smaller)."""
        for start in range(0, len(self), batch_size):
            yield self.batch(range(start, min(len(self), start + batch_size)))

    @staticmethod
    def nbytes(n: int, image_size) -> int:
        """Bytes that ``n`` frames of ``image_size`` take on the device (image, depth, a mask; float32)."""
        h, w = _size(image_size) or (320, 320)
        return n * 5 * h * w * 4


class DeviceBatches:
    """The training batches of a :class:`DeviceSplit` in the order of ``sampler``, ``batch_size`` at a
    time, as a ``DataLoader(split, batch_size, sampler=sampler, generator=generator)`` gives them. Like
    that loader, each pass draws one number from ``generator`` (the loader's base seed), so the
    generator's state after an epoch, which checkpoints keep, is the loader's."""

    def __init__(self, split: DeviceSplit, sampler, batch_size: int, generator: torch.Generator):
        self.split, self.sampler, self.batch_size, self.generator = split, sampler, batch_size, generator

    def __len__(self) -> int:
        return -(-len(self.sampler) // self.batch_size)

    def __iter__(self):
        torch.empty((), dtype=torch.int64).random_(generator=self.generator)
        order = list(self.sampler)
        for start in range(0, len(order), self.batch_size):
            yield self.split.batch(order[start:start + self.batch_size])


def load_split(root: Path, split: str, image_size: int | None, *, cache: str | bool = "auto",
               limit: int | None = None):
    """``SyntheticDepthDataset(root, split, image_size)`` (``limit``: that many evenly spaced
    frames), decoded once and kept in memory when small (per process, reused across runs)."""
    ds = SyntheticDepthDataset(root, split, image_size=image_size)
    if limit is not None and limit < len(ds):
        # evenly spaced frames, so a subset still covers every scene, organ and lighting
        ds = torch.utils.data.Subset(ds, np.linspace(0, len(ds) - 1, limit).round().astype(int).tolist())
    if cache == "auto":
        n = len(ds)
        side = image_size or 320
        cache = n * 4 * side * side * 4 < CACHE_LIMIT_BYTES
    if not cache:
        return ds
    stamp = (root / split / "frames.jsonl").stat().st_mtime_ns if (root / split / "frames.jsonl").exists() else 0
    key = (str(Path(root).resolve()), split, image_size, limit, stamp)
    if key not in MEMORY_CACHE:
        MEMORY_CACHE[key] = MemoryDataset([ds[i] for i in range(len(ds))])
    return MEMORY_CACHE[key]
