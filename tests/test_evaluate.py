"""Evaluation: the seven metrics on a smoke dataset, per-frame CSV, groups, error maps, the CLI."""

import csv
import json

import numpy as np
import pytest
import torch
from conftest import save_untrained_checkpoint

from geodepth_lite.core.metrics import compute_depth_metrics
from geodepth_lite.evaluation import border, evaluate, tables
from geodepth_lite.training import checkpoint, config, inference


@pytest.fixture(scope="module")
def smoke(smoke_root, tmp_path_factory):
    """The smoke dataset and an untrained checkpoint in train's format (network size 32)."""
    cfg = config.make_config("smoke", 4, 0, dataset=str(smoke_root), image_size=32)
    return smoke_root, save_untrained_checkpoint(tmp_path_factory.mktemp("eval_ckpt") / "checkpoint.pt", cfg)


def test_cli_writes_metrics_frames_and_error_maps(smoke, tmp_path, capsys):
    from geodepth_lite import cli
    from geodepth_lite.data.datasets import SyntheticDepthDataset

    root, ckpt = smoke
    out = tmp_path / "eval"
    code = cli.main(["evaluate", "--checkpoint", str(ckpt), "--dataset", str(root), "--split", "test",
                     "--out", str(out), "--error-maps", "2", "--no-progress"])
    assert code == 0, capsys.readouterr().err
    ds = SyntheticDepthDataset(root, "test")
    result = json.loads((out / "metrics.json").read_text())
    assert result["n"] == len(ds)
    for k in evaluate.METRIC_KEYS:
        assert np.isfinite(result["overall"][k])
    assert 0 <= result["overall"]["a1"] <= result["overall"]["a2"] <= result["overall"]["a3"] <= 1
    rows = list(csv.DictReader((out / "frames.csv").open()))
    assert len(rows) == len(ds) and set(evaluate.METRIC_KEYS) <= set(rows[0])
    assert {r["organ"] for r in rows} == {ds[i]["organ"] for i in range(len(ds))}
    # the group tables partition the frames
    assert sum(g["n"] for g in result["by_group"].values()) == len(ds)
    assert sum(g["n"] for g in result["by_organ"].values()) == len(ds)
    assert len(list((out / "error_maps").glob("*.png"))) == 2
    assert "| Abs Rel |" in (out / "tables.md").read_text()
    assert "RMSE" in capsys.readouterr().out


def test_per_frame_means_equal_the_metric_on_the_whole_set(smoke):
    """Groups are averaged from per-frame values: the same numbers as one call on all frames."""
    from geodepth_lite.data.datasets import SyntheticDepthDataset

    root, ckpt = smoke
    model, cfg = checkpoint.load_model(ckpt)
    ds = SyntheticDepthDataset(root, "test")
    result = evaluate.evaluate_model(model, ds, image_size=cfg["image_size"])
    images = torch.stack([ds[i]["image"] for i in range(len(ds))])
    gts = np.stack([ds[i]["depth"][0].numpy() for i in range(len(ds))])
    preds = inference.predict_depth(model, images, cfg["image_size"])[:, 0].numpy()
    whole = compute_depth_metrics(preds, gts)
    for k in evaluate.METRIC_KEYS:
        assert result["overall"][k] == pytest.approx(whole[k], rel=1e-5, abs=1e-7)
    by_organ = {o: [i for i in range(len(ds)) if ds[i]["organ"] == o] for o in result["by_organ"]}
    for organ, idx in by_organ.items():
        sub = compute_depth_metrics(preds[idx], gts[idx])
        assert result["by_organ"][organ]["rmse"] == pytest.approx(sub["rmse"], rel=1e-5)


def test_cli_flips_score_the_mean_over_the_mirrorings(smoke, tmp_path):
    """evaluate --flips hv scores the mean over the four mirrorings (the same metrics as
    evaluate_model with flips="hv"), not the one-pass prediction it scores by default."""
    from geodepth_lite import cli
    from geodepth_lite.data.datasets import SyntheticDepthDataset

    root, ckpt = smoke
    model, cfg = checkpoint.load_model(ckpt)
    ds = SyntheticDepthDataset(root, "test")
    scores = {}
    for flips in ("none", "hv"):
        out = tmp_path / flips
        assert cli.main(["evaluate", "--checkpoint", str(ckpt), "--dataset", str(root), "--split", "test",
                         "--out", str(out), "--error-maps", "0", "--no-baselines", "--no-progress",
                         "--flips", flips]) == 0
        scores[flips] = json.loads((out / "metrics.json").read_text())["overall"]
        direct = evaluate.evaluate_model(model, ds, image_size=cfg["image_size"], flips=flips)["overall"]
        for k in evaluate.METRIC_KEYS:
            assert scores[flips][k] == pytest.approx(direct[k], rel=1e-5, abs=1e-7)
    assert scores["hv"]["abs_rel"] != scores["none"]["abs_rel"]
    with pytest.raises(ValueError, match="flips must be one of"):
        evaluate.evaluate_model(model, ds, image_size=cfg["image_size"], flips="vh")


