"""``python -m geodepth_lite predict``: zero-shot depth for your own images or video (Section 4.3).

The paper's stage II applies the network trained on synthetic frames to clinical images
(Kvasir, clinical videos) and turns each depth map into 3D with the endoscope's intrinsics.
For every frame this writes, into ``--out``:

- ``<name>_depth.npy``: float32 H x W z-depth at the frame's own size, in the training
  set's scene units (relative: monocular depth has no metric scale);
- ``<name>_depth.png``: the depth colorized (``viz.colorize_depth``);
- ``<name>.ply``: the coloured back-projected point cloud (or mesh, ``--ply mesh``).

Frames of any size are resized to the network's input and the prediction back to the
frame (``inference.predict_depth``); each depth map is the mean of the network's predictions
for the frame and its three mirror images, mirrored back (``--flips hv``; ``none`` for one
pass). Intrinsics come from ``--intrinsics`` (YAML/JSON) or a
horizontal field of view (``--fov``, default: the authors' set, fx = 0.5556 W, about 84
degrees). A file that cannot be read or written is reported by name, the others are
still processed, and the exit status is 1 if any frame failed (2 for a usage error).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Iterator

import numpy as np
import torch
import torch.nn.functional as F

from . import camera, recon, utils
from .dataset import resize_image
from .inference import FLIPS

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
VIDEO_EXTS = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".mpg", ".mpeg", ".m4v", ".wmv"}
DEFAULT_FOV_DEG = camera.fov_x_deg(camera.intrinsics(1000), 1000)  # the authors' set: about 83.97 degrees
DEFAULT_BATCH_SIZE = 8


# --------------------------------------------------------------------------- intrinsics
def load_intrinsics(path) -> dict:
    """Intrinsics file (YAML or JSON): ``K`` (3x3) or ``fx, fy, cx, cy``, in pixels, and optionally
    ``width``, ``height``: the image size the calibration refers to (frames of another size
    get K scaled). Returns {"K": 3x3 array, "size": (W, H) or None}."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--intrinsics file not found: {path}")
    text = path.read_text()
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            import yaml

            data = yaml.safe_load(text)
    except Exception as exc:  # noqa: BLE001 - any parse error is the user's file
        raise ValueError(f"--intrinsics {path}: cannot parse ({exc.__class__.__name__}: {exc})") from None
    if not isinstance(data, dict):
        raise ValueError(f"--intrinsics {path}: expected a mapping with K or fx, fy, cx, cy")
    if "K" in data:
        K = np.asarray(data["K"], dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"--intrinsics {path}: K must be 3x3, got shape {K.shape}")
    else:
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in data]
        if missing:
            raise ValueError(f"--intrinsics {path}: missing {', '.join(missing)} (or give K as a 3x3 list)")
        K = np.array([[data["fx"], 0, data["cx"]], [0, data["fy"], data["cy"]], [0, 0, 1]], dtype=np.float64)
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"--intrinsics {path}: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
    size = None
    if "width" in data or "height" in data:
        if not all(isinstance(data.get(k), int) and data[k] > 0 for k in ("width", "height")):
            raise ValueError(f"--intrinsics {path}: width and height must both be positive integers")
        size = (data["width"], data["height"])
    return {"K": K, "size": size}


def frame_intrinsics(width: int, height: int, calib: dict | None, fov_deg: float | None) -> np.ndarray:
    """K for a frame of ``width`` x ``height``: the calibration scaled to it, else the field of view."""
    if calib is not None:
        if calib["size"] is None:
            return calib["K"]
        W0, H0 = calib["size"]
        return camera.scale_intrinsics(calib["K"], width / W0, height / H0)
    return camera.intrinsics_from_fov(width, height, DEFAULT_FOV_DEG if fov_deg is None else fov_deg)


