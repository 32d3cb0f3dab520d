"""compute_depth_metrics: hand-computed values, median scaling, masking, input forms, errors."""

import math

import numpy as np
import pytest
import torch

from geodepth_lite.core import metrics
from geodepth_lite.core.metrics import compute_depth_metrics

GT = np.array([[1.0, 2.0], [4.0, 8.0]])
PRED = np.array([[2.0, 2.0], [2.0, 2.0]])


def test_hand_computed_with_median_scaling():
    m = compute_depth_metrics(PRED, GT)
    # median(gt) = 3, median(pred) = 2 -> ratio 1.5, scaled pred = 3 everywhere
    assert m["ratios"].tolist() == [1.5]
    assert math.isclose(m["abs_rel"], (2 / 1 + 1 / 2 + 1 / 4 + 5 / 8) / 4)
    assert math.isclose(m["sq_rel"], (4 / 1 + 1 / 2 + 1 / 4 + 25 / 8) / 4)
    assert math.isclose(m["rmse"], math.sqrt((4 + 1 + 1 + 25) / 4))
    logs = [math.log(g / 3) ** 2 for g in (1, 2, 4, 8)]
    assert math.isclose(m["rmse_log"], math.sqrt(sum(logs) / 4))
    # max(gt/pred, pred/gt) = 3, 1.5, 1.333, 2.667 against 1.25, 1.5625, 1.953
    assert (m["a1"], m["a2"], m["a3"]) == (0.0, 0.5, 0.5)
    assert m["n_frames"] == 1


def test_hand_computed_without_scaling_and_clamp():
    pred = np.array([[0.5, 2.0], [4.0, 200.0]])  # 200 is clamped to max_depth = 10
    m = compute_depth_metrics(pred, GT, max_depth=10.0, median_scaling=False)
    assert m["ratios"].tolist() == [1.0]
    # errors: 0.5, 0, 0, 2 (8 vs 10)
    assert math.isclose(m["abs_rel"], (0.5 / 1 + 0 + 0 + 2 / 8) / 4)
    assert math.isclose(m["rmse"], math.sqrt((0.25 + 4) / 4))
    # max ratios 2, 1, 1, 1.25 (strict "<": 1.25 fails a1); 2 fails a3 too (1.25^3 = 1.953)
    assert (m["a1"], m["a2"], m["a3"]) == (0.5, 0.75, 0.75)


def test_mean_over_frames_masking_and_input_forms():
    gt = np.stack([GT, np.array([[1.0, 1.0], [1.0, 50.0]])])  # 50 > max_depth: masked
    pred = np.stack([PRED, np.array([[2.0, 2.0], [2.0, 2.0]])])
    m = compute_depth_metrics(pred, gt, max_depth=10.0)
    f0 = compute_depth_metrics(PRED, GT)
    # frame 1 after masking: gt all 1, scaled pred all 1 -> perfect
    assert m["ratios"].tolist() == [1.5, 0.5]
    assert math.isclose(m["abs_rel"], f0["abs_rel"] / 2)
    assert m["per_frame"]["a1"].tolist() == [0.0, 1.0]
    # torch, N x 1 x H x W and float32 give the same numbers
    mt = compute_depth_metrics(torch.from_numpy(pred)[:, None].float(), torch.from_numpy(gt)[:, None], max_depth=10.0)
    for k in ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3"):
        assert math.isclose(mt[k], m[k], rel_tol=1e-6)


def test_scale_invariance_and_frames_without_valid_pixels():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0.5, 5.0, size=(3, 8, 8))
    pred = gt * rng.uniform(0.9, 1.1, size=gt.shape)
    m1 = compute_depth_metrics(pred, gt)
    m2 = compute_depth_metrics(pred * 7.0, gt)
    assert math.isclose(m1["rmse"], m2["rmse"], rel_tol=1e-12)
    gt[1] = np.nan  # no valid pixel: skipped, not NaN
    m3 = compute_depth_metrics(pred, gt)
    assert m3["n_frames"] == 2 and math.isfinite(m3["abs_rel"]) and np.isnan(m3["ratios"][1])


def test_errors():
    with pytest.raises(ValueError, match="same shape"):
        compute_depth_metrics(np.ones((2, 4, 4)), np.ones((2, 4, 5)))
    with pytest.raises(ValueError, match="no valid"):
        compute_depth_metrics(np.ones((4, 4)), np.zeros((4, 4)))
    with pytest.raises(ValueError, match="non-finite"):
        compute_depth_metrics(np.full((4, 4), np.nan), np.ones((4, 4)))
    with pytest.raises(ValueError, match="N x H x W"):
        compute_depth_metrics(np.ones(4), np.ones(4))
    with pytest.raises(ValueError, match="min_depth"):
        compute_depth_metrics(np.ones((4, 4)), np.ones((4, 4)), min_depth=5, max_depth=1)


def test_the_evaluation_mask_and_median_scaling_by_hand():
    gt = np.array([[np.nan, 0.0005, 2.0], [4.0, 100.0, np.inf]])
    assert metrics.eval_mask(gt).tolist() == [[False, False, True], [True, False, False]]
    valid = np.array([[1, 1, 0], [1, 1, 1]])
    assert metrics.eval_mask(gt, valid=valid).tolist() == [[False, False, False], [True, False, False]]
    assert metrics.eval_mask(gt, max_depth=200.0).tolist() == [[False, False, True], [True, True, False]]
    # median(gt) = 3, median(pred) = 1.5: the factor that gives the prediction the ground truth's scale
    assert metrics.median_scale(np.array([1.0, 1.5, 9.0]), np.array([2.0, 3.0, 4.0])) == 2.0
    # an outlier moves a mean-based scale (3 / 3.83) but not the median's
    assert metrics.median_scale(np.array([1.0, 1.5, 90.0]), np.array([2.0, 3.0, 4.0])) == 2.0
