"""What the public datasets share: reading their pixels and files, the abstract ``PublicDepthDataset``,
the registry (``REGISTRY``, ``register``, ``dataset_class``) and ``open_dataset``.

Each dataset is one small module beside this one (``endoslam``, ``colondepth``, ``simcol3d``,
``c3vd``) holding its class and its constants; ``datasets/__init__.py`` registers them, in the
order ``REGISTRY`` lists them. See ``geodepth_lite.data.datasets`` for the item dict.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Iterable

import numpy as np
import torch
from PIL import Image
from torch.utils.data import Dataset

from geodepth_lite import utils
from geodepth_lite.data import bounds
from geodepth_lite.core.errors import UserError
from geodepth_lite.data.images import read_rgb
from geodepth_lite.data.datasets.synthetic import resize_frame


# =========================================================================== reading pixels
def read_png_unit(path: Path, channel: int | None = None) -> np.ndarray:
    """A PNG's values divided by its dtype's maximum (8- or 16-bit), as float64 H x W."""
    bounds.check_image_file(path, "depth map")  # over bounds.MAX_PIXELS: refused from the header
    import imageio.v3 as iio  # public datasets' files only: training and gpu-check need no imageio

    arr = np.asarray(iio.imread(path))
    if arr.ndim == 3:
        arr = arr[..., channel if channel is not None else 0]
    if arr.dtype == np.uint8:
        return arr.astype(np.float64) / 255.0
    if arr.dtype == np.uint16:
        return arr.astype(np.float64) / 65535.0
    raise UserError(f"{path}: unexpected pixel type {arr.dtype} for a depth PNG (8- or 16-bit expected)")


def read_png_raw(path: Path) -> np.ndarray:
    """A PNG's stored values (channel 0 of a multi-channel image), in its own dtype."""
    bounds.check_image_file(path, "depth map")  # over bounds.MAX_PIXELS: refused from the header
    import imageio.v3 as iio  # public datasets' files only: training and gpu-check need no imageio

    arr = np.asarray(iio.imread(path))
    if arr.ndim == 3:
        arr = arr[..., 0]
    return arr


# =========================================================================== finding frames
def numbered(folder: Path, pattern: str) -> dict[int, Path]:
    """{frame number: path} for files in ``folder`` whose name fully matches ``pattern`` (one group)."""
    rx = re.compile(pattern)
    out = {}
    if folder.is_dir():
        for p in folder.iterdir():
            m = rx.fullmatch(p.name)
            if m and p.is_file():
                out[int(m.group(1))] = p
    return out


def norm_name(s: str) -> str:
    """``s`` lower-cased without spaces, ``_`` and ``-``: folder names matched that way."""
    return re.sub(r"[\s_\-]", "", s).lower()


def pair_images_with_depths(rgb: dict[int, Path], depth: dict[int, Path], base: dict) -> list[dict]:
    """One frame record (``base`` plus ``rgb``, ``depth`` paths and ``frame`` number) per number
    that has both an image and a depth file, in number order."""
    return [dict(base, rgb=rgb[n], depth=depth[n], frame=n) for n in sorted(rgb.keys() & depth.keys())]


