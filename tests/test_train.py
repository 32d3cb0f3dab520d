"""Training: resume == uninterrupted, atomic checkpoints, logs, DDP with 2 CPU processes, caching."""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from geodepth_lite import utils
from geodepth_lite.core import metrics
from geodepth_lite.data import augment, datasets
from geodepth_lite.training import checkpoint, config, inference, run_cache, train


def _cfg(root, case=4, seed=0, **kw):
    """Smoke settings at 32x32 (the smallest size the encoder takes) to keep the tests quick."""
    kw.setdefault("epochs", 3)
    kw.setdefault("batch_size", 4)
    kw.setdefault("image_size", 32)
    return config.make_config("smoke", case, seed, dataset=str(root), **kw)


def _scramble_process_state():
    """What a fresh process would look like: no cached data, unrelated RNG states."""
    datasets.MEMORY_CACHE.clear()
    torch.manual_seed(12345)
    np.random.seed(999)


def test_resume_after_stop_ends_with_the_same_weights(smoke_root, tmp_path):
    cfg = _cfg(smoke_root, epochs=2, lr_schedule="cosine")  # the schedule's state is resumed too
    straight = torch.load(train.fit(cfg, tmp_path / "straight", progress=False), weights_only=False)

    _scramble_process_state()
    first = train.fit(cfg, tmp_path / "resumed", progress=False, stop_after=1)
    assert torch.load(first, weights_only=False)["epoch"] == 1
    _scramble_process_state()
    resumed = torch.load(train.fit(cfg, tmp_path / "resumed", progress=False, resume=True), weights_only=False)

    assert resumed["epoch"] == straight["epoch"] == 2 and resumed["complete"]
    assert straight["model"].keys() == resumed["model"].keys()
    for k, v in straight["model"].items():
        assert torch.equal(v, resumed["model"][k]), k
    for a, b in zip(straight["optimizer"]["state"].values(), resumed["optimizer"]["state"].values()):
        assert torch.equal(a["exp_avg"], b["exp_avg"])
    loss_cols = [k for k in straight["history"][0] if k.startswith(("train_", "val_")) and "per_s" not in k]
    for ra, rb in zip(straight["history"], resumed["history"]):
        assert [ra[k] for k in loss_cols] == [rb[k] for k in loss_cols]
    # and training did something: the weights moved away from the seeded initialisation
    torch.manual_seed(0)
    from geodepth_lite.core.model import DepthNet

    init = DepthNet().state_dict()
    assert any(not torch.equal(init[k], straight["model"][k]) for k in init if init[k].is_floating_point())


def test_different_seed_gives_different_weights(smoke_root, tmp_path):
    a = torch.load(train.fit(_cfg(smoke_root, epochs=1), tmp_path / "a", progress=False), weights_only=False)
    b = torch.load(train.fit(_cfg(smoke_root, epochs=1, seed=1), tmp_path / "b", progress=False), weights_only=False)
    assert any(not torch.equal(a["model"][k], b["model"][k]) for k in a["model"] if a["model"][k].is_floating_point())


def test_logs_hold_every_epoch_and_every_term(smoke_root, tmp_path):
    cfg = _cfg(smoke_root, epochs=2)
    train.fit(cfg, tmp_path / "run", progress=False)
    rows = json.loads((tmp_path / "run" / "log.json").read_text())["epochs"]
    csv_lines = (tmp_path / "run" / "log.csv").read_text().strip().splitlines()
    assert [r["epoch"] for r in rows] == [1, 2] and len(csv_lines) == 3
    header = csv_lines[0].split(",")
    for term in train.log_keys():
        assert f"train_{term}" in header and f"val_{term}" in header
    for m in metrics.METRIC_NAMES:
        assert f"val_{m}" in header
    for r in rows:
        assert 0.0 <= r["data_wait_share"] <= 1.0
        assert np.isfinite([r[k] for k in r if k.startswith(("train_", "val_"))]).all()
        # Case 4: every term is computed; the weighted total is their sum (lambdas all 1)
        parts = sum(r[f"train_{k}"] for k in ("depth", "smooth", "grad", "normal", "sdf"))
        assert r["train_total"] == pytest.approx(parts, rel=1e-5)


