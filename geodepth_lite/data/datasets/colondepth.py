"""ColonDepth, Unity renderings of a colon (Rau et al. 2019): the paper's three-fold cross validation
(Section 4.1). The class ``ColonDepthDataset`` and its constants ``COLONDEPTH_*``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from geodepth_lite.core import camera
from geodepth_lite.data.datasets.base import PublicDepthDataset, numbered, pair_images_with_depths, read_png_unit

# Rau et al. 2019: T{t}_L{l}_{k}_resized/FrameBuffer_%04d.png + Depth_%04d.png, 256x256.
COLONDEPTH_DEPTH_RANGE_CM = 20.0  # depth PNG read to [0, 1] maps linearly to 0..20 cm
COLONDEPTH_FOCAL_RATIO = camera.DEFAULT_FOCAL_RATIO  # UNVERIFIED: fx / W of the Unity camera


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
            frames += pair_images_with_depths(numbered(d, r"FrameBuffer_(\d+)\.png"),
                                              numbered(d, r"Depth_(\d+)\.png"), base)
        return frames

    @staticmethod
    def decode_depth(path) -> tuple[np.ndarray, np.ndarray]:
        """ColonDepth ``Depth_*.png``: [0, 1] -> 0..20 cm; 0 (nothing rendered) is invalid."""
        d = read_png_unit(Path(path)) * COLONDEPTH_DEPTH_RANGE_CM
        return d.astype(np.float32), d > 0

    @classmethod
    def intrinsics(cls, rec: dict, width: int, height: int) -> np.ndarray:
        return camera.intrinsics(width, height, focal_ratio=COLONDEPTH_FOCAL_RATIO)
