"""Known-answer tests of the five losses (Sec. 3.C) and of the exact nearest-neighbour search."""

import math

import numpy as np
import pytest
import torch

from geodepth_lite.core import camera, sdf
from geodepth_lite.core import losses as L
from geodepth_lite.core.errors import UserError
from geodepth_lite.core.losses import LossSpec, SDFOptions

K32 = camera.intrinsics(32)


def smooth_depth(B=2, H=16, W=16, seed=0, dtype=torch.float64):
    """A smooth positive depth map with some structure (a bump on a tilted plane)."""
    g = torch.Generator().manual_seed(seed)
    v, u = torch.meshgrid(torch.linspace(-1, 1, H, dtype=dtype), torch.linspace(-1, 1, W, dtype=dtype), indexing="ij")
    c = torch.rand(B, 3, generator=g, dtype=dtype)
    d = 2.0 + c[:, :1, None] * u + 0.5 * c[:, 1:2, None] * v + torch.exp(-4 * (u**2 + v**2)) * c[:, 2:3, None]
    return d[:, None] if d.dim() == 3 else d.unsqueeze(1)


def plane(z, B=1, H=32, W=32, dtype=torch.float64):
    return torch.full((B, 1, H, W), float(z), dtype=dtype)


# ----------------------------------------------------------------------------- zero for identical inputs
def test_every_loss_is_zero_for_identical_inputs():
    d = smooth_depth(2, 16, 16).reshape(2, 1, 16, 16)
    img = torch.rand(2, 3, 16, 16, dtype=torch.float64)
    K = camera.intrinsics(16)
    assert L.depth_loss(d, d.clone()) == 0
    assert L.gradient_loss(d, d.clone()) == 0
    assert L.normal_loss(d, d.clone()) < 1e-15  # 1 - cos(0) up to rounding
    assert L.sdf_loss(d, d.clone(), K, SDFOptions(grid=8)) == 0
    assert L.smoothness_loss(plane(3.0, 2, 16, 16), img) == 0  # a constant depth has no gradient
    loss, terms = L.total_loss(d, d.clone(), img, K, LossSpec(sdf=SDFOptions(grid=8)))
    assert terms["depth"] == terms["grad"] == terms["sdf"] == 0 and terms["normal"] < 1e-15
    assert math.isclose(terms["total"], terms["smooth"]) and math.isclose(float(loss), terms["total"])


def test_gradient_loss_ignores_a_constant_offset():
    d = smooth_depth(2, 16, 16).reshape(2, 1, 16, 16)
    assert L.gradient_loss(d + 0.37, d) < 1e-12
    assert L.normal_loss(d + 0.37, d) < 1e-12
    assert abs(float(L.depth_loss(d + 0.37, d)) - 0.37) < 1e-12


@pytest.mark.parametrize("a", [0.1, 0.5, 2.0])
def test_normal_loss_of_a_slope_against_a_flat_plane(a):
    H = W = 12
    u = torch.arange(W, dtype=torch.float64).expand(H, W)
    tilted = (3.0 + a * u)[None, None]
    flat = plane(3.0, 1, H, W)
    per_pixel, valid = L.normal_map(tilted, flat)
    assert valid.all()
    expected = 1 - 1 / math.sqrt(1 + a * a)
    assert torch.allclose(per_pixel, torch.full_like(per_pixel, expected), atol=1e-12)
    assert math.isclose(float(L.normal_loss(tilted, flat)), expected, rel_tol=1e-12)
    # the gradient loss of the same pair: |a| per pixel along x, nothing along y
    assert math.isclose(float(L.gradient_loss(tilted, flat)), a, rel_tol=1e-12)


def test_smoothness_loss_known_value_and_edge_weighting():
    H = W = 8
    u = torch.arange(W, dtype=torch.float64).expand(H, W)
    ramp = (2.0 + 0.1 * u)[None, None]
    flat_img = torch.zeros(1, 3, H, W, dtype=torch.float64)
    # x differences all 0.1, weight e^0 = 1: mean 0.01; y differences 0
    assert math.isclose(float(L.smoothness_loss(ramp, flat_img)), 0.01, rel_tol=1e-12)
    edgy = flat_img.clone()
    edgy[..., :, 1::2] = 1.0  # every x step of the image has |grad I| = 1
    assert math.isclose(float(L.smoothness_loss(ramp, edgy)), 0.01 * math.exp(-2), rel_tol=1e-12)