def test_existing_checkpoint_needs_resume_and_the_same_config(smoke_root, tmp_path):
    cfg = _cfg(smoke_root, epochs=1)
    train.fit(cfg, tmp_path / "run", progress=False)
    with pytest.raises(FileExistsError, match="--resume"):
        train.fit(cfg, tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match="lr"):
        train.fit(_cfg(smoke_root, epochs=1, lr=0.5), tmp_path / "run", progress=False, resume=True)
    # a finished run resumed is returned untouched
    before = (tmp_path / "run" / "checkpoint.pt").stat().st_mtime_ns
    train.fit(cfg, tmp_path / "run", progress=False, resume=True)
    assert (tmp_path / "run" / "checkpoint.pt").stat().st_mtime_ns == before


def test_interrupted_checkpoint_write_keeps_the_previous_one_whole(smoke_root, tmp_path, monkeypatch):
    cfg = _cfg(smoke_root, epochs=2)
    run = tmp_path / "run"
    train.fit(cfg, run, progress=False, stop_after=1)
    good = (run / "checkpoint.pt").read_bytes()

    real_write = Path.write_bytes

    def dying_write(self, data):  # half the checkpoint reaches the disk, then the process "dies"
        if self.name.startswith(utils.temp_prefix("checkpoint.pt")):
            real_write(self, data[: len(data) // 2])
            raise KeyboardInterrupt
        return real_write(self, data)

    monkeypatch.setattr(Path, "write_bytes", dying_write)
    with pytest.raises(KeyboardInterrupt):
        train.fit(cfg, run, progress=False, resume=True)
    monkeypatch.setattr(Path, "write_bytes", real_write)
    assert (run / "checkpoint.pt").read_bytes() == good
    assert not list(run.glob(utils.TEMP_GLOB))  # no temp files left (the lock file stays, by design)
    assert torch.load(run / "checkpoint.pt", weights_only=False)["epoch"] == 1
    assert train.fit(cfg, run, progress=False, resume=True).exists()
    assert torch.load(run / "checkpoint.pt", weights_only=False)["epoch"] == 2


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="image_size"):
        config.make_config("smoke", image_size=100)
    with pytest.raises(ValueError, match="case"):
        config.make_config("smoke", case=5)
    with pytest.raises(ValueError, match="profile"):
        config.make_config("laptop")
    with pytest.raises(ValueError, match="unknown training setting 'epoch'"):
        config.make_config("smoke", epoch=3)
    with pytest.raises(ValueError, match="batch_size"):
        config.make_config("smoke", batch_size=0)
    with pytest.raises(ValueError, match="lr_schedule"):
        config.make_config("smoke", lr_schedule="linear")
    with pytest.raises(FileNotFoundError, match="encoder_weights"):
        config.make_config("smoke", encoder_weights="/nonexistent/resnet18.pth")
    for key in ("optimizer", "depth_term", "augment"):
        with pytest.raises(ValueError, match=key):
            config.make_config("smoke", **{key: "nonsense"})
    for bad in (-1.0, "2", True, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="border_weight"):
            config.make_config("smoke", border_weight=bad)
    for bad in (-16, 8, "16", True, 16.0):
        with pytest.raises(ValueError, match="input_pad"):
            config.make_config("smoke", input_pad=bad)


@pytest.mark.parametrize("key, other", [("border_weight", 2.0), ("input_pad", 16)])
def test_a_later_key_at_its_default_keeps_old_checkpoint_names(key, other):
    """border_weight and input_pad were added after checkpoints existed: at their defaults they are
    not part of the identity, so a configuration saved without the key has the same hash; any other
    value is a different run."""
    cfg = config.make_config("teach", 4, 0)
    old = {k: v for k, v in cfg.items() if k != key}  # a checkpoint's cfg from before the key
    assert cfg[key] == config.LATER_KEY_DEFAULTS[key]
    assert config.config_hash(old) == config.config_hash(cfg)
    assert config.config_identity(old) == config.config_identity(cfg)
    changed = config.make_config("teach", 4, 0, **{key: other})
    assert changed[key] == other and config.config_hash(changed) != config.config_hash(cfg)
    assert config.config_identity(changed)[key] == other



def test_the_configured_border_weight_reaches_the_depth_term():
    """train.compute_losses passes cfg["border_weight"] on: an error only in the outermost ring of a
    16 x 16 frame weighs more with border_weight 2 than with 0, by the map's hand-computable factor."""
    from geodepth_lite.core import camera, losses

    gt = torch.full((1, 1, 16, 16), 2.0)
    ring = torch.zeros_like(gt, dtype=torch.bool)
    ring[..., 0, :] = ring[..., -1, :] = ring[..., :, 0] = ring[..., :, -1] = True
    batch = {"depth": gt, "image": torch.rand(1, 3, 16, 16), "K": torch.as_tensor(camera.intrinsics(16)).float()}
    pred = torch.where(ring, gt * 1.1, gt)
    terms = {}
    for bw in (0.0, 2.0):
        cfg = config.make_config("smoke", 1, 0, depth_term="log_l1", border_weight=bw)
        terms[bw] = train.compute_losses(pred, batch, cfg)[1]["depth"]
    w = losses.border_weight_map(16, 16, 2.0)[0, 0]
    share = float(w[ring[0, 0]].sum() / w.sum())  # the ring's share of the total weight
    assert terms[0.0] == pytest.approx(np.log(1.1) * 60 / 256, rel=1e-5)
    assert terms[2.0] == pytest.approx(np.log(1.1) * share, rel=1e-5) and terms[2.0] > terms[0.0]


def test_paper_profile_has_the_papers_settings():
    cfg = config.make_config("paper")
    assert ((cfg["image_size"], cfg["epochs"], cfg["batch_size"], cfg["lr"], cfg["weight_decay"])
            == (320, 18, 20, 1e-4, 0.01))
    assert cfg["betas"] == [0.9, 0.999] and cfg["sdf_grid"] == 32 and cfg["lambdas"] == [1.0, 1.0, 1.0]
    assert cfg["lr_schedule"] == "constant"
    assert (cfg["optimizer"], cfg["depth_term"], cfg["augment"]) == ("adam", "l1", "none")


def test_case_lambdas_switch_terms_on_with_the_profiles_weights():
    from geodepth_lite.training import config

    w2, w3 = config.PROFILES["teach"]["geo_weights"]
    assert [config.make_config("teach", c)["lambdas"] for c in (1, 2, 3, 4)] == [
        [1.0, 0.0, 0.0], [1.0, w2, 0.0], [1.0, 0.0, w3], [1.0, w2, w3]]
    assert config.make_config("paper", 4)["lambdas"] == [1.0, 1.0, 1.0]  # the paper states no weights


def test_flip_augmentation_mirrors_the_3d_scene():
    """A flipped frame with K's cx moved to W - 1 - cx back-projects to the mirror image (x -> -x)."""
    from geodepth_lite.core import camera

    torch.manual_seed(0)
    B, H, W = 6, 8, 10
    depth = torch.rand(B, 1, H, W) + 1
    K = torch.tensor([[7.0, 0, 4.3], [0, 7.0, 3.9], [0, 0, 1]]).expand(B, 3, 3).clone()
    batch = {"image": torch.rand(B, 3, H, W), "depth": depth, "K": K, "valid": depth > 1.5}
    torch.manual_seed(1)
    out = augment.augment_batch(batch, "flip")
    torch.manual_seed(1)
    flipped = torch.rand(B) < 0.5  # the same draw
    assert 0 < int(flipped.sum()) < B
    P = camera.backproject(depth, K).reshape(B, H, W, 3)
    Q = camera.backproject(out["depth"], out["K"]).reshape(B, H, W, 3)
    for b in range(B):
        if flipped[b]:
            mirror = P[b].flip(1) * torch.tensor([-1.0, 1.0, 1.0])
            torch.testing.assert_close(Q[b], mirror)
            assert torch.equal(out["valid"][b], batch["valid"][b].flip(-1))
            assert torch.equal(out["image"][b], batch["image"][b].flip(-1))
        else:
            torch.testing.assert_close(Q[b], P[b])
    assert augment.augment_batch(batch, "none") is batch
    color = augment.augment_batch(batch, "flip_color")
    assert color["image"].min() >= 0 and color["image"].max() <= 1


def test_camera_augmentation_changes_the_image_only_and_repeats_under_the_same_seed():
    """augment="camera": flips like "flip" (same K and depth), then camera effects on the image alone."""
    torch.manual_seed(0)
    B, H, W = 8, 16, 16
    depth = torch.rand(B, 1, H, W) + 1
    K = torch.tensor([[11.0, 0, 7.5], [0, 11.0, 7.5], [0, 0, 1]]).expand(B, 3, 3).clone()
    batch = {"image": torch.rand(B, 3, H, W) * 0.5 + 0.25, "depth": depth, "K": K, "valid": depth > 0}
    torch.manual_seed(3)
    flip = augment.augment_batch(batch, "flip")
    torch.manual_seed(3)
    cam = augment.augment_batch(batch, "camera")
    torch.manual_seed(3)
    again = augment.augment_batch(batch, "camera")
    assert torch.equal(cam["depth"], flip["depth"]) and torch.equal(cam["K"], flip["K"])
    assert torch.equal(cam["image"], again["image"])  # drawn from torch's RNG: resume repeats it
    assert cam["image"].shape == (B, 3, H, W) and cam["image"].dtype == batch["image"].dtype
    assert 0 <= float(cam["image"].min()) and float(cam["image"].max()) <= 1
    changed = (cam["image"] - flip["image"]).abs().mean(dim=(1, 2, 3))
    assert int((changed > 2 / 255).sum()) >= B // 2  # most frames visibly altered (exposure, cast, gamma ...)


def test_ensure_checkpoint_trains_once_then_reuses(smoke_root, tmp_path):
    run = config.profile("smoke").run(case=1, seed=0, dataset=str(smoke_root), image_size=32)
    path = run_cache.ensure_checkpoint(run)
    stamp = path.stat().st_mtime_ns
    again = run_cache.ensure_checkpoint(config.profile("smoke").run(1, 0, dataset=str(smoke_root), image_size=32))
    assert again == path and path.stat().st_mtime_ns == stamp
    assert path.parent.parent == utils.runs_dir() / "smoke" / "checkpoints"
    model, cfg = checkpoint.load_model(path)
    assert cfg["lambdas"] == [1.0, 0.0, 0.0] and not model.training


def test_predict_depth_resizes_to_the_network_and_back(smoke_root):
    from geodepth_lite.core.model import DepthNet

    torch.manual_seed(0)
    model = DepthNet().eval()
    images = torch.rand(2, 3, 50, 70)
    out = inference.predict_depth(model, images, 64)
    assert out.shape == (2, 1, 50, 70) and torch.isfinite(out).all() and (out > 0).all()
    # at the network size nothing is resized: the same as calling the model
    x = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        assert torch.allclose(inference.predict_depth(model, x, 64), model(x))
    with pytest.raises(ValueError, match="B x 3"):
        inference.predict_depth(model, torch.rand(2, 1, 64, 64), 64)


def test_test_time_flips_make_the_prediction_mirror_with_the_image():
    """flips="h" averages the prediction for the mirrored frame back in, so the result mirrors exactly
    with its input, which the bare network does not; "hv" does so along both axes; "none" is one pass
    (the network's own output); an unknown name is refused with the choices."""
    from geodepth_lite.core.model import DepthNet

    torch.manual_seed(0)
    model = DepthNet().eval()
    x = torch.rand(2, 3, 64, 64)

    def close(a, b):
        return torch.allclose(a, b, rtol=1e-5, atol=1e-6)

    with torch.no_grad():
        assert torch.equal(inference.predict_depth(model, x, 64, "none"), model(x))
        assert not close(model(x.flip(-1)), model(x).flip(-1))  # the untrained network is not symmetric
        h = inference.predict_depth(model, x, 64, "h")
        assert close(inference.predict_depth(model, x.flip(-1), 64, "h"), h.flip(-1))
        assert not close(inference.predict_depth(model, x.flip(-2), 64, "h"), h.flip(-2))
        hv = inference.predict_depth(model, x, 64, "hv")
        for dims in ((-1,), (-2,), (-2, -1)):
            assert close(inference.predict_depth(model, x.flip(dims), 64, "hv"), hv.flip(dims))
        # the mean of the passes: between the smallest and largest of them at every pixel
        passes = torch.stack([model(x.flip(d)).flip(d) if d else model(x) for d in inference.FLIPS["hv"]])
        assert (hv >= passes.min(0).values - 1e-6).all() and (hv <= passes.max(0).values + 1e-6).all()
    with pytest.raises(ValueError, match="flips must be one of none, h, hv, got 'lr'"):
        inference.predict_depth(model, x, 64, "lr")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ddp_two_cpu_processes_with_gloo(smoke_root, tmp_path):
    run = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_addr", "127.0.0.1",
           "--master_port", str(_free_port()), "-m", "geodepth_lite", "train", "--profile", "smoke",
           "--dataset", str(smoke_root), "--epochs", "1", "--batch-size", "3", "--image-size", "32",
           "--run-dir", str(run),
           "--no-progress", "--device", "cpu"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ckpt = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ckpt["world_size"] == 2 and ckpt["epoch"] == 1
    rows = json.loads((run / "log.json").read_text())["epochs"]
    assert len(rows) == 1 and np.isfinite(rows[0]["train_total"]) and np.isfinite(rows[0]["val_rmse"])
    assert proc.stdout.count("checkpoint:") == 1  # only rank 0 reports


def test_predict_checkpoint_uses_the_profiles_predict_image_size(monkeypatch, smoke_root):
    """The model of notebooks 04/06/07 and predict: the profile's predict_image_size and
    predict_overrides, its own run folder; the loaded network pads as it was trained."""
    from geodepth_lite.training import config

    monkeypatch.setitem(config.PROFILES, "smoke", dict(config.PROFILES["smoke"], predict_image_size=32,
                                                         predict_overrides={"input_pad": 16, "border_weight": 2.0},
                                                         dataset=str(smoke_root)))
    smoke = config.profile("smoke")
    path = run_cache.ensure_checkpoint(smoke.predict_run(case=1, seed=0))
    net, cfg = checkpoint.load_model(path)
    assert cfg["image_size"] == 32 and cfg["case"] == 1 and cfg["border_weight"] == 2.0
    assert cfg["input_pad"] == 16 and net.input_pad == 16
    assert path.parent == run_cache.checkpoint_dir(smoke.run(1, 0, image_size=32, input_pad=16, border_weight=2.0))
    assert path.parent != run_cache.checkpoint_dir(smoke.run(1, 0))  # the ablation's run (64 px) is another folder
    assert config.PROFILES["teach"]["predict_image_size"] % 32 == 0
    for name in config.PROFILES:  # every profile's predict model is a valid configuration
        config.profile(name).predict_run()


def test_the_model_for_real_frames_is_the_predict_model_with_the_real_overrides():
    """teach: the predict settings and augment="crop", its own run folder; paper: the predict model
    itself (no overrides). The train command's --augment names the same run."""
    from geodepth_lite import cli
    from geodepth_lite.training import config
    from geodepth_lite.workbook import reproduce

    teach, paper = config.profile("teach"), config.profile("paper")
    real, pred = teach.real_settings(), teach.predict_settings()
    assert real == {**pred, "augment": "crop"}
    assert run_cache.checkpoint_dir(teach.real_run()) != run_cache.checkpoint_dir(teach.predict_run())
    assert paper.real_settings() == paper.predict_settings() and paper.real_run() == paper.predict_run()
    for name in config.PROFILES:
        config.profile(name).real_run()
    assert reproduce.SETTINGS["real"](teach) == real
    args = cli.build_parser().parse_args(["train", "--image-size", "96", "--input-pad", "16", "--border-weight",
                                          "2", "--augment", "crop"])
    cfg = config.make_config("teach", 4, 0, image_size=args.image_size, input_pad=args.input_pad,
                             border_weight=args.border_weight, augment=args.augment)
    assert config.config_hash(cfg) == config.config_hash(config.make_config("teach", 4, 0, **real))
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["train", "--augment", "zoom"])


