"""Signed distance fields of depth maps, for the SDF geometric consistency loss (Sec. 3.C).

The paper's geometric consistency loss compares two surfaces through their signed distance
fields sampled on a regular 3D grid (equations numbered by counting those of the paper's text,
shared/paper/):

- Eq. 5: phi(q, S) = min_{X in S} ||X - q||_2, the distance from a point q to the surface S,
  signed: positive ahead of the surface from the camera viewpoint, negative behind it;
- Eqs. 6-8: S = pi^-1(I, D), the depth map D back-projected through the camera, one point per
  valid pixel (:func:`geodepth_lite.core.camera.backproject`);
- Eq. 9: the sample grid X_ijk, r_x x r_y x r_z points spanning the ground truth's bounding
  box [X_lb, X_ub] (:func:`grid_points`, with the + X_lb offset the paper's formula drops);
- Eq. 10: L_sdf = mean over the grid of |phi(X_ijk, S_pred) - phi(X_ijk, S_gt)|, the loss term
  itself, in :func:`geodepth_lite.core.losses.sdf_loss`.

This module holds what that term is built from, in three layers:

- search: the exact nearest neighbour of each grid point (:func:`nearest_indices`: scipy's
  cKDTree for CPU tensors, the batched torch search of :mod:`geodepth_lite.core.nnsearch` on other
  devices, every image of a batch in one call; the paper uses PyTorch3D's KNN).
  Indices are searched without gradient; distances are then recomputed in torch from the
  nearest points, so gradients reach the prediction through them;
- fields: phi of one point set at given queries (:func:`signed_distance`), and the fields of a
  batch of predicted and ground-truth depth maps on the grid, image by image (:func:`sdf_fields`,
  the reference) or as B x M tensors with no per-image loop (:func:`sdf_fields_batched`, what the
  loss uses; the same numbers);
- cache: ground-truth fields, which do not depend on the network, kept per frame
  (:class:`GTFieldCache`, :data:`GT_FIELD_CACHE`).

What the term takes beside the tensors (grid, sampling, sign rule, search, signed, cache) is one
:class:`SDFOptions`; ``SDFOptions()`` is the paper's term.

It also holds the depth-map input checks (:func:`check_depths`, :func:`valid_mask`) that
:mod:`geodepth_lite.core.losses` shares: that module imports this one, not the other way round.

Sign (no gradient; :data:`SIGN_RULES`). The "view" rule, the paper's and the default: a sample
point q is projected with K, (u, v) = (fx q_x/q_z + cx, fy q_y/q_z + cy) rounded to the nearest
pixel (``torch.round``, halves to even), and signed by sign(D(v, u) - q_z) with D the depth map
whose surface is measured: +1 in front of the depth map along its own ray, -1 beyond it, 0 on
it. Fallback, where q_z <= 0, q projects outside the image, or onto a pixel that is not valid
(masked, non-finite or <= 0): the nearest-point rule sign((X_n - q) . X_n), X_n the nearest
surface point, i.e. whether q lies on the camera's side of the surface at X_n (the local
estimate of the same thing: for q near a front-facing smooth surface both rules agree). The
two rules differ behind occluding edges, e.g. a point behind a near step, nearest to the far
wall. The "nearest" rule uses the nearest-point sign everywhere (the former rule, for
comparison). The magnitude is always the exact Euclidean nearest distance. The "masked" rule
(not the paper's) signs by the view rule and leaves the points where it does not apply, in either
map's field, out of the loss (:func:`geodepth_lite.core.losses.sdf_loss`); its fields are the view
rule's, so cached ground-truth fields are shared.

Sampling (:data:`SDF_SAMPLINGS`; the paper gives Eq. 9's box, but not where the box lies nor the
grid size). "bbox" (default): Eq. 9's uniform grid over the ground truth's bounding box
(:func:`grid_points`). "frustum": r_x x r_y pixel positions uniform over the image times r_z
depths uniform in log depth between the ground truth's nearest and farthest valid depth
(:func:`frustum_points`): every sample projects inside the image and the samples are dense near
the camera, where most pixels are. :func:`view_rule_coverage` measures, per image, the share of
samples the view rule signs (docs/network_and_losses.md has the measured shares).
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from geodepth_lite.core import camera, nnsearch, nnsearch_triton
from geodepth_lite.core.errors import UserError

DEFAULT_SDF_GRID = (32, 32, 32)  # r_x, r_y, r_z of the paper's SDF sample grid
CHUNK_ELEMENTS = 2**25  # query x point pairs per block of the on-device exact search
KDTREE_LEAFSIZE = 32  # points per cKDTree leaf (tuned on 320x320 depth maps)
KDTREE_WORKERS = -1  # threads of each cKDTree query (-1: all cores)
SIGN_RULES = {  # SDF sign rules, with the tag that keys cached ground-truth fields
    "view": "sign:view-ray-projection,fallback:nearest-direction",  # the paper's (default)
    "nearest": "sign:nearest-direction",  # sign((X_n - q) . X_n) everywhere (the former rule)
    # the view rule's field, with the points it does not sign left out of the loss (losses.sdf_loss):
    # the fields are those of "view", so their cached ground-truth fields are shared
    "masked": "sign:view-ray-projection,fallback:nearest-direction",
}
SDF_SAMPLINGS = {  # where the SDF samples lie, with the tag that keys cached ground-truth fields
    "bbox": "grid:bbox-uniform",  # Eq. 9: uniform over the ground truth's 3D bounding box (default)
    "frustum": "grid:pixel-uniform,log-depth-uniform",  # pixels x log-spaced depths (frustum_points)
}


# ----------------------------------------------------------------------------- depth-map inputs
def valid_mask(gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Pixels usable as ground truth: finite, > 0, and in ``mask`` when given (B x 1 x H x W bool)."""
    valid = torch.isfinite(gt) & (gt > 0)
    if mask is not None:
        if mask.shape != gt.shape:
            raise ValueError(f"mask must have the depth's shape {tuple(gt.shape)}, got {tuple(mask.shape)}")
        valid = valid & mask.to(torch.bool)
    return valid


def check_depths(pred: torch.Tensor, gt: torch.Tensor) -> None:
    """Raise ValueError unless ``pred`` and ``gt`` are B x 1 x H x W tensors of the same shape."""
    for name, t in (("pred", pred), ("gt", gt)):
        if not isinstance(t, torch.Tensor) or t.dim() != 4 or t.shape[1] != 1:
            shape = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
            raise ValueError(f"{name} must be a B x 1 x H x W tensor, got {shape}")
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt must have the same shape, got {tuple(pred.shape)} and {tuple(gt.shape)}")