# --------------------------------------------------------------------------- inputs
def list_inputs(path) -> tuple[list[Path], str]:
    """(files, kind) with kind "images" or "video"; a folder is read non-recursively, sorted by name."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"--input not found: {path}")
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTS)
        if not files:
            raise ValueError(f"--input folder {path} holds no images ({', '.join(sorted(IMAGE_EXTS))})")
        return files, "images"
    ext = path.suffix.lower()
    if ext in IMAGE_EXTS:
        return [path], "images"
    if ext in VIDEO_EXTS:
        return [path], "video"
    raise ValueError(f"--input {path}: not an image ({', '.join(sorted(IMAGE_EXTS))}) "
                     f"or a video ({', '.join(sorted(VIDEO_EXTS))})")


def _output_stems(files: list[Path]) -> dict[Path, str]:
    """Output name per input: its stem, or stem_ext where two inputs share a stem."""
    stems = [f.stem for f in files]
    return {f: (f.stem if stems.count(f.stem) == 1 else f"{f.stem}_{f.suffix.lstrip('.').lower()}") for f in files}


def iter_frames(files: list[Path], kind: str, failures: list[str]) -> Iterator[tuple[str, np.ndarray]]:
    """(output name, H x W x 3 uint8) per frame; unreadable inputs are appended to ``failures``."""
    from PIL import Image

    if kind == "video":
        import imageio.v3 as iio

        video = files[0]
        k = -1
        try:
            for k, frame in enumerate(iio.imiter(video, plugin="FFMPEG")):
                frame = np.asarray(frame)
                if frame.ndim == 2:
                    frame = np.repeat(frame[..., None], 3, axis=-1)
                yield f"{video.stem}_{k:06d}", np.ascontiguousarray(frame[..., :3])
        except Exception as exc:  # noqa: BLE001 - report and go on with what was read
            failures.append(f"{video.name} (after frame {k}): {exc.__class__.__name__}: {exc}")
        if k < 0 and not failures:
            failures.append(f"{video.name}: no frames could be read")
        return
    names = _output_stems(files)
    for f in files:
        try:
            with Image.open(f) as im:
                im.load()
                rgb = np.array(im.convert("RGB"))
        except Exception as exc:  # noqa: BLE001 - a corrupt file must not stop the others
            failures.append(f"{f.name}: cannot read image ({exc.__class__.__name__}: {exc})")
            continue
        yield names[f], rgb


def _batches(frames, batch_size: int):
    batch = []
    for item in frames:
        batch.append(item)
        if len(batch) == batch_size:
            yield batch
            batch = []
    if batch:
        yield batch


# --------------------------------------------------------------------------- inference and outputs
@torch.no_grad()
def predict_frames(model, frames: list[np.ndarray], image_size, flips: str = "none") -> list[np.ndarray]:
    """Depth (H x W float32, each frame's own size) for a list of H x W x 3 uint8 frames of any sizes.

    Each frame is resized to the network's ``image_size`` so that one batch holds frames of
    different sizes; ``inference.predict_depth`` runs the network; each prediction is resized
    back (bilinear) to its frame. flips: test-time flips (``inference.predict_depth``).
    """
    from .inference import predict_depth

    size = (image_size, image_size) if isinstance(image_size, int) else tuple(image_size)
    x = torch.stack([resize_image(torch.from_numpy(f).permute(2, 0, 1).float().div(255.0), size) for f in frames])
    pred = predict_depth(model, x, size, flips).cpu()
    out = []
    for f, p in zip(frames, pred):
        p = F.interpolate(p[None], size=f.shape[:2], mode="bilinear", align_corners=False)[0, 0]
        out.append(p.numpy().astype(np.float32))
    return out


def write_outputs(out_dir: Path, name: str, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray,
                  ply: str = "points", stride: int = 1) -> list[Path]:
    """The three files of one frame, each written atomically."""
    from . import viz

    paths = []
    p = out_dir / f"{name}_depth.npy"
    with utils.atomic_path(p) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, depth.astype(np.float32))
    paths.append(p)
    paths.append(recon.save_png(viz.colorize_depth(depth), out_dir / f"{name}_depth.png"))
    if ply != "none":
        poly = (recon.depth_mesh if ply == "mesh" else recon.point_cloud)(depth, K, rgb, stride=stride)
        paths.append(recon.save_ply(poly, out_dir / f"{name}.ply"))
    return paths


# --------------------------------------------------------------------------- CLI
def add_arguments_predict(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--checkpoint", required=True, help="a checkpoint written by train (checkpoint.pt)")
    parser.add_argument("--input", required=True,
                        help="an image, a folder of images (PNG/JPG/BMP/TIFF, any size) or a video file")
    parser.add_argument("--out", required=True, help="output folder (created if missing)")
    parser.add_argument("--intrinsics", default=None,
                        help="YAML/JSON with K (3x3) or fx, fy, cx, cy in pixels, optionally width, height "
                             "(the size they refer to); default: --fov")
    parser.add_argument("--fov", type=float, default=None,
                        help=f"horizontal field of view in degrees when no --intrinsics "
                             f"(default {DEFAULT_FOV_DEG:.1f}: the authors' fx = 0.5556 W)")
    parser.add_argument("--batch-size", type=int, default=DEFAULT_BATCH_SIZE,
                        help=f"frames per forward pass (default {DEFAULT_BATCH_SIZE})")
    parser.add_argument("--ply", choices=("points", "mesh", "none"), default="points",
                        help="PLY per frame: coloured point cloud (default), surface mesh, or none")
    parser.add_argument("--ply-stride", type=int, default=1, help="keep every N-th pixel in the PLY (default 1)")
    parser.add_argument("--device", default=None, help="cpu | cuda | cuda:N (default: CUDA when available)")
    parser.add_argument("--flips", choices=tuple(FLIPS), default="hv",
                        help="test-time flips averaged into each depth map: hv (default; the mean over the four "
                        "mirrorings of the frame, 4 passes of the network), h (left-right, 2 passes) or none (one "
                        "pass, as the paper); see the teach profile's predict_flips for what it gains")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run_predict(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from .checkpoint import load_model
    from .inference import pick_device

    if args.batch_size < 1:
        raise ValueError(f"--batch-size must be at least 1, got {args.batch_size}")
    if args.ply_stride < 1:
        raise ValueError(f"--ply-stride must be at least 1, got {args.ply_stride}")
    if args.fov is not None and not 0.0 < args.fov < 180.0:
        raise ValueError(f"--fov must be between 0 and 180 degrees, got {args.fov}")
    if args.intrinsics is not None and args.fov is not None:
        raise ValueError("give either --intrinsics or --fov, not both")
    calib = load_intrinsics(args.intrinsics) if args.intrinsics else None
    files, kind = list_inputs(args.input)
    ckpt = Path(args.checkpoint)
    if not ckpt.is_file():
        raise FileNotFoundError(f"--checkpoint not found: {ckpt}")
    model, cfg = load_model(ckpt, device=pick_device(args.device))
    out_dir = utils.make_dir(args.out)

    failures: list[str] = []
    done = 0
    total = len(files) if kind == "images" else None
    bar = tqdm(total=total, unit="frame", desc="predict", disable=args.no_progress, file=sys.stderr)
    for batch in _batches(iter_frames(files, kind, failures), args.batch_size):
        depths = predict_frames(model, [rgb for _, rgb in batch], cfg["image_size"], args.flips)
        for (name, _), depth in zip(batch, depths):
            if not np.isfinite(depth).all():  # refuse before writing anything of this batch
                raise ValueError(f"checkpoint {ckpt} predicts non-finite depth (NaN or inf) for {name}: "
                                 f"nothing written for it; the model is unusable")
        for (name, rgb), depth in zip(batch, depths):
            H, W = depth.shape
            # an output that cannot be written (read-only, disk full) stops the run: utils.FileProblem
            write_outputs(out_dir, name, rgb, depth, frame_intrinsics(W, H, calib, args.fov), args.ply, args.ply_stride)
            done += 1
        bar.update(len(batch))
    bar.close()
    for msg in failures:
        print(f"failed: {msg}", file=sys.stderr)
    print(f"{done} frame(s) written to {out_dir}" + (f"; {len(failures)} failed" if failures else ""))
    return 1 if failures else 0