# ----------------------------------------------------------------------------- SDF
def test_sdf_of_fronto_parallel_planes_grows_one_for_one_with_offset():
    gt = plane(2.0)
    losses_at = {dz: float(L.sdf_loss(plane(2.0 + dz), gt, K32, SDFOptions(grid=8))) for dz in (0.5, 1.0, 1.5)}
    # each loss is the offset plus a small pixel-sampling constant
    assert abs(losses_at[1.0] - losses_at[0.5] - 0.5) < 0.01
    assert abs(losses_at[1.5] - losses_at[1.0] - 0.5) < 0.01
    assert abs(losses_at[1.0] - 1.0) < 0.05


def test_signed_distance_sign_convention():
    # a fronto-parallel plane z = 2 sampled on a grid of points
    xs = torch.linspace(-1, 1, 21, dtype=torch.float64)
    X, Y = torch.meshgrid(xs, xs, indexing="ij")
    pts = torch.stack((X.flatten(), Y.flatten(), torch.full((441,), 2.0, dtype=torch.float64)), -1)
    q = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 3.5], [0.5, -0.5, 2.0], [0.3, 0.2, 1.75]], dtype=torch.float64)
    sd = sdf.signed_distance(pts, q)
    # in front of the surface (camera side) positive, behind negative, on it zero
    assert torch.allclose(sd, torch.tensor([1.0, -1.5, 0.0, 0.25], dtype=torch.float64), atol=1e-12)
    assert torch.allclose(sdf.signed_distance(pts, q, signed=False), sd.abs())


def reference_view_sign(D, K, q):
    """Paper's sign by hand: project q, round to the nearest pixel, compare q_z with D there.

    D: H x W numpy (all valid), q: M x 3 -> (sign, known); unknown where q_z <= 0 or outside."""
    H, W = D.shape
    sign, known = np.zeros(len(q)), np.zeros(len(q), dtype=bool)
    for i, (x, y, z) in enumerate(q):
        if z <= 0:
            continue
        u, v = int(np.rint(K[0, 0] * x / z + K[0, 2])), int(np.rint(K[1, 1] * y / z + K[1, 2]))
        if 0 <= u < W and 0 <= v < H:
            sign[i], known[i] = np.sign(D[v, u] - z), True
    return sign, known


def reference_sdf_loss(pred, gt, K, r, signed=True, sign="view"):
    """Independent numpy brute force of Eqs. 9-10 with the +X_lb grid; ``sign``: "view" (the paper's
    projection rule, nearest-direction fallback outside the image) or "nearest" (direction to the
    nearest point everywhere)."""
    out = []
    for b in range(pred.shape[0]):
        Dp, Dg = pred[b, 0].numpy(), gt[b, 0].numpy()
        P = camera.backproject(Dp, K).reshape(-1, 3)
        G = camera.backproject(Dg, K).reshape(-1, 3)
        lo, hi = G.min(0), G.max(0)
        t = np.linspace(0, 1, r)
        grid = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3) * (hi - lo) + lo

        def field(S, D):
            d = np.linalg.norm(S[None] - grid[:, None], axis=-1)
            n = d.argmin(1)
            if not signed:
                return d.min(1)
            s = np.sign(np.einsum("ij,ij->i", S[n] - grid, S[n]))
            if sign == "view":
                vs, known = reference_view_sign(D, K, grid)
                s = np.where(known, vs, s)
            return s * d.min(1)

        out.append(np.abs(field(P, Dp) - field(G, Dg)).mean())
    return float(np.mean(out))