# ----------------------------------------------------------------------------- nearest neighbours
@torch.no_grad()
def nearest_indices_kdtree(points: torch.Tensor, queries: torch.Tensor, workers: int | None = None) -> torch.Tensor:
    """Exact nearest neighbour of each query among ``points`` with scipy's cKDTree (CPU).

    points: N x 3, queries: M x 3 (any device; searched in float64 on the CPU) -> M indices (int64,
    on the queries' device).
    """
    p = points.detach().cpu().double().numpy()  # (N, 3)
    q = queries.detach().cpu().double().numpy()  # (M, 3)
    from scipy.spatial import cKDTree  # heavy (~0.4 s to import): only when a nearest-point search runs

    # an unbalanced, non-compact tree builds and searches about 2x faster on depth-map surfaces
    tree = cKDTree(p, leafsize=KDTREE_LEAFSIZE, balanced_tree=False, compact_nodes=False)
    _, idx = tree.query(q, k=1, workers=KDTREE_WORKERS if workers is None else workers)
    return torch.from_numpy(np.asarray(idx, dtype=np.int64)).to(queries.device)  # (M,)


@torch.no_grad()
def nearest_indices_chunked(points: torch.Tensor, queries: torch.Tensor, chunk_elements: int = CHUNK_ELEMENTS,
                            exact: bool = True) -> torch.Tensor:
    """Nearest neighbour by brute force in blocks of queries, on the tensors' device (CUDA path).

    With ``exact`` (default) distances are computed as differences, so the result is the exact
    argmin up to floating-point ties; ``exact=False`` uses the faster matrix-product expansion
    |q|^2 - 2 q.x + |x|^2, which can pick a near-tie wrongly (used only as a speed baseline).
    points: N x 3, queries: M x 3 -> M indices (int64).
    """
    dtype = torch.promote_types(points.dtype, queries.dtype)  # cdist needs one dtype
    points, queries = points.to(dtype), queries.to(dtype)
    n = points.shape[0]
    step = max(1, chunk_elements // max(n, 1))
    mode = "donot_use_mm_for_euclid_dist" if exact else "use_mm_for_euclid_dist"
    out = []
    for s in range(0, queries.shape[0], step):
        d = torch.cdist(queries[s:s + step], points, compute_mode=mode)  # (step, N)
        out.append(d.argmin(dim=1))
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.int64, device=queries.device)


NN_METHODS = ("auto", "kdtree", "device", "triton", "chunked", "brute_mm")


def _check_method(method: str) -> None:
    if method not in NN_METHODS:
        raise UserError(f"unknown nearest-neighbour method {method!r}: use {', '.join(map(repr, NN_METHODS))}")


def resolve_method(method: str, device: torch.device) -> str:
    """The search a ``method`` runs for tensors on ``device``: "auto" is "kdtree" for CPU tensors (the
    committed results' search), "triton" (:mod:`geodepth_lite.core.nnsearch_triton`) for CUDA tensors where
    Triton is installed, and "device" (:mod:`geodepth_lite.core.nnsearch`) for any other device."""
    _check_method(method)
    kind = torch.device(device).type
    if method == "auto":
        if kind == "cpu":
            return "kdtree"
        return "triton" if kind == "cuda" and nnsearch_triton.usable(device) else "device"
    if method == "triton" and not nnsearch_triton.usable(device):
        raise UserError(f"the triton search needs Triton and a CUDA device (tensors on {device}): "
                         "use method 'device' or 'auto'")
    return method


def nearest_indices(points: torch.Tensor, queries: torch.Tensor, method: str = "auto") -> torch.Tensor:
    """Nearest-neighbour indices: "kdtree" (exact, scipy's cKDTree on the CPU), "device" (exact, torch
    ops on the tensors' device: :func:`geodepth_lite.core.nnsearch.nearest_indices`), "auto" (kdtree for
    CPU tensors, device otherwise), "chunked" (exact brute force in blocks with ``torch.cdist``, the
    former CUDA path, kept for comparison) or "brute_mm" (matrix-product brute force, a speed baseline
    only). The exact methods agree on every query (ties: the least point index)."""
    method = resolve_method(method, points.device)
    if method == "kdtree":
        return nearest_indices_kdtree(points, queries)
    if method == "device":
        return nnsearch.nearest_indices(points, queries)
    if method == "triton":
        valid = torch.ones(1, points.shape[0], dtype=torch.bool, device=queries.device)
        return nnsearch_triton.nearest_indices_grid(points[None], valid, queries[None])[0]
    if method == "chunked":
        return nearest_indices_chunked(points, queries)
    return nearest_indices_chunked(points, queries, exact=False)


def nearest_indices_many(pairs: list, method: str = "auto") -> list:
    """Nearest-neighbour indices of several (points N_i x 3, queries M_i x 3) pairs, one list entry
    each: "device" searches them all in one batched call
    (:func:`geodepth_lite.core.nnsearch.nearest_indices_batched`), the other methods one pair at a time."""
    if not pairs:
        return []
    method = resolve_method(method, pairs[0][0].device)
    if method != "device":
        return [nearest_indices(p, q, method) for p, q in pairs]
    dev = pairs[0][1].device
    pimg = torch.cat([torch.full((len(p),), i, dtype=torch.int64, device=dev) for i, (p, _) in enumerate(pairs)])
    qimg = torch.cat([torch.full((len(q),), i, dtype=torch.int64, device=dev) for i, (_, q) in enumerate(pairs)])
    pts = torch.cat([p.detach().to(device=dev, dtype=torch.float64) for p, _ in pairs])
    qs = torch.cat([q.detach().to(dtype=torch.float64) for _, q in pairs])
    narrow = all(p.dtype in (torch.float32, torch.float16, torch.bfloat16) and
                 q.dtype in (torch.float32, torch.float16, torch.bfloat16) for p, q in pairs)
    if narrow:  # every coordinate exact in float32: the search may bound in float32
        pts, qs = pts.float(), qs.float()
    idx = nnsearch.nearest_indices_batched(pts, pimg, qs, qimg, len(pairs))  # (sum M_i,) into pts
    offsets = torch.cumsum(torch.tensor([0] + [len(p) for p, _ in pairs[:-1]], device=dev), 0)
    out, q0 = [], 0
    for i, (_, q) in enumerate(pairs):
        out.append(idx[q0:q0 + len(q)] - offsets[i])
        q0 += len(q)
    return out


