"""C3VD, real colonoscopy video of a phantom with registered depth (Bobrow et al. 2023); not one of the
paper's test sets. The class ``C3VDDataset`` and its constants ``C3VD_*``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from geodepth_lite.core import camera
from geodepth_lite.core.errors import UserError
from geodepth_lite.data import bounds
from geodepth_lite.data.datasets.base import PublicDepthDataset, numbered, pair_images_with_depths

# Bobrow et al. 2023: <sequence>/<n>_color.png, <sequence>/<nnnn>_depth.tiff (16-bit,
# 0..100 mm over 0..65535; 0 and 65535 invalid), <sequence>/pose.txt (16 values a line,
# camera-to-world, mm; row- or column-major is detected from where the 0 0 0 1 row sits).
C3VD_DEPTH_RANGE_MM = 100.0
C3VD_INVALID_RAW = (0, 65535)
# C3VD's camera is omnidirectional (Scaramuzza). The depth metrics need no intrinsics; for
# 3D views the loader returns this pinhole approximation near the image centre (pixels at
# 1350x1080, scaled to the actual size). UNVERIFIED; off-centre rays are distorted by it.
C3VD_PINHOLE_APPROX = {"width": 1350, "height": 1080, "fx": 767.4, "fy": 767.5, "cx": 679.1, "cy": 543.6}


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
            recs = pair_images_with_depths(numbered(d, r"(\d+)_color\.png"), numbered(d, r"(\d+)_depth\.tiff?"),
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
        for lineno, line in enumerate(bounds.read_text(path, "C3VD pose file").splitlines(), 1):
            vals = bounds.finite_numbers([v for v in re.split(r"[,\s]+", line.strip()) if v], f"{path}:{lineno}")
            if not vals:
                continue
            if len(vals) != 16:
                raise UserError(f"{path}:{lineno}: expected 16 numbers a line, got {len(vals)}")
            M = np.array(vals).reshape(4, 4)
            if np.allclose(M[3], [0, 0, 0, 1]):
                poses.append(M)
            elif np.allclose(M[:, 3], [0, 0, 0, 1]):
                poses.append(M.T)
            else:
                raise UserError(f"{path}:{lineno}: not a 4x4 rigid transform (no 0 0 0 1 row or column)")
        return poses

    @staticmethod
    def decode_depth(path) -> tuple[np.ndarray, np.ndarray]:
        """C3VD ``*_depth.tiff``: 16-bit, 0..65535 -> 0..100 mm z-depth; raw 0 and 65535 are invalid."""
        import tifffile  # C3VD's files only: training and gpu-check need no tifffile

        with tifffile.TiffFile(str(path)) as tif:  # its size from the header, before decoding
            shape = tif.pages[0].shape if tif.pages else ()
        if len(shape) >= 2:
            bounds.check_pixels(int(shape[1]), int(shape[0]), path, "depth map")
        raw = np.asarray(tifffile.imread(str(path)))
        if raw.ndim == 3:
            raw = raw[..., 0]
        if raw.dtype != np.uint16:
            raise UserError(f"{path}: C3VD depth must be a 16-bit TIFF, got {raw.dtype}")
        valid = ~np.isin(raw, C3VD_INVALID_RAW)
        d = np.where(valid, raw.astype(np.float64) / 65535.0 * C3VD_DEPTH_RANGE_MM, 0.0)
        return d.astype(np.float32), valid

    @classmethod
    def intrinsics(cls, rec: dict, width: int, height: int) -> np.ndarray:
        """``C3VD_PINHOLE_APPROX`` scaled to the frame's size."""
        a = C3VD_PINHOLE_APPROX
        K0 = np.array([[a["fx"], 0, a["cx"]], [0, a["fy"], a["cy"]], [0, 0, 1.0]])
        return camera.scale_intrinsics(K0, width / a["width"], height / a["height"])
