"""Known-answer tests of the SDF term's two options (not the paper's): where the samples lie
(``sdf_sampling``: "bbox", the paper's Eq. 9 grid, or "frustum", pixels x log-spaced depths) and
what happens where the paper's view rule does not sign a sample (``sdf_sign``: "view", the
nearest-point fallback, or "masked", left out of the loss). Each known answer is checked by a
helper that is also fed a deliberately wrong value, to show that the check can fail."""

import math

import numpy as np
import pytest
import torch

from geodepth_lite.core import camera, sdf
from geodepth_lite.core import losses as L
from geodepth_lite.core.losses import LossSpec, SDFOptions
from geodepth_lite.training import config, train

H, W = 12, 16
K_NARROW = camera.intrinsics(W, H, focal_ratio=1.0)  # fx = fy = 16: x/z within +-0.5, room for a steep tilt
K_NARROW[0, 2], K_NARROW[1, 2] = 7.3, 5.6  # off-centre: no exact distance ties


def tilted_plane(theta_deg: float, c: float = 2.0, K=K_NARROW, h: int = H, w: int = W) -> torch.Tensor:
    """1 x 1 x h x w depth of the plane sin(theta) x + cos(theta) z = c (a wall turned by theta about
    the y axis): z = c / (sin(theta) (u - cx)/fx + cos(theta)), float64."""
    th = math.radians(theta_deg)
    x = (np.arange(w) - K[0, 2]) / K[0, 0]
    d = c / (math.sin(th) * x + math.cos(th))
    assert (d > 0).all()
    return torch.from_numpy(np.broadcast_to(d, (h, w)).copy())[None, None]


# ----------------------------------------------------------------------------- independent numpy reference
def reference_view_sign(D, valid, K, q):
    """The paper's sign by hand: q projected and rounded to a pixel, sign(D - q_z) there; known only
    where q_z > 0, inside the image, on a valid pixel. D, valid: h x w numpy; q: M x 3."""
    h, w = D.shape
    sign, known = np.zeros(len(q)), np.zeros(len(q), dtype=bool)
    for i, (x, y, z) in enumerate(q):
        if z <= 0:
            continue
        u, v = int(np.rint(K[0, 0] * x / z + K[0, 2])), int(np.rint(K[1, 1] * y / z + K[1, 2]))
        if 0 <= u < w and 0 <= v < h and valid[v, u]:
            sign[i], known[i] = np.sign(D[v, u] - z), True
    return sign, known


def reference_samples(G, K, h, w, r, sampling):
    """The samples by hand: Eq. 9's box over the points G (N x 3), or pixels x log-spaced depths."""
    rx, ry, rz = r
    if sampling == "bbox":
        lo, hi = G.min(0), G.max(0)
        t = [np.linspace(0, 1, n) for n in r]
        return np.stack(np.meshgrid(*t, indexing="ij"), -1).reshape(-1, 3) * (hi - lo) + lo
    zn, zf = G[:, 2].min(), G[:, 2].max()
    # uniform in log depth, written as sdf.frustum_points does, so that a sample at the nearest (or
    # farthest) depth has it exactly: the view sign there is that of D - q_z = 0 in both
    z = zn * (zf / zn) ** np.linspace(0, 1, rz)
    x = (np.linspace(0, w - 1, rx) - K[0, 2]) / K[0, 0]
    y = (np.linspace(0, h - 1, ry) - K[1, 2]) / K[1, 1]
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    return np.stack((X * Z, Y * Z, Z), -1).reshape(-1, 3)


