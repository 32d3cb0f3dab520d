"""Depth maps and images of analytic endoscopic scenes, without rendering (no VTK).

Three kinds of view, each a closed-form ray cast from a pinhole camera at the origin looking
along +z (:func:`depth_map`):

- "lumen": inside a tube of radius R whose axis is tilted from the optical axis and passes near
  the camera, with ring folds (the radius modulated along the axis): the depth grows towards a
  far, dark centre, as in a colon seen along its length;
- "wall": a tilted plane with smooth bumps, seen at a glancing angle;
- "closeup": a curved surface a few millimetres from the lens filling the view.

Units: the shapes are drawn in millimetres (a colon-sized tube of radius 12-20 mm, a wall 15-30 mm
away, a close-up 3-6 mm from the lens) and returned in the scenario data's scene units, one unit
being :data:`MM_PER_SCENE_UNIT` mm (the scenario colon's radius is 2 units): every depth lies in
0.19-21 units (by construction: no surface nearer than 1.9 mm, the wall clipped at 210 mm), inside
the network head's ranges (``model.MIN_DEPTH``-``model.MAX_DEPTH``, and the paper profile's 0.1-40)
and the scenario manifests' near and far planes (0.01, 100), as the paper's set does (Sec. 3.A).

Images (:func:`shaded_image`) are Lambertian shading from a light at the camera with inverse-
square fall-off and a tissue colour, so the depth is visible in the brightness, as in
endoscopy. Used by the nearest-point search's tests and benchmark and by ``gpu-check``'s data.
"""

from __future__ import annotations

import json
import math
import multiprocessing
from pathlib import Path

import numpy as np
from PIL import Image

from geodepth_lite.data import integrity
from geodepth_lite import utils

KINDS = ("lumen", "wall", "closeup")
MM_PER_SCENE_UNIT = 10.0  # millimetres per scene unit: the scenario colon (radius 2 units) is 20 mm in radius


def intrinsics(size: int, fov_deg: float = 90.0) -> np.ndarray:
    """3 x 3 pinhole K of a square size x size image with the given horizontal field of view."""
    f = 0.5 * size / math.tan(math.radians(fov_deg) / 2)
    c = (size - 1) / 2
    return np.array([[f, 0, c], [0, f, c], [0, 0, 1]], dtype=np.float64)


def _rays(size: int, K: np.ndarray):
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    return x, y  # ray (x, y, 1): z-depth t gives the point t (x, y, 1)


def depth_map(kind: str, size: int, seed: int = 0, K: np.ndarray | None = None,
              mm_per_unit: float = MM_PER_SCENE_UNIT) -> np.ndarray:
    """z-depth (float32, size x size, all finite > 0) of an analytic view of ``kind`` (:data:`KINDS`),
    in units of ``mm_per_unit`` millimetres (default: the scenario data's scene units; 1: millimetres).

    ``seed`` varies the pose and shape (tilt, radius, fold phase, bumps) reproducibly.
    """
    if not (isinstance(mm_per_unit, (int, float)) and 0 < mm_per_unit < math.inf):
        raise ValueError(f"mm_per_unit must be a positive number, got {mm_per_unit!r}")
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    rng = np.random.default_rng(seed)
    K = intrinsics(size) if K is None else K
    x, y = _rays(size, K)
    if kind == "lumen":
        R = rng.uniform(12.0, 20.0)
        tilt = np.radians(rng.uniform(5.0, 20.0))
        az = rng.uniform(0, 2 * np.pi)
        a = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])  # axis direction
        c = np.array([rng.uniform(-0.4, 0.4) * R, rng.uniform(-0.4, 0.4) * R, 0.0])  # a point of the axis
        d = np.stack([x, y, np.ones_like(x)], -1)  # (H, W, 3), z = 1: t is the z-depth
        # |(t d - c) - ((t d - c).a) a|^2 = R^2, a quadratic in t
        da = d @ a
        dp = d - da[..., None] * a
        cp = -c + (c @ a) * a
        A = (dp * dp).sum(-1)
        Bq = 2 * (dp * cp).sum(-1)
        C = (cp * cp).sum() - R**2  # < 0: the camera is inside the tube
        t = (-Bq + np.sqrt(np.maximum(Bq * Bq - 4 * A * C, 0.0))) / (2 * np.maximum(A, 1e-12))
        t = np.minimum(t, 8 * R)  # the far end of the visible lumen
        along = t * da  # distance along the axis
        folds = 1.0 - 0.06 * np.sin(2 * np.pi * along / rng.uniform(15.0, 25.0) + rng.uniform(0, 2 * np.pi)) ** 8
        z = t * folds
    elif kind == "wall":
        n = np.array([rng.uniform(-0.6, 0.6), rng.uniform(0.4, 0.8), -1.0])
        n /= np.linalg.norm(n)
        p0 = np.array([0.0, 0.0, rng.uniform(15.0, 30.0)])
        d = np.stack([x, y, np.ones_like(x)], -1)
        t = (p0 @ n) / np.minimum(d @ n, -1e-3)  # (H, W): plane, facing the camera
        t = np.clip(t, 2.0, 200.0)
        fx, fy = rng.uniform(0.1, 0.3, 2)
        z = t * (1.0 + 0.05 * np.sin(fx * t * x * 3) * np.cos(fy * t * y * 3))
    else:
        z0 = rng.uniform(3.0, 6.0)
        cx, cy = rng.uniform(-0.3, 0.3, 2)
        z = z0 * (1.0 + 0.8 * ((x - cx) ** 2 + (y - cy) ** 2)) + 0.3 * np.sin(5 * x + rng.uniform(0, 6))
    return (np.maximum(z, 0.5) / mm_per_unit).astype(np.float32)


