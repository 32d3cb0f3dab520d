"""Training-time augmentation (teach/paper recipes, ``cfg["augment"]``): cheaper than rendering.

Every kind keeps a frame a valid pinhole view: flips and crops move K with the pixels. Draws
come from torch's global RNG, which checkpoints save, so a resumed run repeats them. The
appearance effects themselves live in :mod:`geodepth_lite.data.appearance` (notebook 01 shows them).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from geodepth_lite.data import appearance, fov
from geodepth_lite.core.camera import scale_intrinsics

AUGMENTS = ("none", "flip", "flip_color", "camera", "crop", "fov")  # see augment_batch
# augment="camera": the appearance effects that are cheaper to add to a training image than to
# render (appearance.py), drawn afresh every time a frame is seen; ranges beyond the datasets'.
CAMERA_AUGMENT = {"exposure_stops": [-1.0, 1.0], "gamma": [0.8, 1.3], "color_cast": [-1.0, 1.0],
                  "vignetting": [0.0, 0.5], "specular_flecks": [0, 10], "noise": [0.0, 0.04],
                  "p_blur": 0.3, "blur_px": [0.5, 2.0], "p_jpeg": 0.3, "jpeg_quality": [30, 95]}
CROP_SCALE = (0.5, 1.0)  # augment="crop": the crop's side as a share of the frame's, uniform in this range
# augment="fov": the share of frames given an endoscope's border, and that border's radius range
FOV_AUGMENT = {"p": 0.5, "radius": (0.9, 1.3)}


def augment_batch(batch: dict, kind: str) -> dict:
    """Training-time augmentation, drawn from torch's global RNG (saved in checkpoints, so resume repeats it).

    flip: each frame mirrored left-right with probability 1/2; image, depth and validity are
    flipped and K follows (cx -> W - 1 - cx), so the frame stays a valid pinhole view.
    flip_color: flip, then a per-frame gain in [0.7, 1.4] and gamma in [0.8, 1.25] on the image
    (exposure and camera response; the depth is unchanged).
    camera: flip, then per frame the appearance effects of ``CAMERA_AUGMENT`` (exposure, gamma,
    colour cast, vignetting, flecks, noise, blur, JPEG; ``appearance.apply_appearance``) on the
    image quantized to 8 bits, as a camera would deliver it.
    crop: flip, then per frame a random crop (side CROP_SCALE of the frame's, anywhere in it)
    scaled back to the frame's size, K following (:func:`random_crop_batch`): what lies at the image
    border changes from view to view, so the network cannot learn "near at the border".
    fov: flip, then a share ``FOV_AUGMENT["p"]`` of the frames get a round or octagonal field of
    view with on-screen text (``fov.synthetic_mask``, ``fov.add_overlay``), and the outside filled
    from the inside (``fov.fill_outside``) as ``predict`` does; the loss sees the inside only
    (``valid``). Trains on what the network sees of a clinical frame.
    """
    if kind == "none":
        return batch
    img, depth = batch["image"], batch["depth"]
    B, W = img.shape[0], img.shape[-1]
    flip = torch.rand(B) < 0.5
    out = dict(batch)
    if bool(flip.any()):
        f = flip.to(img.device).view(B, 1, 1, 1)
        out["image"] = torch.where(f, img.flip(-1), img)
        out["depth"] = torch.where(f, depth.flip(-1), depth)
        if batch.get("valid") is not None:
            out["valid"] = torch.where(f, batch["valid"].flip(-1), batch["valid"])
        K = batch["K"].clone()
        K[flip.to(K.device), 0, 2] = (W - 1) - K[flip.to(K.device), 0, 2]
        out["K"] = K
    if kind == "crop":
        out = random_crop_batch(out, CROP_SCALE)
    if kind == "fov":
        out = fov_batch(out, FOV_AUGMENT)
    if kind == "flip_color":
        gain = (0.7 + 0.7 * torch.rand(B)).to(img).view(B, 1, 1, 1)
        gamma = torch.exp(torch.empty(B).uniform_(np.log(0.8), np.log(1.25))).to(img).view(B, 1, 1, 1)
        out["image"] = (out["image"].clamp(0, 1) ** gamma * gain).clamp(0, 1)
    if kind == "camera":
        params = dict(appearance.APPEARANCE_DEFAULTS, **CAMERA_AUGMENT)
        seeds = torch.randint(0, 2**31 - 1, (B,)).tolist()
        frames = (out["image"].detach().clamp(0, 1).permute(0, 2, 3, 1).cpu().numpy() * 255.0).round().astype(np.uint8)
        looks = [appearance.sample_appearance(params, np.random.default_rng(sd)) for sd in seeds]
        done = np.stack([appearance.apply_appearance(f, look) for f, look in zip(frames, looks)])
        out["image"] = torch.from_numpy(done).permute(0, 3, 1, 2).to(img).div(255.0)
    return out


def fov_batch(batch: dict, settings: dict) -> dict:
    """A share ``settings["p"]`` of the frames painted with an endoscope's border and text and
    filled from the inside (``augment_batch``'s "fov"); ``valid`` is False where they painted.
    Draws from torch's global RNG (a numpy generator seeded from it per frame)."""
    img = batch["image"]
    B, _, H, W = img.shape
    pick = (torch.rand(B) < settings["p"]).tolist()
    seeds = torch.randint(0, 2**31 - 1, (B,)).tolist()
    images = img.clone()
    valid = (batch["valid"].clone() if batch.get("valid") is not None
             else torch.ones(B, 1, H, W, dtype=torch.bool, device=img.device))
    for j in range(B):
        if not pick[j]:
            continue
        rng = np.random.default_rng(seeds[j])
        kind = ("round", "octagon")[int(rng.integers(2))]
        mask = fov.synthetic_mask(H, W, kind, radius=float(rng.uniform(*settings["radius"])),
                                  center=(float(rng.uniform(0.45, 0.55)), float(rng.uniform(0.45, 0.55))))
        frame = img[j].detach().clamp(0, 1).permute(1, 2, 0).cpu().numpy()
        painted, inside = fov.add_overlay(frame, mask, rng, over_image=bool(rng.integers(2)))
        filled = fov.fill_outside(painted, inside)
        images[j] = torch.from_numpy(np.ascontiguousarray(filled)).permute(2, 0, 1).to(img)
        valid[j] &= torch.from_numpy(inside).to(valid.device)[None]
    return dict(batch, image=images, valid=valid)


def random_crop_batch(batch: dict, scale: tuple[float, float]) -> dict:
    """Each frame cropped to a random window (side ``s`` x the frame's, s uniform in ``scale``,
    integer offsets) and resized back: image bilinear, depth and validity nearest-exact (no depth
    is invented across an edge), K shifted by the offset and scaled (``camera.scale_intrinsics``).
    Draws from torch's global RNG."""
    img = batch["image"]
    B, _, H, W = img.shape
    s = torch.empty(B).uniform_(*scale).tolist()
    u = torch.rand(B, 2).tolist()
    images, depths, valids, Ks = [], [], [], []
    for j in range(B):
        ch, cw = max(1, round(s[j] * H)), max(1, round(s[j] * W))
        y0, x0 = int(u[j][0] * (H - ch + 1)), int(u[j][1] * (W - cw + 1))
        win = (slice(None), slice(y0, y0 + ch), slice(x0, x0 + cw))
        images.append(F.interpolate(img[j][win][None], size=(H, W), mode="bilinear", align_corners=False)[0])
        depths.append(F.interpolate(batch["depth"][j][win][None], size=(H, W), mode="nearest-exact")[0])
        if batch.get("valid") is not None:
            v = batch["valid"][j][win][None].float()
            valids.append(F.interpolate(v, size=(H, W), mode="nearest-exact")[0] > 0.5)
        K = batch["K"][j].detach().cpu().double().numpy().copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        Ks.append(torch.from_numpy(scale_intrinsics(K, W / cw, H / ch)).to(batch["K"]))
    out = dict(batch, image=torch.stack(images).clamp_(0, 1), depth=torch.stack(depths), K=torch.stack(Ks))
    if valids:
        out["valid"] = torch.stack(valids)
    return out