def reference_sdf_loss(pred, gt, K, r, sampling="bbox", sign="view", valid=None):
    """Brute-force L_sdf in numpy: "view" the mean over all samples (nearest-point sign where the
    view rule does not apply), "masked" per image the mean over the samples both fields' view rule
    signs, then the mean over images that have some."""
    out = []
    for b in range(pred.shape[0]):
        Dp, Dg = pred[b, 0].numpy(), gt[b, 0].numpy()
        vb = np.ones(Dg.shape, dtype=bool) if valid is None else valid[b, 0].numpy()
        P, G = camera.backproject(Dp, K)[vb], camera.backproject(Dg, K)[vb]
        q = reference_samples(G, K, *Dg.shape, r, sampling)

        def field(S, D):
            d = np.linalg.norm(S[None] - q[:, None], axis=-1)
            n = d.argmin(1)
            s = np.sign(np.einsum("ij,ij->i", S[n] - q, S[n]))
            vs, known = reference_view_sign(D, vb, K, q)
            return np.where(known, vs, s) * d.min(1), known

        (fp, kp), (fg, kg) = field(P, Dp), field(G, Dg)
        use = (kp & kg) if sign == "masked" else np.ones(len(q), dtype=bool)
        if use.any():
            out.append(np.abs(fp - fg)[use].mean())
    return float(np.mean(out)) if out else 0.0


# ----------------------------------------------------------------------------- frustum samples
def check_frustum_samples(q: torch.Tensor, K, h: int, w: int, z_near: float, z_far: float, r) -> None:
    """Assert that q (M x 3) are the frustum samples: column i, row j, depth k at pixel
    (i (w-1)/(r_x-1), j (h-1)/(r_y-1)) and depth z_near (z_far/z_near)^(k/(r_z-1))."""
    g = q.reshape(*r, 3).double()
    z = g[..., 2]  # (rx, ry, rz)
    want_z = z_near * (z_far / z_near) ** (torch.arange(r[2], dtype=torch.float64) / (r[2] - 1))
    assert torch.allclose(z, want_z.expand_as(z), rtol=1e-12, atol=0), "depths are not log-spaced"
    u = K[0, 0] * g[..., 0] / z + K[0, 2]
    v = K[1, 1] * g[..., 1] / z + K[1, 2]
    want_u = torch.linspace(0, w - 1, r[0], dtype=torch.float64)[:, None, None]
    want_v = torch.linspace(0, h - 1, r[1], dtype=torch.float64)[None, :, None]
    assert torch.allclose(u, want_u.expand_as(u), atol=1e-9), "columns are not uniform over the image"
    assert torch.allclose(v, want_v.expand_as(v), atol=1e-9), "rows are not uniform over the image"


def test_frustum_samples_are_pixels_times_log_spaced_depths():
    gt = tilted_plane(55.0)  # depths 2.07 .. 10.0
    r = (4, 3, 5)
    f = sdf.sdf_fields(gt * 1.1, gt, K_NARROW, SDFOptions(grid=r, sampling="frustum", cache=None))[0]
    zn, zf = float(gt.min()), float(gt.max())
    check_frustum_samples(f["grid"], K_NARROW, H, W, zn, zf, r)
    assert torch.equal(f["grid"], sdf.frustum_points(torch.as_tensor(K_NARROW), H, W, gt.min(), gt.max(), r))
    assert torch.allclose(f["lower"], f["grid"].min(0).values) and torch.allclose(f["upper"], f["grid"].max(0).values)
    # half of the depths below the geometric mean: dense near the camera
    assert float(f["grid"][:, 2].median()) <= math.sqrt(zn * zf) + 1e-12
    # the check catches wrong samples: linearly spaced depths, and the paper's bounding-box grid
    wrong = f["grid"].reshape(*r, 3).clone()
    lin = torch.linspace(zn, zf, r[2], dtype=torch.float64)
    wrong = wrong / wrong[..., 2:] * lin[:, None]  # same rays, linear depths
    with pytest.raises(AssertionError, match="log-spaced"):
        check_frustum_samples(wrong.reshape(-1, 3), K_NARROW, H, W, zn, zf, r)
    box = sdf.sdf_fields(gt * 1.1, gt, K_NARROW, SDFOptions(grid=r, cache=None))[0]["grid"]
    with pytest.raises(AssertionError):
        check_frustum_samples(box, K_NARROW, H, W, zn, zf, r)
    with pytest.raises(ValueError, match="z_near"):
        sdf.frustum_points(torch.as_tensor(K_NARROW), H, W, torch.tensor(2.0), torch.tensor(1.0), r)


