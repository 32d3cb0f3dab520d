"""Validation on the device: the seven metrics in torch (``metrics.frame_metrics_torch``) against the numpy
protocol (``metrics.compute_depth_metrics``), the validation SDF term only where ``val_sdf`` asks for it, and
cached ground-truth fields keyed by frame id in training, with the same numbers as content keys."""

import math

import numpy as np
import pytest
import torch

from geodepth_lite.core import losses, metrics, sdf
from geodepth_lite.training import config, train


def frames(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(6, 1, 17, 19, generator=g) * 20 + 0.5
    gt[1] = 0.0  # no valid pixel: left out of the means
    gt[2, 0, :5] = float("nan")
    gt[3, 0, 3:] = 200.0  # beyond the protocol's maximum: 3 rows x 19 = 57 valid pixels (odd)
    gt[4, 0, 2:] = -1.0  # 2 rows x 19 = 38 valid pixels (even: the median is the mean of the two middle ones)
    pred = gt.clamp(0.1, 150) * (1 + 0.3 * torch.randn(gt.shape, generator=g)).abs() + 0.01
    pred[2, 0, :5] = float("nan")  # on invalid pixels only
    return pred, gt


def assert_same_metrics(ref: dict, got: dict, rel: float = 1e-12) -> None:
    for k in metrics.METRIC_NAMES:
        a, b = ref["per_frame"][k], got[k].numpy()
        assert np.array_equal(np.isnan(a), np.isnan(b)), k
        ok = ~np.isnan(a)
        assert np.allclose(a[ok], b[ok], rtol=rel, atol=0), (k, a, b)
    assert np.allclose(ref["ratios"], got["ratios"].numpy(), rtol=rel, atol=0, equal_nan=True)


@pytest.mark.parametrize("median_scaling", [True, False])
def test_device_metrics_are_the_numpy_protocol_s(median_scaling):
    pred, gt = frames()
    ref = metrics.compute_depth_metrics(pred.numpy(), gt.numpy(), median_scaling=median_scaling)
    got = metrics.frame_metrics_torch(pred, gt, median_scaling=median_scaling)
    assert_same_metrics(ref, got)
    assert got["used"].tolist() == [True, False, True, True, True, True] and not bool(got["bad"].any())
    # the lower middle value instead of numpy's mean of the two: the check sees it (frame 4, 38 pixels)
    lower = dict(got)
    valid = (gt[4] > 1e-3) & (gt[4] < 100)
    lower["ratios"] = got["ratios"].clone()
    lower["ratios"][4] = gt[4][valid].double().median() / pred[4][valid].double().median()
    if median_scaling:
        with pytest.raises(AssertionError):
            assert_same_metrics(ref, lower)


def test_device_metrics_flag_the_frames_numpy_refuses():
    pred, gt = frames()
    pred[0, 0, 0, 0] = float("inf")  # a non-finite prediction on a valid pixel
    with pytest.raises(ValueError, match="frame 0"):
        metrics.compute_depth_metrics(pred.numpy(), gt.numpy())
    assert metrics.frame_metrics_torch(pred, gt)["bad"].tolist() == [True] + [False] * 5
    with pytest.raises(ValueError, match="frame 0"):
        train._metric_means([metrics.frame_metrics_torch(pred, gt)])


def _smoke_cfg(root, **kw):
    kw = {"epochs": 1, "batch_size": 4, "image_size": 32, **kw}
    return config.make_config("smoke", 4, 0, dataset=str(root), **kw)


@pytest.mark.parametrize("val_sdf", [True, False])
def test_validation_evaluates_the_sdf_term_only_where_asked_and_leaves_the_rng_alone(monkeypatch, smoke_root,
                                                                                  val_sdf):
    from geodepth_lite.core.model import DepthNet
    from geodepth_lite.data.datasets import load_split

    cfg = _smoke_cfg(smoke_root, val_sdf=val_sdf)
    ds = load_split(smoke_root, "val", 32, limit=6)
    torch.manual_seed(3)
    model = DepthNet(encoder_weights=None)
    calls = []
    fields = losses.sdf_fields_batched
    monkeypatch.setattr(losses, "sdf_fields_batched", lambda *a, **k: calls.append(1) or fields(*a, **k))
    rng = torch.get_rng_state()
    weights = {k: v.clone() for k, v in model.state_dict().items()}
    out = train.validate(model, ds, cfg, torch.device("cpu"), space=train.frame_space(smoke_root, "val", 32))
    after = torch.get_rng_state()
    torch.set_rng_state(rng)
    iter(torch.utils.data.DataLoader(ds, batch_size=4, shuffle=False))  # draws its base seed, as ever
    assert torch.equal(after, torch.get_rng_state())  # validation draws nothing else
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in weights.items())
    assert bool(calls) is val_sdf
    assert not torch.equal(after, rng)  # the comparison can fail: the loader's draw is seen
    assert math.isnan(out["val_sdf"]) is (not val_sdf) and math.isnan(out["val_total"]) is (not val_sdf)
    # the metrics as the numpy protocol gives them on the same predictions
    model.eval()
    with torch.no_grad():
        pred = torch.cat([model(ds[i]["image"][None]) for i in range(len(ds))])
        gt = torch.stack([ds[i]["depth"] for i in range(len(ds))])
    ref = metrics.compute_depth_metrics(pred.numpy(), gt.numpy())
    for k in metrics.METRIC_NAMES:
        assert out[f"val_{k}"] == pytest.approx(ref[k], rel=1e-6)


def test_the_profiles_validation_sdf():
    assert config.make_config("teach")["val_sdf"] and config.make_config("smoke")["val_sdf"]
    assert not config.make_config("paper")["val_sdf"]
    with pytest.raises(ValueError, match="val_sdf"):
        config.make_config("smoke", val_sdf="no")
    # not a setting of the trained weights: the configuration's name does not change with it
    assert config.config_hash(config.make_config("paper")) == config.config_hash(
        config.make_config("paper", val_sdf=True))


def test_training_keys_cached_fields_by_frame_id_with_the_numbers_of_content_keys(monkeypatch, smoke_root,
                                                                                 tmp_path):
    """Two epochs with frame ids (no frame hashed: key() would fail the test) and two with content keys
    (frame ids withheld): the same log, loss for loss, and the cache hit in the second epoch."""
    cfg = _smoke_cfg(smoke_root, epochs=2, train_frames=8, val_frames=4)
    key = sdf.GTFieldCache.key
    sdf.GT_FIELD_CACHE.clear()
    monkeypatch.setattr(sdf.GTFieldCache, "key", staticmethod(lambda *a, **k: pytest.fail("hashed a frame")))
    by_id = train.fit(cfg, tmp_path / "ids", progress=False)
    hits = sdf.GT_FIELD_CACHE.hits
    assert hits >= 8 + 4  # epoch 2: every training and validation frame
    monkeypatch.setattr(sdf.GTFieldCache, "key", staticmethod(key))
    monkeypatch.setattr(train, "batch_frame_ids", lambda batch, space: None)
    sdf.GT_FIELD_CACHE.clear()
    by_content = train.fit(cfg, tmp_path / "content", progress=False)
    rows = [train.ckpt_io.read_log(p)[-1] for p in (by_id, by_content)]
    for k in rows[0]:
        if k.startswith(("train_", "val_", "gradnorm_")) and k != "train_frames_per_s":
            assert rows[0][k] == rows[1][k], k
    sdf.GT_FIELD_CACHE.clear()
