"""Trivial depth baselines, scored with exactly the protocol of ``evaluate`` (Section 4.2.1).

Per-frame median scaling forgives any global scale, so a prediction that knows nothing
about the frame can still score well: a model must beat these baselines for its numbers
to mean anything. Each predictor maps a batch of frames (images N x 3 x H x W in [0, 1],
torch or numpy) to depth N x H x W float32 at the frames' own size:

- ``constant_depth``: the same depth everywhere (what median scaling gives for free);
- ``apply_mean_depth_map``: the pixel-wise mean of the training depths (``mean_depth_map``,
  ``fit_mean_depth_map``): the average scene layout, e.g. "the lumen is in the middle";
- ``shading_prior``: depth from brightness alone, 1 / sqrt(blurred luminance): the light
  sits at the lens, so brightness falls with the inverse square of distance.

``evaluate.evaluate_baselines`` scores them, each with the same result dict as
``evaluate.evaluate_model``, so baseline rows sit beside model rows (the ``evaluate`` CLI adds
them to its tables). This module holds the predictors only.
"""

from __future__ import annotations

import os
from typing import Any, Iterable

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import gaussian_filter

from geodepth_lite.data import bounds
from geodepth_lite.data.datasets import SyntheticDepthDataset

# name -> what it predicts (one line; shown in the evaluate tables' notes)
BASELINES: dict[str, str] = {
    "constant": "the same depth at every pixel (after per-frame median scaling any constant is the same)",
    "mean_depth_map": "the pixel-wise mean of the training depth maps, the same map for every frame",
    "shading_prior": ("1 / sqrt(luminance blurred with a 2 px Gaussian): "
                      "a light at the lens falls off as 1 / distance^2"),
}

LUMA_WEIGHTS = (0.299, 0.587, 0.114)  # ITU-R BT.601 luma, as PIL's convert("L")
SHADING_EPS_REL = 1e-3  # gray is clipped below at this fraction of the frame's brightest (blurred) pixel


def _images(images: Any) -> np.ndarray:
    """Images (torch or numpy; N x 3 x H x W or 3 x H x W) as float32 numpy N x 3 x H x W."""
    if hasattr(images, "detach"):
        images = images.detach().float().cpu().numpy()
    x = np.asarray(images, dtype=np.float32)
    if x.ndim == 3:
        x = x[None]
    if x.ndim != 4 or x.shape[1] != 3:
        raise ValueError(f"images must be N x 3 x H x W (or 3 x H x W), got shape {x.shape}")
    return x


def _resize_depth(depth: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """An H x W depth map to ``size`` = (h, w) by pixel-centre nearest neighbour, the package's
    convention for depth (``datasets.resize_frame``: no depth is invented between two others)."""
    if tuple(depth.shape) == tuple(size):
        return depth
    t = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))[None, None]
    return F.interpolate(t, size=tuple(size), mode="nearest-exact")[0, 0].numpy()


# --------------------------------------------------------------------------- predictors


def constant_depth(images: Any) -> np.ndarray:
    """Depth 1 everywhere: the floor any model must clear, since median scaling turns it into
    the frame's median ground-truth depth (its Abs Rel is the spread of the depths alone).

    Explained with its formula in notebook 04, "The three baselines as formulas".
    """
    x = _images(images)
    return np.ones((x.shape[0], x.shape[2], x.shape[3]), dtype=np.float32)