def test_a_perfect_prediction_up_to_scale_scores_perfectly(smoke):
    """A model that returns the ground truth up to a scale gets Abs Rel 0, a1 1 (median scaling)."""
    root, _ = smoke
    from geodepth_lite.data.datasets import SyntheticDepthDataset

    ds = SyntheticDepthDataset(root, "test")
    gts = {int(ds[i]["index"]): ds[i]["depth"] for i in range(len(ds))}

    class Oracle(torch.nn.Module):  # returns 3 x ground truth of the frame whose image it sees
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(1))
            self.lookup = [(ds[i]["image"], ds[i]["depth"]) for i in range(len(ds))]

        def forward(self, x):
            out = []
            for img in x:
                d = next(d for im, d in self.lookup if torch.equal(im, img))
                out.append(3.0 * d)
            return torch.stack(out)

    result = evaluate.evaluate_model(Oracle(), ds, image_size=None)
    assert result["overall"]["abs_rel"] == pytest.approx(0.0, abs=1e-6)
    assert result["overall"]["a1"] == pytest.approx(1.0)
    assert all(r["ratio"] == pytest.approx(1 / 3, rel=1e-5) for r in result["frames"])
    assert len(gts) == result["n"]


def test_bad_requests_are_named(smoke, tmp_path):
    from geodepth_lite import cli

    root, ckpt = smoke
    with pytest.raises(ValueError, match="--root is required"):
        evaluate.open_eval_dataset("colondepth")
    with pytest.raises(ValueError, match="split 'nope'"):
        evaluate.open_eval_dataset(str(root), split="nope")
    assert cli.main(["evaluate", "--checkpoint", str(tmp_path / "missing.pt"), "--dataset", str(root)]) == 2
    assert cli.main(["evaluate", "--checkpoint", str(ckpt), "--dataset", str(root), "--group", "T1-L1"]) == 2


def test_markdown_table_rounds_to_three_decimals():
    md = tables.markdown_table(["a", "b"], [["x", 0.123456], ["y", float("nan")]])
    assert md.splitlines() == ["| a | b |", "|---|---|", "| x | 0.123 |", "| y | nan |"]


class _ConstantFrames(torch.utils.data.Dataset):
    """Frames of constant depth 2 (H x W), for border-map known answers."""

    def __init__(self, n=3, H=40, W=40):
        self.n, self.H, self.W = n, H, W

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        return {"image": torch.zeros(3, self.H, self.W), "depth": torch.full((1, self.H, self.W), 2.0),
                "index": i, "organ": "x", "group": "g", "K": torch.eye(3)}


def test_border_error_map_known_answer():
    """Log error 0.2 on the top band, 0.1 on the centre, exact elsewhere (median scaling leaves it so)."""
    ds = _ConstantFrames()
    H = W = 40
    e = torch.zeros(H, W)
    e[:4] = 0.2                      # the top band: 10% of the rows
    e[10:30, 10:30] = 0.1            # the centre: the middle half in both directions

    def pred(images):
        return (2.0 * torch.exp(e)).expand(images.shape[0], 1, H, W)

    out = border.border_error_map(pred, ds, batch_size=2)
    np.testing.assert_allclose(out["signed"], e.numpy(), atol=1e-6)
    np.testing.assert_allclose(out["count"], np.full((H, W), 3.0))
    assert out["bands"]["top"] == pytest.approx(0.2) and out["bands"]["centre"] == pytest.approx(0.1)
    assert out["ratios"]["top"] == pytest.approx(2.0) and out["ratios"]["bottom"] == pytest.approx(0.0)
    assert out["ratios"]["left"] == pytest.approx(0.2 * 4 / 40 / 0.1)  # the band's top 4 rows of 40
    # a prediction right up to scale has no error anywhere
    scaled = border.border_error_map(lambda images: torch.full((images.shape[0], 1, H, W), 7.0), ds)
    assert np.abs(scaled["abs"]).max() == pytest.approx(0.0, abs=1e-6)


class _NumberedFrames(_ConstantFrames):
    """_ConstantFrames whose image holds its index (so a predictor can tell the frames apart)."""

    def __getitem__(self, i):
        return super().__getitem__(i) | {"image": torch.full((3, self.H, self.W), float(i))}


