"""The SDF loss built for the whole batch at once (``sdf.sdf_fields_batched``, ``losses.sdf_loss``) against
its former image-by-image form (``losses.sdf_loss_reference``): the same loss and gradient bit for bit
(``torch.equal``), and the aten operations and host syncs one batched loss costs, counted with a
``TorchDispatchMode``. Each check is also fed a value of our own making that it must reject."""

import itertools
from collections import Counter

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from geodepth_lite.core import camera, sdf
from geodepth_lite.core import losses as L
from geodepth_lite.core.sdf import SDFOptions
from geodepth_lite.data import analytic

SYNC_OPS = {"aten._local_scalar_dense", "aten.item", "aten.is_nonzero", "aten.nonzero", "aten.nonzero_static"}
MAX_OPS, MAX_SYNCS = 200, 0  # one batched loss of 20 frames, forward and backward (ground-truth fields cached)


class OpCounter(TorchDispatchMode):
    """Counts the aten operations that run (views left out) and the host syncs among them: reading a
    value to the host (item, bool, float, tolist), nonzero (its output's size depends on values), and
    copies from another device to the CPU."""

    def __init__(self):
        super().__init__()
        self.ops, self.syncs = Counter(), Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = str(func.overloadpacket)
        if not func.is_view:
            self.ops[name] += 1
        src = next((a for a in args if isinstance(a, torch.Tensor)), None)
        to_host = (name in ("aten._to_copy", "aten.copy_") and src is not None and src.device.type != "cpu"
                   and isinstance(out, torch.Tensor) and out.device.type == "cpu")
        if name in SYNC_OPS or to_host:
            self.syncs[name] += 1
        return out

    @property
    def n_ops(self) -> int:
        return sum(self.ops.values())

    @property
    def n_syncs(self) -> int:
        return sum(self.syncs.values())


def views(B: int, size: int, seed: int = 0):
    """B analytic frames, lumen, wall and close-up in turn: (gt B x 1 x size x size float32, K 3 x 3)."""
    K = torch.from_numpy(analytic.intrinsics(size)).float()
    gt = torch.stack([torch.from_numpy(analytic.depth_map(analytic.KINDS[i % 3], size, seed=seed + i))[None]
                      for i in range(B)]).float()
    return gt, K