# ----------------------------------------------------------------------------- fields
def _grid_shape(grid) -> tuple[int, int, int]:
    g = (grid,) * 3 if isinstance(grid, (int, np.integer)) else tuple(grid)
    if len(g) != 3 or not all(isinstance(r, (int, np.integer)) and r >= 2 for r in g):
        raise UserError(f"sdf grid must be an int >= 2 or three of them (r_x, r_y, r_z), got {grid!r}")
    return tuple(int(r) for r in g)


def grid_points(lower: torch.Tensor, upper: torch.Tensor, grid=DEFAULT_SDF_GRID) -> torch.Tensor:
    """The paper's sample grid with the offset put back (Sec. 3.C, Eq. 9):

    X_ijk = X_lb + (i/(r_x-1), j/(r_y-1), k/(r_z-1)) * (X_ub - X_lb),  i < r_x, j < r_y, k < r_z.
    lower, upper: 3-vectors -> (r_x r_y r_z) x 3 points, i slowest (x), k fastest (z).

    Explained with its equation in notebook 03, section 5 (the sample grid X_ijk).
    """
    rx, ry, rz = _grid_shape(grid)
    axes = [torch.linspace(0.0, 1.0, r, dtype=lower.dtype, device=lower.device) for r in (rx, ry, rz)]
    t = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)  # (M, 3), M = rx ry rz
    return lower + t * (upper - lower)  # (M, 3)


def frustum_points(K: torch.Tensor, height: int, width: int, z_near: torch.Tensor, z_far: torch.Tensor,
                   grid=DEFAULT_SDF_GRID) -> torch.Tensor:
    """Samples that follow the pixels (``sampling="frustum"``; not the paper's, whose Eq. 9 is a box):

    q_ijk = z_k ((u_i - cx)/fx, (v_j - cy)/fy, 1) = z_k K^-1 [u_i, v_j, 1] (zero skew, as
    :func:`geodepth_lite.core.camera.backproject`), u_i = i (W-1)/(r_x-1), v_j = j (H-1)/(r_y-1) (pixel
    centres, edge to edge), z_k = z_near (z_far/z_near)^(k/(r_z-1)) (uniform in log depth). Every
    sample projects inside the image, and half of the depths lie below sqrt(z_near z_far).
    K: 3 x 3; z_near, z_far: 0 < z_near <= z_far, 0-dim tensors whose dtype and device the points
    take -> (r_x r_y r_z) x 3 points, ordered as :func:`grid_points` (i slowest (u), k fastest (z)).
    """
    rx, ry, rz = _grid_shape(grid)
    z_near, z_far = torch.as_tensor(z_near), torch.as_tensor(z_far)
    if not bool(0 < z_near <= z_far < float("inf")):
        raise UserError(f"frustum depths must satisfy 0 < z_near <= z_far < inf, got {float(z_near)}, {float(z_far)}")
    dtype, device = z_near.dtype, z_near.device
    K = torch.as_tensor(np.asarray(K) if not isinstance(K, torch.Tensor) else K).to(dtype=dtype, device=device)
    u = torch.linspace(0.0, width - 1, rx, dtype=dtype, device=device)  # (rx,) pixel columns
    v = torch.linspace(0.0, height - 1, ry, dtype=dtype, device=device)  # (ry,) pixel rows
    t = torch.linspace(0.0, 1.0, rz, dtype=dtype, device=device)  # (rz,)
    z = z_near * torch.pow(z_far.to(dtype) / z_near, t)  # (rz,) log-spaced, z[0] = z_near
    x = (u - K[0, 2]) / K[0, 0]  # (rx,) normalised image coordinates
    y = (v - K[1, 2]) / K[1, 1]  # (ry,)
    X, Y, Z = torch.meshgrid(x, y, z, indexing="ij")  # (rx, ry, rz) each
    return torch.stack((X * Z, Y * Z, Z), dim=-1).reshape(-1, 3)  # (M, 3), M = rx ry rz


def _samples(g_pts: torch.Tensor, K: torch.Tensor, hw: tuple[int, int], shape, sampling: str, hit=None):
    """One image's SDF samples: (q, lower, upper), q: M x 3, lower/upper: 3-vectors (the samples' box).

    g_pts: N x 3, the ground truth's valid points (z = its depth); K: 3 x 3; hw: (H, W); ``hit``:
    a cached (lower, upper, field) whose box the "bbox" grid reuses.
    """
    if sampling == "frustum":
        z = g_pts[:, 2]  # (N,) the valid depths
        q = frustum_points(K, hw[0], hw[1], z.min(), z.max(), shape)  # (M, 3)
        return q, q.min(0).values, q.max(0).values
    if hit is not None:
        lower, upper = hit[0].to(g_pts), hit[1].to(g_pts)  # (3,) each
    else:
        lower, upper = g_pts.min(0).values, g_pts.max(0).values  # (3,) each: X_lb, X_ub of the ground truth
    return grid_points(lower, upper, shape), lower, upper  # (M, 3), (3,), (3,)


def _check_sign_rule(sign_rule: str) -> None:
    if sign_rule not in SIGN_RULES:
        raise UserError(f"sign_rule must be one of {', '.join(SIGN_RULES)}, got {sign_rule!r}")


def check_sdf_options(sign_rule: str = "view", sampling: str = "bbox") -> None:
    """Raise ValueError naming the option unless ``sign_rule`` is in :data:`SIGN_RULES` and
    ``sampling`` in :data:`SDF_SAMPLINGS`."""
    _check_sign_rule(sign_rule)
    if sampling not in SDF_SAMPLINGS:
        raise UserError(f"sdf sampling must be one of {', '.join(SDF_SAMPLINGS)}, got {sampling!r}")