# =========================================================================== the Dataset and its registry
class PublicDepthDataset(Dataset):
    """Frames of a public dataset: items as ``SyntheticDepthDataset`` plus ``valid``.

    Abstract: each dataset is a subclass (registered with ``register``) that sets the class
    attributes ``name``, ``layout``, ``depth_units``, ``max_depth`` (largest encodable depth)
    and ``subset_manifest`` and overrides ``find_frames``, ``decode_depth`` and ``intrinsics``.
    ``open_dataset`` makes the instances. Instance attributes: ``root``, ``frames`` (one dict
    per item: ``rgb``, ``depth`` paths, ``organ``, ``group``, ``sequence``, ``frame`` number,
    ``K`` at native size, and ``T_world_cam`` 4x4 or None). ``image_size`` (int or (H, W))
    resizes image (bilinear), depth and valid (nearest) and K; None keeps the native size,
    which the evaluation protocol wants (Section 4.2.1).
    """

    name: str = ""
    layout: str = ""
    depth_units: str = ""
    max_depth: float = 0.0
    subset_manifest: str | None = None  # a file stem in data_manifests/eval_subsets/, or None

    def __init__(self, root: Path, frames: list[dict], image_size=None):
        if not type(self).name:
            raise TypeError("PublicDepthDataset is abstract: open a dataset with open_dataset(name, root)")
        self.root = Path(root)
        self.frames = frames
        if image_size is None:
            self.image_size = None
        else:
            hw = (image_size, image_size) if isinstance(image_size, int) else tuple(image_size)
            if len(hw) != 2 or not all(isinstance(s, int) and s > 0 for s in hw):
                raise UserError(f"image_size must be a positive int or (H, W), got {image_size!r}")
            self.image_size = hw

    # ------------------------------------------------------------------ what a subclass overrides
    @classmethod
    def find_frames(cls, root: Path) -> list[dict]:
        """One record per frame/depth pair under ``root``: ``rgb``, ``depth``, ``organ``, ``group``,
        ``sequence``, ``frame`` and, where the dataset has poses, ``T_world_cam``."""
        raise NotImplementedError

    @staticmethod
    def decode_depth(path) -> tuple[np.ndarray, np.ndarray]:
        """(float32 H x W depth in ``depth_units``, bool H x W valid) from one depth file."""
        raise NotImplementedError

    @classmethod
    def intrinsics(cls, rec: dict, width: int, height: int) -> np.ndarray:
        """3x3 K in pixels of frame record ``rec`` at its native size ``width`` x ``height``."""
        raise NotImplementedError

    # ------------------------------------------------------------------ shared
    @classmethod
    def native_K(cls, rec: dict) -> np.ndarray:
        """Intrinsics at the frame's native size (reads the image header only)."""
        with Image.open(rec["rgb"]) as im:
            W, H = im.size
        return cls.intrinsics(rec, W, H)

    @classmethod
    def layout_error(cls, root: Path, why: str) -> Exception:
        msg = f"{cls.name} root {root} {why}; expected {cls.layout}"
        return FileNotFoundError(msg) if why == "does not exist" else UserError(msg)

    def __len__(self) -> int:
        return len(self.frames)

    def counts(self, by: str = "group") -> dict[str, int]:
        """Number of frames per ``group``, ``organ`` or ``sequence``."""
        out: dict[str, int] = {}
        for f in self.frames:
            out[f[by]] = out.get(f[by], 0) + 1
        return dict(sorted(out.items()))

    def __getitem__(self, i: int) -> dict:
        rec = self.frames[i]
        rgb = read_rgb(rec["rgb"])  # a damaged file is named (utils.FileProblem)
        try:
            depth, valid = self.decode_depth(rec["depth"])
        except utils.FileProblem:
            raise
        except (OSError, ValueError) as exc:
            reason = utils.os_reason(exc).replace(f"{rec['depth']}: ", "")
            raise utils.FileProblem(f"cannot read {rec['depth']}: {reason}", rec["depth"]) from exc
        if rgb.shape[:2] != depth.shape:
            raise UserError(f"{rec['rgb'].name} is {rgb.shape[1]}x{rgb.shape[0]} but its depth "
                             f"{rec['depth'].name} is {depth.shape[1]}x{depth.shape[0]}")
        depth = np.where(valid, depth, 0.0).astype(np.float32)
        image = torch.from_numpy(rgb).permute(2, 0, 1).float().div_(255.0)
        depth_t = torch.from_numpy(depth)[None]
        valid_t = torch.from_numpy(valid)[None]
        K = np.asarray(rec["K"], dtype=np.float64)
        if self.image_size is not None and tuple(depth.shape) != self.image_size:
            image, depth_t, K, valid_t = resize_frame(image, depth_t, K, self.image_size, valid_t)
        return {
            "image": image.contiguous(),
            "depth": depth_t.contiguous(),
            "K": torch.from_numpy(K.astype(np.float32)),
            "organ": rec["organ"],
            "group": rec["group"],
            "index": int(i),
            "valid": valid_t.contiguous(),
        }


REGISTRY: dict[str, type[PublicDepthDataset]] = {}  # name -> class: the only list of public datasets