def expected_plane_field(q: torch.Tensor, d: float, K, h: int, w: int) -> torch.Tensor:
    """phi at q (M x 3) of the back-projected fronto-parallel plane z = d, every pixel valid, by hand:
    the points form the separable grid x = (u - cx) d/fx, y = (v - cy) d/fy, so the nearest distance
    is sqrt((d - q_z)^2 + min_u (x_u - q_x)^2 + min_v (y_v - q_y)^2), signed sign(d - q_z) (the view rule)."""
    xs = (torch.arange(w, dtype=torch.float64) - K[0, 2]) * d / K[0, 0]  # (w,)
    ys = (torch.arange(h, dtype=torch.float64) - K[1, 2]) * d / K[1, 1]  # (h,)
    dx = (xs[None] - q[:, :1]).abs().min(1).values  # (M,)
    dy = (ys[None] - q[:, 1:2]).abs().min(1).values  # (M,)
    dz = d - q[:, 2]
    return torch.sign(dz) * torch.sqrt(dz * dz + dx * dx + dy * dy)


def test_frustum_view_sign_against_a_fronto_parallel_plane():
    """The prediction a plane z = 4 seen through the ground truth's frustum (a tilted wall, depths
    2.07-10): every sample projects inside the image, the view rule signs all of them, and phi is
    exactly the distance to the nearest back-projected pixel, signed sign(d - q_z). In front of the
    plane that is d - q_z up to the lateral offset to the nearest pixel's point (at most half a
    pixel diagonal at depth d); beyond it, samples near the image border lie laterally outside
    the plane's extent and are farther than q_z - d from it."""
    gt = tilted_plane(55.0)
    d = 4.0
    pred = torch.full_like(gt, d)
    r = (5, 4, 6)
    f = sdf.sdf_fields(pred, gt, K_NARROW, SDFOptions(grid=r, sampling="frustum", sign_rule="masked", cache=None))[0]
    assert bool(f["known"].all())  # the view rule applies at every sample: nothing is left out
    q = f["grid"]
    want = expected_plane_field(q, d, K_NARROW, H, W)
    assert torch.allclose(f["pred"], want, rtol=1e-12, atol=1e-12)
    half_diagonal = 0.5 * d * math.hypot(1 / K_NARROW[0, 0], 1 / K_NARROW[1, 1])
    front = q[:, 2] <= d
    assert ((f["pred"] - (d - q[:, 2])).abs()[front] <= half_diagonal + 1e-12).all()
    assert (f["pred"][~front] <= d - q[~front, 2] + 1e-12).all()  # |phi| >= q_z - d beyond the plane
    assert (f["pred"] > 0).any() and (f["pred"] < 0).any()  # samples on both sides of the plane
    # the same samples under the view sign, and the check catches a field without the sign
    view = SDFOptions(grid=r, sampling="frustum", cache=None)
    assert torch.equal(sdf.sdf_fields(pred, gt, K_NARROW, view)[0]["pred"], f["pred"])
    unsigned = sdf.sdf_fields(pred, gt, K_NARROW, SDFOptions(grid=r, sampling="frustum", signed=False,
                                                             cache=None))[0]["pred"]
    assert not torch.allclose(unsigned, want, rtol=1e-12, atol=1e-12)
    assert math.isclose(float(L.sdf_loss(pred, gt, K_NARROW, SDFOptions(grid=r, sampling="frustum", cache=None))),
                        reference_sdf_loss(pred, gt, K_NARROW, r, "frustum"), rel_tol=1e-9)


# ----------------------------------------------------------------------------- view-rule coverage
def reference_coverage(gt, K, r, sampling):
    """Share of samples the view rule signs in the ground truth's field (numpy, every pixel valid)."""
    D = gt[0, 0].numpy()
    q = reference_samples(camera.backproject(D, K).reshape(-1, 3), K, *D.shape, r, sampling)
    return reference_view_sign(D, np.ones(D.shape, dtype=bool), K, q)[1].mean()