@torch.no_grad()
def _view_sign(queries: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, valid: torch.Tensor):
    """The view rule's sign of each query and whether it applies (batched, no gradient).

    queries: B x M x 3 (camera frame); depth: B x H x W; K: B x 3 x 3; valid: B x H x W bool ->
    (sign, known), both B x M: sign = sign(D(v, u) - q_z) in the queries' dtype at the rounded
    projection (u, v), known = q_z > 0, (u, v) inside the image, valid there and D finite > 0.
    """
    B, H, W = depth.shape
    K = K.to(dtype=queries.dtype, device=queries.device)  # (B, 3, 3)
    x, y, z = queries.unbind(-1)  # (B, M) each
    front = z > 0
    zs = torch.where(front, z, torch.ones_like(z))  # no division by zero behind the camera
    u = torch.round(K[:, 0, 0, None] * x / zs + K[:, 0, 2, None])  # (B, M)
    v = torch.round(K[:, 1, 1, None] * y / zs + K[:, 1, 2, None])  # (B, M)
    known = front & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)  # False for NaN/inf too
    lin = torch.where(known, v * W + u, torch.zeros_like(u)).long()  # (B, M) pixel indices
    D = torch.gather(depth.detach().reshape(B, H * W), 1, lin).to(queries.dtype)  # (B, M)
    ok = torch.gather(valid.reshape(B, H * W).to(torch.bool), 1, lin)  # (B, M)
    known = known & ok & torch.isfinite(D) & (D > 0)
    return torch.where(known, torch.sign(D - z), torch.zeros_like(z)), known


def _signed_from_nearest(nearest: torch.Tensor, queries: torch.Tensor, signed: bool = True,
                         view=None) -> torch.Tensor:
    """phi(q) from the nearest surface points X_n (... x 3, differentiable) and queries q (... x 3).

    ``view``: None (nearest-point sign everywhere) or the (sign, known) pair of :func:`_view_sign`
    (... each): the view sign where known, the nearest-point sign elsewhere (the fallback).
    """
    diff = nearest - queries  # (..., 3)
    d2 = (diff * diff).sum(-1)  # (...)
    pos = d2 > 0  # the distance's gradient is set to 0 on the surface instead of NaN
    dist = torch.where(pos, torch.sqrt(torch.where(pos, d2, torch.ones_like(d2))), torch.zeros_like(d2))
    if not signed:
        return dist
    with torch.no_grad():
        sign = torch.sign((diff * nearest).sum(-1))  # (...)
        if view is not None:
            sign = torch.where(view[1], view[0].to(sign), sign)
    return sign * dist


def signed_distance(points: torch.Tensor, queries: torch.Tensor, method: str = "auto", signed: bool = True,
                    depth=None, K=None, valid=None) -> torch.Tensor:
    """Signed distance from each query q to the point set S = {X} (camera frame, Sec. 3.C, Eq. 5).

    phi(q) = ||X_n - q||_2 with X_n the exact nearest point of S (index searched without
    gradient, distance recomputed in torch so gradients reach ``points`` through X_n).

    Sign (the paper: positive ahead of the surface as seen from the camera, negative behind),
    computed without gradient:
    - with ``depth`` (H x W, torch or numpy) and ``K`` (3 x 3), the view rule: q projects to the
      nearest pixel (u, v) = round(fx q_x/q_z + cx, fy q_y/q_z + cy) and the sign is
      sign(D(v, u) - q_z) (+1 in front of the depth map along q's ray, -1 beyond, 0 on it).
      Where q_z <= 0, (u, v) is outside the image, or the pixel is not usable (``valid``, H x W
      bool, False there, or D not finite or <= 0), the fallback is the nearest-point rule below.
      ``points`` should be the back-projection of ``depth``'s usable pixels (not checked);
    - without them, the nearest-point rule everywhere: sign((X_n - q) . X_n), positive when q
      lies on the camera's side of the surface at X_n, negative beyond, 0 on it. For a
      fronto-parallel plane z = d both rules give sign(d - q_z); they differ behind occluding
      edges (a point behind a near step whose nearest surface point is on the far wall).
    points: N x 3, queries: M x 3 -> M signed distances (unsigned when ``signed=False``).

    Explained with its equation in notebook 03, section 5 (phi and its sign rule).
    """
    return _phi(points, queries, nearest_indices(points, queries, method), signed, depth, K, valid)


def _phi(points, queries, idx, signed: bool = True, depth=None, K=None, valid=None) -> torch.Tensor:
    """:func:`signed_distance` from the nearest points' indices ``idx`` (M,), already searched."""
    view = None
    if depth is not None and signed:
        if K is None:
            raise ValueError("signed_distance: the view rule needs K with depth")
        d = torch.as_tensor(depth).to(device=queries.device)  # (H, W)
        if d.dim() != 2:
            raise ValueError(f"depth must be H x W, got shape {tuple(d.shape)}")
        Kt = torch.as_tensor(np.asarray(K) if not isinstance(K, torch.Tensor) else K).to(queries.device)
        v = torch.ones_like(d, dtype=torch.bool) if valid is None else torch.as_tensor(valid).to(d.device)
        if v.shape != d.shape:
            raise ValueError(f"valid must have the depth's shape {tuple(d.shape)}, got {tuple(v.shape)}")
        view = tuple(t[0] for t in _view_sign(queries[None], d[None], Kt.reshape(1, 3, 3), v[None]))  # (M,) each
    # X_n by gather, not points[idx]: gather's backward sums the gradients of a point's queries in
    # query order at any thread count (indexing's accumulating backward does not, on the CPU)
    nearest = torch.gather(points, 0, idx[:, None].expand(-1, 3))  # (M, 3)
    return _signed_from_nearest(nearest, queries, signed, view)  # (M,)


