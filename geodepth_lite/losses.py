"""The five losses of Section 3.C and their weighted sum (Eq. for L_total).

Shapes and units (all losses):
- ``pred``, ``gt``: z-depth maps ``B x 1 x H x W`` (float tensors, scene units);
- ``image``: ``B x 3 x H x W`` in [0, 1];
- ``K``: ``3 x 3`` or ``B x 3 x 3`` intrinsics in pixels (see :mod:`geodepth_lite.camera`);
- ``mask``: optional ``B x 1 x H x W`` bool, True where the ground truth may be used.

Ground truth that is NaN, infinite, zero or negative is always treated as invalid (in
addition to ``mask``), and each loss returns a finite scalar tensor even when no pixel is
valid (then 0, still connected to ``pred`` for autograd).

Image gradients are forward differences in depth units per pixel:
``grad_x D(v, u) = D(v, u+1) - D(v, u)`` and ``grad_y D(v, u) = D(v+1, u) - D(v, u)``;
a difference is valid when both of its pixels are valid.

SDF sign (Sec. 3.C: positive ahead of the surface from the camera viewpoint, negative
behind). The "view" rule (default of :func:`sdf_loss`): a sample point q is projected with K,
(u, v) = (fx q_x/q_z + cx, fy q_y/q_z + cy) rounded to the nearest pixel (``torch.round``,
halves to even), and signed by sign(D(v, u) - q_z) with D the depth map whose surface is
measured: +1 in front of the depth map along its own ray, -1 beyond it, 0 on it. Fallback,
where q_z <= 0, q projects outside the image, or onto a pixel that is not valid (masked,
non-finite or <= 0): the nearest-point rule sign((X_n - q) . X_n), X_n the nearest surface
point, i.e. whether q lies on the camera's side of the surface at X_n (the local estimate of
the same thing: for q near a front-facing smooth surface both rules agree). The two rules
differ behind occluding edges, e.g. a point behind a near step, nearest to the far wall.
The magnitude is always the exact Euclidean nearest distance; the sign carries no gradient.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np
import torch

from . import camera

DEFAULT_SDF_GRID = (32, 32, 32)  # r_x, r_y, r_z of the paper's SDF sample grid
CHUNK_ELEMENTS = 2**25  # query x point pairs per block of the on-device exact search
KDTREE_LEAFSIZE = 32  # points per cKDTree leaf (tuned on 320x320 depth maps)
KDTREE_WORKERS = -1  # threads of each cKDTree query (-1: all cores)
SIGN_RULES = {  # SDF sign rules, with the tag that keys cached ground-truth fields
    "view": "sign:view-ray-projection,fallback:nearest-direction",  # the paper's (default)
    "nearest": "sign:nearest-direction",  # sign((X_n - q) . X_n) everywhere (the former rule)
}


# ----------------------------------------------------------------------------- helpers
def valid_mask(gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Pixels usable as ground truth: finite, > 0, and in ``mask`` when given (B x 1 x H x W bool)."""
    valid = torch.isfinite(gt) & (gt > 0)
    if mask is not None:
        if mask.shape != gt.shape:
            raise ValueError(f"mask must have the depth's shape {tuple(gt.shape)}, got {tuple(mask.shape)}")
        valid = valid & mask.to(torch.bool)
    return valid


def _check_depths(pred: torch.Tensor, gt: torch.Tensor) -> None:
    for name, t in (("pred", pred), ("gt", gt)):
        if not isinstance(t, torch.Tensor) or t.dim() != 4 or t.shape[1] != 1:
            shape = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
            raise ValueError(f"{name} must be a B x 1 x H x W tensor, got {shape}")
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt must have the same shape, got {tuple(pred.shape)} and {tuple(gt.shape)}")


def _prepare(pred, gt, mask):
    """Check shapes; return (gt with invalid pixels replaced by 1, validity mask)."""
    _check_depths(pred, gt)
    valid = valid_mask(gt, mask)
    gt_safe = torch.where(valid, gt, torch.ones_like(gt))  # no NaN/inf can reach autograd
    return gt_safe, valid