def shaded_image(depth: np.ndarray, K: np.ndarray, seed: int = 0) -> np.ndarray:
    """H x W x 3 uint8 RGB: tissue colour x Lambert shading x inverse-square fall-off of a light at the camera."""
    rng = np.random.default_rng(seed)
    x, y = _rays(depth.shape[0], K)
    P = np.stack([x * depth, y * depth, depth], -1).astype(np.float64)  # (H, W, 3)
    du = np.gradient(P, axis=1)
    dv = np.gradient(P, axis=0)
    n = np.cross(du, dv)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12
    r = np.linalg.norm(P, axis=-1)
    lam = np.abs((n * P).sum(-1)) / (r + 1e-12)
    intensity = lam * (np.median(r) / r) ** 2
    colour = np.array([0.85, 0.45, 0.35]) * rng.uniform(0.9, 1.1, 3)
    img = np.clip(intensity[..., None] * colour * 1.2, 0, 1)
    return (img * 255 + 0.5).astype(np.uint8)


def write_dataset(root, splits: dict, size: int = 320, seed: int = 0, workers: int = 1,
                  mm_per_unit: float = MM_PER_SCENE_UNIT) -> Path:
    """A dataset folder of analytic frames in the synthetic dataset's layout (``synth.py``), without VTK.

    ``splits``: frames per split, e.g. {"train": 40, "val": 8, "test": 8}; views cycle through
    :data:`KINDS`, each frame its own seed. Writes manifest.json, ``<split>/frames.jsonl``,
    ``<split>/rgb/NNNNNN.png``, ``<split>/depth/NNNNNN.npy`` and checksums.sha256 last, so ``train``
    and ``evaluate`` check it as they check a generated dataset. ``root`` must not exist or be empty.
    ``workers`` > 1 writes the frames in that many processes; each frame depends on its index alone,
    so the folder is byte-identical whatever the count. ``mm_per_unit``: the depth unit
    (:func:`depth_map`; the manifest records it). Returns the folder.
    """
    root = Path(root)
    if root.exists() and any(root.iterdir()):
        raise utils.FileProblem(f"cannot write the analytic dataset into {root}: the folder is not empty", root)
    K = intrinsics(size)
    m = {"name": "analytic", "generator": "geodepth_lite.data.analytic", "size": size, "seed": seed,
         "splits": {k: int(v) for k, v in splits.items()}, "mm_per_depth_unit": float(mm_per_unit)}
    jobs, frame = [], 0
    for split, n in m["splits"].items():
        (root / split / "rgb").mkdir(parents=True, exist_ok=True)
        (root / split / "depth").mkdir(parents=True, exist_ok=True)
        records = []
        for i in range(n):
            jobs.append((str(root), split, i, frame, size, seed, float(mm_per_unit)))
            records.append({"index": i, "rgb": f"{split}/rgb/{i:06d}.png", "depth": f"{split}/depth/{i:06d}.npy",
                            "K": K.tolist(), "organ": KINDS[frame % len(KINDS)], "group": "analytic"})
            frame += 1
        (root / split / "frames.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    if workers > 1 and len(jobs) > 1:
        with multiprocessing.get_context("fork").Pool(min(workers, len(jobs))) as pool:
            pool.map(_write_frame, jobs, chunksize=max(1, len(jobs) // (8 * workers)))
    else:
        for job in jobs:
            _write_frame(job)
    utils.write_json_atomic(root / "manifest.json", m)
    integrity.write_checksums(root, m)
    return root


def _write_frame(job) -> None:
    """One frame's image and depth map (a worker's unit of :func:`write_dataset`)."""
    root, split, i, frame, size, seed, mm_per_unit = job
    K = intrinsics(size)
    depth = depth_map(KINDS[frame % len(KINDS)], size, seed=seed * 100003 + frame, K=K, mm_per_unit=mm_per_unit)
    Image.fromarray(shaded_image(depth, K, seed=frame)).save(Path(root) / split / "rgb" / f"{i:06d}.png")
    np.save(Path(root) / split / "depth" / f"{i:06d}.npy", depth)
