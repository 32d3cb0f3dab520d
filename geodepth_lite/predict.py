"""``python -m geodepth_lite predict``: zero-shot depth for your own images or video (Section 4.2.3).

The paper's stage II applies the network trained on synthetic frames to clinical images
(Kvasir, clinical videos) and turns each depth map into 3D with the endoscope's intrinsics.
For every frame this writes, into ``--out``:

- ``<name>_depth.npy``: float32 H x W z-depth at the frame's own size, in the training
  set's scene units (relative: monocular depth has no metric scale), NaN outside the
  endoscope's field of view;
- ``<name>_depth.png``: the depth colorized (``viz.colorize_depth``), black outside the field
  of view, its colour range (2nd-98th percentile) taken from the pixels inside;
- ``<name>_panel.png``: frame | depth with its colour bar (near = bright) | with ``--panel prior``
  the shading prior (``baselines.shading_prior``), outside the field of view grey; ``--panel none``
  writes none;
- ``<name>.ply``: the coloured back-projected point cloud (or mesh, ``--ply mesh``) of the
  pixels inside the field of view;

and prints one line on it (``frame_summary``): the share masked, the depth range and median
inside, the PLY's points.

The field of view (``--mask``): real endoscope frames show tissue inside a round or octagonal
window in a black border, with on-screen text. ``auto`` (the default) finds the border and the
text in each frame (``fov.detect_mask``; a frame without a border is all inside), ``none``
takes every pixel as tissue, a path gives one mask image for every frame of the run (nonzero =
inside; read and checked against the frames' size before any work). The network sees the frame
with every pixel outside replaced by its nearest inside pixel (``fov.fill_outside``), so the
border and the text cannot change the depth inside.

Frames of any size from 2 x 2 pixels up are resized to the network's input and the
prediction back to the frame (``inference.predict_depth``); each depth map is the mean of
the network's predictions for the frame and its three mirror images, mirrored back
(``--flips hv``; ``none`` for one pass). Images of 16 bits a sample are scaled to 8 bits
(``images.to_rgb8``), not clipped. Intrinsics come from ``--intrinsics`` (YAML/JSON) or a
horizontal field of view (``--fov``, default: the authors' set, fx = 0.5556 W, about 84
degrees).

Failures: before any work, the inputs (and a ``--mask`` image) are checked and ``--out`` is
created, probed for writing and for room for one frame's outputs (``utils.check_output_dir``);
a refused run leaves no folder behind. Half-written temporary files of an interrupted run are
removed from ``--out``. A folder's images that ``predict`` itself wrote (``<name>_depth.png``
and ``<name>_panel.png`` beside ``<name>_depth.npy``) are skipped, and ``--out`` may not be the
``--input`` folder. An image or video that cannot be read, a frame of another size than the
``--mask`` image, or a frame whose outputs cannot be made, is reported by name and the others
are still processed; a frame's outputs are written all or none. At the end each failure is
one line ``error: <message naming the file>`` on stderr, followed by the summary, and the exit
status is 2 if anything failed, else 0. A full or read-only disk stops the run at the first
frame it refuses (exit status 2).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import io
import json
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
import torch
import torch.nn.functional as F
import yaml
from PIL import Image
from tqdm.auto import tqdm

from . import baselines, checkpoint, fov, recon, utils, viz
from .core import camera
from .core.errors import UserError
from .datasets import resize_image
from .images import read_rgb
from .inference import FLIPS, pick_device, predict_depth
from .utils import FileProblem, os_reason

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
VIDEO_EXTS = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".mpg", ".mpeg", ".m4v", ".wmv"}
DEFAULT_FOV_DEG = camera.fov_x_deg(camera.intrinsics(1000), 1000)  # the authors' set: about 83.97 degrees
DEFAULT_BATCH_SIZE = 8
MIN_SIDE = 2  # the smallest frame side: the colorized depth and the mesh need 2 x 2 pixels
OUTPUT_SUFFIX = "_depth.png"  # with "_depth.npy" beside it, a file predict wrote (never read as an input)
PANEL_SUFFIX = "_panel.png"  # the side-by-side view, likewise never read as an input
MASK_CHOICES = ("auto", "none")  # --mask: detect per frame, every pixel in view; anything else is a mask image
PANELS = {"none": 0, "depth": 2, "prior": 3}  # --panel: columns of the side-by-side PNG
PANEL_TILE_PX = 240  # height of each image in the panel, pixels
PANEL_BAR_PX = 100  # room right of a depth image for its colour bar and labels, pixels
PANEL_PAD_PX, PANEL_TITLE_PX = 8, 22  # margins and the title line, pixels
PANEL_DPI = 100
NEUTRAL = 128  # grey of the pixels outside the field of view in the panel
ROOM_MARGIN = 2**20  # bytes --out must have free beyond one frame's outputs
# a write failure with one of these reasons stops the run: every later frame would fail the same way
DISK_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS})


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
            data = yaml.safe_load(text)
    except Exception as exc:  # noqa: BLE001 - any parse error is the user's file
        raise UserError(f"--intrinsics {path}: cannot parse ({exc.__class__.__name__}: {exc})") from None
    if not isinstance(data, dict):
        raise UserError(f"--intrinsics {path}: expected a mapping with K or fx, fy, cx, cy")
    if "K" in data:
        K = np.asarray(data["K"], dtype=np.float64)
        if K.shape != (3, 3):
            raise UserError(f"--intrinsics {path}: K must be 3x3, got shape {K.shape}")
    else:
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in data]
        if missing:
            raise UserError(f"--intrinsics {path}: missing {', '.join(missing)} (or give K as a 3x3 list)")
        K = np.array([[data["fx"], 0, data["cx"]], [0, data["fy"], data["cy"]], [0, 0, 1]], dtype=np.float64)
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise UserError(f"--intrinsics {path}: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
    size = None
    if "width" in data or "height" in data:
        if not all(isinstance(data.get(k), int) and data[k] > 0 for k in ("width", "height")):
            raise UserError(f"--intrinsics {path}: width and height must both be positive integers")
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
def check_input_path(path: Path) -> None:
    """Nothing if ``path`` leads to a file or folder; else a one-line error saying why not:
    not found, a broken symbolic link (and to what), a symbolic link loop."""
    try:
        path.stat()
        return
    except OSError as exc:
        problem = exc
    if problem.errno == errno.ELOOP:
        raise FileProblem(f"--input {path}: a symbolic link loop ({os_reason(problem)})", path)
    if path.is_symlink():
        raise FileProblem(f"--input {path}: a broken symbolic link to {os.readlink(path)}", path)
    if problem.errno in (errno.ENOENT, errno.ENOTDIR):
        raise FileNotFoundError(f"--input not found: {path}")
    raise FileProblem(f"cannot read --input {path}: {os_reason(problem)}", path)


def is_predict_output(path: Path) -> bool:
    """Whether ``path`` is an image that predict wrote: ``<name>_depth.png`` or ``<name>_panel.png``
    with ``<name>_depth.npy`` beside it (a photo that merely ends in ``_depth.png`` is an input)."""
    for suffix in (OUTPUT_SUFFIX, PANEL_SUFFIX):
        if path.name.endswith(suffix):
            return path.with_name(path.name[: -len(suffix)] + "_depth.npy").is_file()
    return False


def _is_image_entry(path: Path) -> bool:
    """An image of a folder listing: a file with an image extension, or a symbolic link named
    like one (a broken link is then reported by name rather than skipped)."""
    return path.suffix.lower() in IMAGE_EXTS and (path.is_file() or path.is_symlink())


def list_inputs(path) -> tuple[list[Path], str]:
    """(files, kind) with kind "images" or "video"; a folder is read non-recursively, sorted by
    name, without the files predict itself wrote there (``is_predict_output``)."""
    path = Path(path)
    check_input_path(path)
    if path.is_dir():
        try:
            entries = sorted(path.iterdir())
        except OSError as exc:
            raise FileProblem(f"cannot read folder {path}: {os_reason(exc)}", path) from exc
        files = [p for p in entries if _is_image_entry(p) and not is_predict_output(p)]
        if not files:
            raise UserError(f"--input folder {path} holds no images ({', '.join(sorted(IMAGE_EXTS))})")
        return files, "images"
    ext = path.suffix.lower()
    if ext in IMAGE_EXTS:
        return [path], "images"
    if ext in VIDEO_EXTS:
        return [path], "video"
    raise UserError(f"--input {path}: not an image ({', '.join(sorted(IMAGE_EXTS))}) "
                     f"or a video ({', '.join(sorted(VIDEO_EXTS))})")


def check_out_is_not_input(out, input_path) -> None:
    """A ValueError when ``--out`` is the ``--input`` folder: a second run would read its own outputs."""
    src = Path(input_path)
    if src.is_dir() and Path(out).resolve() == src.resolve():
        raise UserError(f"--out {out} is the --input folder: the outputs would be mixed with the images "
                         f"(and read as images by the next run); choose another --out")


def _output_stems(files: list[Path]) -> dict[Path, str]:
    """Output name per input: its stem, or stem_ext where two inputs share a stem."""
    stems = [f.stem for f in files]
    return {f: (f.stem if stems.count(f.stem) == 1 else f"{f.stem}_{f.suffix.lstrip('.').lower()}") for f in files}


# --------------------------------------------------------------------------- reading images
def check_frame_size(width: int, height: int, what: str, path: Path) -> None:
    """A FileProblem naming ``path`` when a frame is smaller than MIN_SIDE x MIN_SIDE pixels."""
    if width < MIN_SIDE or height < MIN_SIDE:
        raise FileProblem(f"cannot use {what} {path}: {width} x {height} pixels is too small "
                          f"(predict needs at least {MIN_SIDE} x {MIN_SIDE})", path)


def read_frame(path: Path, max_pixels: int | None = None) -> np.ndarray:
    """H x W x 3 uint8 of an image file (``images.read_rgb``: 16-bit scaled to 8); a FileProblem
    naming the file if it cannot be decoded, is too small (``check_frame_size``) or too large (over
    ``max_pixels``, default ``utils.MAX_PIXELS``, checked from its header before decoding)."""
    return read_rgb(path, max_pixels, check_size=lambda width, height: check_frame_size(width, height, "image", path))


def _image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from an image's header, or None if it cannot be read (reported later)."""
    try:
        with Image.open(path) as im:
            return im.size
    except Exception:  # noqa: BLE001 - read_frame names the file when its turn comes
        return None


