"""The endoscope's field of view: which pixels of a frame show tissue (clinical frames, Section 4.2.3).

A clinical endoscope frame shows the scene through a round or octagonal field of view inside
a black border, and the video processor writes text on it (date, patient, scope settings,
"NBI"), mostly in the black corners, sometimes over the image. Those pixels are not tissue:
fed to the network they come out as dark, far blobs that also stretch the colour scale and
land in the 3D views. This module finds them and keeps them out of what the network sees:

- ``detect_mask``: the field of view of one frame (True = tissue), the rule in its docstring;
- ``read_mask``: a mask image the user gives (nonzero = inside), checked;
- ``fill_outside``: the pixels outside replaced by their nearest inside pixel, so that what
  was there (black, text, anything) cannot change the network's input;
- ``synthetic_mask`` and ``add_overlay``: round / octagonal fields of view and an endoscope's
  black border with on-screen text painted onto a frame, with the exact mask of what stays
  tissue: the known answers of the tests, and an augmentation for training frames.

Masks are H x W bool arrays, True inside the field of view; images are H x W x 3 (uint8 0-255
or float 0-1, as given).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError
from scipy import ndimage

from geodepth_lite.core.errors import UserError
from geodepth_lite.data.bounds import check_pixels
from geodepth_lite.utils import FileProblem, os_reason

# --------------------------------------------------------------------------- detection thresholds
DARK_MAX = 32  # 0-255: a pixel whose brightest channel is at most this is black (sensor black + JPEG noise < ~20)
OVERLAY_ON, OVERLAY_OFF = 200, 64  # 0-255: on-screen text colours have every channel >= ON or <= OFF ...
# ... and green on: white, yellow, green, cyan. Red is left out: deep red mucosa can look like pure red.
LINK_FRAC = 0.02  # text glyphs closer than 2 x this fraction of the smaller side (at least 3 px) form one line
CORNER_FRAC = 0.02  # corner patches of this fraction of the smaller side (at least 1 px) must be mostly black
MIN_OUTSIDE, MAX_OUTSIDE = 0.005, 0.8  # a border covers between 0.5% and 80% of the frame, else no border
# inset boxes (a scope-position display): flat, one colour, box-shaped
INSET_FLAT = 14  # 0-255: a pixel is flat when every channel varies by at most this over its 3 x 3 neighbours
INSET_AREA = (0.01, 0.15)  # a box covers 1-15% of the frame ...
INSET_FILL = 0.8  # ... fills at least 80% of its bounding rectangle (holes such as a drawing in it filled) ...
INSET_ASPECT = (0.5, 2.0)  # ... with height / width in this range ...
INSET_SPREAD = 12  # ... its colour's standard deviation at most this in every channel ...
INSET_WHITE = 245  # ... and it is neither white (a saturated highlight is flat too) nor black (DARK_MAX)

SYNTHETIC_KINDS = ("round", "octagon", "none")
# on-screen text colours of ``add_overlay`` (0-1): white, yellow, green, cyan
OVERLAY_COLOURS = ((1.0, 1.0, 1.0), (1.0, 1.0, 0.0), (0.0, 1.0, 0.0), (0.0, 1.0, 1.0))
# the seven segments of a digit cell (x0, y0, x1, y1 as fractions of the cell): glyph-like strokes
SEGMENTS = ((0, 0, 1, 0), (1, 0, 1, 0.5), (1, 0.5, 1, 1), (0, 1, 1, 1), (0, 0.5, 0, 1), (0, 0, 0, 0.5),
            (0, 0.5, 1, 0.5))


# --------------------------------------------------------------------------- detection
def _to_uint8(rgb) -> np.ndarray:
    """H x W x 3 uint8 of a uint8 or float (0-1) image."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] < 3:
        raise ValueError(f"expected an H x W x 3 image, got shape {a.shape}")
    a = a[..., :3]
    if a.dtype == np.uint8:
        return a
    return np.clip(np.rint(a.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)


def overlay_coloured(rgb8: np.ndarray) -> np.ndarray:
    """H x W bool: pixels in on-screen text colours (every channel >= OVERLAY_ON or <= OVERLAY_OFF,
    green >= OVERLAY_ON: white, yellow, green, cyan), as a video processor writes them."""
    on, off = rgb8 >= OVERLAY_ON, rgb8 <= OVERLAY_OFF
    return (on | off).all(axis=-1) & on[..., 1]


def _touches_border(labels: np.ndarray) -> np.ndarray:
    """The label numbers (> 0) that occur on the image's outer rows or columns."""
    edge = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    return np.unique(edge[edge > 0])


def _corners_black(outside: np.ndarray) -> bool:
    """Whether at least half of each of the four corner patches (CORNER_FRAC) is in ``outside``."""
    H, W = outside.shape
    c = max(1, round(CORNER_FRAC * min(H, W)))
    patches = (outside[:c, :c], outside[:c, -c:], outside[-c:, :c], outside[-c:, -c:])
    return all(p.mean() >= 0.5 for p in patches)


def convex_hull_mask(mask: np.ndarray) -> np.ndarray:
    """H x W bool: the pixels whose centres lie in the convex hull of the True pixels' centres.

    The hull of the leftmost and rightmost pixel of every row (the same hull as of all pixels),
    by Andrew's monotone chain, rasterised row by row (a convex region meets a row in one run).
    """
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return np.zeros_like(mask, dtype=bool)
    left = mask[rows].argmax(axis=1)
    right = mask.shape[1] - 1 - mask[rows, ::-1].argmax(axis=1)
    pts = sorted(set(zip(np.r_[left, right].tolist(), np.r_[rows, rows].tolist())))
    hull = _monotone_chain(pts)
    out = np.zeros_like(mask, dtype=bool)
    xs = np.array([p[0] for p in hull] + [hull[0][0]], dtype=np.float64)
    ys = np.array([p[1] for p in hull] + [hull[0][1]], dtype=np.float64)
    for y in range(rows[0], rows[-1] + 1):
        lo, hi = _row_span(xs, ys, y)
        out[y, int(np.ceil(lo - 1e-9)):int(np.floor(hi + 1e-9)) + 1] = True
    return out


def _monotone_chain(pts: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The convex hull (counter-clockwise, no collinear points) of sorted distinct integer points."""
    if len(pts) <= 2:
        return pts

    def half(points):
        chain: list[tuple[int, int]] = []
        for p in points:
            while len(chain) >= 2 and ((chain[-1][0] - chain[-2][0]) * (p[1] - chain[-2][1])
                                       - (chain[-1][1] - chain[-2][1]) * (p[0] - chain[-2][0])) <= 0:
                chain.pop()
            chain.append(p)
        return chain

    lower, upper = half(pts), half(pts[::-1])
    return lower[:-1] + upper[:-1]


def _row_span(xs: np.ndarray, ys: np.ndarray, y: float) -> tuple[float, float]:
    """(x min, x max) where the closed polygon (xs, ys) meets the row ``y``."""
    x0, x1, y0, y1 = xs[:-1], xs[1:], ys[:-1], ys[1:]
    hit = (np.minimum(y0, y1) <= y) & (y <= np.maximum(y0, y1))
    flat = hit & (y0 == y1)
    slope = hit & (y0 != y1)
    t = (y - y0[slope]) / (y1[slope] - y0[slope])
    xs_hit = np.concatenate([x0[slope] + t * (x1[slope] - x0[slope]), x0[flat], x1[flat]])
    return float(xs_hit.min()), float(xs_hit.max())


def detect_mask(rgb) -> np.ndarray:
    """The field of view of one endoscope frame: H x W bool, True where it shows tissue.

    The rule (thresholds on 0-255 values, constants at the top of this module):

    1. Black: a pixel whose brightest channel is at most ``DARK_MAX`` (32). The border is the
       black pixels connected (8-neighbours) to the image's edge through black pixels: a dark
       lumen in the middle of the image is not.
    2. It is a border only if black covers at least half of each of the four corner patches
       (``CORNER_FRAC`` = 2% of the smaller side) and between ``MIN_OUTSIDE`` (0.5%) and
       ``MAX_OUTSIDE`` (80%) of the frame; otherwise the frame has no border (a frame without
       border, a dark lumen touching one edge, an all-dark frame) and every pixel is inside
       but for coloured inset boxes (step 6).
    3. On-screen text: pixels in text colours (``overlay_coloured``: every channel >= 200 or
       <= 64 with green >= 200, i.e. white, yellow, green, cyan) within ``LINK_FRAC`` (2% of
       the smaller side, at least 3 px) of the border or of other such pixels linked to it:
       the glyphs of a line of text that starts in the black border and runs over the image.
    4. The field of view is the largest connected region of what is neither border nor text,
       its holes filled (text in the border that is not in text colours lies apart from it).
    5. A field of view is convex (round or octagonal): the region is replaced by its convex
       hull, less the text pixels. This gives back the black bites of a dark lumen or shadow
       that touches the field of view's edge, and keeps the boundary straight or round.
    6. Inset boxes (``inset_boxes``): a flat box of one colour that the processor draws over the
       image, such as a scope-position display, is left out with its bounding rectangle.

    Known limits: text in other colours (grey, red) over the image, and a black box over the
    image that joins the border (the hull of rule 5 gives it back), stay inside; white text on
    bright tissue inside the image is found only where it is linked to the border; a frame whose
    border does not reach all four corners is taken as borderless. Give a mask image
    (``read_mask``) for such a video.
    """
    rgb8 = _to_uint8(rgb)
    H, W = rgb8.shape[:2]
    eight = np.ones((3, 3), dtype=bool)
    dark = rgb8.max(axis=-1) <= DARK_MAX
    labels, _ = ndimage.label(dark, structure=eight)
    border = np.isin(labels, _touches_border(labels))
    share = border.mean()
    if not (MIN_OUTSIDE <= share <= MAX_OUTSIDE and _corners_black(border)):
        return ~inset_boxes(rgb8)
    text = overlay_coloured(rgb8)
    link = max(3, round(LINK_FRAC * min(H, W)))
    near = ndimage.binary_dilation(text, structure=eight, iterations=link) | border
    linked, _ = ndimage.label(near, structure=eight)
    text &= np.isin(linked, np.unique(linked[border]))
    rest, n = ndimage.label(~(border | text))
    if n == 0:
        return np.ones((H, W), dtype=bool)
    sizes = ndimage.sum_labels(np.ones_like(rest), rest, index=np.arange(1, n + 1))
    inside = ndimage.binary_fill_holes(rest == 1 + int(np.argmax(sizes)))
    return convex_hull_mask(inside) & ~text & ~inset_boxes(rgb8)


def inset_boxes(rgb) -> np.ndarray:
    """H x W bool: the bounding rectangles of flat, one-colour boxes drawn over the image, widened
    by 2 px (the flatness test cannot see a box's outermost pixel, nor JPEG's blur at its edge).

    A box is a connected region of flat pixels (every channel within ``INSET_FLAT`` over the
    3 x 3 neighbours) covering ``INSET_AREA`` of the frame, filling ``INSET_FILL`` of its bounding
    rectangle once its holes are filled, of height / width in ``INSET_ASPECT``, with a colour
    spread (standard deviation) of at most ``INSET_SPREAD`` per channel, neither white nor black
    (brightest channel below ``INSET_WHITE``, above ``DARK_MAX``). Tissue is never this flat over
    so large a box; a saturated highlight is white; a black box is taken for border or lumen.
    """
    a = _to_uint8(rgb).astype(np.int16)
    H, W = a.shape[:2]
    spread = ndimage.maximum_filter(a, size=(3, 3, 1)) - ndimage.minimum_filter(a, size=(3, 3, 1))
    labels, _ = ndimage.label((spread <= INSET_FLAT).all(axis=-1))
    out = np.zeros((H, W), dtype=bool)
    for i, box in enumerate(ndimage.find_objects(labels), start=1):
        part = labels[box] == i
        if not INSET_AREA[0] * H * W <= part.sum() <= INSET_AREA[1] * H * W:
            continue
        h, w = part.shape
        colours = a[box][part]
        colour = np.median(colours, axis=0)
        if (ndimage.binary_fill_holes(part).mean() < INSET_FILL or not INSET_ASPECT[0] <= h / w <= INSET_ASPECT[1]
                or colours.std(axis=0).max() > INSET_SPREAD or not DARK_MAX < colour.max() < INSET_WHITE):
            continue
        out[max(0, box[0].start - 2):box[0].stop + 2, max(0, box[1].start - 2):box[1].stop + 2] = True
    return out


# --------------------------------------------------------------------------- user masks
def read_mask(path, shape: tuple[int, int] | None = None, what: str = "mask",
              max_pixels: int | None = None) -> np.ndarray:
    """H x W bool of a mask image (any format PIL reads; nonzero = inside the field of view).

    ``shape`` (H, W): the frames' size it must have. Errors name the file (``what`` is how the
    user named it, e.g. "--mask"): FileNotFoundError if missing, utils.FileProblem if it cannot
    be read or decoded, ValueError for a wrong size (both sizes given) or no pixel inside.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} not found: {path}")
    try:
        with Image.open(path) as im:
            check_pixels(*im.size, path, what, max_pixels)  # from the header, before decoding
            im.load()
            if im.mode in ("I", "I;16", "I;16B", "I;16L", "F"):
                mask = np.asarray(im) != 0
            else:  # palette, grey, colour (alpha ignored): any channel above zero
                mask = np.asarray(im.convert("RGB")).any(axis=-1)
    except FileProblem:
        raise
    except Image.DecompressionBombError as exc:
        raise FileProblem(f"cannot read {what} {path}: {exc}", path) from exc
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        reason = "not an image file, or a damaged one" if isinstance(exc, UnidentifiedImageError) else os_reason(exc)
        raise FileProblem(f"cannot read {what} {path}: {reason}", path) from exc
    if shape is not None and mask.shape != tuple(shape):
        raise UserError(f"{what} {path} is {mask.shape[1]} x {mask.shape[0]} pixels but the frames are "
                         f"{shape[1]} x {shape[0]}: give a mask of the frames' size")
    if not mask.any():
        raise UserError(f"{what} {path} has no pixel inside the field of view (all zero): "
                         f"nonzero pixels mark the field of view")
    return mask


