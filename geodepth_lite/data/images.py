"""Image files: reading an RGB image (one reader, and one rule for samples of more than 8 bits), and
the bytes of the images the project writes (``encode_png``, ``encode_npy`` for depth maps).

``read_rgb`` is what every command reads a colour frame with: the training and evaluation
datasets (``datasets/``), ``predict`` (``frames.read_frame`` adds its smallest-frame check), the
gallery (``gallery.py``) and another simulator's sample frames (``external.py``). A 16-bit image
is scaled to 8 bits (65535 -> 255), never clipped (``to_rgb8``); an 8-bit image reads as PIL
decodes it.
"""

from __future__ import annotations

import io
import os
from typing import Callable

import numpy as np
from PIL import Image

from geodepth_lite.data.bounds import check_pixels
from geodepth_lite.utils import FileProblem, os_reason


def _scaled_gray(a: np.ndarray, full_scale: float) -> np.ndarray:
    """H x W x 3 uint8 from one channel whose ``full_scale`` maps to 255 (NaN and below 0: black)."""
    v = np.nan_to_num(a.astype(np.float64) * (255.0 / full_scale), nan=0.0)
    g = np.clip(np.rint(v), 0, 255).astype(np.uint8)
    return np.repeat(g[..., None], 3, axis=-1)


def to_rgb8(im) -> np.ndarray:
    """H x W x 3 uint8 of a PIL image, samples of more than 8 bits scaled to 8, not clipped.

    PIL's ``convert("RGB")`` clips 16-bit grey ("I;16") and 32-bit ("I") images to white. Here
    16-bit data is divided by 257 (65535 -> 255); an "I" image is taken as 16-bit data when all
    its values fit (how 16-bit files often arrive), else scaled by the int32 range; a float
    ("F") image by 1 when its values lie in [0, 1], else as 0-255. PIL itself reduces 16-bit
    colour PNG and TIFF to 8 bits (their high byte) when it opens them.
    """
    if im.mode.startswith("I;16"):
        return _scaled_gray(np.asarray(im), 65535.0)
    if im.mode == "I":
        a = np.asarray(im)
        return _scaled_gray(a, 65535.0 if a.size == 0 or 0 <= a.min() <= a.max() <= 65535 else 2.0**31 - 1)
    if im.mode == "F":
        a = np.asarray(im)
        finite = a[np.isfinite(a)]
        return _scaled_gray(a, 1.0 if finite.size and finite.min() >= 0 and finite.max() <= 1 else 255.0)
    return np.array(im.convert("RGB"))


def image_reason(exc: BaseException) -> str:
    """Why an image could not be decoded, in a few words (whatever the decoder raised)."""
    if isinstance(exc, Image.DecompressionBombError):  # past PIL's own limit, from the header
        return str(exc)
    if isinstance(exc, Image.UnidentifiedImageError):
        return "not an image file, or a damaged one"
    if isinstance(exc, OSError):  # unreadable, truncated ("image file is truncated")
        return os_reason(exc)
    return f"damaged or unsupported image ({exc.__class__.__name__}: {exc})"


def read_rgb(path: str | os.PathLike, max_pixels: int | None = None,
             check_size: Callable[[int, int], None] | None = None) -> np.ndarray:
    """H x W x 3 uint8 of an image file (``to_rgb8``); a FileProblem naming the file if it cannot
    be decoded or is over ``max_pixels`` (default ``bounds.MAX_PIXELS``, from its header before
    decoding). ``check_size(width, height)``, where given, is called on the header's size first."""
    try:
        with Image.open(path) as im:
            if check_size is not None:
                check_size(*im.size)
            check_pixels(*im.size, path, "image", max_pixels)
            im.load()
            return to_rgb8(im)
    except FileProblem:
        raise
    except Exception as exc:  # noqa: BLE001 - any decoder error means this file, named, not the run
        raise FileProblem(f"cannot read {path}: {image_reason(exc)}", path) from exc


def encode_png(rgb: np.ndarray, compress_level: int = 6) -> bytes:
    """The bytes of an H x W x 3 uint8 image as PNG (lossless at every ``compress_level``, 0-9: 1 is fast,
    6 PIL's default)."""
    buf = io.BytesIO()
    Image.fromarray(np.asarray(rgb, dtype=np.uint8)).save(buf, format="PNG", compress_level=compress_level)
    return buf.getvalue()


def encode_npy(depth: np.ndarray) -> bytes:
    """The bytes of a depth map as a float32 ``.npy`` file (no pickle), written as one Python write: numpy
    writing to a file itself reports a full disk as "4096 requested and 3040 written", without the reason."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(depth, dtype=np.float32), allow_pickle=False)
    return buf.getvalue()