# --------------------------------------------------------------------------- reading video
_FFMPEG_TAG = re.compile(r"^\[[^\]]*\]\s*")  # ffmpeg's "[in#0 @ 0x55d1f8d38040] " line prefix


def _short(text: str, limit: int = 120) -> str:
    """One trimmed line, lower-case first letter, no final full stop, at most ``limit`` characters."""
    text = " ".join(text.split()).rstrip(".")
    text = text[:1].lower() + text[1:]
    return text if len(text) <= limit else text[: limit - 1] + "…"


def ffmpeg_reason(exc: BaseException) -> str:
    """A few words on why ffmpeg could not read a video, never its banner or log: ffmpeg's own
    "Error opening input: <reason>" line where there is one, else the first line of the
    reader's message that says something (e.g. "end of file reached before full frame ...")."""
    head, _, log = str(exc).partition("=== stderr ===")
    for line in (_FFMPEG_TAG.sub("", ln).strip() for ln in log.splitlines()):
        if "does not contain any stream" in line:
            return "no video stream in it"
        if line.startswith("Error opening input:"):
            return _short(line.partition(":")[2])
    lines = [ln.strip() for ln in head.splitlines() if ln.strip()]
    said = [ln for ln in lines if not re.fullmatch(r"Could not read frame \d+:", ln)]
    return _short((said or lines or [exc.__class__.__name__])[0])


