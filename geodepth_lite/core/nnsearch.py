"""Exact nearest-point search in torch ops only, batched over images (the device path of the SDF).

For every query of a batch of point clouds (one cloud and one set of queries per image), the
index of the nearest point of its own image's cloud, exactly as a brute force in float64 would
give it, ties broken by the smallest point index. The same code runs on CPU and CUDA tensors
(sort, gather, scatter_reduce, repeat_interleave); it never holds a query x point matrix.

The shape (docs/network_and_losses.md, "The nearest-point search on the device"):

1. **Order.** Each image's points are sorted along a Morton (Z-order) curve of their quantised
   coordinates, so that consecutive points lie close together in space, whatever the cloud (a
   depth map's back-projection, a masked one, a random cloud). The queries are ordered the same
   way and cut into tiles of :data:`TILE` consecutive queries.
2. **A hierarchy of blocks.** Consecutive sorted points form blocks of ``LEVELS[0]`` points, each
   cut into blocks of ``LEVELS[1]``, and so on (each image's sorted points are padded to a
   multiple of ``LEVELS[0]`` by copies of its last point, which change no answer). Each block
   keeps its bounding box and a representative point (one of its own points).
3. **Bounds, level by level.** For a query q and a block B: a lower bound lb(q, B), the squared
   distance from q to B's box, and an upper bound on q's nearest distance, the squared distance
   to B's representative point. Starting from tiles x top-level blocks (the tile's box against
   the block's box, the farthest point of the tile's box from the representative), then queries x
   blocks, each level keeps only the blocks with lb <= ub (ub: the least upper bound so far) and
   goes down to their children. At the last level the surviving blocks' points are compared
   exactly.
4. **Exactness.** Bounds and distances are computed in float64 from per-axis differences, the
   same sum in the same order for the bounds and the final distances, so rounding is monotone:
   the block holding the nearest point always survives (lb <= d <= ub). The final choice is the
   least squared distance, then the least point index among equal distances.

5. **Groups.** The tile stage runs once for the whole batch (tiles x top-level blocks of their
   own image: M/32 x N/1024 pairs per image); the rest runs over groups of whole tiles whose pairs
   fit :data:`PAIR_BUDGET`, a group split in halves wherever a level would pass it.

The work per query grows with the points near its nearest distance, not with the cloud: on the
paper's 320x320 depth maps and 32^3 grids about a hundred point comparisons per query (the
lumen's grid points near the axis, nearly equidistant from a ring of wall points, most of them).
Pathological inputs (every point at the same distance from a query) degrade towards brute
force, in groups of the budget's size, so memory stays bounded.
"""

from __future__ import annotations

import torch

TILE = 32  # queries per tile (consecutive in Morton order)
LEVELS = (1024, 128, 16, 4)  # points per block at each level (each divides the one before)
# most (query, block) or (query, point) pairs held at once, beyond which the tiles are searched in smaller
# groups; None: 2**18 for CPU tensors (working sets that stay in the caches: about 3x faster than 2**24
# on 320x320 maps, 1.2x faster than 2**19), 2**24 on a GPU
PAIR_BUDGET: int | None = None
MORTON_BITS = 10  # bits per axis of the Morton code (30 bits in all)
# The pruning bounds are computed in float32 when points and queries are float32 or narrower (then
# every coordinate is exact in float32), else in float64; the final distances always in float64. A
# bound is a sum of three squared differences of exact inputs: its relative rounding error is below
# 5 * 2**-24 (one rounding per subtraction, square and addition) while no value is subnormal. Upper
# bounds are widened and lower bounds narrowed by far more than that, plus an absolute slack for
# subnormals, so the block holding the nearest point is never pruned.
_UP, _DOWN, _ABS = 1.0 + 2.0**-16, 1.0 - 2.0**-16, 1e-30
_WIDE = _UP / _DOWN * (1.0 + 2.0**-20)  # an upper bound widened for a comparison with an unnarrowed lower bound


def spread_bits(v: torch.Tensor) -> torch.Tensor:
    """Spread the low 10 bits of v (int64) so that two zero bits separate each (Morton interleave)."""
    v = v & 0x3FF
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    v = (v | (v << 2)) & 0x09249249
    return v


def morton_code(q: torch.Tensor) -> torch.Tensor:
    """The Morton code of integer cells q (..., 3, int64, each axis in 0..2**MORTON_BITS - 1): the axes' bits
    interleaved, x lowest."""
    return spread_bits(q[..., 0]) | (spread_bits(q[..., 1]) << 1) | (spread_bits(q[..., 2]) << 2)


