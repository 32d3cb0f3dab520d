"""The endoscope's field of view (``fov``): detection against masks with known answers, the
fill that keeps the border out of the network's input, user mask files, and the overlays."""

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

from geodepth_lite.data import fov
from geodepth_lite.utils import FileProblem

H, W = 120, 160  # a 4:3 frame, small enough to be fast, large enough for glyphs of 8 px
MIN_IOU = 0.95


def tissue(h: int, w: int, seed: int, lumen: tuple[float, float] | None = None, lumen_r: float = 0.0) -> np.ndarray:
    """A pink, textured, unevenly lit H x W x 3 uint8 frame; with ``lumen`` (x, y in pixels) a dark
    lumen of radius ``lumen_r`` px whose core is black (max channel well under ``fov.DARK_MAX``)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] + 0.5
    texture = ndimage.gaussian_filter(rng.normal(size=(h, w)), 3)
    light = 0.6 + 0.35 * np.cos(2 * np.pi * (x / w - 0.3)) * np.cos(np.pi * (y / h - 0.5))
    light = light * (1 + 0.25 * texture / texture.std())
    if lumen is not None:
        r = np.hypot(x - lumen[0], y - lumen[1]) / lumen_r
        light = light * np.clip(r**2, 0.0, 1.0)  # black at the centre, full light from the radius out
    return np.clip(light[..., None] * np.array([215.0, 120.0, 100.0]), 0, 255).astype(np.uint8)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def endoscope_frame(kind: str, seed: int, *, noise: float = 0.0, lumen: str | None = None):
    """(frame with black border and on-screen text, the tissue still visible: the known answer)."""
    mask = fov.synthetic_mask(H, W, kind, radius=1.05 if kind == "round" else 0.95)
    if lumen == "middle":
        rgb = tissue(H, W, seed, (0.5 * W, 0.5 * H), 18)
    elif lumen == "edge":  # centred on the field of view's left edge: a dark bite from the border into it
        left = int(np.flatnonzero(mask[H // 2])[0])
        rgb = tissue(H, W, seed, (left, 0.5 * H), 60)
    else:
        rgb = tissue(H, W, seed)
    frame, valid = fov.add_overlay(rgb, mask, np.random.default_rng(seed))
    if noise:
        frame = np.clip(frame + np.random.default_rng(seed + 99).normal(0, noise, frame.shape), 0, 255)
        frame = frame.astype(np.uint8)
    return frame, valid


CASES = [(kind, seed, noise, lumen) for kind in ("round", "octagon") for seed in (0, 1)
         for noise, lumen in ((0.0, None), (6.0, None), (0.0, "middle"), (6.0, "edge"))]


@pytest.mark.parametrize("kind, seed, noise, lumen", CASES)
def test_detection_finds_the_generating_mask(kind, seed, noise, lumen):
    frame, valid = endoscope_frame(kind, seed, noise=noise, lumen=lumen)
    assert (valid != fov.synthetic_mask(H, W, kind, radius=1.05 if kind == "round" else 0.95)).any()  # text on it
    assert iou(fov.detect_mask(frame), valid) >= MIN_IOU


def test_the_iou_check_can_fail():
    """Without the convex hull (rule 5) the dark lumen's bite is cut out of the field of view and
    the IoU falls below the bar; taking every pixel as inside (``--mask none``) does too."""
    frame, valid = endoscope_frame("round", 0, lumen="edge")
    hull = fov.convex_hull_mask
    try:
        fov.convex_hull_mask = lambda m: m
        bitten = fov.detect_mask(frame)
    finally:
        fov.convex_hull_mask = hull
    assert iou(bitten, valid) < MIN_IOU <= iou(fov.detect_mask(frame), valid)
    assert iou(np.ones_like(valid), valid) < MIN_IOU


def test_text_over_the_image_is_excluded_and_text_in_the_border_is_outside():
    frame, valid = endoscope_frame("octagon", 0)
    mask = fov.synthetic_mask(H, W, "octagon", radius=0.95)
    det = fov.detect_mask(frame)
    over_image = mask & ~valid
    assert over_image.sum() >= 10 and not (det & over_image).any()
    text_in_border = (frame.max(axis=-1) > fov.DARK_MAX) & ~mask
    assert text_in_border.sum() >= 50 and not (det & text_in_border).any()


def _with_box(frame: np.ndarray, y0: int, x0: int, size: int, colour) -> tuple[np.ndarray, np.ndarray]:
    """``frame`` with a flat ``size`` px box of ``colour`` at (y0, x0) holding a black line drawing
    (as a scope-position display does); and the box's pixels."""
    out = frame.copy()
    box = np.zeros(frame.shape[:2], dtype=bool)
    box[y0:y0 + size, x0:x0 + size] = True
    out[box] = colour
    out[y0 + size // 4:y0 + 3 * size // 4, x0 + size // 2 - 1:x0 + size // 2 + 1] = 0  # the drawing
    return out, box


@pytest.mark.parametrize("kind", ["round", "octagon"])
def test_an_inset_box_over_the_image_is_left_out(kind):
    """A flat teal box over the lower left of the image (a scope-position display): out with its
    rectangle (2 px wider); the rest as before."""
    frame, valid = endoscope_frame(kind, 0)
    framed, box = _with_box(frame, H - 40, 22, 34, (16, 163, 134))
    det = fov.detect_mask(framed)
    truth = valid & ~ndimage.binary_dilation(box, iterations=2)
    assert (valid & box).sum() > 100  # the box covers tissue
    assert not (det & box).any() and iou(det, truth) >= MIN_IOU
    saved = fov.inset_boxes
    try:  # the check can fail: without step 6 the box stays in the field of view
        fov.inset_boxes = lambda rgb: np.zeros(rgb.shape[:2], dtype=bool)
        assert (fov.detect_mask(framed) & box).sum() > 100
    finally:
        fov.inset_boxes = saved


@pytest.mark.parametrize("colour, border", [((0, 0, 0), True), ((0, 0, 0), False), ((255, 255, 255), True),
                                            ((16, 163, 134), False)],
                         ids=["black lumen, border", "black lumen, no border", "white highlight", "teal, no border"])
def test_flat_regions_that_are_not_boxes_stay_in(colour, border):
    """A flat black lumen in the middle and a saturated highlight stay inside; a coloured box is
    left out of a frame without border too."""
    if border:
        frame, valid = endoscope_frame("octagon", 1)
    else:
        frame, valid = tissue(H, W, 2), np.ones((H, W), dtype=bool)
    framed, box = _with_box(frame, H // 2 - 16, W // 2 - 16, 32, colour)
    det = fov.detect_mask(framed)
    if colour == (16, 163, 134):
        assert not (det & box).any() and det[~ndimage.binary_dilation(box, iterations=2)].all()
    else:
        assert det[box].all() and iou(det, valid) >= MIN_IOU


@pytest.mark.parametrize("lumen", [None, "middle", "left edge", "corner"])
def test_a_frame_without_border_is_all_inside(lumen):
    """A dark lumen in the middle, or touching one edge or one corner of the frame, is no border."""
    where = {None: None, "middle": (0.5 * W, 0.5 * H), "left edge": (0.0, 0.5 * H), "corner": (0.0, 0.0)}[lumen]
    rgb = tissue(H, W, 3, where, 40)
    if lumen is not None:
        assert (rgb.max(axis=-1) <= fov.DARK_MAX).mean() > 0.02  # a real dark region
    assert fov.detect_mask(rgb).all()


@pytest.mark.parametrize("frame", [np.zeros((20, 20, 3), np.uint8), np.full((2, 2, 3), 200, np.uint8),
                                   np.random.default_rng(0).integers(0, 256, (40, 56, 3), dtype=np.uint8)],
                         ids=["all black", "2 x 2", "noise"])
def test_frames_with_no_field_of_view_to_find_are_all_inside(frame):
    assert fov.detect_mask(frame).all()


def test_detection_accepts_float_images():
    frame, valid = endoscope_frame("round", 1)
    assert iou(fov.detect_mask(frame / 255.0), valid) >= MIN_IOU


def test_convex_hull_mask():
    disc = fov.synthetic_mask(41, 41, "round", radius=0.9)
    np.testing.assert_array_equal(fov.convex_hull_mask(disc), disc)
    ell = np.zeros((5, 5), bool)
    ell[:, 0] = ell[-1, :] = True  # an L: its hull is the lower-left triangle
    np.testing.assert_array_equal(fov.convex_hull_mask(ell), np.tril(np.ones((5, 5), bool)))
    assert not fov.convex_hull_mask(np.zeros((3, 3), bool)).any()


# --------------------------------------------------------------------------- fill


def test_fill_outside_depends_on_the_inside_only():
    mask = fov.synthetic_mask(H, W, "round")
    rgb = tissue(H, W, 0)
    other = rgb.copy()
    other[~mask] = np.random.default_rng(1).integers(0, 256, (int((~mask).sum()), 3), dtype=np.uint8)
    filled = fov.fill_outside(rgb, mask)
    np.testing.assert_array_equal(filled, fov.fill_outside(other, mask))
    np.testing.assert_array_equal(filled[mask], rgb[mask])
    assert not np.array_equal(rgb, other)  # the check can fail: the inputs did differ outside


def test_fill_outside_takes_the_nearest_inside_pixel():
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    mask = np.zeros((3, 4), bool)
    mask[1, 1:3] = True  # two pixels, values 5 and 6
    np.testing.assert_array_equal(fov.fill_outside(image, mask), [[5, 5, 6, 6], [5, 5, 6, 6], [5, 5, 6, 6]])
    np.testing.assert_array_equal(fov.fill_outside(image, np.ones((3, 4), bool)), image)


def test_fill_outside_refuses_an_empty_or_misfit_mask():
    with pytest.raises(ValueError, match="no pixel inside"):
        fov.fill_outside(np.zeros((3, 4, 3)), np.zeros((3, 4), bool))
    with pytest.raises(ValueError, match="must match"):
        fov.fill_outside(np.zeros((3, 4, 3)), np.ones((4, 3), bool))


# --------------------------------------------------------------------------- mask files


def test_read_mask_round_trip_and_nonzero_is_inside(tmp_path):
    mask = fov.synthetic_mask(30, 40, "octagon")
    assert np.array_equal(fov.read_mask(fov.save_mask(mask, tmp_path / "m.png"), (30, 40)), mask)
    grey = np.where(mask, 1, 0).astype(np.uint8)  # 1 is inside, as 255 is
    Image.fromarray(grey).save(tmp_path / "g.png")
    assert np.array_equal(fov.read_mask(tmp_path / "g.png"), mask)
    colour = np.zeros((30, 40, 3), np.uint8)
    colour[mask, 2] = 7  # any channel above zero
    Image.fromarray(colour).save(tmp_path / "c.png")
    assert np.array_equal(fov.read_mask(tmp_path / "c.png", (30, 40)), mask)


def test_read_mask_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=f"--mask not found: {tmp_path / 'none.png'}"):
        fov.read_mask(tmp_path / "none.png", what="--mask")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n not a png")
    with pytest.raises(FileProblem, match=f"cannot read --mask {tmp_path / 'bad.png'}: not an image"):
        fov.read_mask(tmp_path / "bad.png", what="--mask")
    fov.save_mask(np.ones((30, 40), bool), tmp_path / "m.png")
    with pytest.raises(ValueError, match=f"--mask {tmp_path / 'm.png'} is 40 x 30 pixels but the frames are 64 x 48"):
        fov.read_mask(tmp_path / "m.png", (48, 64), what="--mask")
    fov.save_mask(np.zeros((30, 40), bool), tmp_path / "zero.png")
    with pytest.raises(ValueError, match=f"mask {tmp_path / 'zero.png'} has no pixel inside"):
        fov.read_mask(tmp_path / "zero.png", (30, 40))


# --------------------------------------------------------------------------- synthetic masks and overlays


def test_synthetic_masks():
    assert fov.synthetic_mask(H, W, "none").all()
    disc = fov.synthetic_mask(H, W, "round", radius=1.0)
    assert abs(disc.sum() - np.pi * 60**2) < 0.01 * np.pi * 60**2
    assert disc[H // 2, W // 2] and not disc[0, 0] and not disc[H // 2, 10]
    cut = fov.synthetic_mask(H, W, "round", radius=1.1)  # a disc cut by the top and bottom edges
    assert cut[0, W // 2] and cut[-1, W // 2] and not cut[0, 0]
    octagon = fov.synthetic_mask(H, W, "octagon", radius=0.95, corner=0.3)
    assert octagon[H // 2, 5] and not octagon[0, 0] and not octagon[-1, -1] and octagon[H // 2, W // 2]
    with pytest.raises(ValueError, match="kind must be one of round, octagon, none"):
        fov.synthetic_mask(H, W, "square")


def test_add_overlay_paints_black_outside_and_text():
    mask = fov.synthetic_mask(H, W, "round")
    rgb = tissue(H, W, 0)
    frame, valid = fov.add_overlay(rgb, mask, np.random.default_rng(0), over_image=False)
    np.testing.assert_array_equal(valid, mask)  # no text over the image
    np.testing.assert_array_equal(frame[mask], rgb[mask])
    assert fov.overlay_coloured(frame[~mask]).sum() > 50  # text in the black corners
    assert (frame[~mask & ~fov.overlay_coloured(frame)] == 0).all()
    floats, valid_f = fov.add_overlay(rgb / 255.0, mask, np.random.default_rng(0))
    assert floats.dtype == np.float64 and floats.max() <= 1.0 and valid_f.sum() < mask.sum()
    same, _ = fov.add_overlay(rgb, mask, np.random.default_rng(0), over_image=False)
    np.testing.assert_array_equal(same, frame)  # the generator alone decides