def video_error(path: Path, frames_read: int, exc: BaseException) -> str:
    """The one-line message for a video that failed after ``frames_read`` good frames."""
    if frames_read == 0:
        return f"cannot read video {path}: not a readable video ({ffmpeg_reason(exc)})"
    return f"cannot read video {path} after frame {frames_read - 1}: {ffmpeg_reason(exc)}"


def read_video(path: Path) -> Iterator[np.ndarray]:
    """The frames (H x W x 3 uint8) of a video file, decoded by ffmpeg (``imageio_ffmpeg``);
    ffmpeg is stopped when the iteration ends or is abandoned."""
    import imageio_ffmpeg  # optional ffmpeg binary, needed only for video input

    with contextlib.closing(imageio_ffmpeg.read_frames(str(path))) as reader:
        width, height = next(reader)["size"]
        for data in reader:
            yield np.frombuffer(data, dtype=np.uint8).reshape(height, width, 3).copy()


def video_size(path: Path, max_pixels: int | None = None) -> tuple[int, int]:
    """(width, height) of a video's frames; a FileProblem naming it if ffmpeg cannot read it or
    its frames are too small."""
    import imageio_ffmpeg  # optional ffmpeg binary, needed only for video input

    try:
        with contextlib.closing(imageio_ffmpeg.read_frames(str(path))) as reader:
            width, height = next(reader)["size"]
    except Exception as exc:  # noqa: BLE001 - ffmpeg's errors come in many types; the message says why
        raise FileProblem(video_error(path, 0, exc), path) from exc
    check_frame_size(width, height, "video", path)
    utils.check_pixels(width, height, path, "video", max_pixels)
    return width, height