def prediction(gt: torch.Tensor, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (gt * (1 + 0.2 * torch.rand(gt.shape, generator=g) - 0.1)).contiguous()


def loss_and_grad(fn, pred0, *args, **kwargs):
    p = pred0.clone().requires_grad_()
    loss = fn(p, *args, **kwargs)
    loss.backward()
    return loss.detach(), p.grad


def masks(gt: torch.Tensor) -> dict:
    g = torch.Generator().manual_seed(5)
    holes = torch.rand(gt.shape, generator=g) > 0.3
    empty = torch.ones(gt.shape, dtype=torch.bool)
    empty[1] = False  # one frame without any valid pixel
    disc = torch.zeros(gt.shape, dtype=torch.bool)
    disc[..., 3:-3, 2:-4] = True  # a field of view: samples beyond it fall back (view) or drop out (masked)
    return {"none": None, "holes": holes, "empty frame": empty, "field of view": disc}


def assert_same(a, b) -> None:
    assert torch.equal(a[0], b[0]), f"loss {a[0].item()!r} != {b[0].item()!r}"
    assert torch.equal(a[1], b[1]), f"gradient differs by up to {(a[1] - b[1]).abs().max().item()!r}"


# ----------------------------------------------------------------------------- bit for bit
ROUNDING = 2**-21  # relative: a float32 sum of the same numbers grouped otherwise (a few units in the last place)


def assert_close(a, b) -> None:
    """The same gradient bit for bit, the same loss up to the rounding of its last sum."""
    assert torch.equal(a[1], b[1]), f"gradient differs by up to {(a[1] - b[1]).abs().max().item()!r}"
    assert torch.isclose(a[0], b[0], rtol=ROUNDING, atol=0.0), f"loss {a[0].item()!r} != {b[0].item()!r}"


@pytest.mark.parametrize("sign_rule, sampling", list(itertools.product(("view", "nearest", "masked"),
                                                                         ("bbox", "frustum"))))
def test_batched_loss_and_gradient_equal_the_per_image_ones(sign_rule, sampling):
    """Bit for bit where the loss averages whole rows of samples: the view and nearest rules on frames that
    each have a valid pixel. Where it averages a varying number per frame (the masked rule's known samples,
    or the images that have a valid pixel), the per-image loss sums exactly that many numbers and the batched
    one a fixed-length row whose tail is zero: torch groups the terms of a sum by its length, so the loss may
    differ in its last bits; the gradient (one over each count, exact) does not."""
    gt, K = views(4, 20)
    pred0 = prediction(gt)
    for (name, mask), grid in itertools.product(masks(gt).items(), (5, (4, 6, 7))):
        options = SDFOptions(grid=grid, cache=None, sign_rule=sign_rule, sampling=sampling)
        ref = loss_and_grad(L.sdf_loss_reference, pred0, gt, K, options, mask)
        new = loss_and_grad(L.sdf_loss, pred0, gt, K, options, mask)
        if sign_rule == "masked" or name == "empty frame":
            assert_close(ref, new)
        else:
            assert_same(ref, new)
        assert ref[0] > 0 and ref[1].abs().sum() > 0, name


@pytest.mark.parametrize("keyed_by", ["content", "frame id"])
def test_batched_loss_equals_the_per_image_one_with_the_ground_truth_cache(keyed_by):
    gt, K = views(3, 16, seed=4)
    pred0 = prediction(gt, seed=2)
    mask = masks(gt)["holes"]
    ids = [("train", i) for i in range(3)] if keyed_by == "frame id" else None
    for sign_rule, sampling in itertools.product(("view", "masked"), ("bbox", "frustum")):
        c_ref, c_new = sdf.GTFieldCache(), sdf.GTFieldCache()
        for _ in range(2):  # misses (fields computed and stored), then hits
            ref = loss_and_grad(L.sdf_loss_reference, pred0, gt, K,
                                SDFOptions(grid=6, cache=c_ref, sign_rule=sign_rule, sampling=sampling), mask)
            new = loss_and_grad(L.sdf_loss, pred0, gt, K,
                                SDFOptions(grid=6, cache=c_new, sign_rule=sign_rule, sampling=sampling), mask,
                                frame_ids=ids)
            (assert_same if sign_rule == "view" else assert_close)(ref, new)
        assert (c_new.misses, c_new.hits, len(c_new)) == (c_ref.misses, c_ref.hits, len(c_ref)) == (3, 3, 3)


def test_the_checks_reject_a_loss_right_but_for_rounding_and_a_wrong_gradient():
    """With a frame without valid pixels, the batched view loss sums 4 rows, the last zero, where the
    per-image one sums 3: the same number up to rounding, and on some batches not the same bits (the first
    such batch of a few seeds is taken). assert_same rejects it, assert_close accepts it; a gradient off by
    one nearest point fails assert_close."""
    for seed in range(40):
        gt, K = views(4, 20, seed)
        pred0 = prediction(gt, seed + 1)
        mask = masks(gt)["empty frame"]
        ref = loss_and_grad(L.sdf_loss_reference, pred0, gt, K, SDFOptions(grid=5, cache=None), mask)
        padded = loss_and_grad(L.sdf_loss, pred0, gt, K, SDFOptions(grid=5, cache=None), mask)
        if not torch.equal(ref[0], padded[0]):
            break
    assert not torch.equal(ref[0], padded[0]), "no batch of 40 shows the rounding difference"
    with pytest.raises(AssertionError, match="loss"):
        assert_same(ref, padded)
    assert_close(ref, padded)
    ref = loss_and_grad(L.sdf_loss_reference, pred0, gt, K, SDFOptions(grid=9, cache=None))

    def one_off(p, *a, **k):
        B = p.shape[0]
        f = sdf.sdf_fields_batched(p.detach(), *a, **k)
        near = sdf.nearest_indices_grid(camera.backproject(p.detach(), K), (gt > 0).reshape(B, -1), f["grid"])
        near[0, 0] = (near[0, 0] + 1) % near.new_tensor(20 * 20)  # one sample's nearest point moved
        return L.sdf_loss_from_fields(sdf.sdf_fields_batched(p, *a, nearest=near, **k), p)

    with pytest.raises(AssertionError, match="gradient"):
        assert_close(ref, loss_and_grad(one_off, pred0, gt, K, SDFOptions(grid=9, cache=None)))


def test_nearest_indices_grid_finds_the_per_image_search_s_points():
    gt, K = views(3, 16, seed=2)
    valid = masks(gt)["empty frame"].reshape(3, -1)
    valid[0, ::3] = False
    S = camera.backproject(gt, K)
    q = torch.randn(3, 50, 3) * 2 + torch.tensor([0.0, 0.0, 4.0])
    for method in ("kdtree", "device"):
        idx = sdf.nearest_indices_grid(S, valid, q, method)  # (3, 50) into the 256 pixels
        for b in (0, 2):
            sel = valid[b].nonzero().squeeze(1)
            want = sel[sdf.nearest_indices_kdtree(S[b, sel], q[b])]
            assert torch.equal(idx[b], want)
        assert torch.equal(idx[1], torch.zeros(50, dtype=torch.int64))  # no valid pixel: index 0, never read
    assert bool(valid[0].gather(0, idx[0]).all())  # only valid points are nearest


# ----------------------------------------------------------------------------- operations and syncs
def count_batched_loss(B: int = 20, size: int = 32, grid: int = 8, sign_rule: str = "view", reference=False):
    """(OpCounter of the forward, OpCounter of the backward) of one SDF loss of B frames whose ground-truth
    fields are cached under their frame ids; the prediction's nearest points are given (searched apart)."""
    gt, K = views(B, size)
    pred0 = prediction(gt)
    cache, ids = sdf.GTFieldCache(), [("train", i) for i in range(B)]
    options = SDFOptions(grid=grid, cache=cache, sign_rule=sign_rule)
    if reference:
        L.sdf_loss_reference(pred0, gt, K, options)  # fills the cache
    else:
        f = sdf.sdf_fields_batched(pred0, gt, K, options, frame_ids=ids)
        nearest = sdf.nearest_indices_grid(camera.backproject(pred0, K), (gt > 0).reshape(B, -1), f["grid"])
    p = pred0.clone().requires_grad_()
    with OpCounter() as fwd:
        if reference:
            loss = L.sdf_loss_reference(p, gt, K, options)
        else:
            f = sdf.sdf_fields_batched(p, gt, K, options, frame_ids=ids, nearest=nearest)
            loss = L.sdf_loss_from_fields(f, p)
    with OpCounter() as bwd:
        loss.backward()
    assert cache.hits == B
    return fwd, bwd


@pytest.mark.parametrize("sign_rule", ["view", "masked"])
def test_one_batched_loss_of_20_frames_is_under_200_operations_and_never_waits(sign_rule, monkeypatch):
    # frame ids key the cache: no content hash (which would copy each frame to the host) is computed
    monkeypatch.setattr(sdf.GTFieldCache, "key", staticmethod(lambda *a, **k: pytest.fail("hashed a frame")))
    fwd, bwd = count_batched_loss(sign_rule=sign_rule)
    assert fwd.n_ops + bwd.n_ops <= MAX_OPS, (fwd.ops, bwd.ops)
    assert fwd.n_syncs + bwd.n_syncs == MAX_SYNCS, (fwd.syncs, bwd.syncs)


def test_the_operation_count_rejects_the_per_image_loss():
    """The former loss, image by image, on the same batch: over the bound in operations and in syncs."""
    fwd, bwd = count_batched_loss(reference=True)
    assert fwd.n_ops + bwd.n_ops > MAX_OPS
    assert fwd.syncs["aten._local_scalar_dense"] >= 20  # vb.any() and vb.all() per image


def test_the_counter_sees_syncs_and_leaves_views_out():
    x = torch.arange(6.0)
    with OpCounter() as c:
        y = x.view(2, 3)[0]  # views: not counted
        z = (y + 1).sum()
        bool(z > 0)
        float(z)
        (x > 2).nonzero()
    assert c.ops["aten.add"] == 1 and c.ops["aten.sum"] == 1 and "aten.view" not in c.ops
    assert c.syncs == Counter({"aten._local_scalar_dense": 2, "aten.nonzero": 1})


@pytest.mark.parametrize("sampling", ["bbox", "frustum"])
def test_bit_for_bit_at_the_paper_s_grid_and_batch(sampling):
    """20 frames (lumen, wall, close-up), the 32^3 grid, at 32 px: the sums are as long as the paper's."""
    gt, K = views(20, 32, seed=9)
    pred0 = prediction(gt, seed=3)
    options = SDFOptions(grid=32, cache=None, sampling=sampling)
    ref = loss_and_grad(L.sdf_loss_reference, pred0, gt, K, options)
    assert_same(ref, loss_and_grad(L.sdf_loss, pred0, gt, K, options))


@pytest.mark.parametrize("sampling", ["bbox", "frustum"])
def test_bit_for_bit_unsigned_and_in_float64(sampling):
    gt, K = views(4, 20)
    pred0 = prediction(gt)
    for kw in ({"signed": False}, {"method": "device"}):
        options = SDFOptions(grid=6, cache=None, sampling=sampling, **kw)
        assert_same(loss_and_grad(L.sdf_loss_reference, pred0, gt, K, options),
                    loss_and_grad(L.sdf_loss, pred0, gt, K, options))
    g64, p64, K64 = gt.double(), pred0.double(), K.double()
    options = SDFOptions(grid=6, cache=None, sampling=sampling)
    assert_same(loss_and_grad(L.sdf_loss_reference, p64, g64, K64, options),
                loss_and_grad(L.sdf_loss, p64, g64, K64, options))
