"""Loaders for public endoscopy depth datasets: the two the paper evaluates on (Section 4.1) and two more.

One small class per dataset, as monodepth2's ``kitti_dataset.py`` has one per KITTI split:
``EndoSLAMDataset``, ``ColonDepthDataset``, ``SimCol3DDataset`` and ``C3VDDataset`` subclass
``PublicDepthDataset`` (the torch Dataset and the description of a dataset in one) and are
listed in ``REGISTRY`` ({name: class}, filled by the ``@register`` decorator), the only list
of dataset names (``DATASETS`` is ``tuple(REGISTRY)``). A class holds its ``name``,
``layout`` (the folder layout quoted in errors), ``depth_units``, ``max_depth`` (the largest
depth its encoding holds: the evaluation mask's bound, Section 4.2.1) and ``subset_manifest``
(its paper subsets in ``data_manifests/eval_subsets/``, or None), and says how frames are
found under a root (``find_frames``, with the poses where the dataset has them), how a
depth file is decoded (``decode_depth``) and its intrinsics at native size (``intrinsics``).

``open_dataset(name, root, **filters)`` reads a user's copy of EndoSLAM (UnityCam),
ColonDepth, SimCol3D or C3VD in its original layout and depth encoding and returns an
instance of that class, whose items look like the synthetic set's
(``dataset.SyntheticDepthDataset``)::

    {"image": float32 3xHxW in [0, 1], "depth": float32 1xHxW z-depth (0 where invalid),
     "K": float32 3x3 pixels, "organ": str, "group": str, "index": int,
     "valid": bool 1xHxW (pixels with a usable ground-truth depth)}

Depth stays in each dataset's own unit (``ds.depth_units``; EndoSLAM is relative, so
evaluation must median-scale, as the paper does, Section 4.2.1). ``ds.frames`` lists one
record per item (file paths, sequence, frame number, ``T_world_cam`` where the dataset
has poses). Every fact below that the datasets' documentation does not pin down is one
named constant marked UNVERIFIED, so a user whose copy differs changes one line.

``check_subset(manifest, root)`` counts the frames of the paper's evaluation subsets
(``data_manifests/eval_subsets/*.json``) in a user's copy and reports mismatches;
``python -m geodepth_lite evaluate --dataset endoslam --root PATH --check`` prints that report.
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path
from typing import Iterable

import imageio.v3 as iio
import numpy as np
import tifffile
import torch
from PIL import Image
from torch.utils.data import Dataset

from . import camera, utils
from .dataset import resize_frame

# --------------------------------------------------------------------------- EndoSLAM (UnityCam)
# Ozyoruk et al. 2021: UnityCam/<Organ>/Frames/image_%04d.png,
# UnityCam/<Organ>/Pixelwise Depths/aov_image_%04d.png (channel 0, relative 0..1 gray),
# UnityCam/<Organ>/Poses/*.csv (header, then tX,tY,tZ,rX,rY,rZ,rW,time).
ENDOSLAM_ORGAN_DIRS = {  # organ name used by the workbook -> folder name under UnityCam/
    "colon": "Colon",
    "small_intestine": "SmallIntestine",  # UNVERIFIED folder name (matched ignoring case, spaces, _ and -)
    "stomach": "Stomach",  # UNVERIFIED folder name (matched ignoring case, spaces, _ and -)
}
ENDOSLAM_FRAMES_DIR = "Frames"
ENDOSLAM_DEPTH_DIR = "Pixelwise Depths"  # note the space
ENDOSLAM_POSES_DIR = "Poses"
ENDOSLAM_DEPTH_CHANNEL = 0
ENDOSLAM_DEPTH_NEAR_IS_BRIGHT = False  # UNVERIFIED: gray value grows with distance (set True to invert)
ENDOSLAM_FOCAL_RATIO = camera.DEFAULT_FOCAL_RATIO  # UNVERIFIED: fx / W of the VR-Caps Unity camera
ENDOSLAM_POSE_ROW_IS_FRAME_ORDER = True  # UNVERIFIED: k-th CSV data row is the k-th frame in number order

# --------------------------------------------------------------------------- ColonDepth
# Rau et al. 2019: T{t}_L{l}_{k}_resized/FrameBuffer_%04d.png + Depth_%04d.png, 256x256.
COLONDEPTH_DEPTH_RANGE_CM = 20.0  # depth PNG read to [0, 1] maps linearly to 0..20 cm
COLONDEPTH_FOCAL_RATIO = camera.DEFAULT_FOCAL_RATIO  # UNVERIFIED: fx / W of the Unity camera

# --------------------------------------------------------------------------- SimCol3D
# Rau et al. 2023: SyntheticColon_X/Frames_<S|B|O><n>/FrameBuffer_%04d.png + Depth_%04d.png,
# SyntheticColon_X/cam.txt; depth 16-bit PNG, value / 255 / 256 in [0, 1] -> 0..20 cm;
# SyntheticColon_X/SavedPosition_<S1>.txt (cm) + SavedRotationQuaternion_<S1>.txt (qx qy qz qw,
# left-handed), converted like EndoSLAM's Unity poses (UNITY_TO_OPENCV).
SIMCOL3D_DEPTH_DIVISOR = 255.0 * 256.0
SIMCOL3D_DEPTH_RANGE_CM = 20.0
SIMCOL3D_FOCAL_RATIO = camera.DEFAULT_FOCAL_RATIO  # used only when cam.txt is missing (a warning says so)

# --------------------------------------------------------------------------- C3VD
# Bobrow et al. 2023: <sequence>/<n>_color.png, <sequence>/<nnnn>_depth.tiff (16-bit,
# 0..100 mm over 0..65535; 0 and 65535 invalid), <sequence>/pose.txt (16 values a line,
# camera-to-world, mm; row- or column-major is detected from where the 0 0 0 1 row sits).
C3VD_DEPTH_RANGE_MM = 100.0
C3VD_INVALID_RAW = (0, 65535)
# C3VD's camera is omnidirectional (Scaramuzza). The depth metrics need no intrinsics; for
# 3D views the loader returns this pinhole approximation near the image centre (pixels at
# 1350x1080, scaled to the actual size). UNVERIFIED; off-centre rays are distorted by it.
C3VD_PINHOLE_APPROX = {"width": 1350, "height": 1080, "fx": 767.4, "fy": 767.5, "cx": 679.1, "cy": 543.6}


# =========================================================================== reading pixels
def _read_png_unit(path: Path, channel: int | None = None) -> np.ndarray:
    """A PNG's values divided by its dtype's maximum (8- or 16-bit), as float64 H x W."""
    arr = np.asarray(iio.imread(path))
    if arr.ndim == 3:
        arr = arr[..., channel if channel is not None else 0]
    if arr.dtype == np.uint8:
        return arr.astype(np.float64) / 255.0
    if arr.dtype == np.uint16:
        return arr.astype(np.float64) / 65535.0
    raise ValueError(f"{path}: unexpected pixel type {arr.dtype} for a depth PNG (8- or 16-bit expected)")


def _read_png_raw(path: Path) -> np.ndarray:
    arr = np.asarray(iio.imread(path))
    if arr.ndim == 3:
        arr = arr[..., 0]
    return arr


# =========================================================================== poses
def quaternion_to_matrix(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """3x3 rotation of a unit quaternion (x, y, z, w); normalised first."""
    q = np.array([qx, qy, qz, qw], dtype=np.float64)
    n = np.linalg.norm(q)
    if not n > 0:
        raise ValueError("zero quaternion")
    x, y, z, w = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


# Unity is left-handed with y up; the workbook's camera frame is OpenCV's (y down).
# Flipping y on both sides turns a Unity camera-to-world pose into a right-handed one.
UNITY_TO_OPENCV = np.diag([1.0, -1.0, 1.0, 1.0])  # UNVERIFIED for EndoSLAM's exported poses


def unity_pose_to_T_world_cam(t_xyz, q_xyzw) -> np.ndarray:
    """4x4 camera-to-world (OpenCV camera axes) from a Unity position and rotation quaternion."""
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(*q_xyzw)
    T[:3, 3] = t_xyz
    return UNITY_TO_OPENCV @ T @ UNITY_TO_OPENCV


# =========================================================================== finding frames
def _numbered(folder: Path, pattern: str) -> dict[int, Path]:
    """{frame number: path} for files in ``folder`` whose name fully matches ``pattern`` (one group)."""
    rx = re.compile(pattern)
    out = {}
    if folder.is_dir():
        for p in folder.iterdir():
            m = rx.fullmatch(p.name)
            if m and p.is_file():
                out[int(m.group(1))] = p
    return out


def _norm(s: str) -> str:
    return re.sub(r"[\s_\-]", "", s).lower()


def _pair_images_with_depths(rgb: dict[int, Path], depth: dict[int, Path], base: dict) -> list[dict]:
    """One frame record (``base`` plus ``rgb``, ``depth`` paths and ``frame`` number) per number
    that has both an image and a depth file, in number order."""
    return [dict(base, rgb=rgb[n], depth=depth[n], frame=n) for n in sorted(rgb.keys() & depth.keys())]


# =========================================================================== the Dataset and its registry
class PublicDepthDataset(Dataset):
    """Frames of a public dataset: items as ``SyntheticDepthDataset`` plus ``valid``.

    Abstract: each dataset is a subclass registered with ``@register`` that sets the class
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
                raise ValueError(f"image_size must be a positive int or (H, W), got {image_size!r}")
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
        return FileNotFoundError(msg) if why == "does not exist" else ValueError(msg)

    @classmethod
    def check_eval_subsets(cls, root, manifest=None) -> list[dict]:
        """``check_subset`` of ``root`` against ``manifest`` (default: this dataset's ``subset_manifest``)."""
        if manifest is None:
            if cls.subset_manifest is None:
                have = ", ".join(n for n, c in REGISTRY.items() if c.subset_manifest)
                raise ValueError(f"{cls.name} has no evaluation subset manifest (the paper's subsets: {have}); "
                                 "give a manifest JSON to check against")
            manifest = cls.subset_manifest
        m = load_subset_manifest(manifest)
        if m["dataset"] != cls.name:
            raise ValueError(f"subset manifest {manifest} describes {m['dataset']}, not {cls.name}")
        return check_subset(m, root)

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
        rgb = utils.read_rgb(rec["rgb"])  # a damaged file is named (utils.FileProblem)
        try:
            depth, valid = self.decode_depth(rec["depth"])
        except utils.FileProblem:
            raise
        except (OSError, ValueError) as exc:
            reason = utils.os_reason(exc).replace(f"{rec['depth']}: ", "")
            raise utils.FileProblem(f"cannot read {rec['depth']}: {reason}", rec["depth"]) from exc
        if rgb.shape[:2] != depth.shape:
            raise ValueError(f"{rec['rgb'].name} is {rgb.shape[1]}x{rgb.shape[0]} but its depth "
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
    """Class decorator: list a ``PublicDepthDataset`` subclass in ``REGISTRY`` under its ``name``."""
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
        raise ValueError(f"unknown dataset {name!r}: choose one of {', '.join(REGISTRY)}")
    return REGISTRY[name]


# =========================================================================== the datasets
@register
class EndoSLAMDataset(PublicDepthDataset):
    """EndoSLAM, its simulated UnityCam part (Ozyoruk et al. 2021, Medical Image Analysis 71);
    the paper's stomach, small-intestine and colon test sets (Section 4.1). Constants ``ENDOSLAM_*``."""

    name = "endoslam"
    layout = ("ROOT/UnityCam/<Organ>/Frames/image_0000.png and ROOT/UnityCam/<Organ>/Pixelwise Depths/"
              "aov_image_0000.png (<Organ> one of Colon, SmallIntestine, Stomach; "
              "ROOT may also be the UnityCam folder)")
    depth_units = "relative"
    max_depth = 1.0
    subset_manifest = "endoslam"

    @classmethod
    def find_frames(cls, root: Path) -> list[dict]:
        unity = root / "UnityCam" if (root / "UnityCam").is_dir() else root
        organ_of = {_norm(d): organ for organ, d in ENDOSLAM_ORGAN_DIRS.items()}
        frames = []
        for d in sorted(p for p in unity.iterdir() if p.is_dir()):
            organ = organ_of.get(_norm(d.name))
            if organ is None:
                continue
            rgb = _numbered(d / ENDOSLAM_FRAMES_DIR, r"image_(\d+)\.png")
            dep = _numbered(d / ENDOSLAM_DEPTH_DIR, r"aov_image_(\d+)\.png")
            recs = _pair_images_with_depths(rgb, dep, {"organ": organ, "group": organ, "sequence": d.name})
            poses = cls.read_poses(d / ENDOSLAM_POSES_DIR, sorted(rgb))
            for r in recs:
                r["T_world_cam"] = poses.get(r["frame"])
            frames += recs
        return frames

    @staticmethod
    def read_poses(folder: Path, frame_numbers: list[int]) -> dict[int, np.ndarray]:
        """{frame number: T_world_cam} from the one CSV in Poses/ (empty when absent or ambiguous)."""
        csvs = sorted(folder.glob("*.csv")) if folder.is_dir() else []
        if len(csvs) != 1:
            return {}
        rows = []
        for line in csvs[0].read_text().splitlines()[1:]:
            vals = [v for v in re.split(r"[,;\s]+", line.strip()) if v]
            if len(vals) >= 7:
                try:
                    rows.append([float(v) for v in vals[:7]])
                except ValueError:
                    raise ValueError(f"{csvs[0]}: non-numeric pose row {line!r}") from None
        if not ENDOSLAM_POSE_ROW_IS_FRAME_ORDER or len(rows) != len(frame_numbers):
            if rows:
                warnings.warn(f"{csvs[0]}: {len(rows)} pose rows for {len(frame_numbers)} frames; poses not used")
            return {}
        return {n: unity_pose_to_T_world_cam(r[:3], r[3:7]) for n, r in zip(frame_numbers, rows)}

    @staticmethod
    def decode_depth(path) -> tuple[np.ndarray, np.ndarray]:
        """EndoSLAM ``aov_image_*.png``: channel 0 scaled to [0, 1] (relative depth); 0 is invalid."""
        d = _read_png_unit(Path(path), ENDOSLAM_DEPTH_CHANNEL)
        valid = d > 0
        if ENDOSLAM_DEPTH_NEAR_IS_BRIGHT:
            d = np.where(valid, 1.0 - d, 0.0)
            valid = d > 0
        return d.astype(np.float32), valid

    @classmethod
    def intrinsics(cls, rec: dict, width: int, height: int) -> np.ndarray:
        return camera.intrinsics(width, height, focal_ratio=ENDOSLAM_FOCAL_RATIO)


@register
class ColonDepthDataset(PublicDepthDataset):
    """ColonDepth, Unity renderings of a colon (Rau et al. 2019, IJCARS 14), groups T{1,2,3}-L{1,2,3}
    of texture and lighting; the paper's three-fold cross validation (Section 4.1). Constants ``COLONDEPTH_*``."""

    name = "colondepth"
    layout = ("ROOT/T1_L1_1_resized/FrameBuffer_0000.png and ROOT/T1_L1_1_resized/Depth_0000.png "
              "(folders T{t}_L{l}_{k}_resized)")
    depth_units = "cm"
    max_depth = COLONDEPTH_DEPTH_RANGE_CM
    subset_manifest = "colondepth"

    @classmethod
    def find_frames(cls, root: Path) -> list[dict]:
        frames = []
        for d in sorted(p for p in root.iterdir() if p.is_dir()):
            m = re.fullmatch(r"T(\d+)_L(\d+)_(\d+)_resized", d.name)
            if not m:
                continue
            base = {"organ": "colon", "group": f"T{m.group(1)}-L{m.group(2)}", "sequence": d.name}
            frames += _pair_images_with_depths(_numbered(d, r"FrameBuffer_(\d+)\.png"),
                                               _numbered(d, r"Depth_(\d+)\.png"), base)
        return frames

    @staticmethod
    def decode_depth(path) -> tuple[np.ndarray, np.ndarray]:
        """ColonDepth ``Depth_*.png``: [0, 1] -> 0..20 cm; 0 (nothing rendered) is invalid."""
        d = _read_png_unit(Path(path)) * COLONDEPTH_DEPTH_RANGE_CM
        return d.astype(np.float32), d > 0

    @classmethod
    def intrinsics(cls, rec: dict, width: int, height: int) -> np.ndarray:
        return camera.intrinsics(width, height, focal_ratio=COLONDEPTH_FOCAL_RATIO)


@register
class SimCol3DDataset(PublicDepthDataset):
    """SimCol3D, the synthetic colons of the MICCAI 2022 EndoVis challenge (Rau et al. 2023); not
    one of the paper's test sets (Section 4.1), scored with its protocol (Section 4.2.1). Constants ``SIMCOL3D_*``."""

    name = "simcol3d"
    layout = ("ROOT/SyntheticColon_I/Frames_S1/FrameBuffer_0000.png and .../Depth_0000.png, with "
              "ROOT/SyntheticColon_I/cam.txt (ROOT may also be one SyntheticColon_X folder)")
    depth_units = "cm"
    max_depth = SIMCOL3D_DEPTH_RANGE_CM * 65535.0 / SIMCOL3D_DEPTH_DIVISOR

    @classmethod
    def find_frames(cls, root: Path) -> list[dict]:
        colons = [root] if re.fullmatch(r"SyntheticColon_\w+", root.name) else \
            sorted(p for p in root.iterdir() if p.is_dir() and re.fullmatch(r"SyntheticColon_\w+", p.name))
        frames = []
        for c in colons:
            K = cls.read_cam(c / "cam.txt") if (c / "cam.txt").is_file() else None
            for d in sorted(p for p in c.iterdir() if p.is_dir() and re.fullmatch(r"Frames_[SBO]\d+", p.name)):
                recs = _pair_images_with_depths(
                    _numbered(d, r"FrameBuffer_(\d+)\.png"), _numbered(d, r"Depth_(\d+)\.png"),
                    {"organ": "colon", "group": c.name, "sequence": f"{c.name}/{d.name}", "T_world_cam": None})
                poses = cls.read_poses(c, d.name.split("_", 1)[1], len(recs))
                for r, T in zip(recs, poses):
                    r["T_world_cam"] = T
                if K is None and recs:
                    warnings.warn(f"{c / 'cam.txt'} missing: using fx = {SIMCOL3D_FOCAL_RATIO} W")
                for r in recs:
                    r["K_file"] = K
                frames += recs
        return frames

    @staticmethod
    def read_cam(path) -> np.ndarray:
        """SimCol3D ``cam.txt``: 9 numbers (3x3 K, row-major) or 4 numbers (fx fy cx cy)."""
        vals = [float(v) for v in re.split(r"[,\s]+", Path(path).read_text().strip()) if v]
        if len(vals) == 9:
            K = np.array(vals).reshape(3, 3)
        elif len(vals) == 4:
            fx, fy, cx, cy = vals
            K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        else:
            raise ValueError(f"{path}: expected 9 numbers (3x3 K) or 4 (fx fy cx cy), got {len(vals)}")
        if not (K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] == 1):
            raise ValueError(f"{path}: not a pinhole intrinsics matrix: {K.tolist()}")
        return K

    @staticmethod
    def read_poses(colon: Path, seq: str, n: int) -> list[np.ndarray]:
        """T_world_cam (cm) per frame from SavedPosition_<seq>.txt and SavedRotationQuaternion_<seq>.txt
        (one "x y z" / "qx qy qz qw" line a frame, Unity's left-handed axes); [] when absent or
        when the line count differs from the frame count."""
        pos_f, rot_f = colon / f"SavedPosition_{seq}.txt", colon / f"SavedRotationQuaternion_{seq}.txt"
        if not (pos_f.is_file() and rot_f.is_file()):
            return []

        def rows(path, k):
            out = []
            for lineno, line in enumerate(path.read_text().splitlines(), 1):
                vals = [v for v in re.split(r"[,\s]+", line.strip()) if v]
                if not vals:
                    continue
                if len(vals) != k:
                    raise ValueError(f"{path}:{lineno}: expected {k} numbers, got {len(vals)}")
                out.append([float(v) for v in vals])
            return out

        pos, rot = rows(pos_f, 3), rows(rot_f, 4)
        if len(pos) != n or len(rot) != n:
            warnings.warn(f"{pos_f.name}/{rot_f.name}: {len(pos)}/{len(rot)} poses for {n} frames; poses not used")
            return []
        return [unity_pose_to_T_world_cam(t, q) for t, q in zip(pos, rot)]

    @staticmethod
    def decode_depth(path) -> tuple[np.ndarray, np.ndarray]:
        """SimCol3D ``Depth_*.png``: 16-bit value / 255 / 256 -> [0, 1] -> 0..20 cm; 0 is invalid."""
        raw = _read_png_raw(Path(path))
        if raw.dtype != np.uint16:
            raise ValueError(f"{path}: SimCol3D depth must be a 16-bit PNG, got {raw.dtype}")
        d = raw.astype(np.float64) / SIMCOL3D_DEPTH_DIVISOR * SIMCOL3D_DEPTH_RANGE_CM
        return d.astype(np.float32), raw > 0

    @classmethod
    def intrinsics(cls, rec: dict, width: int, height: int) -> np.ndarray:
        """The colon's ``cam.txt`` when it has one, else ``SIMCOL3D_FOCAL_RATIO``."""
        if rec.get("K_file") is not None:
            return rec["K_file"]
        return camera.intrinsics(width, height, focal_ratio=SIMCOL3D_FOCAL_RATIO)


