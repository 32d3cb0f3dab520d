"""The exact batched nearest-point search of the device path (geodepth_lite.core.nnsearch), on CPU tensors,
against scipy's cKDTree and a float64 brute force (ties: the least point index)."""

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from geodepth_lite.core import camera, nnsearch, sdf
from geodepth_lite.data import analytic


def _brute(points: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """float64 brute force, the least index among equal least distances (argmin takes the first)."""
    d = ((queries.double()[:, None, :] - points.double()[None, :, :]) ** 2).sum(-1)  # (M, N), small tests only
    return d.argmin(1)


def _kdtree(points: torch.Tensor, queries: torch.Tensor) -> np.ndarray:
    return cKDTree(points.double().numpy()).query(queries.double().numpy(), workers=1)[1]


def _depth_cloud(kind: str, size: int, seed: int):
    d = torch.from_numpy(analytic.depth_map(kind, size, seed=seed))[None, None]
    K = torch.from_numpy(analytic.intrinsics(size)).float()
    P = camera.backproject(d, K)[0]  # (N, 3) float32, as the SDF loss builds it
    return P, sdf.grid_points(P.min(0).values, P.max(0).values, 16)


@pytest.mark.parametrize("n,m,dtype", [(1, 5, torch.float32), (7, 300, torch.float64), (3000, 2000, torch.float32),
                                       (5000, 1000, torch.float64)])
def test_random_clouds_match_kdtree(n, m, dtype):
    g = torch.Generator().manual_seed(n)
    p = torch.rand(n, 3, generator=g, dtype=dtype)
    q = torch.rand(m, 3, generator=g, dtype=dtype) * 1.4 - 0.2  # some queries outside the cloud's box
    got = nnsearch.nearest_indices(p, q)
    assert got.dtype == torch.int64 and got.shape == (m,)
    assert np.array_equal(got.numpy(), _kdtree(p, q))


@pytest.mark.parametrize("kind", analytic.KINDS)
def test_depth_map_surfaces_match_kdtree_on_every_query(kind):
    P, q = _depth_cloud(kind, 96, seed=3)
    assert np.array_equal(nnsearch.nearest_indices(P, q).numpy(), _kdtree(P, q))


def test_a_batch_searches_each_image_in_its_own_cloud():
    clouds = [_depth_cloud(k, 64, seed=i) for i, k in enumerate(analytic.KINDS)]
    pts = torch.cat([c[0] for c in clouds])
    qs = torch.cat([c[1] for c in clouds])
    pimg = torch.cat([torch.full((len(c[0]),), i) for i, c in enumerate(clouds)])
    qimg = torch.cat([torch.full((len(c[1]),), i) for i, c in enumerate(clouds)])
    got = nnsearch.nearest_indices_batched(pts, pimg, qs, qimg)
    offset = 0
    q0 = 0
    for P, q in clouds:
        want = _kdtree(P, q) + offset
        assert np.array_equal(got[q0:q0 + len(q)].numpy(), want)
        offset += len(P)
        q0 += len(q)
    # a wrong image assignment gives other answers: the comparison can fail
    wrong = nnsearch.nearest_indices_batched(pts, torch.zeros_like(pimg), qs, torch.zeros_like(qimg))
    assert not torch.equal(wrong, got)


def test_an_image_without_points_answers_minus_one():
    p = torch.rand(10, 3)
    got = nnsearch.nearest_indices_batched(p, torch.zeros(10, dtype=torch.int64), torch.rand(4, 3),
                                           torch.tensor([0, 1, 1, 0]), 2)
    assert got[1] == got[2] == -1 and got[0] >= 0 and got[3] >= 0


def test_exact_ties_on_a_lattice_take_the_least_index():
    # lattice points 0..4 on each axis; queries at cell centres and edge midpoints: 8 or 2 points at equal distances
    ax = torch.arange(5.0)
    p = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    perm = torch.randperm(len(p), generator=torch.Generator().manual_seed(0))
    p = p[perm]  # the least index is not the first lattice point
    c = torch.arange(4.0) + 0.5
    q = torch.cat([torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3),
                   torch.tensor([[0.5, 0.0, 0.0], [2.0, 1.5, 3.0], [4.0, 4.0, 3.5]])])
    got = nnsearch.nearest_indices(p, q)
    assert torch.equal(got, _brute(p, q))
    d = ((q[:, None] - p[None]) ** 2).sum(-1)
    ties = (d == d.min(1, keepdim=True).values).sum(1)
    assert int(ties.min()) >= 2  # every query is a tie, so the rule is exercised
    # the tie rule is the least index: the largest tied index differs
    last = torch.where(d == d.min(1, keepdim=True).values, torch.arange(len(p)), -1).max(1).values
    assert not torch.equal(got, last)
    # cKDTree reaches the same distance
    kd = _kdtree(p, q)
    assert torch.equal(d[torch.arange(len(q)), got], d[torch.arange(len(q)), torch.from_numpy(kd)])


