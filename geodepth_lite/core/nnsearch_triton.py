"""Exact nearest-point search as one fused Triton kernel (the CUDA path of the SDF loss).

The same answer as :func:`geodepth_lite.core.sdf.nearest_indices_grid` with the other exact methods: for
each query of image b, the index (into the image's N pixels) of the nearest *valid* point of image
b, at the least float64 Euclidean distance, the least pixel index among equal distances; 0 for an
image without a valid point. Distances are ``(dx*dx + dy*dy) + dz*dz`` in float64 from the
float64 values of the inputs.

Unlike :mod:`geodepth_lite.core.nnsearch`, nothing is written per (query, point) pair: each program of
the kernel holds a tile of ``BQ`` queries in registers and walks the image's point blocks.

1. **Order, in torch ops (fixed shapes, no host sync).** Each image's points are sorted along a
   Morton (Z-order) curve of its valid points' box, the invalid points last and set to +inf; the
   sorted points are cut into blocks of ``BP`` with their boxes; the queries are sorted the same
   way and cut into tiles of ``BQ`` (a tile is then a small cube of the grid).
2. **A first bound.** For each query, the least distance to the blocks' first points (an actual
   point of the image, so an upper bound of its nearest distance).
3. **The walk.** Blocks go in chunks of ``CB``; a chunk whose least box gap to the tile's box
   exceeds the tile's largest bound so far is skipped whole, else its blocks are tested one by one
   and a surviving block's points are compared exactly with every query of the tile.

Pruning is exact: a point's squared distance to a query is at least the squared gap between the
query's (or its tile's) box and the point's block box, computed with the same roundings in the same
order, so the block holding the nearest point always passes (``<=``).

Importing this module needs Triton only for :func:`nearest_indices_grid`; :data:`AVAILABLE` says
whether it can run (Triton present; on CPU tensors only under ``TRITON_INTERPRET=1``, which tests use).
"""

from __future__ import annotations

import math
import os
import warnings

import torch

from geodepth_lite.core import nnsearch
from geodepth_lite.core.errors import UserError

try:
    import triton
    import triton.language as tl
except ImportError:  # CPU builds of torch ship without Triton: the other exact searches are used
    triton = None

AVAILABLE = triton is not None
INTERPRET = os.environ.get("TRITON_INTERPRET") == "1"
# queries per tile, points per block, blocks per chunk (powers of two), warps per program, and whether the
# bound a block is tested against is refreshed per block (0) or per chunk (1: fewer reductions, a staler
# bound). Smaller tiles prune better (pair comparisons per query on 320 px analytic views, 32^3 grids:
# 3,193-7,247 at 16 x 32, 6,398-15,616 at 64 x 64; brute force 102,400); on one H200, 16 x 32 searched a
# batch of 20 such fields in 25.8 ms against 31.2 ms at 32 x 32 and 55.4 ms at 64 x 64 (benchmarks/gpu/)
TILE_ENV = "GEODEPTH_LITE_TRITON_TILE"  # "BQ,BP,CB,WARPS[,MODE]" overrides the default (gpu-check's sweep)


def parse_tile(text: str) -> tuple[int, int, int, int, int]:
    """(BQ, BP, CB, WARPS, MODE) from "BQ,BP,CB,WARPS[,MODE]": powers of two, BQ, BP, CB in 8..256, WARPS
    in 1..16; MODE 0 or 1 (default 0)."""
    try:
        vals = tuple(int(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) == 4:
        vals = (*vals, 0)
    ok = len(vals) == 5
    if ok:
        bq, bp, cb, warps, mode = vals
        ok = (all(v > 0 and v & (v - 1) == 0 for v in (bq, bp, cb, warps)) and mode in (0, 1)
              and all(8 <= v <= 256 for v in (bq, bp, cb)) and warps <= 16)
    if not ok:
        raise UserError(f"{TILE_ENV} must be 'BQ,BP,CB,WARPS[,MODE]': powers of two in 8-256, 8-256, 8-256, 1-16, "
                         f"and MODE 0 or 1, got {text!r}")
    return vals


BQ, BP, CB, NUM_WARPS, MODE = parse_tile(os.environ.get(TILE_ENV, "16,32,32,2"))
_INVALID = 1 << 31  # sort key of an invalid point: after every Morton code (30 bits)


_CHECKED: dict[str, bool] = {}


def usable(device: torch.device) -> bool:
    """Whether the kernel runs on tensors of ``device``: Triton is installed, the device is CUDA (or
    CPU under ``TRITON_INTERPRET=1``), and the kernel, compiled there once per process, gives a float64
    brute force's answers on a small cloud (else a warning says why, and the other searches are used)."""
    dev = torch.device(device)
    if not AVAILABLE or not (dev.type == "cuda" or INTERPRET):
        return False
    if str(dev) not in _CHECKED:
        _CHECKED[str(dev)] = _self_check(dev)
    return _CHECKED[str(dev)]


def _self_check(dev: torch.device) -> bool:
    g = torch.Generator().manual_seed(0)
    P = torch.rand(2, 300, 3, generator=g).to(dev)
    Q = (torch.rand(2, 70, 3, generator=g) * 1.5 - 0.25).to(dev)
    V = torch.ones(2, 300, dtype=torch.bool, device=dev)
    V[1, ::3] = False
    try:
        got = _search(P, V, Q)
    except Exception as exc:  # a compiler or driver failure of any kind: fall back, saying why
        warnings.warn(f"the Triton nearest-point search does not run on {dev} ({type(exc).__name__}: "
                      f"{str(exc).splitlines()[0] if str(exc) else ''}); using the device search instead")
        return False
    diff = Q.double()[:, :, None, :] - P.double()[:, None, :, :]
    d2 = (diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1]) + diff[..., 2] * diff[..., 2]
    d2 = torch.where(V[:, None, :], d2, torch.full_like(d2, float("inf")))
    if torch.equal(got, d2.argmin(2)):  # random points: no ties
        return True
    warnings.warn(f"the Triton nearest-point search gives wrong answers on {dev}; using the device search instead")
    return False