@pytest.mark.parametrize("theta", [45.0, 55.0, 62.0])
def test_tilted_wall_falls_back_under_bbox_but_never_under_frustum(theta):
    gt = tilted_plane(theta)
    r = (6, 6, 6)
    box = sdf.view_rule_coverage(gt, K_NARROW, r)
    fr = sdf.view_rule_coverage(gt, K_NARROW, r, sampling="frustum")
    assert box.shape == fr.shape == (1,) and box.dtype == torch.float64
    assert math.isclose(float(box), reference_coverage(gt, K_NARROW, r, "bbox"), rel_tol=1e-12)
    assert 1 - float(box) > 0.3  # a third or more of the box's samples: the nearest-point fallback
    assert float(fr) == 1.0 == reference_coverage(gt, K_NARROW, r, "frustum")
    # the masked sign keeps exactly the covered samples (the ground truth's field; the prediction's
    # is valid wherever the ground truth is)
    f = sdf.sdf_fields(gt * 1.1, gt, K_NARROW, SDFOptions(grid=r, sign_rule="masked", cache=None))[0]
    assert math.isclose(float(f["known"].double().mean()), float(box), rel_tol=1e-12)


def test_view_rule_coverage_with_masks_and_empty_images():
    gt = tilted_plane(55.0).expand(3, 1, H, W).clone()
    mask = torch.ones_like(gt, dtype=torch.bool)
    mask[1, 0, :, ::2] = False  # every other column invalid
    mask[2] = False  # nothing valid
    cov = sdf.view_rule_coverage(gt, K_NARROW, (4, 4, 3), mask=mask, sampling="frustum")
    assert float(cov[0]) == 1.0 and math.isnan(float(cov[2]))
    # frustum columns u = 0, 5, 10, 15: 5 and 15 are odd (valid), 0 and 10 even (invalid)
    assert float(cov[1]) == 0.5
    with pytest.raises(ValueError, match="sampling"):
        sdf.view_rule_coverage(gt, K_NARROW, 4, sampling="cone")


# ----------------------------------------------------------------------------- masked sign
def test_masked_loss_is_the_mean_over_the_samples_the_view_rule_signs():
    gt = torch.cat([tilted_plane(55.0), tilted_plane(-40.0, c=3.0)])  # (2, 1, H, W)
    pred = torch.cat([gt[:1] * 1.1, gt[1:] * 0.93 + 0.05])
    r = 6
    masked = float(L.sdf_loss(pred, gt, K_NARROW, SDFOptions(grid=r, sign_rule="masked", cache=None)))
    view = float(L.sdf_loss(pred, gt, K_NARROW, SDFOptions(grid=r, cache=None)))
    assert math.isclose(masked, reference_sdf_loss(pred, gt, K_NARROW, (r,) * 3, sign="masked"), rel_tol=1e-9)
    assert math.isclose(view, reference_sdf_loss(pred, gt, K_NARROW, (r,) * 3), rel_tol=1e-9)
    # per image: the view loss splits into the kept samples' sum and the left-out ones'
    fields = sdf.sdf_fields(pred, gt, K_NARROW, SDFOptions(grid=r, sign_rule="masked", cache=None))
    per_image = []
    for f in fields:
        err = (f["pred"] - f["gt"]).abs()
        per_image.append(float(err[f["known"]].mean()))
        assert 0 < int(f["known"].sum()) < r**3 and float(err[~f["known"]].sum()) > 0
    assert math.isclose(masked, float(np.mean(per_image)), rel_tol=1e-12)
    # a wrong implementation, the mean over all samples, is caught by the reference
    wrong = float(torch.cat([(f["pred"] - f["gt"]).abs() for f in fields]).mean())
    assert not math.isclose(wrong, reference_sdf_loss(pred, gt, K_NARROW, (r,) * 3, sign="masked"), rel_tol=1e-3)