# ----------------------------------------------------------------------------- cache
class GTFieldCache:
    """LRU cache of ground-truth SDF fields, keyed by the bytes of the frame (depth, validity, K),
    the grid, ``signed``, the sign rule's tag (:data:`SIGN_RULES`; fields signed under another
    rule, such as the former nearest-point-only sign, never match) and the sampling's tag
    (:data:`SDF_SAMPLINGS`; fields sampled at other points never match).

    The ground truth's field does not depend on the network, and training sees every frame once
    per epoch, so from the second epoch on only the prediction's field has to be searched. A
    hit returns exactly what the search would (same inputs, same exact search). Fields are kept
    on the device they were computed on (a GPU's fields stay on the GPU, so a hit copies nothing),
    in their dtype: 128 KiB per frame at 32^3 in float32, so the paper split's 3600 training and
    900 validation frames take 4500 x 128 KiB = 562.5 MiB. The least recently used are dropped
    beyond ``max_bytes`` (1 GiB: about 8000 frames at 32^3); ``max_bytes = 0`` disables the cache.

    Keys (:func:`sdf_fields_batched`): the frame's content by default, or the frame's identity where
    the caller names it (``frame_ids``: training without augmentation names the dataset, split,
    size and index, :func:`geodepth_lite.training.train.batch_frame_ids`). Augmentation (flips, crops, the
    field-of-view border) changes a frame's ground truth from one epoch to the next, and train and
    validation frames share indices, so an index alone could return another map's field. Hashing
    the content costs a copy of the depth map to the host and a BLAKE2b over it (400 KiB at
    320x320); an identity key costs neither.
    """

    def __init__(self, max_bytes: int = 2**30):
        self.max_bytes = int(max_bytes)
        self._d: OrderedDict = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    @staticmethod
    def key(gt_b: torch.Tensor, valid_b: torch.Tensor, K_b: torch.Tensor, options: SDFOptions) -> str:
        """The content key of one frame's field: a hash of its depth, validity and K, and the options'
        :meth:`SDFOptions.cache_tag`."""
        h = hashlib.blake2b(digest_size=20)
        for t in (gt_b, valid_b, K_b):
            t = t.detach().cpu().contiguous()
            h.update(str((t.dtype, tuple(t.shape))).encode())
            h.update(t.numpy().tobytes())
        h.update(repr(options.cache_tag()).encode())
        return h.hexdigest()

    def get(self, key: str):
        if self.max_bytes <= 0:
            return None
        with self._lock:
            item = self._d.get(key)
            if item is None:
                self.misses += 1
                return None
            self._d.move_to_end(key)
            self.hits += 1
            return item

    def put(self, key: str, lower: torch.Tensor, upper: torch.Tensor, field: torch.Tensor) -> None:
        if self.max_bytes <= 0:
            return
        item = (lower.detach(), upper.detach(), field.detach())  # on their device
        size = item[2].numel() * item[2].element_size() + 64
        with self._lock:
            if key in self._d:
                return
            self._d[key] = item
            self._bytes += size
            while self._bytes > self.max_bytes and self._d:
                _, old = self._d.popitem(last=False)
                self._bytes -= old[2].numel() * old[2].element_size() + 64

    def clear(self) -> None:
        with self._lock:
            self._d.clear()
            self._bytes = 0
            self.hits = self.misses = 0

    def __len__(self) -> int:
        return len(self._d)

    def __repr__(self) -> str:
        return f"GTFieldCache(max_bytes={self.max_bytes}, fields={len(self)})"


GT_FIELD_CACHE = GTFieldCache()  # the cache of SDFOptions() (so of losses.sdf_loss, losses.total_loss by default)


# ----------------------------------------------------------------------------- options
@dataclass(frozen=True)
class SDFOptions:
    """How the SDF term is built, beside the tensors: the sample grid, where the samples lie, the sign
    rule, the nearest-point search, signed or not, and the cache of ground-truth fields.

    ``SDFOptions()`` is the paper's term: ``grid`` r_x x r_y x r_z = 32^3 samples (one int means
    the same on every axis; kept as three ints), ``sampling="bbox"`` (Eq. 9's box, :data:`SDF_SAMPLINGS`),
    ``sign_rule="view"`` (:data:`SIGN_RULES`), ``method="auto"`` (the exact search of
    :func:`resolve_method`, :data:`NN_METHODS`), ``signed=True`` (False: the unsigned variant, for
    comparison) and ``cache=GT_FIELD_CACHE`` (ground-truth fields reused per frame, :class:`GTFieldCache`;
    None searches them every time). A value out of range raises the UserError that names it, here.
    """

    grid: tuple[int, int, int] = DEFAULT_SDF_GRID
    sampling: str = "bbox"
    sign_rule: str = "view"
    method: str = "auto"
    signed: bool = True
    cache: GTFieldCache | None = GT_FIELD_CACHE

    def __post_init__(self):
        object.__setattr__(self, "grid", _grid_shape(self.grid))
        check_sdf_options(self.sign_rule, self.sampling)
        _check_method(self.method)

    def cache_tag(self) -> tuple:
        """What keys a cached ground-truth field beside the frame: the grid, ``signed`` and the tags of the
        sign rule and the sampling (:data:`SIGN_RULES`, :data:`SDF_SAMPLINGS`)."""
        return (self.grid, bool(self.signed), SIGN_RULES[self.sign_rule], SDF_SAMPLINGS[self.sampling])


def _options(options) -> SDFOptions:
    """``options`` itself, or a TypeError saying what the SDF functions take instead."""
    if not isinstance(options, SDFOptions):
        raise TypeError(f"the SDF options must be an SDFOptions (e.g. SDFOptions(grid=8)), got {options!r}")
    return options


# ----------------------------------------------------------------------------- fields of a batch
def _batch_inputs(gt: torch.Tensor, K, mask, B: int):
    """(valid B x 1 x H x W bool, gt with invalid pixels set to 1, K as B x 3 x 3) of a batch."""
    valid = valid_mask(gt, mask)  # (B, 1, H, W) bool
    gt_safe = torch.where(valid, gt, torch.ones_like(gt))  # (B, 1, H, W), no NaN/inf can reach autograd
    Kt = torch.as_tensor(np.asarray(K) if not isinstance(K, torch.Tensor) else K)  # (3, 3) or (B, 3, 3)
    if not (Kt.shape == (3, 3) or (Kt.dim() == 3 and Kt.shape[0] == B and Kt.shape[1:] == (3, 3))):
        raise ValueError(f"K must be 3 x 3 or B x 3 x 3 with B = {B}, got {tuple(Kt.shape)}")
    return valid, gt_safe, Kt.expand(B, 3, 3)  # ..., (B, 3, 3)


