"""EndoSLAM, its simulated UnityCam part (Ozyoruk et al. 2021): the paper's stomach, small-intestine and
colon test sets (Section 4.1). The class ``EndoSLAMDataset`` and its constants ``ENDOSLAM_*``.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from geodepth_lite.core import camera
from geodepth_lite.core.errors import UserError
from geodepth_lite.data import bounds
from geodepth_lite.data.datasets.base import PublicDepthDataset, norm_name, numbered, pair_images_with_depths, read_png_unit

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
        organ_of = {norm_name(d): organ for organ, d in ENDOSLAM_ORGAN_DIRS.items()}
        frames = []
        for d in sorted(p for p in unity.iterdir() if p.is_dir()):
            organ = organ_of.get(norm_name(d.name))
            if organ is None:
                continue
            rgb = numbered(d / ENDOSLAM_FRAMES_DIR, r"image_(\d+)\.png")
            dep = numbered(d / ENDOSLAM_DEPTH_DIR, r"aov_image_(\d+)\.png")
            recs = pair_images_with_depths(rgb, dep, {"organ": organ, "group": organ, "sequence": d.name})
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
        for lineno, line in enumerate(bounds.read_text(csvs[0], "EndoSLAM pose file").splitlines()[1:], 2):
            vals = [v for v in re.split(r"[,;\s]+", line.strip()) if v]
            if len(vals) >= 7:
                rows.append(bounds.finite_numbers(vals[:7], f"{csvs[0]}:{lineno}"))
        if not ENDOSLAM_POSE_ROW_IS_FRAME_ORDER or len(rows) != len(frame_numbers):
            if rows:
                warnings.warn(f"{csvs[0]}: {len(rows)} pose rows for {len(frame_numbers)} frames; poses not used")
            return {}
        return {n: camera.unity_pose_to_T_world_cam(r[:3], r[3:7]) for n, r in zip(frame_numbers, rows)}

    @staticmethod
    def decode_depth(path) -> tuple[np.ndarray, np.ndarray]:
        """EndoSLAM ``aov_image_*.png``: channel 0 scaled to [0, 1] (relative depth); 0 is invalid."""
        d = read_png_unit(Path(path), ENDOSLAM_DEPTH_CHANNEL)
        valid = d > 0
        if ENDOSLAM_DEPTH_NEAR_IS_BRIGHT:
            d = np.where(valid, 1.0 - d, 0.0)
            valid = d > 0
        return d.astype(np.float32), valid

    @classmethod
    def intrinsics(cls, rec: dict, width: int, height: int) -> np.ndarray:
        return camera.intrinsics(width, height, focal_ratio=ENDOSLAM_FOCAL_RATIO)
