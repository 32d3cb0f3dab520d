"""The CUDA paths, where a GPU is present (``python -m pytest -m cuda tests/test_cuda.py``; each test
skips with the reason elsewhere). Their data are analytic views (no VTK), so a GPU machine with only
torch, numpy, scipy and Pillow runs them; ``python -m geodepth_lite gpu-check`` runs them too.

Tolerances: CUDA training and inference run under autocast (bfloat16 where supported), so CUDA and
CPU agree to bfloat16's precision, not bit for bit: depth predictions within 5 % relative per pixel
(median within 1 %), metrics within 2 % relative. Resume on CUDA: cuDNN's convolution backward
sums in an order that may vary from run to run, so uninterrupted and resumed weights agree within
1e-3 of the largest weight, not bit for bit (on the CPU they are bit-identical, tests/test_train.py).
"""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from geodepth_lite.core import camera, losses, sdf
from geodepth_lite.core.model import DepthNet
from geodepth_lite.data import analytic
from geodepth_lite.evaluation import evaluate
from geodepth_lite.training import config, inference, train

pytestmark = pytest.mark.cuda
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def analytic_root(tmp_path_factory) -> Path:
    return analytic.write_dataset(tmp_path_factory.mktemp("analytic") / "data", {"train": 8, "val": 4, "test": 4},
                                  size=64)


def _cfg(root, **kw):
    kw.setdefault("epochs", 2)
    return config.make_config("smoke", 4, 0, dataset=str(root), batch_size=4, image_size=64, **kw)


def test_autocast_and_grad_scaler_train_one_step():
    dev = torch.device("cuda")
    torch.manual_seed(0)
    net = DepthNet().to(dev).train()
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    scaler = torch.amp.GradScaler("cuda", enabled=not torch.cuda.is_bf16_supported())
    d = torch.stack([torch.from_numpy(analytic.depth_map(k, 64, seed=i))[None] for i, k in enumerate(analytic.KINDS)])
    K = torch.from_numpy(analytic.intrinsics(64)).float()
    img = torch.stack([torch.from_numpy(analytic.shaded_image(x[0].numpy(), K.double().numpy())).permute(2, 0, 1)
                       for x in d]).float() / 255
    d, img, Kd = d.to(dev), img.to(dev), K.to(dev)
    before = [p.detach().clone() for p in net.parameters()]
    low = torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
    conv_dtypes = []
    hook = net.encoder.conv1.register_forward_hook(lambda m, i, o: conv_dtypes.append(o.dtype))
    with inference.autocast(dev):
        pred = net(img)
    hook.remove()
    # the convolutions run in the low precision; the depth head's exp is one of autocast's float32 ops
    assert conv_dtypes == [low] and pred.dtype == torch.float32
    loss, terms = losses.total_loss(pred.float(), d, img, Kd, losses.LossSpec(sdf=sdf.SDFOptions(grid=(8, 8, 8))))
    assert all(np.isfinite(v) for v in terms.values()) and terms["sdf"] > 0
    opt.zero_grad()
    scaler.scale(loss).backward()
    scaler.step(opt)
    scaler.update()
    assert any(not torch.equal(a, p.detach()) for a, p in zip(before, net.parameters()))
    assert all(bool(torch.isfinite(p).all()) for p in net.parameters())


@pytest.mark.parametrize("kind", analytic.KINDS)
def test_device_search_on_cuda_matches_kdtree(kind):
    d = torch.from_numpy(analytic.depth_map(kind, 160, seed=5))[None, None].cuda()
    K = torch.from_numpy(analytic.intrinsics(160)).float().cuda()
    P = camera.backproject(d, K)[0]
    q = sdf.grid_points(P.min(0).values, P.max(0).values, 32)
    got = sdf.nearest_indices(P, q)  # auto: the device search on CUDA tensors
    assert got.device.type == "cuda"
    want = cKDTree(P.double().cpu().numpy()).query(q.double().cpu().numpy())[1]
    assert np.array_equal(got.cpu().numpy(), want)
    # the loss on CUDA equals the loss from cKDTree's indices on the CPU, to float32 rounding
    pred = d * 1.07
    a = float(losses.sdf_loss(pred, d, K, sdf.SDFOptions(grid=16, cache=None)))
    b = float(losses.sdf_loss(pred.cpu(), d.cpu(), K.cpu(), sdf.SDFOptions(grid=16, cache=None)))
    assert a == pytest.approx(b, rel=1e-5)
    assert a != pytest.approx(b * 1.01, rel=1e-5)  # the tolerance can fail