def sdf_fields(pred, gt, K, options: SDFOptions, mask=None):
    """Per image: the sample grid and the signed fields of prediction and ground truth, under ``options``
    (:class:`SDFOptions`: the grid, sampling, sign rule, search, signed or not, cache).

    Returns a list (one entry per image; None when the image has no valid pixel) of dicts
    {"grid": M x 3, "lower", "upper": 3-vectors, "pred": M, "gt": M}, M = r_x r_y r_z; fields are
    ordered as :func:`grid_points` (reshape to r_x x r_y x r_z). Each field is
    :func:`signed_distance` of one surface, the depth map back-projected with K at the ground
    truth's valid pixels, at the samples of ``options.sampling``: "bbox" (default, the paper's Eq. 9) the
    grid over the ground truth's bounding box [lower, upper]; "frustum" :func:`frustum_points`
    between the ground truth's nearest and farthest valid depth (lower, upper: the samples' box).
    The prediction's field is differentiable in ``pred``, the ground truth's is not. With a
    ``options.cache`` (:class:`GTFieldCache`), ground-truth fields already computed for an identical frame
    (and sampling, sign rule, grid) are reused.

    Sign (``options.sign_rule``, no gradient): "view" (default, the paper's) projects each grid point
    with K to its nearest pixel and compares q_z with each map's own depth there: the
    prediction's field uses ``pred``, the ground truth's ``gt`` (+1 where q_z < D, -1 where
    q_z > D, 0 on it), both at the ground truth's valid pixels (where ``pred`` is also finite and
    > 0 for the prediction's). Fallback, for points with q_z <= 0, projecting outside the image
    or onto an unusable pixel: the nearest-point sign sign((X_n - q) . X_n). "nearest" uses the
    nearest-point sign everywhere (the former rule, for comparison). See :func:`signed_distance`.
    "masked": the fields of "view", and each dict also holds "known" (M bool): where the view
    rule applies in both fields (what :func:`geodepth_lite.core.losses.sdf_loss` keeps).
    """
    o = _options(options)
    check_depths(pred, gt)
    B = pred.shape[0]
    valid, gt_safe, Kb = _batch_inputs(gt, K, mask, B)  # (B, 1, H, W) bool, (B, 1, H, W), (B, 3, 3)
    view = o.signed and o.sign_rule in ("view", "masked")  # else no depth map is passed: the nearest-point sign
    S_pred = camera.backproject(pred, K)  # (B, H*W, 3), differentiable in pred
    S_gt = camera.backproject(gt_safe, K).detach()  # (B, H*W, 3)
    todo = _image_inputs(S_pred, S_gt, gt, valid, Kb, o)
    out: list = [None] * B
    # every search of the batch at once: the predictions' fields, then the ground truths' not cached
    pairs = [(t.pred_pts, t.q) for t in todo] + [(t.gt_pts, t.q) for t in todo if t.hit is None]
    found = iter(nearest_indices_many(pairs, o.method))
    idx_pred = [next(found) for _ in todo]
    for t, ip in zip(todo, idx_pred):
        b = t.b
        phi_pred = _phi(t.pred_pts, t.q, ip, o.signed, pred[b, 0].detach() if view else None, Kb[b],
                        valid[b, 0])  # (M,)
        if t.hit is not None:
            phi_gt = t.hit[2].to(phi_pred)  # (M,) the cached (lower, upper, field)'s field
        else:
            phi_gt = _phi(t.gt_pts, t.q, next(found), o.signed, gt_safe[b, 0] if view else None, Kb[b],
                          valid[b, 0]).to(phi_pred)  # (M,)
            if t.key is not None:
                o.cache.put(t.key, t.lower, t.upper, phi_gt)
        out[b] = {"grid": t.q, "lower": t.lower, "upper": t.upper, "pred": phi_pred, "gt": phi_gt}
    if o.sign_rule == "masked":
        _mark_known(out, pred, gt_safe, Kb, valid)
    return out


class _ImageInputs(NamedTuple):
    """One image's inputs to :func:`sdf_fields`: its index in the batch, the prediction's and the ground
    truth's valid points, the samples q and their box, the cache's hit (or None) and key (or None)."""

    b: int
    pred_pts: torch.Tensor
    gt_pts: torch.Tensor
    q: torch.Tensor
    lower: torch.Tensor
    upper: torch.Tensor
    hit: tuple | None
    key: object


def _image_inputs(S_pred, S_gt, gt, valid, Kb, options: SDFOptions) -> list[_ImageInputs]:
    """Per image of :func:`sdf_fields` with a valid pixel, its :class:`_ImageInputs`."""
    todo = []
    cache = options.cache
    if cache is not None and cache.max_bytes > 0 and gt.device.type != "cpu":
        # one copy of the batch to the host for the keys, not three per image (each a device sync)
        gt, valid_h, K_h = gt.detach().cpu(), valid.cpu(), Kb.cpu()
    else:
        valid_h, K_h = valid, Kb
    for b in range(S_pred.shape[0]):
        vb = valid[b].reshape(-1)  # (H*W,)
        if not bool(vb.any()):
            continue
        sel = None if bool(vb.all()) else vb.nonzero().squeeze(1)  # (N,) valid pixels; None: all (no gather)
        key = None
        if cache is not None and cache.max_bytes > 0:
            key = GTFieldCache.key(gt[b], valid_h[b], K_h[b], options)
        hit = cache.get(key) if key is not None else None
        g_pts = S_gt[b] if sel is None else S_gt[b, sel]  # (N, 3)
        q, lower, upper = _samples(g_pts, Kb[b], tuple(valid[b, 0].shape), options.grid, options.sampling,
                                   hit)  # (M, 3), (3,), (3,)
        todo.append(_ImageInputs(b, S_pred[b] if sel is None else S_pred[b, sel], g_pts, q, lower, upper, hit, key))
    return todo


@torch.no_grad()
def _mark_known(fields: list, pred: torch.Tensor, gt_safe: torch.Tensor, K: torch.Tensor,
                valid: torch.Tensor) -> None:
    """Add "known" (M bool) to each image's dict of :func:`sdf_fields` (in place): where the view
    rule signs both the prediction's and the ground truth's field, in one batched projection.

    fields: B entries (None for an image without valid pixels); pred, gt_safe: B x 1 x H x W;
    K: B x 3 x 3; valid: B x 1 x H x W bool.
    """
    idx = [b for b, f in enumerate(fields) if f is not None]
    if not idx:
        return
    q = torch.stack([fields[b]["grid"] for b in idx])  # (B', M, 3)
    v = valid[idx, 0]  # (B', H, W); indexed by a list: any device
    known = (_view_sign(q, pred[idx, 0].detach(), K[idx], v)[1]
             & _view_sign(q, gt_safe[idx, 0], K[idx], v)[1])  # (B', M)
    for j, b in enumerate(idx):
        fields[b]["known"] = known[j]