def test_masked_loss_ignores_what_only_left_out_samples_see():
    """Prediction pixels that are the nearest point of left-out samples only: moving them changes the
    view loss (through the fallback samples) but not the masked loss, whose gradient there is 0."""
    gt = tilted_plane(55.0)
    pred = (gt * 1.1).detach()
    r = 6
    f = sdf.sdf_fields(pred, gt, K_NARROW, SDFOptions(grid=r, sign_rule="masked", cache=None))[0]
    nearest = sdf.nearest_indices(camera.backproject(pred, K_NARROW)[0], f["grid"])  # (M,) pixel of each sample
    only_out = torch.tensor(sorted(set(nearest[~f["known"]].tolist()) - set(nearest[f["known"]].tolist())))
    assert len(only_out) > 0
    moved = pred.clone().reshape(-1)
    moved[only_out] *= 1.02
    moved = moved.reshape(pred.shape)
    loss = {rule: [float(L.sdf_loss(p, gt, K_NARROW, SDFOptions(grid=r, sign_rule=rule, cache=None)))
                   for p in (pred, moved)] for rule in ("masked", "view")}
    assert loss["masked"][0] == loss["masked"][1]
    assert abs(loss["view"][0] - loss["view"][1]) > 1e-3
    for rule, zero in (("masked", True), ("view", False)):
        p = pred.clone().requires_grad_()
        L.sdf_loss(p, gt, K_NARROW, SDFOptions(grid=r, sign_rule=rule, cache=None)).backward()
        assert (float(p.grad.reshape(-1)[only_out].abs().max()) == 0.0) == zero


def test_an_image_without_signed_samples_contributes_nothing():
    """Frustum columns and rows fall on pixels 0, 5, 10, 15 and 0, 5, 11 (grid 4 x 3 x 3): an image valid
    only elsewhere has no sample the view rule signs, so the batch loss is the other image's alone."""
    gt = tilted_plane(55.0).expand(2, 1, H, W).clone()
    mask = torch.ones_like(gt, dtype=torch.bool)
    mask[1, 0, :, [0, 5, 10, 15]] = False
    r = (4, 3, 3)
    pred = (gt * 1.1).detach()
    assert float(sdf.view_rule_coverage(gt, K_NARROW, r, mask=mask, sampling="frustum")[1]) == 0.0
    masked = SDFOptions(grid=r, sampling="frustum", sign_rule="masked", cache=None)
    alone = float(L.sdf_loss(pred[:1], gt[:1], K_NARROW, masked))
    p = pred.clone()
    p[1] *= 1.7  # any prediction for the second image
    p.requires_grad_()
    both = L.sdf_loss(p, gt, K_NARROW, masked, mask=mask)
    both.backward()
    assert float(both.detach()) == alone and float(p.grad[1].abs().max()) == 0.0
    assert math.isclose(alone, reference_sdf_loss(pred, gt, K_NARROW, r, "frustum", "masked", mask), rel_tol=1e-9)
    # nothing signed anywhere: 0, finite, connected to pred
    q = pred[1:].clone().requires_grad_()
    none = L.sdf_loss(q, gt[1:], K_NARROW, masked, mask=mask[1:])
    none.backward()
    assert float(none.detach()) == 0.0 and torch.isfinite(q.grad).all()