def test_border_error_map_by_group_known_answer():
    """Frames 0 and 2 ("wall"): too near by log 0.3 on the left band; frame 1 ("lumen") exact;
    frame 3 ("lumen"): too far by 0.1 in the centre. Each group's region means are its own."""
    ds = _NumberedFrames(n=4)
    H = W = 40
    near_left = torch.zeros(H, W)
    near_left[:, :4] = -0.3
    far_centre = torch.zeros(H, W)
    far_centre[10:30, 10:30] = 0.1
    errors = [near_left, torch.zeros(H, W), near_left, far_centre]

    def pred(images):
        return torch.stack([2.0 * torch.exp(errors[int(x[0, 0, 0])])[None] for x in images])

    out = border.border_error_map(pred, ds, batch_size=3, groups=["wall", "lumen", "wall", "lumen"])
    wall, lumen = out["groups"]["wall"], out["groups"]["lumen"]
    assert wall["frames"] == 2 and lumen["frames"] == 2
    assert wall["signed"]["left"] == pytest.approx(-0.3) and wall["bands"]["left"] == pytest.approx(0.3)
    assert wall["signed"]["centre"] == pytest.approx(0.0, abs=1e-9) and wall["bands"]["right"] == pytest.approx(0.0)
    assert lumen["signed"]["centre"] == pytest.approx(0.05) and lumen["bands"]["centre"] == pytest.approx(0.05)
    assert lumen["ratios"]["top"] == pytest.approx(0.0, abs=1e-9)
    # the pooled map is the frame-weighted mean of the groups'
    assert out["bands"]["left"] == pytest.approx(0.15) and out["bands"]["centre"] == pytest.approx(0.025)
    with pytest.raises(ValueError, match="3 group labels for 4 frames"):
        border.border_error_map(pred, ds, groups=["a", "b", "c"])


def test_border_ratio_intervals_resample_frames():
    """Identical frames: the interval is the ratio itself. Two frames with left-band ratios 3 and 1
    (centre 0.1 in both): a resample holds both frames twice, or one of them twice, so the ratio
    is 3, 2 or 1, each extreme with probability 1/4, and the 95% interval is [1, 3]."""
    H = W = 40
    e = torch.zeros(H, W)
    e[:, :4] = 0.2
    e[10:30, 10:30] = 0.1
    same = border.border_error_map(lambda x: (2.0 * torch.exp(e)).expand(x.shape[0], 1, H, W), _ConstantFrames())
    assert same["ratios"]["left"] == pytest.approx(0.2 / 0.1)
    for band, (lo, hi) in same["intervals"].items():
        assert lo == pytest.approx(same["ratios"][band]) and hi == pytest.approx(same["ratios"][band])

    errors = [e.clone(), e.clone()]
    errors[0][:, :4] = 0.3
    errors[1][:, :4] = 0.1

    def pred(images):
        return torch.stack([2.0 * torch.exp(errors[int(x[0, 0, 0])])[None] for x in images])

    out = border.border_error_map(pred, _NumberedFrames(n=2), n_boot=4000)
    assert out["ratios"]["left"] == pytest.approx(2.0)
    assert out["intervals"]["left"] == pytest.approx((1.0, 3.0))
    np.testing.assert_allclose(out["frame_bands"]["left"], [0.3, 0.1], rtol=1e-5)
    np.testing.assert_allclose(out["frame_bands"]["centre"], [0.1, 0.1], rtol=1e-5)
    assert out["frame_index"].tolist() == [0, 1]
    assert border.border_error_map(pred, _NumberedFrames(n=2), n_boot=0)["intervals"] == {}


def test_border_ratio_intervals_resample_whole_clusters():
    """Six frames, three copies each of the two frames above (left-band ratios 3 and 1). Resampled
    one by one, the six look like six draws and the interval is narrower than [1, 3]; resampled as
    the two clusters they are, the interval is the two frames' [1, 3] again. One label per frame
    is a cluster bootstrap that equals the frame bootstrap."""
    H = W = 40
    errors = [torch.zeros(H, W), torch.zeros(H, W)]
    for err, left in zip(errors, (0.3, 0.1)):
        err[10:30, 10:30] = 0.1
        err[:, :4] = left

    def pred(images):
        return torch.stack([2.0 * torch.exp(errors[int(x[0, 0, 0]) % 2])[None] for x in images])

    ds = _NumberedFrames(n=6)
    frames = border.border_error_map(pred, ds, n_boot=4000)
    scenes = border.border_error_map(pred, ds, n_boot=4000, clusters=["a", "b"] * 3)
    assert frames["ratios"] == scenes["ratios"] and scenes["ratios"]["left"] == pytest.approx(2.0)
    lo, hi = frames["intervals"]["left"]
    assert 1.2 < lo < hi < 2.8               # a draw of six holds both kinds of frame but rarely
    assert scenes["intervals"]["left"] == pytest.approx((1.0, 3.0))
    own = border.border_error_map(pred, ds, n_boot=4000, clusters=list(range(6)))
    assert own["intervals"] == frames["intervals"]
    with pytest.raises(ValueError, match="5 cluster labels for 6 frames"):
        border.border_error_map(pred, ds, clusters=list(range(5)))