def mean_depth_map(train_depths: Iterable | np.ndarray, valid: Iterable | np.ndarray | None = None) -> np.ndarray:
    """The pixel-wise mean H x W of training depth maps over their valid pixels (finite, > 0, and
    ``valid`` where given); a pixel never valid gets the mean of all valid pixels.

    train_depths: N x H x W (or N x 1 x H x W) array/tensor, or any iterable of H x W maps
    (streamed: only the running sum and count are kept). ``valid``: the same, boolean.
    A model that only learned the average scene layout would score like this map.
    Explained with its formula in notebook 04, "The three baselines as formulas".
    """
    total = count = None
    valids = iter(valid) if valid is not None else None
    for i, d in enumerate(train_depths):
        d = np.asarray(d.detach().cpu() if hasattr(d, "detach") else d, dtype=np.float64)
        d = d[0] if d.ndim == 3 and d.shape[0] == 1 else d
        if d.ndim != 2:
            raise ValueError(f"depth map {i} must be H x W, got shape {d.shape}")
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(d) & (d > 0)
        if valids is not None:
            v = next(valids, None)
            if v is None:
                raise ValueError(f"valid has fewer maps than train_depths ({i})")
            v = np.asarray(v.detach().cpu() if hasattr(v, "detach") else v).astype(bool)
            ok &= v.reshape(d.shape)  # H x W or 1 x H x W
        if total is None:
            total, count = np.zeros(d.shape), np.zeros(d.shape, dtype=np.int64)
        elif d.shape != total.shape:
            raise ValueError(f"depth map {i} is {d.shape}, the first was {total.shape}: resize them to one size")
        total += np.where(ok, d, 0.0)
        count += ok
    if total is None:
        raise ValueError("mean_depth_map needs at least one training depth map")
    if not count.any():
        raise ValueError("no valid (finite, > 0) depth in any training map")
    fill = total.sum() / count.sum()  # the mean of all valid pixels
    return np.where(count > 0, total / np.maximum(count, 1), fill).astype(np.float32)


def fit_mean_depth_map(root: str | os.PathLike, split: str = "train", image_size=None) -> np.ndarray:
    """``mean_depth_map`` of every frame of a synthetic dataset split (``SyntheticDepthDataset(root,
    split, image_size)``), reading the depth files one at a time (RGB images are not decoded).

    Each file is read as the dataset reads it (``bounds.read_depth_npy``: never unpickled), so a damaged
    or foreign depth file is a :class:`utils.FileProblem` naming it."""
    ds = SyntheticDepthDataset(root, split, image_size=image_size)

    def depths():
        for rec in ds.frames:
            d = bounds.read_depth_npy(ds.root / rec["depth"])
            yield d if ds.size is None else _resize_depth(d, ds.size)  # as ds[i]["depth"], without the image

    return mean_depth_map(depths())


def apply_mean_depth_map(images: Any, mean_map: np.ndarray) -> np.ndarray:
    """The fitted ``mean_map`` as every frame's prediction, resized (nearest) to the frames' size."""
    x = _images(images)
    m = _resize_depth(np.asarray(mean_map, dtype=np.float32), x.shape[2:])
    return np.broadcast_to(m, (x.shape[0], *m.shape)).astype(np.float32)


def shading_prior(images: Any, sigma: float = 2.0) -> np.ndarray:
    """Depth from shading alone: 1 / sqrt(gray), gray = luminance (BT.601) blurred by a Gaussian of
    ``sigma`` px (0: no blur). With the light at the lens, brightness ~ albedo / distance^2, so
    this is the depth a "darker is farther" model gets without learning anything. Gray is
    clipped below at ``SHADING_EPS_REL`` x the frame's brightest pixel (black pixels then lie
    at most ~32x farther than the brightest); an all-black frame gets a constant depth.

    Explained with its formula in notebook 04, "The three baselines as formulas".
    """
    x = _images(images).astype(np.float64)
    gray = np.tensordot(np.asarray(LUMA_WEIGHTS), x, axes=([0], [1]))  # N x H x W
    if sigma > 0:
        gray = gaussian_filter(gray, sigma=(0, sigma, sigma), mode="nearest")
    top = gray.max(axis=(1, 2), keepdims=True)
    eps = np.where(top > 0, SHADING_EPS_REL * top, 1.0)
    return (1.0 / np.sqrt(np.maximum(gray, eps))).astype(np.float32)