def test_resume_on_cuda_ends_near_the_uninterrupted_weights(analytic_root, tmp_path):
    cfg = _cfg(analytic_root)
    straight = torch.load(train.fit(cfg, tmp_path / "a", device="cuda", progress=False), weights_only=False)
    train.fit(cfg, tmp_path / "b", device="cuda", progress=False, stop_after=1)
    resumed = torch.load(train.fit(cfg, tmp_path / "b", device="cuda", progress=False, resume=True),
                         weights_only=False)
    assert resumed["epoch"] == straight["epoch"] == 2
    for k, v in straight["model"].items():
        if v.is_floating_point():
            scale = max(float(v.abs().max()), 1e-6)
            assert float((v - resumed["model"][k]).abs().max()) <= 1e-3 * scale, k


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_torchrun_with_nccl_at_one_process(analytic_root, tmp_path):
    run = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "1", "--master_addr", "127.0.0.1",
           "--master_port", str(_free_port()), "-m", "geodepth_lite", "train", "--profile", "smoke",
           "--dataset", str(analytic_root), "--epochs", "1", "--batch-size", "4", "--image-size", "64",
           "--run-dir", str(run), "--no-progress", "--device", "cuda"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ckpt = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ckpt["world_size"] == 1 and ckpt["epoch"] == 1
    rows = json.loads((run / "log.json").read_text())["epochs"]
    assert np.isfinite(rows[0]["train_total"]) and np.isfinite(rows[0]["val_rmse"])


@pytest.fixture(scope="module")
def trained(analytic_root, tmp_path_factory) -> Path:
    return train.fit(_cfg(analytic_root, epochs=1), tmp_path_factory.mktemp("run") / "r", device="cpu",
                     progress=False)


