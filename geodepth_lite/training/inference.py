"""Running a trained network: device choice, batching, and depth for any image size (Section 4.2.3).

``predict_depth`` is what evaluation (``evaluate``), ``predict`` and the notebooks call: the
images are resized the way the training frames were made (``datasets.resize_image``),
predicted at the network's input size and resized back to the frame's.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch
import torch.nn.functional as F

from geodepth_lite import utils
from geodepth_lite.data.datasets import resize_image
from geodepth_lite.training.distributed import dist_env


def pick_device(device: str | torch.device | None = None) -> torch.device:
    """``device`` as given; else CUDA when available (one GPU per torchrun process), else the CPU."""
    if device is not None:
        return utils.parse_device(device)
    if torch.cuda.is_available():
        return torch.device("cuda", dist_env()[2] % torch.cuda.device_count())
    return torch.device("cpu")


def autocast(device: torch.device):
    """Mixed precision on CUDA (bfloat16 where supported, else float16); nothing on the CPU."""
    if device.type == "cuda":
        dtype = torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16
        return torch.autocast("cuda", dtype=dtype)
    return contextlib.nullcontext()


def collate(batch: list[dict]) -> dict:
    """Item dicts to one batch dict: tensors and arrays stacked, numbers to a tensor, the rest as lists."""
    out = {}
    for key in batch[0]:
        values = [b[key] for b in batch]
        if isinstance(values[0], torch.Tensor):
            out[key] = torch.stack(values)
        elif isinstance(values[0], np.ndarray):
            out[key] = torch.from_numpy(np.stack(values))
        elif isinstance(values[0], (int, float)):
            out[key] = torch.tensor(values)
        else:
            out[key] = values
    return out


def to_device(batch: dict, device: torch.device) -> dict:
    """The batch's tensors on ``device`` (other entries unchanged)."""
    return {k: (v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}


# test-time flips: the image axes each extra prediction mirrors ((): the image as it is). Mirroring
# keeps a centred camera's intrinsics, so each mirrored prediction, mirrored back, is a second
# opinion on the same frame; their mean is the prediction.
FLIPS = {"none": ((),), "h": ((), (-1,)), "hv": ((), (-1,), (-2,), (-2, -1))}


def check_flips(flips: str) -> str:
    """``flips`` if it names an entry of FLIPS, else a ValueError naming the choices."""
    if flips not in FLIPS:
        raise ValueError(f"flips must be one of {', '.join(FLIPS)}, got {flips!r}")
    return flips


@torch.no_grad()
def predict_depth(model, images: torch.Tensor, image_size: int | tuple[int, int] | None = None,
                  flips: str = "none") -> torch.Tensor:
    """Depth B x 1 x H x W for images B x 3 x H x W in [0, 1]: resized (datasets.resize_image) to the
    network's ``image_size`` (int or (h, w), multiples of 32), predicted, resized back.

    flips: "none" (one forward pass, as the paper), "h" (the mean with the prediction for the
    left-right mirrored image, mirrored back) or "hv" (the mean over the four mirrorings); the
    teach profile's ``predict_flips`` says which the ``predict`` model uses, and why.
    """
    axes = FLIPS[check_flips(flips)]
    if images.dim() == 3:
        images = images[None]
    if images.dim() != 4 or images.shape[1] != 3:
        raise ValueError(f"images must be B x 3 x H x W, got shape {tuple(images.shape)}")
    H, W = images.shape[-2:]
    if image_size is None:
        size = (H, W)
    elif isinstance(image_size, int):
        size = (image_size, image_size)
    else:
        size = tuple(int(s) for s in image_size)
    device = next(model.parameters()).device
    x = images.to(device=device, dtype=torch.float32)
    x = resize_image(x, size)  # (B, 3, h, w), as the training frames were made (antialiased)
    was_training = model.training
    model.eval()
    pred = None
    for dims in axes:  # one pass per mirroring, each mirrored back before the mean
        p = model(x.flip(dims) if dims else x).float()  # (B, 1, h, w)
        p = p.flip(dims) if dims else p
        pred = p if pred is None else pred + p
    pred = pred / len(axes)
    model.train(was_training)
    if pred.shape[-2:] != (H, W):
        pred = F.interpolate(pred, size=(H, W), mode="bilinear", align_corners=False)  # (B, 1, H, W)
    return pred


DEFAULT_BATCH_SIZE = 8


def batches(frames, batch_size: int):
    """Lists of ``batch_size`` items of ``frames`` (an iterator), the last one shorter."""
    batch = []
    for item in frames:
        batch.append(item)
        if len(batch) == batch_size:
            yield batch
            batch = []
    if batch:
        yield batch


@torch.no_grad()
def predict_frames(model, frames: list[np.ndarray], image_size, flips: str = "none") -> list[np.ndarray]:
    """Depth (H x W float32, each frame's own size) for a list of H x W x 3 uint8 frames of any sizes.

    Each frame is resized to the network's ``image_size`` so that one batch holds frames of
    different sizes; ``inference.predict_depth`` runs the network; each prediction is resized
    back (bilinear) to its frame. flips: test-time flips (``inference.predict_depth``).
    """
    size = (image_size, image_size) if isinstance(image_size, int) else tuple(image_size)
    x = torch.stack([resize_image(torch.from_numpy(f).permute(2, 0, 1).float().div(255.0), size) for f in frames])
    pred = predict_depth(model, x, size, flips).cpu()
    out = []
    for f, p in zip(frames, pred):
        p = F.interpolate(p[None], size=f.shape[:2], mode="bilinear", align_corners=False)[0, 0]
        out.append(p.numpy().astype(np.float32))
    return out