@register
class C3VDDataset(PublicDepthDataset):
    """C3VD, real colonoscopy video of a phantom with depth from 2D-3D registration (Bobrow et al.
    2023, Medical Image Analysis 90); not one of the paper's test sets (Section 4.1), scored with
    its protocol (Section 4.2.1). Constants ``C3VD_*``."""

    name = "c3vd"
    layout = ("ROOT/<sequence>/0_color.png and ROOT/<sequence>/0000_depth.tiff, with ROOT/<sequence>/pose.txt "
              "(ROOT may also be one sequence folder)")
    depth_units = "mm"
    max_depth = C3VD_DEPTH_RANGE_MM

    @classmethod
    def find_frames(cls, root: Path) -> list[dict]:
        seqs = [root] if any(root.glob("*_color.png")) else sorted(p for p in root.iterdir() if p.is_dir())
        frames = []
        for d in seqs:
            recs = _pair_images_with_depths(_numbered(d, r"(\d+)_color\.png"), _numbered(d, r"(\d+)_depth\.tiff?"),
                                            {"organ": "colon", "group": d.name.split("_")[0], "sequence": d.name})
            poses = cls.read_poses(d / "pose.txt") if (d / "pose.txt").is_file() and recs else []
            for r in recs:
                r["T_world_cam"] = poses[r["frame"]] if r["frame"] < len(poses) else None
            frames += recs
        return frames

    @staticmethod
    def read_poses(path) -> list[np.ndarray]:
        """C3VD ``pose.txt``: one 4x4 camera-to-world a line (16 numbers, comma or space separated).

        The storage order is detected per line: row-major has ``0 0 0 1`` as its last four
        numbers, column-major has 0 at positions 4, 8, 12 and 1 at 16.
        """
        poses = []
        for lineno, line in enumerate(Path(path).read_text().splitlines(), 1):
            vals = [float(v) for v in re.split(r"[,\s]+", line.strip()) if v]
            if not vals:
                continue
            if len(vals) != 16:
                raise ValueError(f"{path}:{lineno}: expected 16 numbers a line, got {len(vals)}")
            M = np.array(vals).reshape(4, 4)
            if np.allclose(M[3], [0, 0, 0, 1]):
                poses.append(M)
            elif np.allclose(M[:, 3], [0, 0, 0, 1]):
                poses.append(M.T)
            else:
                raise ValueError(f"{path}:{lineno}: not a 4x4 rigid transform (no 0 0 0 1 row or column)")
        return poses

    @staticmethod
    def decode_depth(path) -> tuple[np.ndarray, np.ndarray]:
        """C3VD ``*_depth.tiff``: 16-bit, 0..65535 -> 0..100 mm z-depth; raw 0 and 65535 are invalid."""
        raw = np.asarray(tifffile.imread(str(path)))
        if raw.ndim == 3:
            raw = raw[..., 0]
        if raw.dtype != np.uint16:
            raise ValueError(f"{path}: C3VD depth must be a 16-bit TIFF, got {raw.dtype}")
        valid = ~np.isin(raw, C3VD_INVALID_RAW)
        d = np.where(valid, raw.astype(np.float64) / 65535.0 * C3VD_DEPTH_RANGE_MM, 0.0)
        return d.astype(np.float32), valid

    @classmethod
    def intrinsics(cls, rec: dict, width: int, height: int) -> np.ndarray:
        """``C3VD_PINHOLE_APPROX`` scaled to the frame's size."""
        a = C3VD_PINHOLE_APPROX
        K0 = np.array([[a["fx"], 0, a["cx"]], [0, a["fy"], a["cy"]], [0, 0, 1.0]])
        return camera.scale_intrinsics(K0, width / a["width"], height / a["height"])


