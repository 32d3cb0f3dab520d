"""Figures: colorized depth, sample grids (paper Fig. 3), depth histograms, shape-index maps (Fig. 5), 3D views.

Everything returns numpy images or matplotlib figures; nothing needs a display.
"""

from __future__ import annotations

import math

import numpy as np

from . import camera as cam


def colorize_depth(depth, vmin=None, vmax=None, cmap: str = "magma") -> np.ndarray:
    """H x W depth -> H x W x 3 uint8 through a matplotlib colormap (near = bright).

    vmin/vmax default to the 2nd/98th percentiles of the valid (finite, > 0) pixels;
    invalid pixels are black. Accepts numpy or torch (1 x H x W or H x W).
    """
    import matplotlib

    d = depth.detach().cpu().numpy() if hasattr(depth, "detach") else np.asarray(depth)
    d = np.squeeze(d).astype(np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be H x W (or 1 x H x W), got shape {np.shape(depth)}")
    valid = np.isfinite(d) & (d > 0)
    if valid.any():
        lo = np.percentile(d[valid], 2) if vmin is None else float(vmin)
        hi = np.percentile(d[valid], 98) if vmax is None else float(vmax)
    else:
        lo, hi = 0.0, 1.0
    t = np.clip((d - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    rgba = matplotlib.colormaps[cmap](1.0 - t)  # near = bright, as in the paper's figures
    out = (rgba[..., :3] * 255.0 + 0.5).astype(np.uint8)
    out[~valid] = 0
    return out


# ----------------------------------------------------------------------------- shape index (Fig. 5)


def principal_curvatures(points: np.ndarray, valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Principal curvatures k1 <= k2 (1/scene units) of a surface given as an H x W x 3 point grid.

    From the first and second fundamental forms with central differences over the
    pixel grid: E, F, G from the tangents X_u, X_v; e, f, g from the second derivatives
    along the unit normal n = X_u x X_v / |X_u x X_v| oriented away from the camera
    (n_z > 0, into the tissue), so a bump towards the camera (a cap) has positive
    curvatures and a pocket (a cup) negative ones.
    Pixels next to invalid ones (or the border) are NaN.
    """
    P = np.asarray(points, dtype=np.float64)
    Xu = 0.5 * (np.roll(P, -1, 1) - np.roll(P, 1, 1))
    Xv = 0.5 * (np.roll(P, -1, 0) - np.roll(P, 1, 0))
    Xuu = np.roll(P, -1, 1) - 2 * P + np.roll(P, 1, 1)
    Xvv = np.roll(P, -1, 0) - 2 * P + np.roll(P, 1, 0)
    Xuv = 0.25 * (np.roll(np.roll(P, -1, 0), -1, 1) - np.roll(np.roll(P, -1, 0), 1, 1)
                  - np.roll(np.roll(P, 1, 0), -1, 1) + np.roll(np.roll(P, 1, 0), 1, 1))
    n = np.cross(Xu, Xv)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-30
    n *= np.sign(n[..., 2:3] + 1e-30)  # away from the camera
    E, F, G = (Xu * Xu).sum(-1), (Xu * Xv).sum(-1), (Xv * Xv).sum(-1)
    e, f, g = (Xuu * n).sum(-1), (Xuv * n).sum(-1), (Xvv * n).sum(-1)
    denom = E * G - F * F
    with np.errstate(divide="ignore", invalid="ignore"):
        K = (e * g - f * f) / denom
        H = (e * G - 2 * f * F + g * E) / (2 * denom)
        disc = np.sqrt(np.clip(H * H - K, 0.0, None))
        k1, k2 = H - disc, H + disc
    bad = np.zeros(P.shape[:2], dtype=bool)
    bad[0, :] = bad[-1, :] = bad[:, 0] = bad[:, -1] = True
    if valid is not None:
        v = np.asarray(valid, dtype=bool)
        near_bad = ~v
        for ax, sh in ((0, 1), (0, -1), (1, 1), (1, -1)):
            near_bad |= ~np.roll(v, sh, ax)
        bad |= near_bad
    k1[bad] = np.nan
    k2[bad] = np.nan
    return k1, k2


def shape_index(depth: np.ndarray, K: np.ndarray, smooth: float = 1.0) -> np.ndarray:
    """Koenderink's shape index S = (2/pi) arctan((k2 + k1) / (k2 - k1)) of a depth map (paper Fig. 5).

    The depth (H x W z-depth) is back-projected with ``camera.backproject`` and, if
    ``smooth`` > 0, Gaussian-smoothed (sigma in pixels) to suppress pixel noise.
    S lies in [-1, 1]: -1 cup (diverticulum), -0.5 rut, 0 saddle, +0.5 ridge (folds,
    rugae), +1 cap (polyp, papilla), with curvature signs seen from the camera.
    Undefined (umbilic planes, invalid pixels) -> NaN.
    """
    d = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    if smooth > 0:
        from scipy.ndimage import gaussian_filter

        w = gaussian_filter(valid.astype(np.float64), smooth)
        d = np.where(valid, gaussian_filter(np.where(valid, d, 0.0), smooth) / np.maximum(w, 1e-12), 0.0)
    pts = cam.backproject(d, K)
    k1, k2 = principal_curvatures(pts, valid)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (2.0 / math.pi) * np.arctan((k2 + k1) / (k2 - k1))
    return s