def test_near_ties_are_decided_by_the_float64_distance():
    # two points whose distances from the query differ in the last bits of float32
    q = torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float32)
    a = torch.tensor([[1.0, 0.0, 0.0]])
    b = torch.tensor([[0.0, float(np.nextafter(np.float32(1.0), np.float32(2.0))), 0.0]])
    for pts, want in ((torch.cat([b, a]), 1), (torch.cat([a, b]), 0)):
        assert int(nnsearch.nearest_indices(pts, q)[0]) == want
        assert int(_kdtree(pts, q)[0]) == want


def test_queries_far_outside_the_surface():
    P, _ = _depth_cloud("lumen", 64, seed=1)
    g = torch.Generator().manual_seed(1)
    q = (torch.rand(500, 3, generator=g) - 0.5) * 1e4  # metres away, all sides, behind the camera too
    assert np.array_equal(nnsearch.nearest_indices(P, q).numpy(), _kdtree(P, q))


def test_equidistant_points_stay_exact_within_the_pair_budget(monkeypatch):
    # every point on a sphere around the query: no pruning is possible; a small budget splits the tiles
    monkeypatch.setattr(nnsearch, "PAIR_BUDGET", 4096)
    t = torch.linspace(0, 6.0, 600, dtype=torch.float64)
    p = torch.stack([torch.cos(t) * torch.cos(3 * t), torch.sin(t) * torch.cos(3 * t), torch.sin(3 * t)], 1)
    q = torch.cat([torch.zeros(1, 3, dtype=torch.float64), torch.rand(200, 3, dtype=torch.float64)])
    assert torch.equal(nnsearch.nearest_indices(p, q), _brute(p, q))


def test_analytic_views_and_their_dataset(tmp_path):
    from geodepth_lite import utils
    from geodepth_lite.data import datasets, integrity

    for kind in analytic.KINDS:
        d = analytic.depth_map(kind, 48, seed=2)
        assert d.shape == (48, 48) and d.dtype == np.float32 and np.isfinite(d).all() and d.min() > 0
        assert np.array_equal(d, analytic.depth_map(kind, 48, seed=2))  # reproducible
        assert not np.array_equal(d, analytic.depth_map(kind, 48, seed=3))
    # the lumen's far centre is deeper than its rim
    lumen = analytic.depth_map("lumen", 48, seed=0)
    assert np.median(lumen[20:28, 20:28]) > 2 * np.median(np.concatenate([lumen[0], lumen[-1]]))
    root = analytic.write_dataset(tmp_path / "d", {"train": 3, "val": 1, "test": 1}, size=32)
    assert integrity.verify(root) == []
    item = datasets.SyntheticDepthDataset(root, "train")[2]
    assert item["image"].shape == (3, 32, 32) and item["depth"].shape == (1, 32, 32) and item["organ"] == "closeup"
    with pytest.raises(utils.FileProblem, match="not empty"):
        analytic.write_dataset(root, {"train": 1}, size=32)
    # written by three processes, the folder is byte-identical (each frame depends on its index alone)
    par = analytic.write_dataset(tmp_path / "p", {"train": 3, "val": 1, "test": 1}, size=32, workers=3)
    files = sorted(f.relative_to(root) for f in root.rglob("*") if f.is_file())
    assert files == sorted(f.relative_to(par) for f in par.rglob("*") if f.is_file()) and len(files) > 10
    assert all((root / f).read_bytes() == (par / f).read_bytes() for f in files)
