"""SimCol3D, the synthetic colons of the MICCAI 2022 EndoVis challenge (Rau et al. 2023); not one of the
paper's test sets. The class ``SimCol3DDataset`` and its constants ``SIMCOL3D_*``.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from geodepth_lite.core import camera
from geodepth_lite.core.errors import UserError
from geodepth_lite.data import bounds
from geodepth_lite.data.datasets.base import PublicDepthDataset, numbered, pair_images_with_depths, read_png_raw

# Rau et al. 2023: SyntheticColon_X/Frames_<S|B|O><n>/FrameBuffer_%04d.png + Depth_%04d.png,
# SyntheticColon_X/cam.txt; depth 16-bit PNG, value / 255 / 256 in [0, 1] -> 0..20 cm;
# SyntheticColon_X/SavedPosition_<S1>.txt (cm) + SavedRotationQuaternion_<S1>.txt (qx qy qz qw,
# left-handed), converted like EndoSLAM's Unity poses (camera.UNITY_TO_OPENCV).
SIMCOL3D_DEPTH_DIVISOR = 255.0 * 256.0
SIMCOL3D_DEPTH_RANGE_CM = 20.0
SIMCOL3D_FOCAL_RATIO = camera.DEFAULT_FOCAL_RATIO  # used only when cam.txt is missing (a warning says so)


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
                recs = pair_images_with_depths(
                    numbered(d, r"FrameBuffer_(\d+)\.png"), numbered(d, r"Depth_(\d+)\.png"),
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
        text = bounds.read_text(path, "SimCol3D camera file")
        vals = bounds.finite_numbers([v for v in re.split(r"[,\s]+", text.strip()) if v], str(path))
        if len(vals) == 9:
            K = np.array(vals).reshape(3, 3)
        elif len(vals) == 4:
            fx, fy, cx, cy = vals
            K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        else:
            raise UserError(f"{path}: expected 9 numbers (3x3 K) or 4 (fx fy cx cy), got {len(vals)}")
        if not (K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] == 1):
            raise UserError(f"{path}: not a pinhole intrinsics matrix: {K.tolist()}")
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
            for lineno, line in enumerate(bounds.read_text(path, "SimCol3D pose file").splitlines(), 1):
                vals = [v for v in re.split(r"[,\s]+", line.strip()) if v]
                if not vals:
                    continue
                if len(vals) != k:
                    raise UserError(f"{path}:{lineno}: expected {k} numbers, got {len(vals)}")
                out.append(bounds.finite_numbers(vals, f"{path}:{lineno}"))
            return out

        pos, rot = rows(pos_f, 3), rows(rot_f, 4)
        if len(pos) != n or len(rot) != n:
            warnings.warn(f"{pos_f.name}/{rot_f.name}: {len(pos)}/{len(rot)} poses for {n} frames; poses not used")
            return []
        return [camera.unity_pose_to_T_world_cam(t, q) for t, q in zip(pos, rot)]

    @staticmethod
    def decode_depth(path) -> tuple[np.ndarray, np.ndarray]:
        """SimCol3D ``Depth_*.png``: 16-bit value / 255 / 256 -> [0, 1] -> 0..20 cm; 0 is invalid."""
        raw = read_png_raw(Path(path))
        if raw.dtype != np.uint16:
            raise UserError(f"{path}: SimCol3D depth must be a 16-bit PNG, got {raw.dtype}")
        d = raw.astype(np.float64) / SIMCOL3D_DEPTH_DIVISOR * SIMCOL3D_DEPTH_RANGE_CM
        return d.astype(np.float32), raw > 0

    @classmethod
    def intrinsics(cls, rec: dict, width: int, height: int) -> np.ndarray:
        """The colon's ``cam.txt`` when it has one, else ``SIMCOL3D_FOCAL_RATIO``."""
        if rec.get("K_file") is not None:
            return rec["K_file"]
        return camera.intrinsics(width, height, focal_ratio=SIMCOL3D_FOCAL_RATIO)
