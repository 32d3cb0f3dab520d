"""Pinhole camera: intrinsics, back-projection and projection, in one place; and the pose
math the public datasets need (a rotation quaternion to a matrix, a Unity pose to ``T_world_cam``).

Conventions (used by the renderer, the SDF loss, the 3D views and the loaders):
- camera frame as in OpenCV: x right, y down, z forward (the optical axis);
- pixel (u, v) is (column, row); pixel centres sit at integer coordinates;
- ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels;
- depth is z-depth: the distance along the optical axis, not along the ray;
- ``T_world_cam`` is 4x4 and maps camera coordinates to world coordinates.
"""

from __future__ import annotations

import math

import numpy as np
import torch

# The authors' Blender set (Section 3.A; shared/DATASETS.md): fx = fy = 0.5556 W, cx = cy = 0.5 W.
DEFAULT_FOCAL_RATIO = 0.5556  # fx / W, about 84 degrees horizontal field of view

# The scene's depth range (z-depth, scene units), as in the paper's set (Sec. 3.A): depths 0.01 to 100.
# The one definition: the renderer's valid depth (render.NEAR, render.FAR, its near/far planes) and the
# range the network's head can output (model.MIN_DEPTH, model.MAX_DEPTH) are these. Not the evaluation
# protocol's limits (metrics.EVAL_MIN_DEPTH, EVAL_MAX_DEPTH), which are another matter.
MIN_DEPTH, MAX_DEPTH = 0.01, 100.0
DEPTH_RANGE = (MIN_DEPTH, MAX_DEPTH)


def intrinsics(width: int, height: int | None = None, focal_ratio: float = DEFAULT_FOCAL_RATIO) -> np.ndarray:
    """3x3 pinhole K in pixels: fx = fy = focal_ratio * W, cx = 0.5 W, cy = 0.5 H."""
    height = width if height is None else height
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got width={width}, height={height}")
    if focal_ratio <= 0:
        raise ValueError(f"focal_ratio must be positive, got {focal_ratio}")
    f = focal_ratio * width
    return np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]], dtype=np.float64)


def intrinsics_from_fov(width: int, height: int, fov_x_deg: float) -> np.ndarray:
    """K for a horizontal field of view in degrees (0 < fov < 180), principal point at the centre."""
    if not 0.0 < fov_x_deg < 180.0:
        raise ValueError(f"field of view must be between 0 and 180 degrees, got {fov_x_deg}")
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2.0)
    return intrinsics(width, height, focal_ratio=fx / width)


def fov_x_deg(K: np.ndarray, width: int) -> float:
    """Horizontal field of view (degrees) covered by ``width`` pixels, for a centred principal point."""
    return math.degrees(2.0 * math.atan(0.5 * width / float(K[0][0])))


def scale_intrinsics(K: np.ndarray, sx: float, sy: float | None = None) -> np.ndarray:
    """K after resizing the image by (sx, sy): pixel centres stay consistent with the convention above."""
    sy = sx if sy is None else sy
    K = np.array(K, dtype=np.float64, copy=True)
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


def normalized_grid(K, height: int, width: int, *, like: torch.Tensor | None = None) -> torch.Tensor:
    """2 x H x W tensor of normalized coordinates ((u - cx)/fx, (v - cy)/fy), or B x 2 x H x W for batched K."""
    dtype = like.dtype if like is not None else torch.float64
    device = like.device if like is not None else None
    K = torch.as_tensor(np.asarray(K) if not isinstance(K, torch.Tensor) else K, dtype=dtype, device=device)
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device),
        torch.arange(width, dtype=dtype, device=device),
        indexing="ij",
    )
    if K.dim() == 2:
        return torch.stack(((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]))
    fx, fy, cx, cy = (K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2])
    x = (u[None] - cx[:, None, None]) / fx[:, None, None]
    y = (v[None] - cy[:, None, None]) / fy[:, None, None]
    return torch.stack((x, y), dim=1)


def backproject(depth, K):
    """Pixels to 3D camera points: X = z * ((u - cx)/fx, (v - cy)/fy, 1)  (the paper's pi^-1, Sec. 3.C).

    depth: H x W (numpy or torch) or B x 1 x H x W torch; returns H x W x 3 or B x H*W x 3 (same type).
    Differentiable in ``depth`` for torch input.
    """
    as_numpy = isinstance(depth, np.ndarray)
    d = torch.from_numpy(np.asarray(depth)) if as_numpy else depth
    if d.dim() == 2:
        grid = normalized_grid(K, d.shape[0], d.shape[1], like=d)
        pts = torch.stack((grid[0] * d, grid[1] * d, d), dim=-1)
        return pts.numpy() if as_numpy else pts
    if d.dim() != 4 or d.shape[1] != 1:
        raise ValueError(f"depth must be H x W or B x 1 x H x W, got shape {tuple(d.shape)}")
    B, _, H, W = d.shape
    Kt = torch.as_tensor(np.asarray(K) if not isinstance(K, torch.Tensor) else K, dtype=d.dtype, device=d.device)
    if Kt.dim() == 2:
        Kt = Kt.expand(B, 3, 3)
    grid = normalized_grid(Kt, H, W, like=d)  # B x 2 x H x W
    z = d[:, 0]
    pts = torch.stack((grid[:, 0] * z, grid[:, 1] * z, z), dim=-1)  # B x H x W x 3
    return pts.reshape(B, H * W, 3)


def project(points, K):
    """3D camera points (... x 3) to pixels (... x 2) and z-depth (...); numpy or torch."""
    xp = torch if isinstance(points, torch.Tensor) else np
    K = points.new_tensor(K) if xp is torch and not isinstance(K, torch.Tensor) else K
    z = points[..., 2]
    u = K[0, 0] * points[..., 0] / z + K[0, 2]
    v = K[1, 1] * points[..., 1] / z + K[1, 2]
    return xp.stack((u, v), -1), z


def transform(T, points):
    """Apply a 4x4 rigid transform to N x 3 points (numpy)."""
    T = np.asarray(T, dtype=np.float64)
    return points @ T[:3, :3].T + T[:3, 3]


# --------------------------------------------------------------------------- poses from rotation quaternions
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