def morton_order(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """B x N permutation sorting each image's rows of x (B x N x 3, float64) by the Morton code of
    their place in the box of the image's valid rows; invalid rows last, ties in row order."""
    inf = torch.tensor(float("inf"), dtype=x.dtype, device=x.device)
    v = valid[..., None]
    lo = torch.where(v, x, inf).amin(1, keepdim=True)  # (B, 1, 3)
    hi = torch.where(v, x, -inf).amax(1, keepdim=True)
    span = (hi - lo).clamp_min(1e-300)
    cell = ((torch.where(v, x, lo) - lo) / span * (2**nnsearch.MORTON_BITS - 1)).nan_to_num(0.0)
    q = cell.round().clamp(0, 2**nnsearch.MORTON_BITS - 1).long()  # (B, N, 3)
    code = nnsearch.morton_code(q)
    key = torch.where(valid, code, torch.full_like(code, _INVALID))
    return torch.sort(key, dim=1, stable=True).indices  # (B, N)


def _pad_rows(x: torch.Tensor, n: int, value) -> torch.Tensor:
    """x (B x L x ...) padded along dim 1 to n rows of ``value``."""
    if x.shape[1] == n:
        return x
    pad = torch.full((x.shape[0], n - x.shape[1], *x.shape[2:]), value, dtype=x.dtype, device=x.device)
    return torch.cat([x, pad], 1)


def point_blocks(points: torch.Tensor, valid: torch.Tensor):
    """The kernel's point layout: (coords 3 x B x Np float64, sorted and padded with +inf; index
    B x Np int32, each slot's pixel (N for padding); boxes 6 x B x NB (lo xyz, hi xyz; an empty
    block has lo = +inf, hi = -inf); firsts 3 x B x NB, each block's first point)."""
    B, N, _ = points.shape
    nb = math.ceil(math.ceil(N / BP) / CB) * CB
    order = morton_order(points, valid)  # (B, N)
    inf = float("inf")
    P = torch.gather(torch.where(valid[..., None], points, inf), 1, order[..., None].expand(-1, -1, 3))
    P = _pad_rows(P, nb * BP, inf)  # (B, Np, 3)
    index = _pad_rows(order.to(torch.int32), nb * BP, N)  # (B, Np)
    blocks = P.view(B, nb, BP, 3)
    lo = blocks.amin(2)  # (B, nb, 3): +inf for an empty block
    hi = torch.where(torch.isinf(blocks), -inf, blocks).amax(2)  # -inf for an empty block
    boxes = torch.cat([lo, hi], 2).permute(2, 0, 1).contiguous()  # (6, B, nb)
    firsts = blocks[:, :, 0].permute(2, 0, 1).contiguous()  # (3, B, nb)
    return P.permute(2, 0, 1).contiguous(), index.contiguous(), boxes, firsts


if AVAILABLE:
    @triton.jit
    def _gap2(alo, ahi, blo, bhi):
        """Squared gap along one axis between intervals [alo, ahi] and [blo, bhi] (0 where they meet)."""
        g = tl.maximum(tl.maximum(blo - ahi, alo - bhi), 0.0)
        return g * g

    @triton.jit
    def _nearest_kernel(qs, ps, pidx, boxes, firsts, out, B, Mp, Np, NB,
                        BQ: tl.constexpr, BP: tl.constexpr, CB: tl.constexpr, MODE: tl.constexpr):
        t = tl.program_id(0)
        b = tl.program_id(1)
        oq = t * BQ + tl.arange(0, BQ)
        qx = tl.load(qs + (0 * B + b) * Mp + oq)
        qy = tl.load(qs + (1 * B + b) * Mp + oq)
        qz = tl.load(qs + (2 * B + b) * Mp + oq)
        tlx, thx = tl.min(qx, 0), tl.max(qx, 0)
        tly, thy = tl.min(qy, 0), tl.max(qy, 0)
        tlz, thz = tl.min(qz, 0), tl.max(qz, 0)
        # 2. a first bound: the least distance to the blocks' first points
        ub = tl.full([BQ], float("inf"), tl.float64)
        for c in range(0, NB, CB):
            ob = c + tl.arange(0, CB)
            fx = tl.load(firsts + (0 * B + b) * NB + ob)
            fy = tl.load(firsts + (1 * B + b) * NB + ob)
            fz = tl.load(firsts + (2 * B + b) * NB + ob)
            dx = qx[:, None] - fx[None, :]
            dy = qy[:, None] - fy[None, :]
            dz = qz[:, None] - fz[None, :]
            ub = tl.minimum(ub, tl.min((dx * dx + dy * dy) + dz * dz, 1))
        # 3. the walk over the blocks, a chunk at a time
        best = tl.full([BQ], float("inf"), tl.float64)
        bidx = tl.zeros([BQ], tl.int32)
        for c in range(0, NB, CB):
            ob = c + tl.arange(0, CB)
            lb = (_gap2(tlx, thx, tl.load(boxes + (0 * B + b) * NB + ob), tl.load(boxes + (3 * B + b) * NB + ob))
                  + _gap2(tly, thy, tl.load(boxes + (1 * B + b) * NB + ob), tl.load(boxes + (4 * B + b) * NB + ob))
                  ) + _gap2(tlz, thz, tl.load(boxes + (2 * B + b) * NB + ob), tl.load(boxes + (5 * B + b) * NB + ob))
            thr = tl.max(tl.minimum(ub, best), 0)
            if tl.min(lb, 0) <= thr:
                for j in range(c, c + CB):
                    lbj = (_gap2(tlx, thx, tl.load(boxes + (0 * B + b) * NB + j),
                                 tl.load(boxes + (3 * B + b) * NB + j))
                           + _gap2(tly, thy, tl.load(boxes + (1 * B + b) * NB + j),
                                   tl.load(boxes + (4 * B + b) * NB + j))
                           ) + _gap2(tlz, thz, tl.load(boxes + (2 * B + b) * NB + j),
                                     tl.load(boxes + (5 * B + b) * NB + j))
                    if MODE == 0:  # the bound refreshed per block; MODE 1 keeps the chunk's (larger, still safe)
                        thr = tl.max(tl.minimum(ub, best), 0)
                    if lbj <= thr:
                        op = j * BP + tl.arange(0, BP)
                        px = tl.load(ps + (0 * B + b) * Np + op)
                        py = tl.load(ps + (1 * B + b) * Np + op)
                        pz = tl.load(ps + (2 * B + b) * Np + op)
                        pi = tl.load(pidx + b * Np + op)
                        dx = qx[:, None] - px[None, :]
                        dy = qy[:, None] - py[None, :]
                        dz = qz[:, None] - pz[None, :]
                        d = (dx * dx + dy * dy) + dz * dz  # (BQ, BP)
                        dmin = tl.min(d, 1)
                        cand = tl.min(tl.where(d == dmin[:, None], pi[None, :], 2147483647), 1)
                        better = (dmin < best) | ((dmin == best) & (cand < bidx))
                        best = tl.where(better, dmin, best)
                        bidx = tl.where(better, cand, bidx)
        tl.store(out + b * Mp + oq, bidx)


@torch.no_grad()
def nearest_indices_grid(points: torch.Tensor, valid: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """Per image, the exact nearest valid point of each query (module docstring).

    points: B x N x 3, valid: B x N bool, queries: B x M x 3 (one device) -> B x M int64 indices
    into N; 0 for an image without a valid point.
    """
    if not usable(points.device):
        raise RuntimeError("the Triton search needs Triton and a CUDA device (or TRITON_INTERPRET=1)")
    return _search(points, valid, queries)


def _search(points: torch.Tensor, valid: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    B, N, _ = points.shape
    M = queries.shape[1]
    dev = queries.device
    if B == 0 or M == 0 or N == 0:
        return torch.zeros(B, M, dtype=torch.int64, device=dev)
    P = points.detach().to(device=dev, dtype=torch.float64)
    Q = queries.detach().to(torch.float64)
    valid = valid.to(device=dev, dtype=torch.bool)
    ps, pidx, boxes, firsts = point_blocks(P, valid)
    qorder = morton_order(Q, torch.ones(B, M, dtype=torch.bool, device=dev))  # (B, M)
    Qs = torch.gather(Q, 1, qorder[..., None].expand(-1, -1, 3))
    mp = math.ceil(M / BQ) * BQ
    Qs = torch.cat([Qs, Qs[:, -1:].expand(B, mp - M, 3)], 1) if mp > M else Qs  # padding repeats the last query
    qs = Qs.permute(2, 0, 1).contiguous()  # (3, B, mp)
    out = torch.empty(B, mp, dtype=torch.int32, device=dev)
    nb = boxes.shape[2]
    _nearest_kernel[(mp // BQ, B)](qs, ps, pidx, boxes, firsts, out, B, mp, nb * BP, nb,
                                   BQ=BQ, BP=BP, CB=CB, MODE=MODE, num_warps=NUM_WARPS)
    res = torch.empty(B, M, dtype=torch.int64, device=dev)
    return res.scatter_(1, qorder, out[:, :M].long())