@torch.no_grad()
def view_rule_coverage(gt: torch.Tensor, K, grid=DEFAULT_SDF_GRID, mask: torch.Tensor | None = None,
                       sampling: str = "bbox") -> torch.Tensor:
    """Per image, the share of SDF samples at which the view rule signs the ground truth's field.

    The view rule (:func:`signed_distance`) applies at a sample q when q_z > 0 and q projects
    (rounded to the nearest pixel) inside the image onto a valid pixel; elsewhere the "view" sign
    falls back to the nearest-point sign and "masked" leaves q out of the loss, so 1 - coverage is
    the fallback share. The samples are those :func:`sdf_fields` uses under ``sampling``
    ("bbox": the grid over the ground truth's bounding box; "frustum": :func:`frustum_points`,
    where the coverage is the share of samples on valid pixels, 1 for a fully valid map).
    gt: B x 1 x H x W depth; K: 3 x 3 or B x 3 x 3; mask: optional B x 1 x H x W bool ->
    B shares in [0, 1] (float64; NaN for an image without a valid pixel).
    """
    check_sdf_options("view", sampling)
    if not isinstance(gt, torch.Tensor) or gt.dim() != 4 or gt.shape[1] != 1:
        raise ValueError(f"gt must be a B x 1 x H x W tensor, got {getattr(gt, 'shape', type(gt).__name__)}")
    B, _, H, W = gt.shape
    valid, gt_safe, Kb = _batch_inputs(gt, K, mask, B)  # (B, 1, H, W) bool, (B, 1, H, W), (B, 3, 3)
    shape = _grid_shape(grid)
    S_gt = camera.backproject(gt_safe, Kb)  # (B, H*W, 3)
    out = torch.full((B,), float("nan"), dtype=torch.float64)
    for b in range(B):
        vb = valid[b].reshape(-1)  # (H*W,)
        if bool(vb.any()):
            q = _samples(S_gt[b, vb], Kb[b], (H, W), shape, sampling)[0]  # (M, 3)
            known = _view_sign(q[None], gt_safe[b, :1], Kb[b][None], valid[b])[1]  # (1, M) bool
            out[b] = known.double().mean()
    return out


# ----------------------------------------------------------------------------- fields of a batch, as B x M tensors
def nearest_indices_grid(points: torch.Tensor, valid: torch.Tensor, queries: torch.Tensor,
                         method: str = "auto") -> torch.Tensor:
    """Per image, the exact nearest valid point of each query, as an index into all of the image's points.

    points: B x N x 3 (a batch's back-projected depth maps); valid: B x N bool (the points that
    count); queries: B x M x 3 -> B x M int64 indices into N (0 for an image without a valid point).
    Searched among each image's valid points, in pixel order, so ties go to the least pixel index, as
    the per-image search of :func:`sdf_fields` gives them. "kdtree" (the CPU default) builds one
    cKDTree per image on the host; "device" runs one batched search
    (:func:`geodepth_lite.core.nnsearch.nearest_indices_batched`), which selects the valid points and so
    waits for the device once; "triton" (CUDA) runs one fused kernel over the whole batch
    (:func:`geodepth_lite.core.nnsearch_triton.nearest_indices_grid`) without waiting; the others search
    image by image.
    """
    B, N, _ = points.shape
    M = queries.shape[1]
    method = resolve_method(method, points.device)
    if method == "triton":  # one fused kernel, fixed shapes: no host sync
        return nnsearch_triton.nearest_indices_grid(points, valid, queries)
    if method == "device":
        flat = valid.reshape(-1)
        sel = flat.nonzero().squeeze(1)  # (P,) flat indices of the valid points
        pimg = sel // N
        qimg = torch.arange(B, device=queries.device).repeat_interleave(M)
        pts = points.detach().reshape(-1, 3).index_select(0, sel).to(torch.float64)
        qs = queries.detach().reshape(-1, 3).to(torch.float64)
        narrow = (torch.float32, torch.float16, torch.bfloat16)
        if points.dtype in narrow and queries.dtype in narrow:  # exact in float32: the search may bound in float32
            pts, qs = pts.float(), qs.float()
        idx = nnsearch.nearest_indices_batched(pts, pimg, qs, qimg, B)  # (B M,) into sel; -1: no point
        full = sel.index_select(0, idx.clamp_min(0)) - qimg * N
        return torch.where(idx >= 0, full, torch.zeros_like(full)).reshape(B, M)
    out = torch.zeros(B, M, dtype=torch.int64, device=queries.device)
    v_h = valid.detach().cpu()
    for b in range(B):
        sel = v_h[b].nonzero().squeeze(1)  # (N_b,) on the host
        if sel.numel():
            idx = nearest_indices(points[b].index_select(0, sel.to(points.device)), queries[b], method)
            out[b] = sel.to(idx.device)[idx]
    return out


def _masked_box(S: torch.Tensor, valid: torch.Tensor, has: torch.Tensor):
    """(lower, upper), B x 3 each: the least and greatest coordinates of each image's valid points
    (S: B x N x 3, valid: B x N, has: B); 0 for an image without a valid point."""
    inf = torch.tensor(float("inf"), dtype=S.dtype, device=S.device)
    v = valid[..., None]
    lower = torch.where(v, S, inf).amin(1)  # (B, 3)
    upper = torch.where(v, S, -inf).amax(1)  # (B, 3)
    zero = torch.zeros((), dtype=S.dtype, device=S.device)
    return torch.where(has[:, None], lower, zero), torch.where(has[:, None], upper, zero)


