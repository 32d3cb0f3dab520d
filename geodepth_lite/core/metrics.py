"""Depth metrics with per-frame median scaling (Sec. 4.2.1; the monodepth2 / AF-SfMLearner protocol).

For each frame: valid pixels are ``min_depth < gt < max_depth`` (and finite); with median
scaling, ``pred *= median(gt[valid]) / median(pred[valid])``; then ``pred`` is clamped to
``[min_depth, max_depth]``; then the seven metrics are computed over the valid pixels:

- abs_rel  = mean(|gt - pred| / gt)
- sq_rel   = mean((gt - pred)^2 / gt)
- rmse     = sqrt(mean((gt - pred)^2))
- rmse_log = sqrt(mean((ln gt - ln pred)^2))
- a_k      = mean(max(gt / pred, pred / gt) < 1.25^k), k = 1, 2, 3

and each metric is the mean of its per-frame values. Notebook 04 writes these equations out
("How every depth map is scored") before its first number. Evaluation and the notebooks call
:func:`compute_depth_metrics` (numpy); training's validation computes the same per-frame numbers in
torch on its device (:func:`frame_metrics_torch`, checked against it in tests/test_validation_device.py).
"""

from __future__ import annotations

import numpy as np
import torch

EVAL_MIN_DEPTH = 1e-3  # ground truth at or below this is invalid (the protocol's lower cap, scene units)
EVAL_MAX_DEPTH = 100.0  # ... and at or above this (public datasets use their own encoding's maximum)
METRIC_NAMES = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")


def _as_frames(x, name: str) -> np.ndarray:
    """numpy array or torch tensor, N x H x W, N x 1 x H x W or H x W -> float64 N x H x W."""
    if hasattr(x, "detach"):  # torch tensor
        x = x.detach().cpu().numpy()
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 4 and x.shape[1] == 1:
        x = x[:, 0]
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3:
        raise ValueError(f"{name} must be N x H x W or H x W (or N x 1 x H x W), got shape {x.shape}")
    return x


def eval_mask(gt, min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH, valid=None) -> np.ndarray:
    """The pixels the protocol scores: finite ground truth with ``min_depth < gt < max_depth``,
    and ``valid`` where the dataset marks its own invalid pixels. Any shape; a boolean array.

    Explained with its equation in notebook 04, "How every depth map is scored" (the mask V).
    """
    gt = np.asarray(gt)
    with np.errstate(invalid="ignore"):
        mask = np.isfinite(gt) & (gt > min_depth) & (gt < max_depth)
    if valid is not None:
        mask &= np.asarray(valid, dtype=bool).reshape(mask.shape)
    return mask


def median_scale(pred: np.ndarray, gt: np.ndarray) -> float:
    """The protocol's median scaling: ``median(gt) / median(pred)`` over the same scored pixels
    (two 1-D arrays, e.g. ``gt[mask]`` and ``pred[mask]``). Monocular depth has no scale; this
    factor gives each frame the ground truth's.

    Explained with its equation in notebook 04, "How every depth map is scored" (median scaling).
    """
    return float(np.median(gt) / np.median(pred))