def test_a_sixth_loss_term_is_one_table_entry(monkeypatch, smoke_root, tmp_path):
    """A dummy term (total variation of the prediction, in a new weight group) added to
    losses.LOSS_TERMS: total_loss weights it by name, and one smoke epoch trains and logs it."""
    from geodepth_lite.core import losses

    def tv(pred, x):
        return (pred[..., :, 1:] - pred[..., :, :-1]).abs().mean()

    monkeypatch.setitem(losses.LOSS_TERMS, "tv", losses.LossTerm(tv, "lambda4", "test"))
    assert losses.term_names()[-1] == "tv" and losses.group_names()[-1] == "lambda4"
    # known answer: a ramp of slope 0.5 along x has TV 0.5; equal pred and gt zero every other term
    ramp = 2.0 + 0.5 * torch.arange(8.0).expand(1, 1, 8, 8)
    K = torch.tensor([[8.0, 0, 3.5], [0, 8.0, 3.5], [0, 0, 1]])
    image = torch.full((1, 3, 8, 8), 0.5)
    loss, terms = losses.total_loss(ramp, ramp, image, K, losses.LossSpec(lambdas={"lambda1": 1.0, "lambda4": 0.25}))
    assert terms["tv"] == pytest.approx(0.5) and terms["depth"] == 0.0 and terms["sdf"] == 0.0
    assert float(loss) == pytest.approx(terms["smooth"] + 0.25 * 0.5)
    with pytest.raises(ValueError, match="lambdas must be 4"):
        losses.LossSpec(lambdas=(1.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="lambdas must be 4"):
        losses.total_loss(ramp, ramp, image, K)  # the default spec, made before the fourth group
    with pytest.raises(ValueError, match="unknown loss weight group 'lambda9'"):
        config.make_config("smoke", 1, 0, lambdas={"lambda9": 1.0})
    cfg = config.make_config("smoke", 1, 0, dataset=str(smoke_root), image_size=32,
                             lambdas={"lambda1": 1.0, "lambda4": 0.5})
    assert cfg["lambdas"] == [1.0, 0.0, 0.0, 0.5]
    row = checkpoint.read_log(train.fit(cfg, tmp_path / "run", progress=False))[-1]
    assert row["train_tv"] > 0 and row["val_tv"] > 0 and row["gradnorm_tv"] > 0
    assert row["train_sdf"] == 0.0  # lambda3 = 0: not computed


def test_lambdas_by_group_name_are_the_papers_three_weights():
    by_name = config.make_config("smoke", 4, 0, lambdas={"lambda1": 1.0, "lambda2": 0.5, "lambda3": 0.01})
    by_order = config.make_config("smoke", 4, 0, lambdas=[1.0, 0.5, 0.01])
    assert by_name["lambdas"] == by_order["lambdas"] == [1.0, 0.5, 0.01]
    assert config.config_hash(by_name) == config.config_hash(by_order)


def test_crop_augmentation_keeps_every_ray():
    """augment="crop": the image encodes each pixel's source coordinates (linear, so bilinear
    resampling is exact inside the crop); the new K must give every pixel the ray of the frame
    pixel it came from (mirrored in x where flipped). Nearest-exact sampling never invents a depth."""
    B, H, W = 6, 32, 32
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    image = torch.stack((u / (W - 1), v / (H - 1), torch.full_like(u, 0.5))).expand(B, 3, H, W).clone()
    depth = (2.0 + 0.05 * u + 0.03 * v).float().expand(B, 1, H, W).clone()
    K = torch.tensor([[30.0, 0, 14.0], [0, 28.0, 16.5], [0, 0, 1]], dtype=torch.float64).expand(B, 3, 3).clone()
    torch.manual_seed(3)
    out = augment.augment_batch({"image": image, "depth": depth, "K": K}, "crop")
    assert set(out["depth"].flatten().tolist()) <= set(depth.flatten().tolist())
    inner = (slice(1, -1), slice(1, -1))
    cropped = 0
    for b in range(B):
        Kb = out["K"][b]
        u_src, v_src = out["image"][b, 0][inner] * (W - 1), out["image"][b, 1][inner] * (H - 1)
        x_new = (u[inner] - Kb[0, 2]) / Kb[0, 0]
        x_old = (u_src - K[b, 0, 2]) / K[b, 0, 0]
        torch.testing.assert_close((v[inner] - Kb[1, 2]) / Kb[1, 1], (v_src - K[b, 1, 2]) / K[b, 1, 1],
                                   atol=1e-5, rtol=0)
        assert min(float((x_new - x_old).abs().max()), float((x_new + x_old).abs().max())) < 1e-5
        cropped += int(float(Kb[0, 0]) > 30.0 + 1e-6)  # zoomed in
    assert cropped >= 4  # most frames are really cropped (scale uniform in CROP_SCALE)


def test_fov_augmentation_paints_a_border_fills_it_and_leaves_it_out_of_the_loss():
    """augment="fov": about half the frames get a field of view with text; outside it the image is
    the nearest inside pixel (what predict shows the network) and ``valid`` is False there; the
    depth, K and the other frames are the flipped originals."""
    from geodepth_lite.data import fov

    B, H, W = 12, 48, 64
    torch.manual_seed(5)
    image = torch.rand(B, 3, H, W)
    depth = torch.rand(B, 1, H, W) + 1.0
    K = torch.eye(3, dtype=torch.float64).expand(B, 3, 3).clone()
    out = augment.augment_batch({"image": image, "depth": depth, "K": K}, "fov")
    painted = [b for b in range(B) if not bool(out["valid"][b].all())]
    assert 2 <= len(painted) <= B - 2 and out["valid"].dtype == torch.bool
    for b in range(B):
        flipped = not torch.equal(out["depth"][b], depth[b])
        assert torch.equal(out["depth"][b], depth[b].flip(-1) if flipped else depth[b])
        original = image[b].flip(-1) if flipped else image[b]
        inside = out["valid"][b, 0].numpy()
        np.testing.assert_allclose(out["image"][b].permute(1, 2, 0)[inside].numpy(),
                                   original.permute(1, 2, 0)[inside].numpy(), atol=1e-6)
        if b in painted:
            refilled = fov.fill_outside(out["image"][b].permute(1, 2, 0).numpy(), inside)
            np.testing.assert_allclose(refilled, out["image"][b].permute(1, 2, 0).numpy(), atol=1e-6)



def test_ensure_runs_trains_each_run_folder_once_largest_first(monkeypatch, smoke_root):
    """One job per run folder (notebooks 04, 06 and 07 ask for the same model; an override equal
    to the profile's value is the same run), finished runs skipped, the largest input first; the
    paths come back in the order asked."""
    from geodepth_lite.training import config

    monkeypatch.setitem(config.PROFILES, "smoke", dict(config.PROFILES["smoke"], dataset=str(smoke_root)))
    calls = []

    def fake_ensure(run, progress=False, announce=True):
        calls.append((run.case, run.seed, run.overrides.get("image_size")))

    monkeypatch.setattr(run_cache, "ensure_checkpoint", fake_ensure)
    monkeypatch.setattr(run_cache, "resolve_dataset", lambda cfg, progress=False: smoke_root)
    monkeypatch.setattr(run_cache, "is_complete", lambda run: (run.case, run.seed) == (2, 0))
    assert config.PROFILES["smoke"]["image_size"] == 64
    smoke = config.profile("smoke")
    runs = [smoke.run(1, 0), smoke.run(4, 0, image_size=96), smoke.run(1, 1), smoke.run(4, 0, image_size=96),
            smoke.run(1, 0, image_size=64), smoke.run(2, 0)]
    paths = run_cache.ensure_runs(runs, workers=1)
    assert calls == [(4, 0, 96), (1, 0, None), (1, 1, None)]
    assert paths == [run_cache.checkpoint_dir(run) / "checkpoint.pt" for run in runs]
    assert paths[1] == paths[3] and paths[0] == paths[4] and len(set(paths)) == 4


@pytest.mark.parametrize("case, evaluated", [(1, False), (4, True)])
def test_a_term_whose_weight_is_zero_is_never_evaluated(monkeypatch, smoke_root, tmp_path, case, evaluated):
    """Case 1 (SDF weight 0): no SDF field in training, validation or the gradient-norm log; Case 4
    (the control, so the counter can count) evaluates them, and logs every term's gradient norm."""
    from geodepth_lite.core import losses

    calls = []
    fields = losses.sdf_fields_batched
    monkeypatch.setattr(losses, "sdf_fields_batched", lambda *a, **k: calls.append(1) or fields(*a, **k))
    row = checkpoint.read_log(train.fit(_cfg(smoke_root, case=case, epochs=1), tmp_path / "run", progress=False))[-1]
    assert bool(calls) is evaluated
    logged = sorted(k[len("gradnorm_"):] for k in row if k.startswith("gradnorm_"))
    assert logged == sorted(losses.term_names() if evaluated else ("depth", "smooth"))
    assert row["train_sdf"] == 0.0 if not evaluated else row["train_sdf"] > 0


def test_a_fine_tuning_run_starts_from_the_finished_run_beside_it(smoke_root, tmp_path):
    """init_from: the weights of the named run folder beside this one; with a learning rate of 1e-12
    they stay those weights (Adam moves each by about the learning rate a step), while a run without
    init_from stays at its own initialisation; the provenance names the source checkpoint by its SHA-256."""
    from geodepth_lite.data import integrity

    runs = tmp_path / "checkpoints"
    source_cfg = _cfg(smoke_root, epochs=1)
    source = train.fit(source_cfg, runs / f"case4_seed0-{config.config_hash(source_cfg)}", progress=False)
    tuned_cfg = _cfg(smoke_root, epochs=1, lr=1e-12, init_from=source.parent.name)
    tuned = train.fit(tuned_cfg, runs / "tuned", progress=False)
    fresh = train.fit(_cfg(smoke_root, epochs=1, lr=1e-12), runs / "fresh", progress=False)
    src, got, own = (torch.load(p, weights_only=False)["model"] for p in (source, tuned, fresh))
    params = [k for k in src if k.endswith(".weight") and src[k].dim() == 4]  # the convolutions
    assert params and all(torch.allclose(src[k], got[k], rtol=0, atol=1e-9) for k in params)
    assert not any(torch.allclose(src[k], own[k], rtol=0, atol=1e-9) for k in params)
    log = checkpoint.read_log_file(tuned.parent)
    assert log["provenance"][-1]["init_from_sha256"] == integrity.file_sha256(source)
    assert config.config_hash(tuned_cfg) != config.config_hash(_cfg(smoke_root, epochs=1, lr=1e-12))


def test_a_fine_tuning_run_refuses_a_missing_unfinished_or_misnamed_source(smoke_root, tmp_path):
    from geodepth_lite.core.errors import UserError

    runs = tmp_path / "checkpoints"
    cfg = _cfg(smoke_root, epochs=2)
    name = f"case4_seed0-{config.config_hash(cfg)}"
    with pytest.raises(UserError, match=f"no run {name} beside"):
        train.fit(_cfg(smoke_root, epochs=1, init_from=name), runs / "a", progress=False)
    assert not (runs / "a").exists()  # a refused run leaves nothing behind
    train.fit(cfg, runs / name, progress=False, stop_after=1)  # one of two epochs: not finished
    with pytest.raises(UserError, match="is not finished"):
        train.fit(_cfg(smoke_root, epochs=1, init_from=name), runs / "b", progress=False)
    other = _cfg(smoke_root, epochs=1)
    wrong = runs / f"case4_seed0-{'0' * 8}"
    train.fit(other, wrong, progress=False)  # finished, but its configuration is not the one named
    with pytest.raises(UserError, match="other than the one its folder is named for"):
        train.fit(_cfg(smoke_root, epochs=1, init_from=wrong.name), runs / "c", progress=False)
    for bad in ("../case4_seed0-00000000", "case4_seed0-XYZ", 7):
        with pytest.raises(UserError, match="init_from must name a run folder"):
            _cfg(smoke_root, init_from=bad)


def test_ensure_runs_starts_a_fine_tuning_run_after_its_source(monkeypatch, smoke_root):
    """One worker: the run that fine-tunes another waits until that one is trained, whatever the
    order asked; a source already finished is not waited for."""
    from geodepth_lite.training import config

    monkeypatch.setitem(config.PROFILES, "smoke", dict(config.PROFILES["smoke"], dataset=str(smoke_root)))
    calls = []
    monkeypatch.setattr(run_cache, "ensure_checkpoint", lambda run, progress=False, announce=True: calls.append(
        (run.case, run.seed, run["init_from"])))
    monkeypatch.setattr(run_cache, "resolve_dataset", lambda cfg, progress=False: smoke_root)
    monkeypatch.setattr(run_cache, "is_complete", lambda run: False)
    smoke = config.profile("smoke")
    source = smoke.run(4, 0, image_size=96).folder_name
    runs = [smoke.run(4, 0, image_size=64, init_from=source), smoke.run(1, 0), smoke.run(4, 0, image_size=96)]
    run_cache.ensure_runs(runs, workers=1)
    assert calls == [(4, 0, None), (1, 0, None), (4, 0, source)]