def _morton_order(x: torch.Tensor, img: torch.Tensor, n_img: int) -> torch.Tensor:
    """Permutation sorting rows of x (K x 3, float64) by image, then by Morton code within the image's box."""
    big = torch.finfo(x.dtype).max
    lo = torch.full((n_img, 3), big, dtype=x.dtype, device=x.device)
    hi = torch.full((n_img, 3), -big, dtype=x.dtype, device=x.device)
    idx3 = img[:, None].expand(-1, 3)
    lo = lo.scatter_reduce(0, idx3, x, "amin")
    hi = hi.scatter_reduce(0, idx3, x, "amax")
    span = (hi - lo).clamp_min(1e-300)
    q = ((x - lo[img]) / span[img] * (2**MORTON_BITS - 1)).round().long().clamp(0, 2**MORTON_BITS - 1)  # (K, 3)
    code = morton_code(q)
    return torch.argsort(img * (1 << 31) + code, stable=True)


def _ragged_arange(counts: torch.Tensor) -> torch.Tensor:
    """Concatenation of arange(c) for each c of counts (int64)."""
    total = int(counts.sum())
    starts = torch.cumsum(counts, 0) - counts
    return torch.arange(total, device=counts.device) - torch.repeat_interleave(starts, counts, output_size=total)


def _layout(x: torch.Tensor, img: torch.Tensor, n_img: int, multiple: int):
    """Sort x by image and Morton code and pad each image to a multiple of ``multiple`` rows.

    Returns (slots: L, the row of x in each slot (padding repeats the image's last sorted row),
    slot_img: L, image of each slot, img_start: n_img first slot per image, img_len: n_img slots).
    """
    order = _morton_order(x, img, n_img)  # (K,)
    counts = torch.bincount(img, minlength=n_img)  # (n_img,)
    padded = (counts + multiple - 1) // multiple * multiple
    padded = torch.where(counts > 0, padded, torch.zeros_like(padded))
    first = torch.cumsum(counts, 0) - counts  # first sorted row of each image
    slot_img = torch.repeat_interleave(torch.arange(n_img, device=x.device), padded)
    r = _ragged_arange(padded)  # rank of the slot within its image
    src = first[slot_img] + torch.minimum(r, counts[slot_img] - 1)  # padding: the last sorted row
    img_start = torch.cumsum(padded, 0) - padded
    return order[src], slot_img, img_start, padded


