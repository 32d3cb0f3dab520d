"""Trivial baselines: known answers for each predictor, one pass beside the model, the CLI's rows."""

import json
import shutil

import numpy as np
import pytest
import torch
from conftest import save_untrained_checkpoint

from geodepth_lite.core.metrics import compute_depth_metrics
from geodepth_lite.evaluation import baselines, evaluate


def _frames(depths, images=None, organ="colon", group="pink-warm_single"):
    """An in-memory dataset (a list of item dicts, as SyntheticDepthDataset's) of N x H x W depths."""
    depths = np.asarray(depths, dtype=np.float32)
    if images is None:
        images = np.full((len(depths), 3, *depths.shape[1:]), 0.5, dtype=np.float32)
    return [{"image": torch.as_tensor(images[i]), "depth": torch.as_tensor(depths[i])[None], "organ": organ,
             "group": group, "index": i} for i in range(len(depths))]


def _smooth_depth(h=48, w=64):
    """A smooth, positive depth map (a tilted wall with a gentle bump), 1.0 .. ~2.3."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return 1.0 + 0.8 * x / w + 0.3 * y / h + 0.2 * np.exp(-((x - w / 2) ** 2 + (y - h / 2) ** 2) / (2 * 15.0**2))


def _render_inverse_square(depth, tint=(1.0, 0.8, 0.7)):
    """brightness = c / depth^2 with a constant albedo ``tint`` per channel: 3 x H x W in [0, 1]."""
    c = 0.9 * depth.min() ** 2
    return np.stack([t * c / depth**2 for t in tint]).astype(np.float32)


# --------------------------------------------------------------------------- (a) shading prior


def test_shading_prior_recovers_inverse_square_depth_up_to_scale():
    """Without blur (sigma=0) 1 / sqrt(c / d^2) = d / sqrt(c): exact up to scale, Abs Rel ~ 0; a
    uniform albedo (any tint) only changes the scale. With the default 2 px blur the map is smooth
    enough on a 48 x 64 frame that the blur barely matters (Abs Rel ~1e-3, mostly at the borders,
    where the blur sees replicated edge pixels)."""
    depth = _smooth_depth()
    image = _render_inverse_square(depth)
    pred = baselines.shading_prior(image[None], sigma=0)
    assert pred.shape == (1, *depth.shape) and pred.dtype == np.float32
    exact = compute_depth_metrics(pred, depth[None])
    assert exact["abs_rel"] == pytest.approx(0.0, abs=1e-6)
    assert exact["a1"] == 1.0
    # the scale is 1 / sqrt(c * luma(tint)): median scaling removes it
    luma = float(np.dot(baselines.LUMA_WEIGHTS, (1.0, 0.8, 0.7)))
    assert pred[0] == pytest.approx(depth / np.sqrt(0.9 * depth.min() ** 2 * luma), rel=1e-5)
    blurred = compute_depth_metrics(baselines.shading_prior(torch.from_numpy(image), sigma=2.0), depth[None])
    assert blurred["abs_rel"] < 2e-3


def test_shading_prior_guards_black_pixels_relative_to_the_frame():
    image = np.zeros((2, 3, 8, 8), dtype=np.float32)
    image[0, :, :, :4] = 0.64  # left half lit, right half black
    pred = baselines.shading_prior(image, sigma=0)
    assert np.all(np.isfinite(pred))
    assert pred[0, 0, 0] == pytest.approx(1 / np.sqrt(0.64))
    # black pixels are clipped to SHADING_EPS_REL x the brightest: sqrt(1 / eps) times farther
    assert pred[0, 0, -1] / pred[0, 0, 0] == pytest.approx(np.sqrt(1 / baselines.SHADING_EPS_REL), rel=1e-5)
    assert np.all(pred[1] == pred[1, 0, 0])  # an all-black frame: a constant depth


# --------------------------------------------------------------------------- (b) constant


def test_constant_depth_scores_known_abs_rel():
    """Median scaling turns the constant into median(gt): 0 error on a flat wall; on half 1, half 3
    the median is 2, so Abs Rel = (|1-2|/1 + |3-2|/3) / 2 = 2/3, a1 = 0 (ratios 2, 1.5), a2 = 0.5."""
    flat = np.full((1, 4, 4), 2.5, dtype=np.float32)
    two = np.ones((1, 4, 4), dtype=np.float32)
    two[:, :, 2:] = 3.0
    images = np.zeros((1, 3, 4, 4), dtype=np.float32)
    pred = baselines.constant_depth(images)
    assert pred.shape == (1, 4, 4) and pred.dtype == np.float32
    assert compute_depth_metrics(pred, flat)["abs_rel"] == 0.0
    m = compute_depth_metrics(pred, two)
    assert m["abs_rel"] == pytest.approx(2 / 3)
    assert (m["a1"], m["a2"]) == (0.0, 0.5)
    # the same numbers through the evaluation protocol (one pass, per-frame rows, summaries)
    res = evaluate.evaluate_baselines(_frames(np.concatenate([flat, two])), None, names=["constant"])
    assert [r["abs_rel"] for r in res["constant"]["frames"]] == pytest.approx([0.0, 2 / 3])
    assert res["constant"]["overall"]["abs_rel"] == pytest.approx(1 / 3)
    assert res["constant"]["by_organ"]["colon"]["n"] == 2


# --------------------------------------------------------------------------- (c) mean depth map


def test_mean_depth_map_is_the_pixelwise_mean_over_valid_pixels():
    nan, inf = float("nan"), float("inf")
    d = np.array([[[1.0, 2.0, 0.0], [4.0, nan, 6.0]],
                  [[3.0, 4.0, -1.0], [8.0, inf, 5.0]],
                  [[5.0, 9.0, 0.0], [6.0, 0.0, 1.0]]])
    valid = np.ones_like(d, dtype=bool)
    valid[1, 0, 1] = False  # the 4.0 is excluded by the mask
    # pixel (0, 2) and (1, 1) are never valid: they get the mean of all 11 valid depths
    valid_values = [1, 2, 4, 6, 3, 8, 5, 5, 9, 6, 1]
    fill = np.mean(valid_values)
    expected = np.array([[(1 + 3 + 5) / 3, (2 + 9) / 2, fill], [(4 + 8 + 6) / 3, fill, (6 + 5 + 1) / 3]])
    got = baselines.mean_depth_map(d, valid)
    assert got.shape == (2, 3) and got.dtype == np.float32
    assert got == pytest.approx(expected.astype(np.float32))
    # streamed maps (a generator, N x 1 x H x W tensors) give the same map
    streamed = baselines.mean_depth_map((torch.as_tensor(m)[None] for m in d), (v[None] for v in valid))
    assert streamed == pytest.approx(got)
    with pytest.raises(ValueError, match="no valid"):
        baselines.mean_depth_map(np.zeros((2, 3, 3)))
    with pytest.raises(ValueError, match="one size"):
        baselines.mean_depth_map([np.ones((2, 2)), np.ones((3, 3))])


def test_mean_map_is_resized_nearest_and_scores_zero_on_its_own_layout():
    layout = _smooth_depth(8, 8).astype(np.float32)
    ds = _frames(np.stack([2 * layout, 5 * layout]))  # every frame: the same layout up to scale
    res = evaluate.evaluate_baselines(ds, baselines.mean_depth_map([2 * layout, 5 * layout]),
                                       names=["mean_depth_map"])
    assert res["mean_depth_map"]["overall"]["abs_rel"] == pytest.approx(0.0, abs=1e-6)
    up = baselines.apply_mean_depth_map(np.zeros((3, 3, 16, 16)), layout)
    assert up.shape == (3, 16, 16) and np.all(up[:, ::2, ::2] == layout)  # nearest: no new depths


# --------------------------------------------------------------------------- (d) end to end


def test_all_baselines_on_the_smoke_dataset(smoke_root):
    from geodepth_lite.data.datasets import SyntheticDepthDataset

    ds = SyntheticDepthDataset(smoke_root, "test")
    res = evaluate.evaluate_baselines(ds, smoke_root, batch_size=4)
    assert list(res) == list(baselines.BASELINES)
    for name, r in res.items():
        assert r["n"] == len(ds) and len(r["frames"]) == len(ds)
        assert all(np.isfinite(r["overall"][k]) for k in evaluate.METRIC_KEYS), name
        assert sum(g["n"] for g in r["by_group"].values()) == len(ds)
        assert r["description"] == baselines.BASELINES[name]
    assert "12 frames" in res["mean_depth_map"]["notes"][0]
    # fitting from the depth files equals the mean of the dataset's own depth items, at any size
    train = SyntheticDepthDataset(smoke_root, "train", image_size=32)
    fitted = baselines.fit_mean_depth_map(smoke_root, "train", image_size=32)
    assert fitted == pytest.approx(baselines.mean_depth_map(train[i]["depth"] for i in range(len(train))))


@pytest.fixture(scope="module")
def smoke_ckpt(smoke_root, tmp_path_factory):
    from geodepth_lite.training import config

    cfg = config.make_config("smoke", 4, 0, dataset=str(smoke_root), image_size=32)
    return save_untrained_checkpoint(tmp_path_factory.mktemp("baseline_ckpt") / "checkpoint.pt", cfg)


def test_evaluate_cli_tables_have_baseline_rows(smoke_root, smoke_ckpt, tmp_path, capsys):
    from geodepth_lite import cli

    out = tmp_path / "eval"
    args = ["evaluate", "--checkpoint", str(smoke_ckpt), "--dataset", str(smoke_root), "--error-maps", "0",
            "--no-progress"]
    assert cli.main(args + ["--out", str(out)]) == 0, capsys.readouterr().err
    tables = (out / "tables.md").read_text()
    overall = tables.split("## Overall")[1].split("## By")[0]
    for name in baselines.BASELINES:
        assert f"| baseline: {name} | 6 |" in overall
    assert "| model (" in overall and "own train split" in overall
    result = json.loads((out / "metrics.json").read_text())
    assert set(result["baselines"]) == set(baselines.BASELINES)
    assert all("frames" not in b and np.isfinite(b["overall"]["abs_rel"]) for b in result["baselines"].values())
    assert "baseline: shading_prior" in capsys.readouterr().out
    # --no-baselines: the model's row only
    assert cli.main(args + ["--out", str(tmp_path / "plain"), "--no-baselines"]) == 0
    assert "baseline" not in (tmp_path / "plain" / "tables.md").read_text()
    assert "baselines" not in json.loads((tmp_path / "plain" / "metrics.json").read_text())


def test_without_a_train_split_the_mean_map_comes_from_the_checkpoints_dataset(smoke_root, smoke_ckpt, tmp_path):
    """A held-out set (test split only) is scored with the mean map of the training dataset."""
    from geodepth_lite import cli

    heldout = tmp_path / "heldout"
    heldout.mkdir()
    shutil.copy(smoke_root / "manifest.json", heldout / "manifest.json")
    shutil.copytree(smoke_root / "test", heldout / "test")
    out = tmp_path / "eval"
    assert cli.main(["evaluate", "--checkpoint", str(smoke_ckpt), "--dataset", str(heldout), "--error-maps", "0",
                     "--no-progress", "--out", str(out)]) == 0
    tables = (out / "tables.md").read_text()
    assert "checkpoint's training dataset" in tables and f"{smoke_root}/train" in tables
    assert np.isfinite(json.loads((out / "metrics.json").read_text())["baselines"]["mean_depth_map"]["overall"]["rmse"])