def register(cls: type[PublicDepthDataset]) -> type[PublicDepthDataset]:
    """List a ``PublicDepthDataset`` subclass in ``REGISTRY`` under its ``name`` (a class decorator too);
    ``datasets/__init__.py`` registers the datasets, in the order ``REGISTRY`` keeps."""
    missing = [a for a in ("name", "layout", "depth_units", "max_depth") if not getattr(cls, a)]
    if missing:
        raise TypeError(f"{cls.__name__} must set {', '.join(missing)}")
    if cls.name in REGISTRY:
        raise ValueError(f"dataset {cls.name!r} registered twice: {REGISTRY[cls.name].__name__}, {cls.__name__}")
    REGISTRY[cls.name] = cls
    return cls


def dataset_class(name: str) -> type[PublicDepthDataset]:
    """The registered class of public dataset ``name`` (a ValueError listing the names otherwise)."""
    if name not in REGISTRY:
        raise UserError(f"unknown dataset {name!r}: choose one of {', '.join(REGISTRY)}")
    return REGISTRY[name]


# =========================================================================== opening a copy
def as_set(value, field: str) -> set[str] | None:
    """A filter value (a name or a list of names) as a set; None stays None."""
    if value is None:
        return None
    if isinstance(value, str):
        return {value}
    if isinstance(value, Iterable):
        vals = set(value)
        if all(isinstance(v, str) for v in vals):
            return vals
    raise UserError(f"{field} must be a string or a list of strings, got {value!r}")


def open_dataset(name: str, root, *, organ=None, group=None, sequence=None, image_size=None,
                 limit: int | None = None, K=None) -> PublicDepthDataset:
    """A user's copy of a public dataset as a torch Dataset (items: see ``geodepth_lite.data.datasets``).

    name: a name in ``REGISTRY`` ("endoslam", "colondepth", "simcol3d", "c3vd"). root: the
    dataset folder (layout in ``REGISTRY[name].layout``). organ / group / sequence: a name or
    list of names to keep (EndoSLAM organs "colon", "small_intestine", "stomach"; ColonDepth
    groups "T1-L1".."T3-L3"; SimCol3D groups "SyntheticColon_I".."III"; C3VD groups are the
    segment ("cecum", "trans", ...), sequences the folder names). limit: keep the first N
    frames. K: 3x3 intrinsics at native size overriding the dataset default.
    """
    cls = dataset_class(name)
    root = Path(root).expanduser()
    if not root.exists():
        raise cls.layout_error(root, "does not exist")
    if not root.is_dir():
        raise cls.layout_error(root, "is not a folder")
    if not any(root.iterdir()):
        raise cls.layout_error(root, "is empty")
    frames = cls.find_frames(root)
    if not frames:
        seen = ", ".join(sorted(p.name for p in root.iterdir())[:6])
        raise cls.layout_error(root, f"holds no {name} frame/depth pairs (it contains: {seen})")
    for field, wanted in (("organ", organ), ("group", group), ("sequence", sequence)):
        keep = as_set(wanted, field)
        if keep is None:
            continue
        have = sorted({f[field] for f in frames})
        if not keep & set(have):
            raise UserError(f"{field} {sorted(keep)} matches no frames in {root}; available: {', '.join(have)}")
        frames = [f for f in frames if f[field] in keep]
    if limit is not None:
        if not isinstance(limit, int) or limit <= 0:
            raise UserError(f"limit must be a positive integer, got {limit!r}")
        frames = frames[:limit]
    if K is not None:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3) or not (K[0, 0] > 0 and K[1, 1] > 0):
            raise UserError(f"K must be a 3x3 intrinsics matrix with positive focal lengths, got {K.tolist()}")
    size_K: dict[tuple, np.ndarray] = {}
    for rec in frames:
        # Frames of one sequence share a size; read one header a sequence, not one per frame.
        key = rec["sequence"]
        if key not in size_K:
            size_K[key] = K if K is not None else cls.native_K(rec)
        rec.pop("K_file", None)
        rec["K"] = size_K[key]
        rec.setdefault("T_world_cam", None)
    return cls(root, frames, image_size=image_size)
