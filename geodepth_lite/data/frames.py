"""Frames from a user's files for ``predict`` and the gallery: images and videos listed and read (one RGB
reader, ``images.read_rgb``, with its one 16-bit rule), their intrinsics (``--intrinsics`` or a field of
view), and each frame's field of view (``--mask``) with the network's input filled from the inside.

Nothing here writes: a folder's images that ``predict`` itself wrote (``<name>_depth.png`` and
``<name>_panel.png`` beside ``<name>_depth.npy``) are recognised and never read as inputs.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import yaml

from geodepth_lite.core import camera
from geodepth_lite.core.errors import UserError
from geodepth_lite.data import bounds, fov
from geodepth_lite.data.images import read_rgb
from geodepth_lite.utils import FileProblem, os_reason

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
VIDEO_EXTS = {".mp4", ".avi", ".mov", ".mkv", ".webm", ".mpg", ".mpeg", ".m4v", ".wmv"}
DEFAULT_FOV_DEG = camera.fov_x_deg(camera.intrinsics(1000), 1000)  # the authors' set: about 83.97 degrees
MIN_SIDE = 2  # the smallest frame side: the colorized depth and the mesh need 2 x 2 pixels
OUTPUT_SUFFIX = "_depth.png"  # with "_depth.npy" beside it, a file predict wrote (never read as an input)
PANEL_SUFFIX = "_panel.png"  # the side-by-side view, likewise never read as an input
MASK_CHOICES = ("auto", "none")  # --mask: detect per frame, every pixel in view; anything else is a mask image


MAX_INTRINSICS_BYTES = 64 * 2**10  # an --intrinsics file (a few numbers) is refused above this, before parsing


def _read_calibration(path: Path):
    """The parsed YAML/JSON of an ``--intrinsics`` file, read within ``MAX_INTRINSICS_BYTES``."""
    text = bounds.read_text(path, "--intrinsics", MAX_INTRINSICS_BYTES)
    try:
        return json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except Exception as exc:  # noqa: BLE001 - any parse error is the user's file
        reason = " ".join(f"{exc.__class__.__name__}: {exc}".split())[:200]  # YAML's messages span lines
        raise UserError(f"--intrinsics {path}: cannot parse ({reason})") from None


def load_intrinsics(path) -> dict:
    """Intrinsics file (YAML or JSON, at most ``MAX_INTRINSICS_BYTES``): ``K`` (3x3) or ``fx, fy, cx, cy``,
    in pixels, and optionally ``width``, ``height``: the image size the calibration refers to (frames of
    another size get K scaled). Every value must be a finite number (width and height positive integers,
    focal lengths positive); anything else is a UserError naming the file and the value. Returns
    {"K": 3x3 array, "size": (W, H) or None}."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"--intrinsics file not found: {path}")
    data = _read_calibration(path)
    if not isinstance(data, dict):
        raise UserError(f"--intrinsics {path}: expected a mapping with K or fx, fy, cx, cy")
    if "K" in data:
        rows = data["K"]
        if not (isinstance(rows, list) and len(rows) == 3 and all(isinstance(r, list) and len(r) == 3 for r in rows)):
            raise UserError(f"--intrinsics {path}: K must be 3x3 (three lists of three numbers)")
        K = np.array([bounds.finite_numbers(r, f"--intrinsics {path}, K[{i}]") for i, r in enumerate(rows)])
    else:
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in data]
        if missing:
            raise UserError(f"--intrinsics {path}: missing {', '.join(missing)} (or give K as a 3x3 list)")
        fx, fy, cx, cy = (bounds.finite_numbers([data[k]], f"--intrinsics {path}, {k}")[0] for k in ("fx", "fy", "cx", "cy"))
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise UserError(f"--intrinsics {path}: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
    size = None
    if "width" in data or "height" in data:
        if not all(type(data.get(k)) is int and data[k] > 0 for k in ("width", "height")):
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


def check_frame_size(width: int, height: int, what: str, path: Path) -> None:
    """A FileProblem naming ``path`` when a frame is smaller than MIN_SIDE x MIN_SIDE pixels."""
    if width < MIN_SIDE or height < MIN_SIDE:
        raise FileProblem(f"cannot use {what} {path}: {width} x {height} pixels is too small "
                          f"(predict needs at least {MIN_SIDE} x {MIN_SIDE})", path)


def read_frame(path: Path, max_pixels: int | None = None) -> np.ndarray:
    """H x W x 3 uint8 of an image file (``images.read_rgb``: 16-bit scaled to 8); a FileProblem
    naming the file if it cannot be decoded, is too small (``check_frame_size``) or too large (over
    ``max_pixels``, default ``bounds.MAX_PIXELS``, checked from its header before decoding)."""
    return read_rgb(path, max_pixels, check_size=lambda width, height: check_frame_size(width, height, "image", path))


def _usable_size(path: Path, max_pixels: int | None) -> tuple[int, int] | None:
    """(width, height) from an image's header when ``read_frame`` would read it (within ``max_pixels``,
    at least MIN_SIDE a side), else None: ``read_frame`` names that file when its turn comes."""
    try:
        size = bounds.image_header_size(path)
        if size is not None:
            check_frame_size(*size, "image", path)
            bounds.check_pixels(*size, path, "image", max_pixels)
    except FileProblem:
        return None
    return size


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
    bounds.check_pixels(width, height, path, "video", max_pixels)
    return width, height


def first_frame_size(files: list[Path], kind: str, max_pixels: int | None = None) -> tuple[int, int]:
    """(width, height) of the first frame that will be read, (0, 0) if none; a video that cannot be
    read, or whose frames are over ``max_pixels``, is refused here, before any output is made. An image
    that ``read_frame`` will refuse (unreadable, too small, over ``max_pixels``) is passed over, so a
    ``--mask`` image and the room ``--out`` needs are sized by the frames that are written."""
    if kind == "video":
        return video_size(files[0], max_pixels)
    return next((s for s in (_usable_size(f, max_pixels) for f in files) if s is not None), (0, 0))


def iter_frames(files: list[Path], kind: str, failures: list[str],
                max_pixels: int | None = None) -> Iterator[tuple[str, np.ndarray]]:
    """(output name, H x W x 3 uint8) per frame; a file that cannot be used adds one message
    naming it to ``failures`` and the others are still read."""
    if kind == "video":
        yield from _video_frames(files[0], failures)
        return
    names = output_stems(files)
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


def output_stems(files: list[Path]) -> dict[Path, str]:
    """Output name per input: its stem, or stem_ext where two inputs share a stem."""
    stems = [f.stem for f in files]
    return {f: (f.stem if stems.count(f.stem) == 1 else f"{f.stem}_{f.suffix.lstrip('.').lower()}") for f in files}