def _gap2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared length of the per-axis gaps max(a, b, 0) (3 x P, coordinate-major): with a = lo - q, b = q - hi the
    squared distance from q to the box [lo, hi] (one of a, b is <= 0 on each axis)."""
    g = torch.maximum(a, b).clamp_min_(0)
    return (g * g).sum(0)


def _d2(a: torch.Tensor, b: torch.Tensor, dim: int = -1) -> torch.Tensor:
    d = a - b
    return (d * d).sum(dim)


def _segment_min(values: torch.Tensor, seg: torch.Tensor, n: int) -> torch.Tensor:
    out = torch.full((n,), float("inf"), dtype=values.dtype, device=values.device)
    return out.scatter_reduce(0, seg, values, "amin")


@torch.no_grad()
def nearest_indices_batched(points: torch.Tensor, point_img: torch.Tensor, queries: torch.Tensor,
                            query_img: torch.Tensor, n_img: int | None = None) -> torch.Tensor:
    """Exact nearest point of each query among the points of the same image.

    points: N x 3, point_img: N image ids (int64, 0 <= id < n_img); queries: M x 3, query_img: M.
    Returns M indices into ``points`` (int64, on the queries' device): the point of the query's
    image at the least float64 Euclidean distance, the least index among equal distances; -1 for
    a query whose image has no point.
    """
    dev = queries.device
    if n_img is None:
        n_img = int(max(int(point_img.max()) if point_img.numel() else -1,
                        int(query_img.max()) if query_img.numel() else -1)) + 1
    out = torch.full((queries.shape[0],), -1, dtype=torch.int64, device=dev)
    if queries.shape[0] == 0 or points.shape[0] == 0:
        return out
    pimg, qimg = point_img.to(dev).long(), query_img.to(dev).long()
    keep_q = (torch.bincount(pimg, minlength=n_img) > 0)[qimg]
    if not bool(keep_q.all()):  # queries of images without points: -1
        sel = keep_q.nonzero().squeeze(1)
        if sel.numel():
            out[sel] = nearest_indices_batched(points, pimg, queries[sel], qimg[sel], n_img)
        return out
    return _Search(points, pimg, queries, qimg, n_img).run()


class _Search:
    """One batched search (:func:`nearest_indices_batched`): the sorted, blocked points, the tiled
    queries, and the descent over groups of tiles."""

    def __init__(self, points, pimg, queries, qimg, n_img: int):
        dev = self.dev = queries.device
        narrow = (torch.float32, torch.float16, torch.bfloat16)
        bdt = self.bdt = torch.float32 if points.dtype in narrow and queries.dtype in narrow else torch.float64
        P = points.detach().to(device=dev, dtype=torch.float64)
        Q = queries.detach().to(dtype=torch.float64)
        self.budget = PAIR_BUDGET if PAIR_BUDGET is not None else (2**18 if dev.type == "cpu" else 2**24)
        # points: sorted, padded, blocked
        self.pslot, _, self.pstart, self.plen = _layout(P, pimg, n_img, LEVELS[0])
        self.PX = P[self.pslot]  # (L, 3) sorted points
        PX32 = self.PX.to(bdt)
        self.PX32T = PX32.T.contiguous()  # (3, L)
        self.levels = []
        for S in LEVELS:
            blocks = PX32.view(-1, S, 3)
            # coordinate-major (9, nb): lo, hi, representative; gathered by column, every row stays contiguous
            self.levels.append(torch.cat([blocks.amin(1), blocks.amax(1), blocks[:, S // 2]], 1).T.contiguous())
        # queries: sorted, padded to tiles
        self.qslot, qslot_img, _, _ = _layout(Q, qimg, n_img, TILE)
        self.QX = Q[self.qslot]  # (Lq, 3)
        QX32 = self.QX.to(bdt)
        tiles = QX32.view(-1, TILE, 3)
        self.t_box = torch.cat([tiles.amin(1), tiles.amax(1)], 1).T.contiguous()  # (6, T): lo, hi
        self.QT = QX32.T.contiguous()  # (3, Lq)
        self.tile_img = qslot_img[::TILE]  # (T,)
        self.best = torch.empty(self.QX.shape[0], dtype=torch.int64, device=dev)  # nearest per padded query

    def tile_stage(self):
        """Tiles x top-level blocks of the same image, kept where the boxes' gap is within the tile's
        bound: (pt, pb) ordered by tile, and each tile's bound (T,)."""
        dev, S0 = self.dev, LEVELS[0]
        T = self.t_box.shape[1]
        nb = self.plen[self.tile_img] // S0  # (T,) top blocks per tile
        pt = torch.repeat_interleave(torch.arange(T, device=dev), nb)  # (pairs,) tile
        pb = self.pstart[self.tile_img[pt]] // S0 + _ragged_arange(nb)  # (pairs,) block
        blk = self.levels[0].index_select(1, pb)  # (9, pairs)
        tb = self.t_box.index_select(1, pt)  # (6, pairs)
        lb = _gap2(blk[0:3] - tb[3:6], tb[0:3] - blk[3:6])  # box-box gap
        rep = blk[6:9]
        far = torch.maximum((rep - tb[0:3]).abs(), (rep - tb[3:6]).abs())
        ub_tile = _segment_min((far * far).sum(0), pt, T) * _UP + _ABS  # (T,) bound for every query of a tile
        keep = (lb * _DOWN <= ub_tile.index_select(0, pt)).nonzero().squeeze(1)
        return pt.index_select(0, keep), pb.index_select(0, keep), ub_tile

    def run(self) -> torch.Tensor:
        pt, pb, self.ub_tile = self.tile_stage()
        T, dev = self.ub_tile.shape[0], self.dev
        # groups of whole tiles whose level-0 query pairs fit the budget
        cum = torch.cumsum(torch.bincount(pt, minlength=T) * TILE, 0)  # (T,)
        bounds = [0]
        while bounds[-1] < T:
            base = int(cum[bounds[-1] - 1]) if bounds[-1] > 0 else 0
            nxt = int(torch.searchsorted(cum, torch.tensor([base + self.budget], device=dev, dtype=cum.dtype),
                                         right=True))
            bounds.append(min(T, max(nxt, bounds[-1] + 1)))
        starts = torch.searchsorted(pt, torch.tensor(bounds, device=dev, dtype=pt.dtype))
        for i in range(len(bounds) - 1):
            s0, s1 = int(starts[i]), int(starts[i + 1])
            self.descend(bounds[i], bounds[i + 1], pt[s0:s1], pb[s0:s1])
        out = torch.empty(self.best.shape[0], dtype=torch.int64, device=dev)
        # padded query slots repeat a real query: writing all slots gives each real query its answer
        out[self.qslot] = self.best
        return out[:int(self.qslot.max()) + 1]

    def split(self, t0: int, t1: int, pt: torch.Tensor, pb: torch.Tensor) -> None:
        h = (t0 + t1) // 2
        c = int(torch.searchsorted(pt, torch.tensor([h], device=self.dev, dtype=pt.dtype)))
        self.descend(t0, h, pt[:c], pb[:c])
        self.descend(h, t1, pt[c:], pb[c:])

    def descend(self, t0: int, t1: int, pt: torch.Tensor, pb0: torch.Tensor) -> None:
        """Tiles t0..t1-1 (their level-0 pairs pt, pb0) down to their queries' nearest points, in halves
        while the pairs held at once would pass the budget."""
        dev, n = self.dev, (t1 - t0) * TILE  # local query slots
        if t1 - t0 > 1 and pt.numel() * TILE > self.budget:
            return self.split(t0, t1, pt, pb0)
        QTc = self.QT[:, t0 * TILE:t1 * TILE]
        pq = ((pt - t0)[:, None] * TILE + torch.arange(TILE, device=dev)).reshape(-1)  # (pairs,) local slot
        pb = pb0.repeat_interleave(TILE)
        ubq = self.ub_tile[t0:t1].repeat_interleave(TILE) / _DOWN  # (n,) the tile's bound to start with
        for li, S in enumerate(LEVELS):
            if li > 0:  # children of the surviving blocks
                r = LEVELS[li - 1] // S
                if t1 - t0 > 1 and pq.numel() * r > self.budget:
                    return self.split(t0, t1, pt, pb0)
                pq = pq.repeat_interleave(r)
                pb = (pb[:, None] * r + torch.arange(r, device=dev)).reshape(-1)
            q = QTc.index_select(1, pq)  # (3, pairs)
            blk = self.levels[li].index_select(1, pb)  # (9, pairs)
            r3 = blk[6:9] - q
            # ubq holds the bound already widened by _UP / _DOWN: lb <= ubq is lb * _DOWN <= ub * _UP
            ubq = torch.minimum(ubq, _segment_min((r3 * r3).sum(0), pq, n) * _WIDE + _ABS)
            keep = (_gap2(blk[0:3] - q, q - blk[3:6]) <= ubq.index_select(0, pq)).nonzero().squeeze(1)
            pq, pb = pq.index_select(0, keep), pb.index_select(0, keep)
        self.best[t0 * TILE:t1 * TILE] = self.exact(pq, pb, QTc, t0 * TILE, n)

    def exact(self, pq, pb, QTc, first: int, n: int) -> torch.Tensor:
        """The surviving last-level blocks' points: a float32 (or float64) pass keeps those within the
        rounding margin of each query's least distance, then the exact float64 choice among them, ties
        to the least original index. Returns n original point indices."""
        S = LEVELS[-1]
        pq = pq.repeat_interleave(S)
        ps = (pb[:, None] * S + torch.arange(S, device=self.dev)).reshape(-1)  # sorted point slots
        d = _d2(self.PX32T.index_select(1, ps), QTc.index_select(1, pq), 0)
        keep = (d * _DOWN <= _segment_min(d, pq, n).index_select(0, pq) * _UP + _ABS).nonzero().squeeze(1)
        pq, ps = pq.index_select(0, keep), ps.index_select(0, keep)
        d = _d2(self.PX.index_select(0, ps), self.QX.index_select(0, pq + first))
        dmin = _segment_min(d, pq, n)
        orig = self.pslot.index_select(0, ps)  # original point index (padding slots repeat a real point)
        big = torch.iinfo(torch.int64).max
        cand = torch.where(d == dmin.index_select(0, pq), orig, torch.full_like(orig, big))
        return torch.full((n,), big, dtype=torch.int64, device=self.dev).scatter_reduce(0, pq, cand, "amin")


def nearest_indices(points: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """One cloud: the exact nearest point of each query (points: N x 3, queries: M x 3 -> M int64)."""
    zp = torch.zeros(points.shape[0], dtype=torch.int64, device=queries.device)
    zq = torch.zeros(queries.shape[0], dtype=torch.int64, device=queries.device)
    return nearest_indices_batched(points, zp, queries, zq, 1)