def step_depth(H=16, W=16, near=1.03, far=2.97):
    d = torch.full((1, 1, H, W), far, dtype=torch.float64)
    d[..., : W // 2] = near
    return d


def test_signed_and_unsigned_fields_give_different_losses():
    K = camera.intrinsics(16)
    K[0, 2], K[1, 2] = 7.3, 6.6  # off-centre: no exact distance ties
    gt = step_depth()  # a step: the grid spans both sides of each half of the surface
    pred = plane(2.01, 1, 16, 16)  # a flat wall halfway between
    signed = float(L.sdf_loss(pred, gt, K, SDFOptions(grid=6)))
    unsigned = float(L.sdf_loss(pred, gt, K, SDFOptions(grid=6, signed=False)))
    assert math.isclose(signed, reference_sdf_loss(pred, gt, K, 6), rel_tol=1e-9)
    assert math.isclose(unsigned, reference_sdf_loss(pred, gt, K, 6, signed=False), rel_tol=1e-9)
    assert signed > unsigned + 0.1  # points between the surfaces: the signs disagree


# the step of step_depth(near=1, far=3) seen with K = intrinsics(16) (fx = fy = 8.8896, cx = cy = 8):
# columns u <= 7 at z = 1, u >= 8 at z = 3; the far wall's innermost point on row 8 is (0, 0, 3)
K16 = camera.intrinsics(16)
Q_BEHIND_NEAR = [-0.2, 0.0, 2.4]  # projects to u = 7.26 -> 7 (D = 1): behind the near step
Q_AHEAD_FAR = [0.1, 0.0, 1.2]  # projects to u = 8.74 -> 9 (D = 3): in the open, ahead of the far wall


def test_view_sign_differs_from_nearest_direction_behind_a_step_edge():
    D = step_depth(near=1.0, far=3.0)[0, 0]
    pts = camera.backproject(D, K16).reshape(-1, 3)
    q = torch.tensor([Q_BEHIND_NEAR, Q_AHEAD_FAR], dtype=torch.float64)
    view = sdf.signed_distance(pts, q, depth=D, K=K16)
    old = sdf.signed_distance(pts, q)
    # q1: nearest point (0, 0, 3) on the far wall, distance sqrt(0.2^2 + 0.6^2); the old rule
    # calls it ahead ((X_n - q) . X_n = 1.8 > 0), the paper's behind (q_z = 2.4 > D = 1)
    # q2: nearest point (-1/fx, 0, 1), the near step's edge; (X_n - q) . X_n < 0 but q_z = 1.2 < D = 3
    x7 = -1.0 / K16[0, 0]
    d2 = math.hypot(x7 - 0.1, 0.2)
    assert torch.allclose(view, torch.tensor([-math.sqrt(0.4), d2], dtype=torch.float64), atol=1e-12)
    assert torch.allclose(old, -view, atol=1e-12)
    # the numpy reference rule agrees; unsigned magnitudes are unchanged
    sign, known = reference_view_sign(D.numpy(), K16, q.numpy())
    assert known.all() and (sign == [-1.0, 1.0]).all()
    assert torch.allclose(sdf.signed_distance(pts, q, signed=False, depth=D, K=K16), view.abs())


def test_view_sign_falls_back_to_nearest_direction_off_the_image():
    D = step_depth(near=1.0, far=3.0)[0, 0]
    pts = camera.backproject(D, K16).reshape(-1, 3)
    # right of the image (u = 30.2), behind the camera, and onto a masked pixel (u = 7, D = 1)
    q = torch.tensor([[5.0, 0.0, 2.0], [0.0, 0.0, -1.0], Q_BEHIND_NEAR], dtype=torch.float64)
    valid = torch.ones(16, 16, dtype=torch.bool)
    valid[8, 7] = False
    view = sdf.signed_distance(pts, q, depth=D, K=K16, valid=valid)
    assert torch.equal(view, sdf.signed_distance(pts, q))  # all three: the nearest-direction sign
    # q1's nearest point is the far wall's last column (3 * 7/fx, 0, 3): (X_n - q) . X_n < 0
    x15 = 3 * 7 / K16[0, 0]
    assert math.isclose(float(view[0]), -math.hypot(5.0 - x15, 1.0), rel_tol=1e-12)
    assert float(view[1]) > 0  # behind the camera: the camera side of the surface at X_n
    assert float(view[2]) > 0  # Q_BEHIND_NEAR on a masked pixel: the nearest rule's +
    _, known = reference_view_sign(D.numpy(), K16, q.numpy()[:2])
    assert not known.any()


def test_sdf_loss_between_step_edges_follows_the_view_sign():
    K = K16.copy()
    K[0, 2], K[1, 2] = 7.3, 6.6  # off-centre: no exact distance ties
    gt = step_depth(near=1.0, far=3.0)
    pred = step_depth(near=1.4, far=2.5)
    pred[..., :, 5:8] = 2.5  # the edge moved left by three columns
    for method in ("kdtree", "chunked", "device"):
        view = float(L.sdf_loss(pred, gt, K, SDFOptions(grid=6, method=method, cache=None)))
        old = float(L.sdf_loss(pred, gt, K, SDFOptions(grid=6, method=method, cache=None, sign_rule="nearest")))
        assert math.isclose(view, reference_sdf_loss(pred, gt, K, 6), rel_tol=1e-9)
        assert math.isclose(old, reference_sdf_loss(pred, gt, K, 6, sign="nearest"), rel_tol=1e-9)
        assert abs(view - old) > 0.05
    # the two rules key different cached ground-truth fields
    cache = sdf.GTFieldCache()
    L.sdf_loss(pred, gt, K, SDFOptions(grid=6, cache=cache))
    L.sdf_loss(pred, gt, K, SDFOptions(grid=6, cache=cache, sign_rule="nearest"))
    assert (cache.misses, cache.hits, len(cache)) == (2, 0, 2)
    with pytest.raises(ValueError, match="sign_rule"):
        SDFOptions(grid=6, sign_rule="camera")


def test_sdf_loss_matches_reference_on_random_smooth_surfaces():
    K = camera.intrinsics(12)
    gt = smooth_depth(2, 12, 12, seed=1).reshape(2, 1, 12, 12)
    pred = smooth_depth(2, 12, 12, seed=2).reshape(2, 1, 12, 12) * 1.1
    for method in ("kdtree", "chunked", "device"):
        got = float(L.sdf_loss(pred, gt, K, SDFOptions(grid=5, method=method, cache=None)))
        assert math.isclose(got, reference_sdf_loss(pred, gt, K, 5), rel_tol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nearest_neighbour_search_equals_brute_force(seed):
    rng = np.random.default_rng(seed)
    pts = torch.from_numpy(rng.normal(size=(3000, 3)))
    q = torch.from_numpy(rng.uniform(-3, 3, size=(700, 3)))
    brute = torch.from_numpy(np.linalg.norm(pts.numpy()[None] - q.numpy()[:, None], axis=-1).argmin(1))
    kd = sdf.nearest_indices(pts, q, "kdtree")
    ch = sdf.nearest_indices_chunked(pts, q, chunk_elements=50_000)  # many chunks
    assert torch.equal(kd, brute) and torch.equal(ch, brute)
    # float32 on the device path: distances agree with brute force to rounding
    ch32 = sdf.nearest_indices(pts.float(), q.float(), "chunked")
    d = (pts[ch32] - q).norm(dim=1) - (pts[brute] - q).norm(dim=1)
    assert d.abs().max() < 1e-5
    # float32 points with float64 queries (or the reverse) search in the wider type: the exact answer
    assert torch.equal(sdf.nearest_indices(pts.float(), q, "chunked"), sdf.nearest_indices(pts.float(), q, "kdtree"))
    assert torch.equal(sdf.nearest_indices(pts, q.float(), "chunked"), sdf.nearest_indices(pts, q.float(), "kdtree"))


def test_sdf_gradients_reach_pred_through_nearest_points():
    K = camera.intrinsics(16)
    gt = plane(2.0, 1, 16, 16)
    pred = plane(2.5, 1, 16, 16).requires_grad_()
    L.sdf_loss(pred, gt, K, SDFOptions(grid=6)).backward()
    # moving the whole prediction towards the ground truth lowers the loss
    assert pred.grad.sum() > 0 and torch.isfinite(pred.grad).all()


# ----------------------------------------------------------------------------- gradcheck
@pytest.mark.parametrize("name", ["depth", "smooth", "grad", "normal", "sdf", "total"])
def test_gradcheck_every_loss(name):
    g = torch.Generator().manual_seed(3)
    H = W = 6
    gt = 1.0 + torch.rand(2, 1, H, W, generator=g, dtype=torch.float64)
    pred = (1.0 + torch.rand(2, 1, H, W, generator=g, dtype=torch.float64)).requires_grad_()
    img = torch.rand(2, 3, H, W, generator=g, dtype=torch.float64)
    K = camera.intrinsics(W)
    fns = {
        "depth": lambda p: L.depth_loss(p, gt),
        "smooth": lambda p: L.smoothness_loss(p, img),
        "grad": lambda p: L.gradient_loss(p, gt),
        "normal": lambda p: L.normal_loss(p, gt),
        "sdf": lambda p: L.sdf_loss(p, gt, K, SDFOptions(grid=3)),
        "total": lambda p: L.total_loss(p, gt, img, K, LossSpec(lambdas=(1.0, 0.5, 2.0), sdf=SDFOptions(grid=3)))[0],
    }
    assert torch.autograd.gradcheck(fns[name], (pred,), eps=1e-6, atol=1e-6)


# ----------------------------------------------------------------------------- invalid ground truth
def test_invalid_ground_truth_is_masked_and_never_nan():
    gt = smooth_depth(2, 16, 16).reshape(2, 1, 16, 16)
    bad = gt.clone()
    bad[0, 0, 2, 3] = float("nan")
    bad[0, 0, 5, 5] = float("inf")
    bad[1, 0, 7, 1] = 0.0
    bad[1, 0, 9, 9] = -1.0
    good = torch.isfinite(bad) & (bad > 0)
    pred = (gt * 1.05).requires_grad_()
    img = torch.rand(2, 3, 16, 16, dtype=torch.float64)
    K = camera.intrinsics(16)
    loss, terms = L.total_loss(pred, bad, img, K, LossSpec(sdf=SDFOptions(grid=6)))
    loss.backward()
    assert all(math.isfinite(v) for v in terms.values())
    assert torch.isfinite(pred.grad).all()
    pred = pred.detach()
    # masking the bad pixels by hand gives the same values
    for fn in (L.depth_loss, L.gradient_loss, L.normal_loss):
        assert math.isclose(float(fn(pred, bad)), float(fn(pred, gt, good)), rel_tol=1e-12)
    assert math.isclose(float(L.sdf_loss(pred, bad, K, SDFOptions(grid=6))),
                        float(L.sdf_loss(pred, gt, K, SDFOptions(grid=6), mask=good)), rel_tol=1e-12)
    # nothing valid at all: zero, finite, differentiable
    empty = torch.full_like(gt, float("nan"))
    pred2 = gt.clone().requires_grad_()
    loss, terms = L.total_loss(pred2, empty, img, K, LossSpec(lambdas=(1, 1, 1), sdf=SDFOptions(grid=6)))
    loss.backward()
    assert terms["depth"] == terms["grad"] == terms["normal"] == terms["sdf"] == 0.0
    assert torch.isfinite(pred2.grad).all()


def test_total_loss_weights_and_skips():
    gt = smooth_depth(1, 16, 16, seed=4).reshape(1, 1, 16, 16)
    pred = smooth_depth(1, 16, 16, seed=5).reshape(1, 1, 16, 16)
    img = torch.rand(1, 3, 16, 16, dtype=torch.float64)
    K = camera.intrinsics(16)
    _, t = L.total_loss(pred, gt, img, K, LossSpec(lambdas=(1, 1, 1), sdf=SDFOptions(grid=6)))
    loss, t2 = L.total_loss(pred, gt, img, K, LossSpec(lambdas=(2.0, 0.0, 0.5), sdf=SDFOptions(grid=6)))
    assert t2["grad"] == t2["normal"] == 0.0  # skipped
    expected = 2.0 * (t["depth"] + t["smooth"]) + 0.5 * t["sdf"]
    assert math.isclose(t2["total"], expected, rel_tol=1e-12) and math.isclose(float(loss), expected, rel_tol=1e-12)
    with pytest.raises(ValueError, match="lambdas"):
        LossSpec(lambdas=(1, 1))
    with pytest.raises(ValueError, match="sdf grid"):
        SDFOptions(grid=1)
    with pytest.raises(ValueError, match="same shape"):
        L.depth_loss(pred, gt[..., :8])
    with pytest.raises(ValueError, match="mask"):
        L.depth_loss(pred, gt, mask=torch.ones(1, 16, 16, dtype=torch.bool))


def test_ground_truth_field_cache_returns_the_same_loss_and_gradient():
    K = camera.intrinsics(16)
    gt = smooth_depth(2, 16, 16, seed=7).reshape(2, 1, 16, 16)
    pred0 = (gt * 1.07 + 0.01).detach()
    cache = sdf.GTFieldCache()

    def run(c):
        p = pred0.clone().requires_grad_()
        loss = L.sdf_loss(p, gt, K, SDFOptions(grid=6, cache=c))
        loss.backward()
        return float(loss.detach()), p.grad

    ref_loss, ref_grad = run(None)
    first, g1 = run(cache)  # misses: fills the cache
    second, g2 = run(cache)  # hits
    assert (cache.misses, cache.hits, len(cache)) == (2, 2, 2)
    assert first == ref_loss == second
    assert torch.equal(g1, ref_grad) and torch.equal(g2, ref_grad)
    # a different frame (or grid) is a different entry; a full cache drops the oldest
    cache.max_bytes = 3 * (6**3 * 8 + 64)
    run(cache)
    L.sdf_loss(pred0, gt + 0.5, K, SDFOptions(grid=6, cache=cache))
    assert len(cache) == 3
    cache.max_bytes = 0
    assert cache.get("anything") is None


def test_log_and_scale_invariant_depth_terms_known_values():
    gt = torch.rand(3, 1, 6, 7, dtype=torch.float64) + 0.5
    # log-L1: a prediction 2x too far is ln 2 off everywhere
    assert float(L.log_depth_loss(2 * gt, gt)) == pytest.approx(np.log(2), rel=1e-9)
    # scale-invariant log: a global scale c costs only sqrt(1 - lambda) |ln c| ...
    lam = L.SILOG_VARIANCE_FOCUS
    assert float(L.silog_depth_loss(3 * gt, gt)) == pytest.approx(np.sqrt(1 - lam) * np.log(3), rel=1e-9)
    # ... while relative errors cost fully: d = +-a on half the pixels each gives sqrt(a^2)
    a = 0.2
    sign = torch.ones_like(gt)
    sign[..., ::2] = -1  # 7 columns: 4 at -a, 3 at +a per row
    d = a * sign
    mean = d.mean(dim=(1, 2, 3))
    expected = torch.sqrt((d * d).mean(dim=(1, 2, 3)) - lam * mean**2).mean()
    assert float(L.silog_depth_loss(gt * torch.exp(d), gt)) == pytest.approx(float(expected), rel=1e-9)
    # invalid ground truth is ignored, a frame without valid pixels does not count
    gt2 = gt.clone()
    gt2[1] = float("nan")
    per = [float(L.silog_depth_loss((3 * gt)[i:i + 1], gt[i:i + 1])) for i in (0, 2)]
    assert float(L.silog_depth_loss(3 * gt, gt2)) == pytest.approx(np.mean(per), rel=1e-9)
    with pytest.raises(ValueError, match="depth_term"):
        LossSpec(depth_term="l2")


def test_term_gradient_norms_known_values():
    """dL1/dD = sign(D - gt) / N at each of N valid pixels, so its norm is 1 / sqrt(N)."""
    gt = torch.randint(4, 12, (2, 1, 5, 4)).float() / 4  # dyadic: the offset's differences are exact
    pred = gt + 0.25
    K = torch.tensor([[4.0, 0, 2.0], [0, 4.0, 2.5], [0, 0, 1]])
    norms = L.term_gradient_norms(pred, gt, torch.rand(2, 3, 5, 4), K, LossSpec(sdf=SDFOptions(grid=3)))
    assert set(norms) == {"depth", "smooth", "grad", "normal", "sdf"}
    assert norms["depth"] == pytest.approx(1 / np.sqrt(40), rel=1e-6)
    assert norms["grad"] == pytest.approx(0.0, abs=1e-7)  # an offset has the ground truth's gradients
    assert norms["normal"] == pytest.approx(0.0, abs=1e-7)
    assert norms["sdf"] > 0


# ----------------------------------------------------------------------------- the depth term's border weight
def test_border_weight_map_known_values():
    """10 x 10, beta 2: pixel centres at |x| = 0.1, 0.3, ..., 0.9; the ramp runs from 0.7 to 1."""
    w = L.border_weight_map(10, 10, 2.0)[0, 0].double()
    assert w.shape == (10, 10)
    assert torch.allclose(w[1:-1, 1:-1], torch.ones(8, 8, dtype=torch.float64))  # distance <= 0.7: weight 1
    assert torch.allclose(w[0], torch.full((10,), 1 + 2 * (0.9 - 0.7) / 0.3, dtype=torch.float64))
    assert torch.allclose(w[:, -1], w[0])
    assert torch.all(L.border_weight_map(7, 5, 0.0) == 1)
    with pytest.raises(ValueError, match="border weight"):
        L.border_weight_map(4, 4, -1.0)


@pytest.mark.parametrize("term", sorted(L.DEPTH_TERMS))
def test_weighted_depth_terms_against_a_hand_computation(term):
    """Weights of ones change nothing; other weights give the weighted means computed in numpy."""
    pred, gt = smooth_depth(2, 12, 12, seed=1), smooth_depth(2, 12, 12, seed=2)
    mask = torch.ones_like(gt, dtype=torch.bool)
    mask[0, 0, :3] = False
    fn = L.DEPTH_TERMS[term]
    assert float(fn(pred, gt, mask, weight=torch.ones(1, 1, 12, 12, dtype=torch.float64))) == pytest.approx(
        float(fn(pred, gt, mask)), rel=1e-12)
    w = L.border_weight_map(12, 12, 3.0, pred).expand_as(pred).numpy()
    p, g, m = pred.numpy(), gt.numpy(), mask.numpy()
    if term == "silog":
        frames = []
        for b in range(2):
            d, wb = (np.log(p[b]) - np.log(g[b]))[m[b]], w[b][m[b]]
            mean, msq = (wb * d).sum() / wb.sum(), (wb * d * d).sum() / wb.sum()
            frames.append(math.sqrt(msq - L.SILOG_VARIANCE_FOCUS * mean * mean))
        expected = np.mean(frames)
    else:
        e = np.abs(p - g) if term == "l1" else np.abs(np.log(p) - np.log(g))
        expected = (w * e)[m].sum() / w[m].sum()
    got = float(fn(pred, gt, mask, weight=L.border_weight_map(12, 12, 3.0, pred)))
    assert got == pytest.approx(expected, rel=1e-10)


def test_border_weight_pulls_harder_on_border_errors():
    """An error only in the outermost ring weighs (1 + beta * ramp) times more in the log L1 term; an
    error only in the middle weighs less (the mean is over more total weight)."""
    gt = plane(2.0, 1, 20, 20)
    ring = torch.zeros_like(gt, dtype=torch.bool)
    ring[..., 0, :] = ring[..., -1, :] = ring[..., :, 0] = ring[..., :, -1] = True
    for where, more in ((ring, True), (~ring, False)):
        pred = torch.where(where, gt * math.e ** 0.1, gt)
        plain = float(L.log_depth_loss(pred, gt))
        _, terms = L.total_loss(pred, gt, torch.rand(1, 3, 20, 20, dtype=torch.float64), camera.intrinsics(20),
                                LossSpec(lambdas=(1.0, 0.0, 0.0), depth_term="log_l1", border_weight=4.0))
        assert (terms["depth"] > plain) == more
    w = L.border_weight_map(20, 20, 4.0)[0, 0].double()
    expected = 0.1 * float(w[ring[0, 0]].sum() / w.sum())  # hand value for the ring case
    pred = torch.where(ring, gt * math.e ** 0.1, gt)
    _, terms = L.total_loss(pred, gt, torch.rand(1, 3, 20, 20, dtype=torch.float64), camera.intrinsics(20),
                            LossSpec(lambdas=(1.0, 0.0, 0.0), depth_term="log_l1", border_weight=4.0))
    assert terms["depth"] == pytest.approx(expected, rel=1e-6)


# ----------------------------------------------------------------------------- the loss settings as one object
def recipe_inputs():
    """Two 8 x 10 frames in float64: ground truth, a prediction 0.8-1.2 times it, an image, K."""
    g = torch.Generator().manual_seed(2024)
    gt = 1.0 + 3.0 * torch.rand(2, 1, 8, 10, generator=g, dtype=torch.float64)
    pred = gt * (0.8 + 0.4 * torch.rand(2, 1, 8, 10, generator=g, dtype=torch.float64))
    img = torch.rand(2, 3, 8, 10, generator=g, dtype=torch.float64)
    return pred, gt, img, torch.as_tensor(camera.intrinsics(10, 8))


# total_loss(pred, gt, img, K) of recipe_inputs() before the settings became LossSpec (the twelve-argument
# total_loss at its defaults), and with lambdas=(1.0, 0.5, 0.1), sdf_grid=(4, 5, 6), depth_term="silog",
# border_weight=2.0, sdf_sampling="frustum", sdf_sign="masked"; as float.hex, every bit of the float64.
# The totals check by hand: (0.23937 + 1.40427) + (0.68765 + 0.05331) + 0.38991 = 2.77450, and
# 1 (0.11210 + 1.40427) + 0.5 (0.68765 + 0.05331) + 0.1 (0.14715) = 1.90157.
RECIPE_BEFORE = {
    "paper": {"depth": "0x1.ea386da3ab8a6p-3", "smooth": "0x1.677e52317f62ep+0", "grad": "0x1.6013f9d60e0acp-1",
              "normal": "0x1.b4b7103869394p-5", "sdf": "0x1.8f4362b52f3cfp-2", "total": "0x1.6322f70005795p+1"},
    "options": {"depth": "0x1.cb2e656dde8cfp-4", "smooth": "0x1.677e52317f62ep+0", "grad": "0x1.6013f9d60e0acp-1",
                "normal": "0x1.b4b7103869394p-5", "sdf": "0x1.2d5c1c5a7228ap-3", "total": "0x1.e6cd6d331713cp+0"},
}
RECIPE_SPECS = {
    "paper": LossSpec(),
    "options": LossSpec(lambdas=(1.0, 0.5, 0.1), depth_term="silog", border_weight=2.0,
                        sdf=SDFOptions(grid=(4, 5, 6), sampling="frustum", sign_rule="masked")),
}


@pytest.mark.parametrize("name", sorted(RECIPE_SPECS))
def test_loss_spec_gives_the_numbers_of_the_former_arguments(name):
    """``LossSpec()`` is the paper's recipe: the value the former default call gave, and the options the
    former keywords chose, term by term. Tolerance: 1e-12 relative; on the machine where the values were
    recorded they are equal bit for bit (an other CPU may sum a reduction in another order)."""
    torch.set_num_threads(1)
    pred, gt, img, K = recipe_inputs()
    loss, terms = L.total_loss(pred, gt, img, K, RECIPE_SPECS[name])
    want = {k: float.fromhex(v) for k, v in RECIPE_BEFORE[name].items()}
    assert terms.keys() == want.keys()
    for k, v in want.items():
        assert math.isclose(terms[k], v, rel_tol=1e-12, abs_tol=0.0), k
    assert float(loss) == terms["total"]
    if name == "paper":
        assert math.isclose(want["total"], sum(want[k] for k in L.term_names()), rel_tol=1e-15)


def test_loss_spec_and_sdf_options_check_their_values():
    """The defaults are the paper's; a bad value raises the UserError naming it when the settings are made;
    a function given something else than the settings object says what it takes."""
    assert LossSpec() == LossSpec(lambdas=[1.0, 1.0, 1.0], depth_term="l1", border_weight=0.0, sdf=SDFOptions())
    assert SDFOptions() == SDFOptions(grid=32, sampling="bbox", sign_rule="view", method="auto", signed=True,
                                      cache=sdf.GT_FIELD_CACHE)
    assert SDFOptions(grid=8).grid == (8, 8, 8) and LossSpec(lambdas=[1, 0, 2]).lambdas == (1, 0, 2)
    for make, words in ((lambda: LossSpec(depth_term="l2"), "depth_term must be one of l1, log_l1, silog"),
                        (lambda: LossSpec(border_weight=-1.0), "border weight"),
                        (lambda: LossSpec(lambdas={"lambda9": 1.0}), "unknown loss weight group"),
                        (lambda: LossSpec(lambdas=(1.0, -1.0, 0.0)), "non-negative"),
                        (lambda: SDFOptions(grid=(4, 4)), "sdf grid"),
                        (lambda: SDFOptions(sampling="cone"), "sdf sampling"),
                        (lambda: SDFOptions(sign_rule="nearst"), "sign_rule"),
                        (lambda: SDFOptions(method="octree"), "unknown nearest-neighbour method")):
        with pytest.raises(UserError, match=words):
            make()
    pred, gt, img, K = recipe_inputs()
    with pytest.raises(TypeError, match="SDFOptions"):
        L.sdf_loss(pred, gt, K, 8)
    with pytest.raises(TypeError, match="LossSpec"):
        L.total_loss(pred, gt, img, K, (1.0, 1.0, 1.0))
    with pytest.raises(TypeError):
        L.LossInputs(gt, img, K)  # keywords only


def test_term_gradient_norms_follow_the_weights_of_the_spec():
    """A group whose weight is zero is neither evaluated nor reported, as in total_loss."""
    pred, gt, img, K = recipe_inputs()
    every = L.term_gradient_norms(pred, gt, img, K, LossSpec(sdf=SDFOptions(grid=4)))
    some = L.term_gradient_norms(pred, gt, img, K, LossSpec(lambdas=(1.0, 0.0, 2.0), sdf=SDFOptions(grid=4)))
    assert list(every) == list(L.term_names()) and list(some) == ["depth", "smooth", "sdf"]
    assert some == {k: every[k] for k in some}
