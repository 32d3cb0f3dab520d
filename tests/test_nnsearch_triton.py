"""The fused Triton search (geodepth_lite/core/nnsearch_triton.py) against a float64 brute force.

On a CUDA machine tests/test_cuda.py runs it at the paper's size. Here, where Triton is installed (it
ships with CUDA builds of torch, not with the CPU build), the kernel runs in Triton's interpreter on
CPU tensors (``TRITON_INTERPRET=1``, in a child process: the variable is read when Triton compiles).
"""

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from geodepth_lite.core import camera, nnsearch_triton, sdf
from geodepth_lite.data import analytic

ROOT = Path(__file__).resolve().parents[1]


def brute_nearest(P: torch.Tensor, V: torch.Tensor, Q: torch.Tensor) -> torch.Tensor:
    """The definition: per image, the valid point at the least (dx*dx + dy*dy) + dz*dz in float64, the
    least index among equal distances; 0 for an image without a valid point."""
    out = torch.zeros(Q.shape[:2], dtype=torch.int64)
    for b in range(P.shape[0]):
        d = Q[b].double()[:, None, :] - P[b].double()[None, :, :]
        d2 = (d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) + d[..., 2] * d[..., 2]
        d2[:, ~V[b].cpu()] = float("inf")
        if bool(V[b].any()):
            least = d2.min(1, keepdim=True).values
            out[b] = torch.where(d2 == least, torch.arange(P.shape[1])[None, :], P.shape[1]).min(1).values
    return out


def mismatches(got: torch.Tensor, P, V, Q) -> int:
    """Queries whose index differs from the brute force's."""
    return int((got.cpu() != brute_nearest(P.cpu(), V.cpu(), Q.cpu())).sum())


def small_batch(size: int = 20):
    """Three back-projected analytic-like maps with masked pixels, ties (depths and queries on a
    coarse lattice) and one image without a valid point."""
    g = torch.Generator().manual_seed(3)
    depth = 1 + torch.rand(3, 1, size, size, generator=g)
    depth[1] = torch.round(depth[1] * 4) / 4  # many equal distances
    K = torch.tensor([[20.0, 0, size / 2], [0, 20.0, size / 2], [0, 0, 1]])
    P = camera.backproject(depth, K).float()
    V = torch.rand(3, size * size, generator=g) > 0.2
    V[2] = False
    Q = (torch.rand(3, 150, 3, generator=g) * torch.tensor([1.0, 1.0, 2.0]) - torch.tensor([0.5, 0.5, 0.0])).float()
    Q[1] = torch.round(Q[1] * 8) / 8
    return P, V, Q


def test_brute_force_reference_breaks_ties_by_the_least_index_and_skips_invalid_points():
    P = torch.tensor([[[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 0.5], [3.0, 0, 0]]])
    Q = torch.zeros(1, 1, 3)
    assert brute_nearest(P, torch.tensor([[True, True, False, True]]), Q).tolist() == [[0]]  # tie 0/1: 0
    assert brute_nearest(P, torch.tensor([[False, True, True, True]]), Q).tolist() == [[2]]
    assert brute_nearest(P, torch.tensor([[False, False, False, False]]), Q).tolist() == [[0]]


def test_tile_setting_is_checked():
    assert nnsearch_triton.parse_tile("32,64,16,4") == (32, 64, 16, 4, 0)
    assert nnsearch_triton.parse_tile("16,32,32,2,1") == (16, 32, 32, 2, 1)
    for bad in ("32,64,16", "33,64,16,4", "32,64,16,32", "4,64,16,4", "a,b,c,d", "32,512,16,4", "16,32,32,2,2"):
        with pytest.raises(ValueError, match=nnsearch_triton.TILE_ENV):
            nnsearch_triton.parse_tile(bad)


def test_triton_is_asked_for_only_where_it_runs():
    P, V, Q = small_batch(8)
    assert sdf.resolve_method("auto", torch.device("cpu")) == "kdtree"
    if not nnsearch_triton.usable(torch.device("cpu")):
        with pytest.raises(ValueError, match="triton search needs Triton"):
            sdf.nearest_indices_grid(P, V, Q, "triton")


def _interpreted_check() -> None:
    """Run in a child process with TRITON_INTERPRET=1: the kernel on CPU tensors, exact against the
    brute force; then a planted wrong answer (one query's index moved to its second-nearest point)
    is caught by the same comparison."""
    P, V, Q = small_batch()
    got = sdf.nearest_indices_grid(P, V, Q, "triton")
    assert got.dtype == torch.int64 and got.shape == Q.shape[:2]
    assert mismatches(got, P, V, Q) == 0
    assert got[2].eq(0).all()  # the image without a valid point
    wrong = got.clone()
    d = ((Q[0, 0].double() - P[0].double()) ** 2).sum(1)
    d[~V[0]] = float("inf")
    wrong[0, 0] = int(d.argsort()[1])
    assert mismatches(wrong, P, V, Q) == 1
    # a larger tile than the points of an image, and analytic views at 24 px: the same answers
    nnsearch_triton.BQ, nnsearch_triton.BP, nnsearch_triton.CB, nnsearch_triton.NUM_WARPS = 64, 64, 8, 4
    nnsearch_triton.MODE = 1  # the chunk's bound for its blocks
    d = torch.stack([torch.from_numpy(analytic.depth_map(k, 24, seed=i))[None] for i, k in enumerate(analytic.KINDS)])
    S = camera.backproject(d, torch.from_numpy(analytic.intrinsics(24)).float())
    q = torch.stack([sdf.grid_points(s.min(0).values, s.max(0).values, 6) for s in S])
    Vs = torch.ones(S.shape[:2], dtype=torch.bool)
    assert mismatches(sdf.nearest_indices_grid(S, Vs, q, "triton"), S, Vs, q) == 0
    # queries beside and beyond the clouds, where the blocks' boxes lie apart and pruning decides
    far = q * torch.tensor([3.0, 3.0, 1.0]) + torch.tensor([0.0, 0.0, 1.5]) * q[..., 2:].amax(1, keepdim=True)
    assert mismatches(sdf.nearest_indices_grid(S, Vs, far, "triton"), S, Vs, far) == 0
    print("interpreted kernel: exact")


@pytest.mark.skipif(importlib.util.find_spec("triton") is None, reason="Triton is not installed (CPU torch)")
def test_the_kernel_in_tritons_interpreter_equals_the_brute_force():
    env = dict(os.environ, TRITON_INTERPRET="1", PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, __file__], capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "interpreted kernel: exact" in proc.stdout


if __name__ == "__main__":
    _interpreted_check()