def _agree(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Two depth predictions of the same frames agree to the precision the module docstring states:
    within 5 % relative per pixel, within 1 % at the median."""
    rel = (a - b).abs() / b.abs().clamp_min(1e-6)
    return float(rel.max()) <= 0.05 and float(rel.median()) <= 0.01


def test_predict_on_cuda_matches_the_cpu(trained, analytic_root):
    from geodepth_lite.training import checkpoint

    ds = evaluate.open_eval_dataset(str(analytic_root), split="test")
    images = torch.stack([ds[i]["image"] for i in range(len(ds))])
    out = {}
    for dev in ("cpu", "cuda"):
        model, cfg = checkpoint.load_model(trained, dev)
        with torch.no_grad():
            out[dev] = inference.predict_depth(model, images.to(dev), cfg["image_size"]).float().cpu()
    assert _agree(out["cuda"], out["cpu"])
    # the check can fail: the CUDA network built without the checkpoint's depth range (with the
    # paper profile's head range instead: a device path that drops a setting) does not agree
    model, cfg = checkpoint.load_model(trained, "cuda")
    wrong = DepthNet(depth_range=tuple(config.make_config("paper", 4, 0)["head_range"])).to("cuda").eval()
    wrong.load_state_dict(model.state_dict())
    with torch.no_grad():
        planted = inference.predict_depth(wrong, images.to("cuda"), cfg["image_size"]).float().cpu()
    assert not _agree(planted, out["cpu"])


def test_evaluate_on_cuda_matches_the_cpu(trained, analytic_root, tmp_path):
    res = {dev: evaluate.evaluate_checkpoint(trained, str(analytic_root), split="test", device=dev, error_maps=0)
           for dev in ("cpu", "cuda")}
    a, b = res["cpu"]["overall"], res["cuda"]["overall"]
    for k in evaluate.METRIC_KEYS:
        assert b[k] == pytest.approx(a[k], rel=0.02, abs=1e-4), k


def test_ground_truth_fields_are_cached_on_the_gpu():
    d = torch.stack([torch.from_numpy(analytic.depth_map(k, 64, seed=i))[None] for i, k in enumerate(analytic.KINDS)])
    d = d.cuda()
    K = torch.from_numpy(analytic.intrinsics(64)).float().cuda()
    cache = sdf.GTFieldCache()
    first = float(losses.sdf_loss(d * 1.05, d, K, sdf.SDFOptions(grid=8, cache=cache)))
    again = float(losses.sdf_loss(d * 1.05, d, K, sdf.SDFOptions(grid=8, cache=cache)))
    assert (cache.misses, cache.hits) == (3, 3) and first == again
    assert all(item[2].device.type == "cuda" for item in cache._d.values())  # kept where computed
    # the same frames' keys on the CPU: a CPU search finds the same fields
    cpu = float(losses.sdf_loss(d.cpu() * 1.05, d.cpu(), K.cpu(), sdf.SDFOptions(grid=8, cache=None)))
    assert first == pytest.approx(cpu, rel=1e-5)


def test_the_batched_search_and_loss_on_cuda_match_the_cpu_reference():
    """The batched fields on CUDA tensors: the nearest points exactly those of the CPU path (cKDTree, the
    reference), the loss and gradient those of the per-image loss on the CPU up to float32 rounding (CUDA
    sums in another order)."""
    from geodepth_lite.core.sdf import nearest_indices_grid

    d = torch.stack([torch.from_numpy(analytic.depth_map(k, 48, seed=i))[None]
                     for i, k in enumerate(analytic.KINDS * 2)])  # (6, 1, 48, 48)
    K = torch.from_numpy(analytic.intrinsics(48)).float()
    mask = torch.ones_like(d, dtype=torch.bool)
    mask[..., :4, :] = False
    pred = d * 1.05
    S = camera.backproject(pred, K)
    q = sdf.sdf_fields_batched(pred, d, K, sdf.SDFOptions(grid=16, cache=None), mask=mask)["grid"]
    valid = mask.reshape(6, -1)
    cpu = nearest_indices_grid(S, valid, q, "kdtree")
    gpu = nearest_indices_grid(S.cuda(), valid.cuda(), q.cuda(), "device")
    assert torch.equal(cpu, gpu.cpu())
    out = {}
    for dev in ("cpu", "cuda"):
        p = pred.clone().to(dev).requires_grad_()
        fn = losses.sdf_loss_reference if dev == "cpu" else losses.sdf_loss
        loss = fn(p, d.to(dev), K.to(dev), sdf.SDFOptions(grid=16, cache=None), mask.to(dev))
        loss.backward()
        out[dev] = (loss.detach().cpu(), p.grad.cpu())
    assert torch.allclose(out["cuda"][0], out["cpu"][0], rtol=1e-5, atol=0)
    assert torch.allclose(out["cuda"][1], out["cpu"][1], rtol=1e-4, atol=1e-9)


def test_the_triton_search_at_the_papers_size_equals_the_device_search_and_a_brute_force():
    """The fused kernel (``auto`` on CUDA) on 320 px views and 32^3 grids, a batch of 6 with masked rows
    and an image without a valid point: the same indices as the exact device search on every query,
    and as a float64 brute force (least index among ties) on the first 2048 queries of each image."""
    from geodepth_lite.core import nnsearch_triton

    if not nnsearch_triton.usable(torch.device("cuda")):
        pytest.skip("Triton is not installed")
    d = torch.stack([torch.from_numpy(analytic.depth_map(k, 320, seed=i))[None]
                     for i, k in enumerate(analytic.KINDS * 2)]).cuda()
    S = camera.backproject(d, torch.from_numpy(analytic.intrinsics(320)).float().cuda())
    V = torch.ones(S.shape[:2], dtype=torch.bool, device="cuda")
    V[1, : 320 * 40] = False
    V[5] = False
    q = torch.stack([sdf.grid_points(s.min(0).values, s.max(0).values, 32) for s in S])
    assert sdf.resolve_method("auto", S.device) == "triton"
    got = sdf.nearest_indices_grid(S, V, q)
    want = sdf.nearest_indices_grid(S, V, q, "device")
    assert int((got != want).sum()) == 0
    for b in range(5):
        qq = q[b, :2048].double()
        diff = qq[:, None, :] - S[b].double()[None]
        d2 = (diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1]) + diff[..., 2] * diff[..., 2]
        d2[:, ~V[b]] = float("inf")
        least = d2.min(1, keepdim=True).values
        brute = torch.where(d2 == least, torch.arange(S.shape[1], device="cuda")[None], S.shape[1]).min(1).values
        assert torch.equal(got[b, :2048], brute)
    assert got[5].eq(0).all()