def frame_metrics(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """The seven metrics of one frame, for 1-D arrays of valid, positive depths of equal length."""
    thresh = np.maximum(gt / pred, pred / gt)
    diff = gt - pred
    return {
        "abs_rel": float(np.mean(np.abs(diff) / gt)),
        "sq_rel": float(np.mean(diff**2 / gt)),
        "rmse": float(np.sqrt(np.mean(diff**2))),
        "rmse_log": float(np.sqrt(np.mean((np.log(gt) - np.log(pred)) ** 2))),
        "a1": float(np.mean(thresh < 1.25)),
        "a2": float(np.mean(thresh < 1.25**2)),
        "a3": float(np.mean(thresh < 1.25**3)),
    }


def compute_depth_metrics(pred, gt, *, min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH,
                          median_scaling: bool = True) -> dict:
    """Metrics of predicted depth against ground truth (shapes N x H x W or H x W, numpy or torch).

    ``pred`` must already be at the ground truth's resolution. Returns a dict with
    - the seven metrics (floats, means over the frames that have at least one valid pixel),
    - ``"ratios"``: N per-frame scale factors median(gt)/median(pred) (1.0 without median
      scaling; NaN for frames without valid pixels),
    - ``"per_frame"``: dict metric -> N array (NaN for frames without valid pixels),
    - ``"n_frames"``: number of frames averaged.
    Raises ValueError for mismatched shapes, a bad depth range, non-finite or non-positive
    predictions on valid pixels, or when no frame has a valid pixel.

    Explained with its equation in notebook 04, "How every depth map is scored" (the seven metrics).
    """
    p, g = _as_frames(pred, "pred"), _as_frames(gt, "gt")
    if p.shape != g.shape:
        raise ValueError(f"pred and gt must have the same shape (resize pred first), got {p.shape} and {g.shape}")
    if not 0 <= min_depth < max_depth:
        raise ValueError(f"need 0 <= min_depth < max_depth, got min_depth={min_depth}, max_depth={max_depth}")
    n = p.shape[0]
    ratios = np.full(n, np.nan)
    per_frame = {k: np.full(n, np.nan) for k in METRIC_NAMES}
    valid_all = eval_mask(g, min_depth, max_depth)
    for i in range(n):
        valid = valid_all[i]
        if not valid.any():
            continue
        gi, pi = g[i][valid], p[i][valid]
        if not np.all(np.isfinite(pi)):
            raise ValueError(f"pred frame {i} has non-finite values on valid pixels")
        ratio = 1.0
        if median_scaling:
            med = np.median(pi)
            if not med > 0:
                raise ValueError(f"pred frame {i}: median depth on valid pixels is {med}, must be positive")
            ratio = median_scale(pi, gi)
            pi = pi * ratio
        pi = np.clip(pi, min_depth, max_depth)
        if not np.all(pi > 0):
            raise ValueError(f"pred frame {i} has non-positive depths and min_depth=0: cannot take logs")
        ratios[i] = ratio
        for k, v in frame_metrics(pi, gi).items():
            per_frame[k][i] = v
    used = np.isfinite(ratios)
    if not used.any():
        raise ValueError(f"no valid ground-truth pixel in any frame (valid: {min_depth} < gt < {max_depth})")
    out = {k: float(np.mean(per_frame[k][used])) for k in METRIC_NAMES}
    out.update(ratios=ratios, per_frame=per_frame, n_frames=int(used.sum()))
    return out


def _masked_median(x, valid, n):
    """numpy's median of each row's valid entries (x, valid: N x P float64 / bool; n: N counts >= 1): the
    middle one, or the mean of the two middle ones."""
    s = torch.sort(torch.where(valid, x, torch.full_like(x, float("inf"))), dim=1).values
    lo = ((n - 1) // 2).clamp_min(0)[:, None]
    hi = (n // 2).clamp(max=x.shape[1] - 1)[:, None]
    return ((s.gather(1, lo) + s.gather(1, hi)) / 2)[:, 0]


def frame_metrics_torch(pred, gt, *, min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH,
                        median_scaling: bool = True) -> dict:
    """:func:`compute_depth_metrics` per frame, in torch on the tensors' device (float64), nothing read to the host.

    pred, gt: N x 1 x H x W or N x H x W tensors. Returns {metric: N values (NaN where unused),
    "ratios": N, "used": N bool (frames with a valid pixel), "bad": N bool (frames that
    :func:`compute_depth_metrics` refuses: a non-finite prediction on a valid pixel, a non-positive
    median, or a non-positive depth after clamping)}. The same numbers as the numpy protocol up to the
    order of float64 sums.
    """
    p = pred.detach().reshape(pred.shape[0], -1).to(torch.float64)
    g = gt.detach().reshape(gt.shape[0], -1).to(device=p.device, dtype=torch.float64)
    if p.shape != g.shape:
        raise ValueError(f"pred and gt must have the same shape, got {tuple(pred.shape)} and {tuple(gt.shape)}")
    valid = torch.isfinite(g) & (g > min_depth) & (g < max_depth)
    n = valid.sum(1)
    used = n > 0
    bad = (valid & ~torch.isfinite(p)).any(1)
    ratio = torch.ones_like(p[:, 0])
    if median_scaling:
        med_p = _masked_median(p, valid, n)
        bad |= used & ~(med_p > 0)
        ratio = _masked_median(g, valid, n) / med_p
    one = torch.ones((), dtype=p.dtype, device=p.device)
    pi = torch.where(valid, (p * ratio[:, None]).clamp(min_depth, max_depth), one)
    gi = torch.where(valid, g, one)
    bad |= (valid & ~(pi > 0)).any(1)
    thresh = torch.maximum(gi / pi, pi / gi)
    diff = gi - pi
    cnt = n.clamp_min(1).to(p.dtype)

    def mean(x):
        return torch.where(valid, x, torch.zeros((), dtype=p.dtype, device=p.device)).sum(1) / cnt

    per = {"abs_rel": mean(diff.abs() / gi), "sq_rel": mean(diff**2 / gi), "rmse": mean(diff**2).sqrt(),
           "rmse_log": mean((gi.log() - pi.log()) ** 2).sqrt(), "a1": mean((thresh < 1.25).to(p.dtype)),
           "a2": mean((thresh < 1.25**2).to(p.dtype)), "a3": mean((thresh < 1.25**3).to(p.dtype))}
    nan = torch.full_like(ratio, float("nan"))
    out = {k: torch.where(used, v, nan) for k, v in per.items()}
    out.update(ratios=torch.where(used, ratio, nan), used=used, bad=bad & used)
    return out