DATASETS = tuple(REGISTRY)  # the registered names, for compatibility


# =========================================================================== opening a copy
def _as_set(value, field: str) -> set[str] | None:
    if value is None:
        return None
    if isinstance(value, str):
        return {value}
    if isinstance(value, Iterable):
        vals = set(value)
        if all(isinstance(v, str) for v in vals):
            return vals
    raise ValueError(f"{field} must be a string or a list of strings, got {value!r}")


def open_dataset(name: str, root, *, organ=None, group=None, sequence=None, image_size=None,
                 limit: int | None = None, K=None) -> PublicDepthDataset:
    """A user's copy of a public dataset as a torch Dataset (see the module docstring).

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
        keep = _as_set(wanted, field)
        if keep is None:
            continue
        have = sorted({f[field] for f in frames})
        if not keep & set(have):
            raise ValueError(f"{field} {sorted(keep)} matches no frames in {root}; available: {', '.join(have)}")
        frames = [f for f in frames if f[field] in keep]
    if limit is not None:
        if not isinstance(limit, int) or limit <= 0:
            raise ValueError(f"limit must be a positive integer, got {limit!r}")
        frames = frames[:limit]
    if K is not None:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3) or not (K[0, 0] > 0 and K[1, 1] > 0):
            raise ValueError(f"K must be a 3x3 intrinsics matrix with positive focal lengths, got {K.tolist()}")
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


# =========================================================================== evaluation subsets
def load_subset_manifest(manifest) -> dict:
    """A subset manifest: a dict, a path to JSON, or a name in ``data_manifests/eval_subsets/``."""
    if isinstance(manifest, dict):
        m = manifest
    else:
        p = Path(manifest)
        if not p.suffix:
            p = utils.manifests_dir() / "eval_subsets" / f"{manifest}.json"
        if not p.is_file():
            raise FileNotFoundError(f"subset manifest {manifest} not found ({p})")
        m = json.loads(p.read_text())
    for key in ("dataset", "subsets"):
        if key not in m:
            raise ValueError(f"subset manifest lacks {key!r}")
    if m["dataset"] not in REGISTRY:
        raise ValueError(f"subset manifest: unknown dataset {m['dataset']!r}")
    for s in m["subsets"]:
        for key in ("name", "filter", "frames"):
            if key not in s:
                raise ValueError(f"subset manifest: a subset lacks {key!r}")
        if not isinstance(s["frames"], int) or s["frames"] <= 0:
            raise ValueError(f"subset {s['name']}: frames must be a positive integer")
    return m


def check_subset(manifest, root) -> list[dict]:
    """Count the frames of each paper subset in ``root``; one row per subset.

    Row: {"subset", "expected", "found", "status"} with status "ok" (counts equal),
    "more" (the copy holds more frames than the paper used: select as the manifest's
    notes say), "fewer" (frames missing) or "missing" (no frame of that subset).
    A root that is missing or in another layout raises the loader's error.
    """
    m = load_subset_manifest(manifest)
    ds = open_dataset(m["dataset"], root)
    rows = []
    for s in m["subsets"]:
        found = sum(all(f[k] in _as_set(v, k) for k, v in s["filter"].items()) for f in ds.frames)
        exp = s["frames"]
        status = "ok" if found == exp else "missing" if found == 0 else "more" if found > exp else "fewer"
        rows.append({"subset": s["name"], "expected": exp, "found": found, "status": status})
    return rows


def format_check(rows: list[dict]) -> str:
    """``check_subset``'s rows as a fixed-width table (subset, expected, found, status)."""
    lines = [f"{'subset':<18}{'expected':>9}{'found':>8}  status"]
    lines += [f"{r['subset']:<18}{r['expected']:>9}{r['found']:>8}  {r['status']}" for r in rows]
    return "\n".join(lines)