def first_frame_size(files: list[Path], kind: str, max_pixels: int | None = None) -> tuple[int, int]:
    """(width, height) of the first frame that can be sized, (0, 0) if none; a video that cannot
    be read, or whose frames are over ``max_pixels``, is refused here, before any output is made."""
    if kind == "video":
        return video_size(files[0], max_pixels)
    return next((s for s in map(_image_size, files) if s is not None), (0, 0))


def png_bytes(width: int, height: int) -> int:
    """An upper bound on an RGB PNG's bytes: uncompressed samples (3 B a pixel), a filter byte a
    row, 5 B a 64 KiB stored deflate block, and the headers."""
    raw = (3 * width + 1) * height
    return raw + 5 * (raw // 65535 + 1) + 1024


def frame_output_bytes(width: int, height: int, ply: str = "points", stride: int = 1, panel: str = "depth") -> int:
    """An upper bound on the bytes of one frame's outputs: .npy (4 B a pixel), the colorized depth
    and the panel as PNG (``png_bytes``; the panel's size from ``panel_size``), PLY (15 B a
    point; a mesh 27 B a point and two 13 B triangles)."""
    points = -(-width // stride) * -(-height // stride)
    ply_bytes = {"points": 15 * points, "mesh": 53 * points, "none": 0}[ply]
    panel_bytes = png_bytes(*panel_size(width, height, panel)) if panel != "none" and width and height else 0
    return 4 * width * height + 128 + png_bytes(width, height) + panel_bytes + ply_bytes + 2048


def iter_frames(files: list[Path], kind: str, failures: list[str],
                max_pixels: int | None = None) -> Iterator[tuple[str, np.ndarray]]:
    """(output name, H x W x 3 uint8) per frame; a file that cannot be used adds one message
    naming it to ``failures`` and the others are still read."""
    if kind == "video":
        yield from _video_frames(files[0], failures)
        return
    names = _output_stems(files)
    for f in files:
        try:
            rgb = read_frame(f, max_pixels)
        except FileProblem as exc:
            failures.append(str(exc))
            continue
        yield names[f], rgb


def _video_frames(video: Path, failures: list[str]) -> Iterator[tuple[str, np.ndarray]]:
    """iter_frames for a video: frames until the end, or until ffmpeg fails (one message in
    ``failures`` naming the last good frame)."""
    done = 0
    try:
        for frame in read_video(video):
            yield f"{video.stem}_{done:06d}", frame
            done += 1
    except Exception as exc:  # noqa: BLE001 - report it; the frames read so far are kept
        failures.append(video_error(video, done, exc))
        return
    if done == 0:
        failures.append(f"cannot read video {video}: no frame in it")


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
    size = (image_size, image_size) if isinstance(image_size, int) else tuple(image_size)
    x = torch.stack([resize_image(torch.from_numpy(f).permute(2, 0, 1).float().div(255.0), size) for f in frames])
    pred = predict_depth(model, x, size, flips).cpu()
    out = []
    for f, p in zip(frames, pred):
        p = F.interpolate(p[None], size=f.shape[:2], mode="bilinear", align_corners=False)[0, 0]
        out.append(p.numpy().astype(np.float32))
    return out


def save_npy(array: np.ndarray, path) -> Path:
    """``np.save``, atomically, through one Python write: numpy writing to a file itself reports a
    full disk as "4096 requested and 3040 written", without the system's reason."""
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    path = Path(path)
    with utils.atomic_path(path) as tmp:
        tmp.write_bytes(buf.getbuffer())
    return path


def output_paths(out_dir: Path, name: str, ply: str = "points", panel: str = "none") -> list[Path]:
    """The files one frame gets: depth .npy, colorized depth .png, the panel .png (unless panel is
    "none") and the .ply (unless ply is "none")."""
    paths = [out_dir / f"{name}_depth.npy", out_dir / f"{name}{OUTPUT_SUFFIX}"]
    paths += [out_dir / f"{name}{PANEL_SUFFIX}"] if panel != "none" else []
    return paths + ([out_dir / f"{name}.ply"] if ply != "none" else [])


def panel_size(width: int, height: int, panel: str = "depth") -> tuple[int, int]:
    """(width, height) in pixels of the side-by-side PNG of a ``width`` x ``height`` frame: each
    image ``PANEL_TILE_PX`` tall (wider than 4:1 or taller than 1:4 frames are drawn squeezed)."""
    tile = round(PANEL_TILE_PX * min(max(width / height, 0.25), 4.0))
    columns = PANELS[panel]
    return (columns * tile + (columns - 1) * PANEL_BAR_PX + 4 * PANEL_PAD_PX,  # the frame has no bar
            PANEL_TILE_PX + PANEL_TITLE_PX + 2 * PANEL_PAD_PX)


def panel_image(rgb: np.ndarray, depth: np.ndarray, mask: np.ndarray, prior: np.ndarray | None = None) -> np.ndarray:
    """The side-by-side view of one frame, H x W x 3 uint8 (``panel_size``): the frame | its depth
    with a colour bar (``viz.show_depth``: near = bright, range from the inside pixels) | the
    shading prior when given; pixels outside the field of view ``mask`` are neutral grey."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # heavy, needed only to draw the panel
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, no figure kept alive

    H, W = depth.shape
    panel = "prior" if prior is not None else "depth"
    pw, ph = panel_size(W, H, panel)
    tile = round(PANEL_TILE_PX * min(max(W / H, 0.25), 4.0))
    fig = Figure(figsize=(pw / PANEL_DPI, ph / PANEL_DPI), dpi=PANEL_DPI)
    canvas = FigureCanvasAgg(fig)
    shown = np.where(mask[..., None], rgb, np.uint8(NEUTRAL))
    maps = [("predicted depth", depth, "z-depth")]
    maps += [("shading prior 1/sqrt(brightness)", prior, "prior depth")] if prior is not None else []
    x = PANEL_PAD_PX
    for k, (title, image) in enumerate([("frame", shown)] + [(t, d) for t, d, _ in maps]):
        ax = fig.add_axes((x / pw, PANEL_PAD_PX / ph, tile / pw, PANEL_TILE_PX / ph))
        if k == 0:
            ax.imshow(image, aspect="auto", interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
        else:
            im = viz.show_depth(ax, image, label=maps[k - 1][2], bad=f"#{NEUTRAL:02x}{NEUTRAL:02x}{NEUTRAL:02x}")
            im.set_interpolation("nearest")
            ax.set_aspect("auto")
            ax.set_position((x / pw, PANEL_PAD_PX / ph, tile / pw, PANEL_TILE_PX / ph))
            im.colorbar.ax.set_position(((x + tile + 6) / pw, PANEL_PAD_PX / ph, 10 / pw, PANEL_TILE_PX / ph))
        ax.set_title(title, fontsize=9)
        x += tile + (2 * PANEL_PAD_PX if k == 0 else PANEL_BAR_PX)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def write_outputs(out_dir: Path, name: str, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray,
                  ply: str = "points", stride: int = 1, panel: np.ndarray | None = None) -> dict:
    """The files of one frame (``output_paths``), each written atomically, and all or none: if
    one fails after another was written, the frame's files are all removed again (those an
    earlier run left under these names too, which would no longer match), then it re-raises.

    depth: H x W, NaN outside the field of view (no colour in the PNG, no point in the PLY);
    panel: the side-by-side image (``panel_image``) or None. Returns {"paths": the files,
    "points": vertices in the PLY or None, "triangles": its faces or None}.
    """
    paths = output_paths(out_dir, name, ply, "none" if panel is None else "depth")
    written, done = 0, {"paths": paths, "points": None, "triangles": None}
    try:
        save_npy(depth.astype(np.float32), paths[0])
        written += 1
        recon.save_png(viz.colorize_depth(depth), paths[1])
        written += 1
        if panel is not None:
            recon.save_png(panel, paths[2])
        if ply != "none":
            poly = (recon.depth_mesh if ply == "mesh" else recon.point_cloud)(depth, K, rgb, stride=stride)
            recon.save_ply(poly, paths[-1])
            done["points"], done["triangles"] = poly.n_points, (poly.n_cells if ply == "mesh" else None)
    except BaseException:
        if written:
            for p in paths:
                with contextlib.suppress(OSError):
                    p.unlink(missing_ok=True)
        raise
    return done


def frame_summary(name: str, depth: np.ndarray, written: dict) -> str:
    """One line on a frame: share of pixels outside the field of view, depth range and median
    inside it, and what the PLY holds, e.g. ``a: 18.2% masked, depth 0.91-7.4 (median 2.3),
    12 345 points``."""
    inside = depth[np.isfinite(depth)]
    line = f"{name}: {100.0 * (1.0 - inside.size / depth.size):.1f}% masked"
    if inside.size:
        line += f", depth {inside.min():.3g}-{inside.max():.3g} (median {np.median(inside):.3g})"
    if written["points"] is None:
        return line + ", no PLY"
    line += f", {_grouped(written['points'])} points"
    if written["triangles"] is not None:
        line += f", {_grouped(written['triangles'])} triangles"
    return line


def _grouped(n: int) -> str:
    """An integer with its thousands apart: 12345 -> "12 345"."""
    return f"{n:_}".replace("_", " ")


def stops_the_run(exc: BaseException) -> bool:
    """Whether a write failure is the disk's (full, over quota, read-only) rather than one frame's."""
    cause = exc.__cause__ if isinstance(exc, FileProblem) else exc
    return isinstance(cause, OSError) and cause.errno in DISK_ERRNOS


# --------------------------------------------------------------------------- a run
@dataclass
class Tally:
    """What a run did: frames written, one message per failed file or frame, and the write
    failure that stopped it early (None if it ran to the end)."""

    written: int = 0
    failures: list[str] = field(default_factory=list)
    stopped: str | None = None


def _save_frame(out_dir: Path, frame: Frame, depth: np.ndarray, args, calib, tally: Tally) -> None:
    """Write one frame's outputs, count it and print its summary line (``frame_summary``); a
    failure is added to ``tally`` (a disk failure as ``tally.stopped``), never raised."""
    H, W = depth.shape
    K = frame_intrinsics(W, H, calib, args.fov)
    try:
        panel = None
        if args.panel != "none":
            prior = None
            if args.panel == "prior":
                x = frame.net_input.transpose(2, 0, 1).astype(np.float32) / 255.0  # 3 x H x W in [0, 1]
                prior = np.where(frame.mask, baselines.shading_prior(x)[0], np.nan)
            panel = panel_image(frame.rgb, depth, frame.mask, prior)
        written = write_outputs(out_dir, frame.name, frame.rgb, depth, K, args.ply, args.ply_stride, panel)
    except OSError as exc:  # utils.FileProblem: "cannot write <file>: <reason>"
        if stops_the_run(exc):
            tally.stopped = str(exc)
        else:
            tally.failures.append(str(exc))
        return
    except Exception as exc:  # noqa: BLE001 - a frame the reconstruction cannot handle is that frame's failure
        tally.failures.append(f"cannot write the outputs of {frame.name}: {exc.__class__.__name__}: {exc}")
        return
    tally.written += 1
    tqdm.write(frame_summary(frame.name, depth, written), file=sys.stdout)


def _refuse_non_finite(batch, depths, ckpt: Path) -> None:
    """A ValueError if the model predicted NaN or inf for any frame of the batch (nothing of it written)."""
    for frame, depth in zip(batch, depths):
        if not np.isfinite(depth).all():
            raise UserError(f"checkpoint {ckpt} predicts non-finite depth (NaN or inf) for {frame.name}: "
                             f"nothing written for it; the model is unusable")


# --------------------------------------------------------------------------- the field of view
@dataclass
class Frame:
    """One frame on its way through ``predict``: its name, the image as read (H x W x 3 uint8), its
    field of view (H x W bool, True = tissue) and the network's input (outside filled from inside)."""

    name: str
    rgb: np.ndarray
    mask: np.ndarray
    net_input: np.ndarray


def frame_mask(rgb: np.ndarray, mask_arg: str, given: np.ndarray | None) -> np.ndarray:
    """The field of view of one frame for ``--mask``: "auto" ``fov.detect_mask``, "none" every
    pixel, else the mask image read before the run (``given``, already checked)."""
    if mask_arg == "auto":
        return fov.detect_mask(rgb)
    if mask_arg == "none":
        return np.ones(rgb.shape[:2], dtype=bool)
    return given


def masked_frames(frames, mask_arg: str, given: np.ndarray | None, failures: list[str]) -> Iterator[Frame]:
    """A ``Frame`` per (name, rgb) of ``frames``; a frame whose size differs from the ``--mask``
    image adds one message naming both to ``failures`` and is skipped."""
    for name, rgb in frames:
        if given is not None and given.shape != rgb.shape[:2]:
            failures.append(f"cannot use --mask {mask_arg} for {name}: the mask is {given.shape[1]} x "
                            f"{given.shape[0]} pixels, the frame {rgb.shape[1]} x {rgb.shape[0]}")
            continue
        mask = frame_mask(rgb, mask_arg, given)
        yield Frame(name, rgb, mask, fov.fill_outside(rgb, mask))


def predict_into(out_dir: Path, files: list[Path], kind: str, model, cfg: dict, calib, args,
                 given_mask: np.ndarray | None = None) -> Tally:
    """Predict and write every frame of ``files`` into ``out_dir``, in batches; stops early only
    when the disk refuses a write (``stops_the_run``). The network sees each frame with its outside
    filled from the inside (``fov.fill_outside``); its depth is NaN outside the field of view."""
    tally = Tally()
    total = len(files) if kind == "images" else None
    frames = iter_frames(files, kind, tally.failures, getattr(args, "max_pixels", None))
    with contextlib.closing(frames), tqdm(total=total, unit="frame", desc="predict", disable=args.no_progress,
                                          file=sys.stderr) as bar:
        for batch in _batches(masked_frames(frames, args.mask, given_mask, tally.failures), args.batch_size):
            depths = predict_frames(model, [f.net_input for f in batch], cfg["image_size"], args.flips)
            _refuse_non_finite(batch, depths, Path(args.checkpoint))
            for frame, depth in zip(batch, depths):
                _save_frame(out_dir, frame, np.where(frame.mask, depth, np.float32(np.nan)), args, calib, tally)
                if tally.stopped:
                    return tally
            bar.update(len(batch))
    return tally


def report(tally: Tally, out_dir: Path) -> int:
    """One ``error:`` line per failure on stderr, then the summary; the exit status (2 if anything failed)."""
    for msg in tally.failures + ([tally.stopped] if tally.stopped else []):
        print(f"error: {msg}", file=sys.stderr)
    summary = f"{tally.written} frame(s) written to {out_dir}" if tally.written else "no frame written"
    if tally.failures:
        summary += f"; {len(tally.failures)} failed (the error lines above)"
    if tally.stopped:
        summary += "; stopped at the write that failed: the frames after it were not processed"
    print(summary)
    return 2 if tally.failures or tally.stopped else 0


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
    parser.add_argument("--mask", default="auto",
                        help="the endoscope's field of view: auto (default: black border and on-screen text found "
                        "in each frame, fov.detect_mask), none (every pixel is tissue), or a mask image of the "
                        "frames' size for the whole run (nonzero = inside); pixels outside get no depth (NaN), "
                        "no colour and no 3D point")
    parser.add_argument("--panel", choices=tuple(PANELS), default="depth",
                        help="a side-by-side <name>_panel.png per frame: depth (default: frame | depth with its "
                        "colour bar), prior (and the shading prior 1/sqrt(brightness) beside them) or none")
    parser.add_argument("--max-pixels", type=int, default=utils.MAX_PIXELS,
                        help="refuse an image, mask or video frame of more pixels than this, read from its "
                             f"header before decoding (default {utils.MAX_PIXELS})")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _check_options(args: argparse.Namespace) -> None:
    """UserErrors for option values that cannot work, before anything is read."""
    if args.batch_size < 1:
        raise UserError(f"--batch-size must be at least 1, got {args.batch_size}")
    if args.ply_stride < 1:
        raise UserError(f"--ply-stride must be at least 1, got {args.ply_stride}")
    if getattr(args, "max_pixels", 1) < 1:
        raise UserError(f"--max-pixels must be at least 1, got {args.max_pixels}")
    if args.fov is not None and not 0.0 < args.fov < 180.0:
        raise UserError(f"--fov must be between 0 and 180 degrees, got {args.fov}")
    if args.intrinsics is not None and args.fov is not None:
        raise UserError("give either --intrinsics or --fov, not both")


def run_predict(args: argparse.Namespace) -> int:
    """The ``predict`` command: inputs and options checked, then --out made and probed, then the
    model loaded and every frame written (the module docstring says what fails how); exit status."""
    _check_options(args)
    if args.device is not None:
        utils.parse_device(args.device)  # a bad --device: one line, before any work
    calib = load_intrinsics(args.intrinsics) if args.intrinsics else None
    files, kind = list_inputs(args.input)
    check_out_is_not_input(args.out, args.input)
    ckpt = Path(args.checkpoint)
    if not ckpt.is_file():
        raise FileNotFoundError(f"--checkpoint not found: {ckpt}")
    max_pixels = getattr(args, "max_pixels", None)
    width, height = first_frame_size(files, kind, max_pixels)
    given_mask = None
    if args.mask not in MASK_CHOICES:  # one mask image for the run: read and sized before any work
        given_mask = fov.read_mask(args.mask, (height, width) if width else None, what="--mask",
                                   max_pixels=max_pixels)
    need = frame_output_bytes(width, height, args.ply, args.ply_stride, args.panel) + ROOM_MARGIN
    new_folders = utils.missing_dirs(args.out)
    out_dir = utils.check_output_dir(args.out, need)  # creates --out; removes it again if it refuses
    lock = utils.FolderLock(out_dir, "output folder", remove_file=True)  # one writer per --out
    try:
        lock.acquire()
        stale = utils.remove_stale_temps(out_dir, locked=True)
        if stale:
            print(f"removed {stale} half-written temporary file(s) of an interrupted run from {out_dir}")
        model, cfg = checkpoint.load_model(ckpt, device=pick_device(args.device))
        tally = predict_into(out_dir, files, kind, model, cfg, calib, args, given_mask)
    finally:  # a run that wrote nothing leaves no folder it made
        lock.release()
        utils.remove_empty_dirs(new_folders)
    return report(tally, out_dir)