def save_mask(mask: np.ndarray, path: str | os.PathLike) -> Path:
    """Write a mask as an 8-bit PNG (255 inside, 0 outside), the format ``read_mask`` reads."""
    path = Path(path)
    Image.fromarray(np.where(np.asarray(mask, dtype=bool), 255, 0).astype(np.uint8)).save(path, format="PNG")
    return path


# --------------------------------------------------------------------------- filling
def fill_outside(image, mask) -> np.ndarray:
    """The image with every pixel outside ``mask`` replaced by the nearest inside pixel (Euclidean).

    The result depends on the inside pixels only, so black border, text or anything else outside
    cannot change what the network sees; the inside is the image's own. A border continued this
    way looks like the replicate padding of a convolution. image: H x W (x C), any dtype.
    """
    img = np.asarray(image)
    m = np.asarray(mask, dtype=bool)
    if m.shape != img.shape[:2]:
        raise ValueError(f"mask is {m.shape}, the image {img.shape[:2]}: they must match")
    if not m.any():
        raise ValueError("the mask has no pixel inside the field of view: nothing to fill from")
    if m.all():
        return img.copy()
    iy, ix = ndimage.distance_transform_edt(~m, return_distances=False, return_indices=True)
    return img[iy, ix]


# --------------------------------------------------------------------------- synthetic masks and overlays
def synthetic_mask(height: int, width: int, kind: str = "round", *, radius: float = 0.95, corner: float = 0.3,
                   center: tuple[float, float] = (0.5, 0.5)) -> np.ndarray:
    """An endoscope's field of view, H x W bool (True inside).

    kind "round": a disc of radius ``radius`` x half the smaller side (above 1 it is cut by the
    frame's edges, as on many scopes); "octagon": the rectangle of half sides ``radius`` x
    W/2, H/2 with its corners cut at 45 degrees, ``corner`` x the smaller side from each
    corner; "none": every pixel. ``center``: the centre as fractions of (W, H).
    """
    if kind not in SYNTHETIC_KINDS:
        raise ValueError(f"kind must be one of {', '.join(SYNTHETIC_KINDS)}, got {kind!r}")
    if not (isinstance(height, int) and isinstance(width, int) and height > 0 and width > 0):
        raise ValueError(f"height and width must be positive integers, got {height!r}, {width!r}")
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius!r}")
    if kind == "none":
        return np.ones((height, width), dtype=bool)
    dy = np.arange(height)[:, None] + 0.5 - center[1] * height
    dx = np.arange(width)[None, :] + 0.5 - center[0] * width
    if kind == "round":
        r = radius * 0.5 * min(height, width)
        return dx**2 + dy**2 <= r**2
    a, b = radius * 0.5 * width, radius * 0.5 * height
    cut = a + b - corner * min(height, width)
    return (np.abs(dx) <= a) & (np.abs(dy) <= b) & (np.abs(dx) + np.abs(dy) <= cut)