# ----------------------------------------------------------------------------- defaults unchanged
def random_maps(seed: int, B: int = 3, h: int = 14, w: int = 11, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    gt = (1 + 5 * torch.rand(B, 1, h, w, generator=g)).to(dtype)
    gt[0, 0, :2] = 0.0  # invalid rows
    pred = (gt.clamp(min=0.5) * (0.8 + 0.4 * torch.rand(B, 1, h, w, generator=g).to(dtype))).detach()
    return pred, gt, torch.rand(B, 3, h, w, generator=g).to(dtype), camera.intrinsics(w, h)


@pytest.mark.parametrize("seed", [0, 1])
def test_default_options_give_bit_identical_losses_and_gradients(seed):
    pred, gt, img, K = random_maps(seed)
    out = []
    for kw in ({}, {"sampling": "bbox", "sign_rule": "view"}):
        p = pred.clone().requires_grad_()
        loss = L.sdf_loss(p, gt, K, SDFOptions(grid=5, cache=None, **kw))
        loss.backward()
        out.append((loss.detach(), p.grad))
    assert torch.equal(out[0][0], out[1][0]) and torch.equal(out[0][1], out[1][1])
    # the default is the paper's grid and sign, as computed by the independent reference
    assert math.isclose(float(out[0][0]), reference_sdf_loss(pred, gt, K, (5,) * 3, valid=gt > 0), rel_tol=1e-9)
    # ... which the other options are not (the reference can tell them apart)
    for kw in ({"sampling": "frustum"}, {"sign_rule": "masked"}):
        other = float(L.sdf_loss(pred, gt, K, SDFOptions(grid=5, cache=None, **kw)))
        assert not math.isclose(other, float(out[0][0]), rel_tol=1e-6)
    a, ta = L.total_loss(pred, gt, img, K, LossSpec(sdf=SDFOptions(grid=5)))
    b, tb = L.total_loss(pred, gt, img, K, LossSpec(sdf=SDFOptions(grid=5, sampling="bbox", sign_rule="view")))
    assert torch.equal(a, b) and ta == tb
    assert L.term_gradient_norms(pred, gt, img, K, LossSpec(sdf=SDFOptions(grid=5))) == L.term_gradient_norms(
        pred, gt, img, K, LossSpec(sdf=SDFOptions(grid=5, sampling="bbox", sign_rule="view")))


@pytest.mark.parametrize("sampling, sign", [("frustum", "view"), ("bbox", "masked"), ("frustum", "masked")])
def test_options_match_the_reference_on_random_maps(sampling, sign):
    pred, gt, _, K = random_maps(3)
    for method in ("kdtree", "chunked", "device"):
        options = SDFOptions(grid=(4, 5, 3), sampling=sampling, sign_rule=sign, method=method, cache=None)
        got = float(L.sdf_loss(pred, gt, K, options))
        assert math.isclose(got, reference_sdf_loss(pred, gt, K, (4, 5, 3), sampling, sign, gt > 0), rel_tol=1e-9)


# ----------------------------------------------------------------------------- cache
def test_cached_fields_never_mix_samplings():
    pred, gt, _, K = random_maps(4)
    cache = sdf.GTFieldCache()
    box = L.sdf_loss(pred, gt, K, SDFOptions(grid=5, cache=cache))
    fr = L.sdf_loss(pred, gt, K, SDFOptions(grid=5, sampling="frustum", cache=cache))
    assert (cache.misses, cache.hits, len(cache)) == (6, 0, 6)  # 3 frames x 2 samplings
    assert float(fr) != float(box)
    assert torch.equal(L.sdf_loss(pred, gt, K, SDFOptions(grid=5, sampling="frustum", cache=cache)),
                       fr)  # hits, same value
    assert torch.equal(fr, L.sdf_loss(pred, gt, K, SDFOptions(grid=5, sampling="frustum", cache=None)))
    # the masked rule's fields are the view rule's: shared, and the loss is the uncached one
    masked = L.sdf_loss(pred, gt, K, SDFOptions(grid=5, sampling="frustum", sign_rule="masked", cache=cache))
    assert (cache.hits, len(cache)) == (6, 6)
    assert torch.equal(masked, L.sdf_loss(pred, gt, K, SDFOptions(grid=5, sampling="frustum", sign_rule="masked",
                                                                 cache=None)))
    keys = {sdf.GTFieldCache.key(gt[0], gt[0] > 0, torch.as_tensor(K), SDFOptions(grid=5, sampling=s))
            for s in sdf.SDF_SAMPLINGS}
    assert len(keys) == len(sdf.SDF_SAMPLINGS)


# ----------------------------------------------------------------------------- configuration
def test_config_accepts_the_options_and_rejects_other_values():
    cfg = config.make_config("smoke", 4, 0)
    assert (cfg["sdf_sampling"], cfg["sdf_sign"]) == ("bbox", "view")
    assert config.make_config("smoke", 4, 0, sdf_sampling="frustum", sdf_sign="masked")["sdf_sampling"] == "frustum"
    with pytest.raises(ValueError, match=r"sdf_sampling must be one of bbox, frustum, got 'box'"):
        config.make_config("smoke", sdf_sampling="box")
    with pytest.raises(ValueError, match=r"sdf_sign must be one of view, masked, got 'nearest'"):
        config.make_config("smoke", sdf_sign="nearest")
    with pytest.raises(ValueError, match="sdf_sign"):
        config.validate_config({**cfg, "sdf_sign": None})
    # the loss's own settings are checked when they are made, whether or not the term is computed
    with pytest.raises(ValueError, match="sign_rule"):
        LossSpec(lambdas=(1, 0, 0), sdf=SDFOptions(sign_rule="nearst"))
    with pytest.raises(ValueError, match="sampling"):
        SDFOptions(sampling="cone")


@pytest.mark.parametrize("key, other", [("sdf_sampling", "frustum"), ("sdf_sign", "masked")])
def test_the_options_at_their_defaults_keep_config_hashes(key, other):
    for profile in config.PROFILES:
        cfg = config.make_config(profile, 4, 0)
        old = {k: v for k, v in cfg.items() if k not in ("sdf_sampling", "sdf_sign")}  # saved before the keys
        assert config.config_hash(old) == config.config_hash(cfg)
        assert config.config_identity(config.validate_config(old)) == config.config_identity(cfg)
        changed = config.make_config(profile, 4, 0, **{key: other})
        assert config.config_hash(changed) != config.config_hash(cfg)
        assert config.config_identity(changed)[key] == other
    # a hash pinned before the options existed (teach, case 4, seed 0, with the weights of that time)
    assert config.config_hash(config.make_config("teach", 4, 0, lambdas=[1.0, 1.0, 0.01])) == "769350e4"


def test_one_adapter_makes_a_configuration_s_loss_settings():
    """config.loss_spec: the paper profile's Case 4 is the paper's recipe, LossSpec(); each loss key of a
    configuration lands in its field."""
    assert config.loss_spec(config.make_config("paper", 4, 0)) == LossSpec()
    cfg = config.make_config("teach", 3, 1, sdf_sampling="frustum", sdf_sign="masked", border_weight=2.0)
    assert config.loss_spec(cfg) == LossSpec(lambdas=(1.0, 0.0, 0.01), depth_term="silog", border_weight=2.0,
                                             sdf=SDFOptions(grid=8, sampling="frustum", sign_rule="masked"))
    assert config.loss_spec(config.make_config("smoke", 1, 0)).lambdas == (1.0, 0.0, 0.0)  # Case 1: lambda1 alone


def test_training_passes_the_options_to_the_sdf_term():
    pred, gt, img, K = random_maps(6, B=2, h=16, w=16, dtype=torch.float32)
    batch = {"depth": gt, "image": img, "K": torch.as_tensor(K).float()}
    base = config.make_config("smoke", 3, 0)
    got = {}
    for sampling in ("bbox", "frustum"):
        for sign in ("view", "masked"):
            cfg = config.make_config("smoke", 3, 0, sdf_sampling=sampling, sdf_sign=sign)
            got[sampling, sign] = train.compute_losses(pred, batch, cfg)[1]["sdf"]
            want = L.sdf_loss(pred, gt, batch["K"], SDFOptions(grid=8, sampling=sampling, sign_rule=sign))
            assert got[sampling, sign] == float(want)
            norms = train.term_gradient_norms(pred, batch, cfg)  # Case 3: lambda2 = 0, so no grad or normal
            assert sorted(norms) == ["depth", "sdf", "smooth"]
            spec = LossSpec(lambdas=cfg["lambdas"], depth_term="l1",
                            sdf=SDFOptions(grid=(8, 8, 8), sampling=sampling, sign_rule=sign))
            assert norms == L.term_gradient_norms(pred, gt, img, batch["K"], spec)
    assert got["bbox", "view"] == train.compute_losses(pred, batch, base)[1]["sdf"]
    assert len(set(got.values())) == 4