def _batch_samples(S_gt, valid, has, Kb, hw, options: SDFOptions, hit=None):
    """Every image's SDF samples at once: (q B x M x 3, lower B x 3, upper B x 3), as :func:`_samples`
    gives them image by image (the same operations, so the same values), on ``options.grid`` at
    ``options.sampling``. ``hit``: cached (lower, upper) boxes, B x 3 each, which the "bbox" grid reuses."""
    shape = options.grid
    rx, ry, rz = shape
    dtype, dev = S_gt.dtype, S_gt.device
    B = S_gt.shape[0]
    if options.sampling == "frustum":
        z_near, z_far = _masked_box(S_gt[..., 2:], valid, has)  # (B, 1) each
        z_near = torch.where(has[:, None], z_near, torch.ones_like(z_near))  # an image without points: 1..1
        z_far = torch.where(has[:, None], z_far, torch.ones_like(z_far))
        K = Kb.to(dtype=dtype, device=dev)  # (B, 3, 3)
        u = torch.linspace(0.0, hw[1] - 1, rx, dtype=dtype, device=dev)  # (rx,)
        v = torch.linspace(0.0, hw[0] - 1, ry, dtype=dtype, device=dev)  # (ry,)
        t = torch.linspace(0.0, 1.0, rz, dtype=dtype, device=dev)  # (rz,)
        z = z_near * torch.pow(z_far / z_near, t)  # (B, rz)
        x = (u - K[:, 0, 2, None]) / K[:, 0, 0, None]  # (B, rx)
        y = (v - K[:, 1, 2, None]) / K[:, 1, 1, None]  # (B, ry)
        X = x[:, :, None, None].expand(B, rx, ry, rz)
        Y = y[:, None, :, None].expand(B, rx, ry, rz)
        Z = z[:, None, None, :].expand(B, rx, ry, rz)
        q = torch.stack((X * Z, Y * Z, Z), dim=-1).reshape(B, -1, 3)  # (B, M, 3)
        return q, q.amin(1), q.amax(1)
    lower, upper = (hit[0].to(S_gt), hit[1].to(S_gt)) if hit is not None else _masked_box(S_gt, valid, has)
    axes = [torch.linspace(0.0, 1.0, r, dtype=dtype, device=dev) for r in shape]
    t = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)  # (M, 3)
    return lower[:, None] + t * (upper - lower)[:, None], lower, upper  # (B, M, 3), (B, 3), (B, 3)


def _phi_batched(points, queries, idx, signed: bool, view) -> torch.Tensor:
    """:func:`_phi` of a batch: points B x N x 3, queries B x M x 3, idx B x M (into N), ``view`` the
    (sign, known) pair of :func:`_view_sign` or None -> B x M."""
    nearest = torch.gather(points, 1, idx[..., None].expand(-1, -1, 3))  # (B, M, 3); backward in query order
    return _signed_from_nearest(nearest, queries, signed, view)  # (B, M)


def _cache_keys(options: SDFOptions, frame_ids, gt, valid, Kb):
    """One key per image for ``options.cache``: (the frame's id, the options' tag) where ``frame_ids`` is given
    (nothing read from the device), else the content hash of :meth:`GTFieldCache.key`; None without a cache."""
    cache = options.cache
    if cache is None or cache.max_bytes <= 0:
        return None
    if frame_ids is not None:
        if len(frame_ids) != gt.shape[0]:
            raise ValueError(f"frame_ids must name the {gt.shape[0]} frames of the batch, got {len(frame_ids)}")
        return [("frame", fid, options.cache_tag()) for fid in frame_ids]
    if gt.device.type != "cpu":  # one copy of the batch to the host, not three per image
        gt, valid, Kb = gt.detach().cpu(), valid.cpu(), Kb.cpu()
    return [GTFieldCache.key(gt[b], valid[b], Kb[b], options) for b in range(gt.shape[0])]


def sdf_fields_batched(pred, gt, K, options: SDFOptions, mask=None, frame_ids=None, nearest=None) -> dict:
    """The fields of :func:`sdf_fields` for the whole batch at once, as fixed-shape tensors (``options``:
    :class:`SDFOptions`).

    Returns {"grid": B x M x 3, "lower", "upper": B x 3, "pred", "gt": B x M, "has": B bool (the
    image has a valid pixel; the other rows hold no field)} and, for ``sign_rule="masked"``,
    "known": B x M. Row b equals entry b of :func:`sdf_fields` bit for bit (the same operations on
    the same values, batched; the nearest points are searched among the same valid points). Apart
    from the search (:func:`nearest_indices_grid`) and content cache keys, nothing waits for the
    device: no per-image loop, no test of a tensor's value on the host.

    ``frame_ids``: one hashable id per image (e.g. the dataset's split and frame index) that keys the
    ``options.cache`` where the frame's ground truth is the same whenever the id is (no augmentation);
    None keys it by content. The ground-truth fields come from the cache when every frame hits,
    else all are computed and the missing ones stored. ``nearest``: the prediction's nearest-point
    indices (B x M, from :func:`nearest_indices_grid`), to skip its search (tests, benchmarks).
    """
    o = _options(options)
    check_depths(pred, gt)
    B, _, H, W = pred.shape
    valid, gt_safe, Kb = _batch_inputs(gt, K, mask, B)  # (B, 1, H, W) bool, (B, 1, H, W), (B, 3, 3)
    view = o.signed and o.sign_rule in ("view", "masked")
    S_pred = camera.backproject(pred, K)  # (B, H*W, 3), differentiable in pred
    S_gt = camera.backproject(gt_safe, K).detach()  # (B, H*W, 3)
    vflat = valid.reshape(B, H * W)
    has = vflat.any(1)  # (B,)
    keys = _cache_keys(o, frame_ids, gt, valid, Kb)
    hits = [o.cache.get(k) for k in keys] if keys is not None else None
    hit = None
    if hits is not None and all(h is not None for h in hits):
        hit = tuple(torch.stack([h[i] for h in hits]) for i in range(3))  # (B, 3), (B, 3), (B, M)
    q, lower, upper = _batch_samples(S_gt, vflat, has, Kb, (H, W), o, hit)
    if nearest is None:
        nearest = nearest_indices_grid(S_pred, vflat, q, o.method)  # (B, M)
    v_pred = _view_sign(q, pred[:, 0].detach(), Kb, valid[:, 0]) if view else None
    phi_pred = _phi_batched(S_pred, q, nearest, o.signed, v_pred)  # (B, M)
    if hit is not None:
        phi_gt = hit[2].to(phi_pred)
    else:
        v_gt = _view_sign(q, gt_safe[:, 0], Kb, valid[:, 0]) if view else None
        phi_gt = _phi_batched(S_gt, q, nearest_indices_grid(S_gt, vflat, q, o.method), o.signed,
                              v_gt).to(phi_pred)
        for b, h in enumerate(hits or ()):  # rows of frames without a valid pixel too: they are never read
            if h is None:
                o.cache.put(keys[b], lower[b].clone(), upper[b].clone(), phi_gt[b].clone())
    out = {"grid": q, "lower": lower, "upper": upper, "pred": phi_pred, "gt": phi_gt, "has": has}
    if o.sign_rule == "masked":
        out["known"] = v_pred[1] & v_gt[1] if hit is None else (
            v_pred[1] & _view_sign(q, gt_safe[:, 0], Kb, valid[:, 0])[1])
    return out