def _draw_glyphs(canvas: np.ndarray, painted: np.ndarray, box: tuple[int, int, int, int], colour,
                 rng: np.random.Generator) -> None:
    """Digit-like strokes (random segments of a seven-segment cell) in ``box`` = (y0, x0, h, w),
    painted in ``colour`` on ``canvas`` and marked in ``painted``."""
    y0, x0, h, w = box
    t = max(1, h // 6)  # stroke width
    cw, gap = max(3, round(0.55 * h)), max(1, h // 4)  # cell width, gap between cells
    x = x0
    while x + cw <= x0 + w:
        for k in rng.choice(len(SEGMENTS), size=int(rng.integers(2, 6)), replace=False):
            sx0, sy0, sx1, sy1 = SEGMENTS[k]
            ya, yb = y0 + round(sy0 * (h - t)), y0 + round(sy1 * (h - t)) + t
            xa, xb = x + round(sx0 * (cw - t)), x + round(sx1 * (cw - t)) + t
            canvas[ya:yb, xa:xb] = colour
            painted[ya:yb, xa:xb] = True
        x += cw + gap


def _box_in_border(mask: np.ndarray, h: int, w: int, corner: int) -> tuple[int, int] | None:
    """(y0, x0) of an h x w box at one corner of the frame (0-3) lying wholly outside ``mask``."""
    H, W = mask.shape
    m = max(1, min(H, W) // 50)  # margin from the frame's edge
    y0 = m if corner in (0, 1) else H - m - h
    x0 = m if corner in (0, 2) else W - m - w
    if y0 < 0 or x0 < 0 or y0 + h > H or x0 + w > W:
        return None
    # the box and a 1 px rim around it: text sits clear of the field of view
    if mask[max(0, y0 - 1):y0 + h + 1, max(0, x0 - 1):x0 + w + 1].any():
        return None
    return y0, x0


def add_overlay(rgb, mask, rng: np.random.Generator, *, n_texts: int = 3, over_image: bool = True,
                text_height: float = 0.07) -> tuple[np.ndarray, np.ndarray]:
    """An endoscope's look painted onto a frame: black outside ``mask``, on-screen text in the
    black corners and, if ``over_image``, one line of text across the field of view's edge.

    rgb: H x W x 3 uint8 (or float 0-1, kept as such); mask: H x W bool (``synthetic_mask``);
    rng: a numpy Generator (the draws: colours, glyphs, corners, where the line crosses the
    edge). Up to ``n_texts`` lines go into the corners that have room; glyphs are digit-like
    strokes ``text_height`` x H tall in white, yellow, green or cyan (``OVERLAY_COLOURS``).
    Returns (the painted frame, valid): valid = ``mask`` less the pixels the text covers,
    the tissue that is still visible.
    """
    img = np.array(rgb, copy=True)
    m = np.asarray(mask, dtype=bool)
    if img.ndim != 3 or img.shape[:2] != m.shape:
        raise ValueError(f"rgb must be H x W x 3 matching the mask {m.shape}, got {img.shape}")
    scale = 255.0 if img.dtype == np.uint8 else 1.0
    H, W = m.shape
    img[~m] = 0
    painted = np.zeros((H, W), dtype=bool)
    h = max(5, round(text_height * H))
    placed = 0
    for corner in rng.permutation(4):
        w = max(3 * h, round(W * float(rng.uniform(0.12, 0.22))))
        at = _box_in_border(m, h, w, int(corner))
        if at is not None and placed < n_texts:
            colour = np.asarray(OVERLAY_COLOURS[int(rng.integers(len(OVERLAY_COLOURS)))]) * scale
            _draw_glyphs(img, painted, (at[0], at[1], h, w), colour.astype(img.dtype), rng)
            placed += 1
    if over_image and not m.all():
        edge = m & ~ndimage.binary_erosion(m, border_value=1)  # the field of view's outermost pixels
        ys, xs = np.nonzero(edge & _central(H, W, h, 3 * h))
        if ys.size:
            k = int(rng.integers(ys.size))
            w = 3 * h + h // 2
            colour = np.asarray(OVERLAY_COLOURS[int(rng.integers(len(OVERLAY_COLOURS)))]) * scale
            _draw_glyphs(img, painted, (ys[k] - h // 2, xs[k] - w // 2, h, w), colour.astype(img.dtype), rng)
    return img, m & ~painted


def _central(H: int, W: int, h: int, w: int) -> np.ndarray:
    """H x W bool: where an h x w box centred on the pixel stays inside the frame."""
    out = np.zeros((H, W), dtype=bool)
    out[h // 2 + 1:H - h // 2 - 1, w // 2 + 1:W - w // 2 - 1] = True
    return out