def masked_mean(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean of ``x`` over ``valid`` entries; 0 (connected to ``x``) when none is valid."""
    x = torch.where(valid, x, torch.zeros_like(x))
    return x.sum() / valid.sum().clamp(min=1).to(x.dtype)


def grad_x(d: torch.Tensor) -> torch.Tensor:
    """Forward difference along the columns: ... x H x (W-1)."""
    return d[..., :, 1:] - d[..., :, :-1]


def grad_y(d: torch.Tensor) -> torch.Tensor:
    """Forward difference along the rows: ... x (H-1) x W."""
    return d[..., 1:, :] - d[..., :-1, :]


# ----------------------------------------------------------------------------- pixel losses
def depth_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """L_depth = || D_pred - D_gt ||_1, as the mean absolute difference over valid pixels (Sec. 3.C, Eq. 1)."""
    gt_safe, valid = _prepare(pred, gt, mask)
    return masked_mean((pred - gt_safe).abs(), valid)


def log_depth_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """|ln D_pred - ln D_gt|, mean over valid pixels: the depth term in relative units.

    Not the paper's term (its Eq. 1 is the absolute L1 above). A far lumen pixel at 30 units
    weighs no more here than a wall pixel at 1 unit, as in the median-scaled metrics
    (Abs Rel, RMSE log). Measured against L1 and silog in ``config.TEACH_EVIDENCE``.
    """
    gt_safe, valid = _prepare(pred, gt, mask)
    return masked_mean((torch.log(pred.clamp(min=1e-6)) - torch.log(gt_safe)).abs(), valid)


SILOG_VARIANCE_FOCUS = 0.85  # lambda of the scale-invariant log loss (Eigen et al. 2014; BTS)


def silog_depth_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Scale-invariant log loss, per frame sqrt(mean(d^2) - lambda mean(d)^2), d = ln D_pred - ln D_gt.

    Not the paper's term. One image does not say how far away the scene is (the endoscope's
    auto-exposure removes the brightness cue for absolute scale), and the metrics median-scale
    every frame. With lambda = 0.85 the loss mostly ignores a frame's global scale error
    (the mean of d) and spends the network's effort on relative depth; the remaining 15%
    keeps the scale anchored. Mean over the frames that have valid pixels.
    """
    gt_safe, valid = _prepare(pred, gt, mask)
    d = torch.where(valid, torch.log(pred.clamp(min=1e-6)) - torch.log(gt_safe), torch.zeros_like(pred))
    n = valid.flatten(1).sum(1).to(d.dtype)  # valid pixels per frame
    has = n > 0
    n = n.clamp(min=1)
    mean = d.flatten(1).sum(1) / n
    msq = (d * d).flatten(1).sum(1) / n
    per_frame = torch.sqrt((msq - SILOG_VARIANCE_FOCUS * mean * mean).clamp(min=1e-12))
    return torch.where(has, per_frame, torch.zeros_like(per_frame)).sum() / has.sum().clamp(min=1).to(d.dtype)


DEPTH_TERMS = {"l1": depth_loss, "log_l1": log_depth_loss, "silog": silog_depth_loss}  # the depth term's variants


def smoothness_loss(pred: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """L_smooth = (e^{-|grad I|} . grad D)^2, edge-aware (Sec. 3.C, Eq. 2; Godard et al. 2017).

    |grad I| is the channel mean of the absolute image differences; the loss is the mean over
    pixels of the squared, edge-weighted x differences plus that of the y differences.
    """
    if image.dim() != 4 or image.shape[0] != pred.shape[0] or image.shape[-2:] != pred.shape[-2:]:
        raise ValueError(f"image must be B x 3 x H x W matching pred {tuple(pred.shape)}, got {tuple(image.shape)}")
    wx = torch.exp(-grad_x(image).abs().mean(dim=1, keepdim=True))
    wy = torch.exp(-grad_y(image).abs().mean(dim=1, keepdim=True))
    return (wx * grad_x(pred)).pow(2).mean() + (wy * grad_y(pred)).pow(2).mean()


def gradient_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """L_grad = ||grad_x D_pred - grad_x D_gt||_1 + ||grad_y D_pred - grad_y D_gt||_1 (Sec. 3.C, Eq. 3).

    Each term is a mean over the valid differences (depth units per pixel).
    """
    gt_safe, valid = _prepare(pred, gt, mask)
    vx = valid[..., :, 1:] & valid[..., :, :-1]
    vy = valid[..., 1:, :] & valid[..., :-1, :]
    lx = masked_mean((grad_x(pred) - grad_x(gt_safe)).abs(), vx)
    ly = masked_mean((grad_y(pred) - grad_y(gt_safe)).abs(), vy)
    return lx + ly


def surface_normals(d: torch.Tensor) -> torch.Tensor:
    """n = [-grad_x D, -grad_y D, 1] at pixel (v, u), u < W-1, v < H-1: B x 3 x (H-1) x (W-1) (Sec. 3.C)."""
    gx = grad_x(d)[..., :-1, :]
    gy = grad_y(d)[..., :, :-1]
    return torch.cat((-gx, -gy, torch.ones_like(gx)), dim=1)


def normal_map(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None):
    """Per-pixel 1 - cos(n_pred, n_gt), B x 1 x (H-1) x (W-1), and its validity mask."""
    gt_safe, valid = _prepare(pred, gt, mask)
    v = valid[..., :-1, :-1] & valid[..., :-1, 1:] & valid[..., 1:, :-1]
    n_p, n_g = surface_normals(pred), surface_normals(gt_safe)
    cos = (n_p * n_g).sum(1, keepdim=True) / (n_p.norm(dim=1, keepdim=True) * n_g.norm(dim=1, keepdim=True))
    return 1.0 - cos, v  # norms are >= 1 (third component is 1): no division by zero


def normal_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """L_normal = 1 - <n_gt, n_pred> / (|n_gt| |n_pred|), mean over valid pixels (Sec. 3.C, Eq. 4)."""
    per_pixel, v = normal_map(pred, gt, mask)
    return masked_mean(per_pixel, v)


# ----------------------------------------------------------------------------- nearest neighbours
@torch.no_grad()
def nearest_indices_kdtree(points: torch.Tensor, queries: torch.Tensor, workers: int | None = None) -> torch.Tensor:
    """Exact nearest neighbour of each query among ``points`` with scipy's cKDTree (CPU).

    points: N x 3, queries: M x 3 (any device; searched in float64 on the CPU) -> M indices (int64,
    on the queries' device).
    """
    from scipy.spatial import cKDTree

    p = points.detach().cpu().double().numpy()
    q = queries.detach().cpu().double().numpy()
    # an unbalanced, non-compact tree builds and searches about 2x faster on depth-map surfaces
    tree = cKDTree(p, leafsize=KDTREE_LEAFSIZE, balanced_tree=False, compact_nodes=False)
    _, idx = tree.query(q, k=1, workers=KDTREE_WORKERS if workers is None else workers)
    return torch.from_numpy(np.asarray(idx, dtype=np.int64)).to(queries.device)


@torch.no_grad()
def nearest_indices_chunked(points: torch.Tensor, queries: torch.Tensor, chunk_elements: int = CHUNK_ELEMENTS,
                            exact: bool = True) -> torch.Tensor:
    """Nearest neighbour by brute force in blocks of queries, on the tensors' device (CUDA path).

    With ``exact`` (default) distances are computed as differences, so the result is the exact
    argmin up to floating-point ties; ``exact=False`` uses the faster matrix-product expansion
    |q|^2 - 2 q.x + |x|^2, which can pick a near-tie wrongly (used only as a speed baseline).
    points: N x 3, queries: M x 3 -> M indices (int64).
    """
    n = points.shape[0]
    step = max(1, chunk_elements // max(n, 1))
    mode = "donot_use_mm_for_euclid_dist" if exact else "use_mm_for_euclid_dist"
    out = []
    for s in range(0, queries.shape[0], step):
        d = torch.cdist(queries[s:s + step], points, compute_mode=mode)
        out.append(d.argmin(dim=1))
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.int64, device=queries.device)


def nearest_indices(points: torch.Tensor, queries: torch.Tensor, method: str = "auto") -> torch.Tensor:
    """Nearest-neighbour indices: "kdtree" (exact, CPU), "chunked" (exact, on the device), "auto"
    (kdtree for CPU tensors, chunked otherwise) or "brute_mm" (matrix-product brute force, a
    speed baseline only)."""
    if method == "auto":
        method = "kdtree" if points.device.type == "cpu" else "chunked"
    if method == "kdtree":
        return nearest_indices_kdtree(points, queries)
    if method == "chunked":
        return nearest_indices_chunked(points, queries)
    if method == "brute_mm":
        return nearest_indices_chunked(points, queries, exact=False)
    raise ValueError(f"unknown nearest-neighbour method {method!r}: use 'auto', 'kdtree' or 'chunked'")


# ----------------------------------------------------------------------------- SDF loss
def _grid_shape(grid) -> tuple[int, int, int]:
    g = (grid,) * 3 if isinstance(grid, (int, np.integer)) else tuple(grid)
    if len(g) != 3 or not all(isinstance(r, (int, np.integer)) and r >= 2 for r in g):
        raise ValueError(f"sdf grid must be an int >= 2 or three of them (r_x, r_y, r_z), got {grid!r}")
    return tuple(int(r) for r in g)


def sample_grid(lower: torch.Tensor, upper: torch.Tensor, grid=DEFAULT_SDF_GRID) -> torch.Tensor:
    """The paper's sample grid with the offset put back (Sec. 3.C, Eq. 8):

    X_ijk = X_lb + (i/(r_x-1), j/(r_y-1), k/(r_z-1)) * (X_ub - X_lb),  i < r_x, j < r_y, k < r_z.
    lower, upper: 3-vectors -> (r_x r_y r_z) x 3 points, i slowest (x), k fastest (z).
    """
    rx, ry, rz = _grid_shape(grid)
    axes = [torch.linspace(0.0, 1.0, r, dtype=lower.dtype, device=lower.device) for r in (rx, ry, rz)]
    t = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    return lower + t * (upper - lower)


def _check_sign_rule(sign_rule: str) -> None:
    if sign_rule not in SIGN_RULES:
        raise ValueError(f"sign_rule must be one of {', '.join(SIGN_RULES)}, got {sign_rule!r}")


@torch.no_grad()
def _view_sign(queries: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, valid: torch.Tensor):
    """The view rule's sign of each query and whether it applies (batched, no gradient).

    queries: B x M x 3 (camera frame); depth: B x H x W; K: B x 3 x 3; valid: B x H x W bool ->
    (sign, known), both B x M: sign = sign(D(v, u) - q_z) in the queries' dtype at the rounded
    projection (u, v), known = q_z > 0, (u, v) inside the image, valid there and D finite > 0.
    """
    B, H, W = depth.shape
    K = K.to(dtype=queries.dtype, device=queries.device)
    x, y, z = queries.unbind(-1)
    front = z > 0
    zs = torch.where(front, z, torch.ones_like(z))  # no division by zero behind the camera
    u = torch.round(K[:, 0, 0, None] * x / zs + K[:, 0, 2, None])
    v = torch.round(K[:, 1, 1, None] * y / zs + K[:, 1, 2, None])
    known = front & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)  # False for NaN/inf too
    lin = torch.where(known, v * W + u, torch.zeros_like(u)).long()  # B x M pixel indices
    D = torch.gather(depth.detach().reshape(B, H * W), 1, lin).to(queries.dtype)
    ok = torch.gather(valid.reshape(B, H * W).to(torch.bool), 1, lin)
    known = known & ok & torch.isfinite(D) & (D > 0)
    return torch.where(known, torch.sign(D - z), torch.zeros_like(z)), known


def _signed_from_nearest(nearest: torch.Tensor, queries: torch.Tensor, signed: bool = True,
                         view=None) -> torch.Tensor:
    """phi(q) from the nearest surface points X_n (... x 3, differentiable) and queries q (... x 3).

    ``view``: None (nearest-point sign everywhere) or the (sign, known) pair of :func:`_view_sign`
    (... each): the view sign where known, the nearest-point sign elsewhere (the fallback).
    """
    diff = nearest - queries
    d2 = (diff * diff).sum(-1)
    pos = d2 > 0  # the distance's gradient is set to 0 on the surface instead of NaN
    dist = torch.where(pos, torch.sqrt(torch.where(pos, d2, torch.ones_like(d2))), torch.zeros_like(d2))
    if not signed:
        return dist
    with torch.no_grad():
        sign = torch.sign((diff * nearest).sum(-1))
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
    """
    idx = nearest_indices(points, queries, method)
    view = None
    if depth is not None and signed:
        if K is None:
            raise ValueError("signed_distance: the view rule needs K with depth")
        d = torch.as_tensor(depth).to(device=queries.device)
        if d.dim() != 2:
            raise ValueError(f"depth must be H x W, got shape {tuple(d.shape)}")
        Kt = torch.as_tensor(np.asarray(K) if not isinstance(K, torch.Tensor) else K).to(queries.device)
        v = torch.ones_like(d, dtype=torch.bool) if valid is None else torch.as_tensor(valid).to(d.device)
        if v.shape != d.shape:
            raise ValueError(f"valid must have the depth's shape {tuple(d.shape)}, got {tuple(v.shape)}")
        view = tuple(t[0] for t in _view_sign(queries[None], d[None], Kt.reshape(1, 3, 3), v[None]))
    return _signed_from_nearest(points[idx], queries, signed, view)


class GTFieldCache:
    """LRU cache of ground-truth SDF fields, keyed by the bytes of the frame (depth, validity, K),
    the grid, ``signed`` and the sign rule's tag (:data:`SIGN_RULES`; fields signed under another
    rule, such as the former nearest-point-only sign, never match).

    The ground truth's field does not depend on the network, and training sees every frame once
    per epoch, so from the second epoch on only the prediction's field has to be searched. A
    hit returns exactly what the search would (same inputs, same exact search). Fields are kept
    on the CPU in their dtype (128 KiB per frame at 32^3 in float32); the least recently used
    are dropped beyond ``max_bytes`` (512 MiB: about 4000 frames at 32^3); ``max_bytes = 0``
    disables the cache.
    """

    def __init__(self, max_bytes: int = 512 * 2**20):
        self.max_bytes = int(max_bytes)
        self._d: OrderedDict = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    @staticmethod
    def key(gt_b: torch.Tensor, valid_b: torch.Tensor, K_b: torch.Tensor, grid, signed: bool,
            sign_rule: str = "view") -> str:
        h = hashlib.blake2b(digest_size=20)
        for t in (gt_b, valid_b, K_b):
            t = t.detach().cpu().contiguous()
            h.update(str((t.dtype, tuple(t.shape))).encode())
            h.update(t.numpy().tobytes())
        h.update(repr((tuple(grid), bool(signed), SIGN_RULES[sign_rule])).encode())
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
        item = (lower.detach().cpu(), upper.detach().cpu(), field.detach().cpu())
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


GT_FIELD_CACHE = GTFieldCache()  # used by sdf_loss / total_loss unless cache=None is passed


def sdf_fields(pred, gt, K, grid=DEFAULT_SDF_GRID, mask=None, method: str = "auto", signed: bool = True,
               cache: GTFieldCache | None = None, sign_rule: str = "view"):
    """Per image: the sample grid and the signed fields of prediction and ground truth.

    Returns a list (one entry per image; None when the image has no valid pixel) of dicts
    {"grid": M x 3, "lower", "upper": 3-vectors, "pred": M, "gt": M}, M = r_x r_y r_z; fields are
    ordered as :func:`sample_grid` (reshape to r_x x r_y x r_z). The nearest points are searched
    image by image without gradient; the distances are then computed for the whole batch at
    once (few, large tensor operations). With a ``cache`` (:class:`GTFieldCache`), ground-truth
    fields already computed for an identical frame are reused.

    Sign (``sign_rule``, no gradient): "view" (default, the paper's) projects each grid point
    with K to its nearest pixel and compares q_z with each map's own depth there: the
    prediction's field uses ``pred``, the ground truth's ``gt`` (+1 where q_z < D, -1 where
    q_z > D, 0 on it), both at the ground truth's valid pixels (where ``pred`` is also finite and
    > 0 for the prediction's). Fallback, for points with q_z <= 0, projecting outside the image
    or onto an unusable pixel: the nearest-point sign sign((X_n - q) . X_n). "nearest" uses the
    nearest-point sign everywhere (the former rule, for comparison). See :func:`signed_distance`.
    """
    _check_sign_rule(sign_rule)
    gt_safe, valid = _prepare(pred, gt, mask)
    Kt = torch.as_tensor(np.asarray(K) if not isinstance(K, torch.Tensor) else K)
    if not (Kt.shape == (3, 3) or (Kt.dim() == 3 and Kt.shape[0] == pred.shape[0] and Kt.shape[1:] == (3, 3))):
        raise ValueError(f"K must be 3 x 3 or B x 3 x 3 with B = {pred.shape[0]}, got {tuple(Kt.shape)}")
    rx, ry, rz = _grid_shape(grid)
    P_pred = camera.backproject(pred, K)  # B x HW x 3 (differentiable)
    P_gt = camera.backproject(gt_safe, K).detach()
    flat_valid = valid.reshape(valid.shape[0], -1)
    used, grids, lows, ups, idx_g, idx_p, cached = [], [], [], [], [], [], []
    with torch.no_grad():
        for b in range(pred.shape[0]):
            vb = flat_valid[b]
            if bool(vb.all()):  # the common case: no gather
                sel, g_pts, p_pts = None, P_gt[b], P_pred[b].detach()
            elif bool(vb.any()):
                sel = vb.nonzero().squeeze(1)
                g_pts, p_pts = P_gt[b, sel], P_pred[b, sel].detach()
            else:
                continue
            key = hit = None
            if cache is not None and cache.max_bytes > 0:
                key = GTFieldCache.key(gt[b], valid[b], Kt if Kt.dim() == 2 else Kt[b], (rx, ry, rz), signed,
                                       sign_rule)
                hit = cache.get(key)
            if hit is not None:
                lower, upper = hit[0].to(P_gt), hit[1].to(P_gt)
            else:
                lower, upper = g_pts.min(0).values, g_pts.max(0).values  # X_lb, X_ub of the ground truth
            q = sample_grid(lower, upper, (rx, ry, rz))
            ig = None
            if hit is None:
                ig = nearest_indices(g_pts, q, method)
                ig = sel[ig] if sel is not None else ig  # back to pixel indices
            ip = nearest_indices(p_pts, q, method)
            ip = sel[ip] if sel is not None else ip
            used.append(b), grids.append(q), lows.append(lower), ups.append(upper)
            idx_g.append(ig), idx_p.append(ip), cached.append((key, hit))
    out: list = [None] * pred.shape[0]
    if not used:
        return out
    bi = torch.as_tensor(used, device=pred.device)
    q = torch.stack(grids)  # B' x M x 3
    view = signed and sign_rule == "view"
    Kb = Kt.to(device=pred.device).expand(pred.shape[0], 3, 3)[bi] if view else None  # B' x 3 x 3
    Ip = torch.stack(idx_p)  # B' x M
    Xp = torch.gather(P_pred[bi], 1, Ip.unsqueeze(-1).expand(-1, -1, 3))  # differentiable in pred
    vs_p = _view_sign(q, pred.detach()[bi, 0], Kb, valid[bi, 0]) if view else None
    phi_p = _signed_from_nearest(Xp, q, signed, vs_p)
    phi_g = torch.empty_like(phi_p.detach())
    todo = [k for k, ig in enumerate(idx_g) if ig is not None]
    if todo:
        t = torch.as_tensor(todo, device=pred.device)
        Ig = torch.stack([idx_g[k] for k in todo])
        Xg = torch.gather(P_gt[bi[t]], 1, Ig.unsqueeze(-1).expand(-1, -1, 3))
        vs_g = _view_sign(q[t], gt_safe[bi[t], 0], Kb[t], valid[bi[t], 0]) if view else None
        phi_g[t] = _signed_from_nearest(Xg, q[t], signed, vs_g)
    for k, (key, hit) in enumerate(cached):
        if hit is not None:
            phi_g[k] = hit[2].to(phi_g)
        elif key is not None:
            cache.put(key, lows[k], ups[k], phi_g[k])
    for k, b in enumerate(used):
        out[b] = {"grid": q[k], "lower": lows[k], "upper": ups[k], "pred": phi_p[k], "gt": phi_g[k]}
    return out


def sdf_loss(pred, gt, K, grid=DEFAULT_SDF_GRID, mask=None, method: str = "auto", signed: bool = True,
             cache: GTFieldCache | None = GT_FIELD_CACHE, sign_rule: str = "view") -> torch.Tensor:
    """L_sdf: mean over the r_x r_y r_z grid of |phi(X_ijk, S_pred) - phi(X_ijk, S_gt)| (Sec. 3.C, Eq. 9).

    Both depth maps are back-projected with K (valid pixels only); the grid spans the ground
    truth's 3D bounding box [X_lb, X_ub] (:func:`sample_grid`); phi is the exact nearest
    distance, signed by the paper's view rule (``sign_rule="view"``): grid point q projected with K
    to its nearest pixel, +1 where q_z is less than that map's own depth there (the prediction's
    field uses ``pred``, the ground truth's ``gt``), -1 where greater, 0 on it; for q_z <= 0, q
    projecting outside the image or onto an invalid pixel, the fallback sign((X_n - q) . X_n)
    with X_n the nearest surface point (:func:`sdf_fields`, :func:`signed_distance`).
    ``sign_rule="nearest"`` uses that nearest-point sign everywhere (the former rule, for
    comparison). The loss is the mean over images with at least one valid pixel
    (0 if none). ``method``: exact nearest-neighbour search, "auto" = cKDTree on the CPU,
    chunked brute force on CUDA. ``signed=False`` gives the unsigned variant (for comparison).
    ``cache``: ground-truth fields are reused for frames seen before (:class:`GTFieldCache`;
    None to always search).
    """
    fields = [f for f in sdf_fields(pred, gt, K, grid, mask, method, signed, cache, sign_rule) if f is not None]
    if not fields:
        return pred.sum() * 0.0
    return (torch.stack([f["pred"] for f in fields]) - torch.stack([f["gt"] for f in fields])).abs().mean()


# ----------------------------------------------------------------------------- total
TERMS = ("depth", "smooth", "grad", "normal", "sdf", "total")


def total_loss(pred, gt, image, K, lambdas=(1.0, 1.0, 1.0), mask=None, sdf_grid=DEFAULT_SDF_GRID,
               depth_term: str = "l1"):
    """L_total = l1 (L_depth + L_smooth) + l2 (L_grad + L_normal) + l3 L_sdf (Sec. 3.C, Eq. 10).

    Returns (loss, terms): ``loss`` a scalar tensor for backward; ``terms`` a dict of floats
    with keys depth, smooth, grad, normal, sdf, total (unweighted terms, weighted total).
    A zero lambda skips computing its terms, which are then reported as 0.0. The ablation
    cases of Sec. 4.3 are lambda settings (``config.ABLATION_CASES``). ``depth_term``: "l1"
    (the paper's Eq. 1), "log_l1" (:func:`log_depth_loss`) or "silog" (:func:`silog_depth_loss`).
    """
    if depth_term not in DEPTH_TERMS:
        raise ValueError(f"depth_term must be one of {', '.join(DEPTH_TERMS)}, got {depth_term!r}")
    if len(lambdas) != 3 or any(float(l) < 0 for l in lambdas):
        raise ValueError(f"lambdas must be three non-negative weights (l1, l2, l3), got {lambdas!r}")
    l1, l2, l3 = (float(l) for l in lambdas)
    zero = pred.sum() * 0.0
    t = {k: zero for k in TERMS[:-1]}
    if l1:
        t["depth"], t["smooth"] = DEPTH_TERMS[depth_term](pred, gt, mask), smoothness_loss(pred, image)
    if l2:
        t["grad"], t["normal"] = gradient_loss(pred, gt, mask), normal_loss(pred, gt, mask)
    if l3:
        t["sdf"] = sdf_loss(pred, gt, K, sdf_grid, mask)
    loss = l1 * (t["depth"] + t["smooth"]) + l2 * (t["grad"] + t["normal"]) + l3 * t["sdf"]
    terms = {k: float(v.detach()) for k, v in t.items()}
    terms["total"] = float(loss.detach())
    return loss, terms


def term_gradient_norms(pred, gt, image, K, mask=None, sdf_grid=DEFAULT_SDF_GRID, depth_term: str = "l1",
                        terms=TERMS[:-1]) -> dict[str, float]:
    """||dL_term / dD_pred||_2 of each unweighted term at the network's output (a loss-balancing diagnostic).

    The network sees the losses only through this gradient on its output depth map, so the
    ratio of two norms says how strongly each term pulls on the prediction at a given lambda:
    a term whose gradient is 10x the depth term's dominates the update at lambda = 1.
    ``pred`` is detached here (nothing reaches the network); returns {term: norm} for ``terms``.
    """
    p = pred.detach().float().clone().requires_grad_(True)
    fns = {
        "depth": lambda: DEPTH_TERMS[depth_term](p, gt, mask),
        "smooth": lambda: smoothness_loss(p, image),
        "grad": lambda: gradient_loss(p, gt, mask),
        "normal": lambda: normal_loss(p, gt, mask),
        "sdf": lambda: sdf_loss(p, gt, K, sdf_grid, mask),
    }
    out = {}
    for name in terms:
        (g,) = torch.autograd.grad(fns[name](), p, allow_unused=True)
        out[name] = 0.0 if g is None else float(g.norm())
    return out

