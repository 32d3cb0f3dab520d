"""Appearance post-process: identity, determinism, draw discipline, and each effect against a known answer."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from scipy import ndimage

from geodepth_lite.data import appearance as ap


def _record(**changes) -> dict:
    """The identity record (defaults, seed 0) with ``changes``."""
    rec = ap.sample_appearance(ap.APPEARANCE_DEFAULTS, np.random.default_rng(0))
    rec.update(changes)
    return rec


def _flat(value, size=64) -> np.ndarray:
    return np.full((size, size, 3), value, np.uint8)


def _textured(size=128, seed=0) -> np.ndarray:
    """Mid-grey with smooth colour texture, no pixel at 0 or 255."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    base = 128 + 50 * np.sin(2 * np.pi * 3 * xx) * np.cos(2 * np.pi * 2 * yy)
    noise = np.random.default_rng(seed).normal(0, 6, (size, size, 3))
    return np.clip(base[..., None] + noise + np.array([10, -5, -15]), 5, 250).astype(np.uint8)


def _all_on() -> dict:
    return {"exposure_stops": [-1.0, 1.0], "gamma": [0.8, 2.2], "color_cast": [-1.0, 1.0], "vignetting": [0.1, 0.5],
            "specular_flecks": [5, 40], "bubbles": [1, 6], "bubble_radius": [0.01, 0.04], "mucus": [0.2, 0.8],
            "noise": [0.01, 0.05], "p_blur": 1.0, "blur_px": [1.0, 3.0], "p_jpeg": 1.0, "jpeg_quality": [30, 90]}


def _hf(img: np.ndarray) -> float:
    """High-frequency energy: mean absolute difference between horizontal and vertical neighbours."""
    x = img.astype(np.float64)
    return float(np.abs(np.diff(x, axis=0)).mean() + np.abs(np.diff(x, axis=1)).mean())


# ----------------------------------------------------------------------------- record, identity, determinism


def test_defaults_are_identity_and_valid():
    ap.check_appearance("appearance", copy.deepcopy(ap.APPEARANCE_DEFAULTS))
    img = _textured()
    for seed in range(3):
        rec = ap.sample_appearance(ap.APPEARANCE_DEFAULTS, np.random.default_rng(seed))
        assert ap.is_identity(rec)
        out = ap.apply_appearance(img, rec)
        assert out.dtype == np.uint8 and out.shape == img.shape
        assert np.array_equal(out, img) and out is not img


def test_record_is_json_with_plain_types():
    rec = ap.sample_appearance(_all_on(), np.random.default_rng(3))
    assert json.loads(json.dumps(rec)) == rec
    assert set(rec) == {"exposure_stops", "gamma", "color_cast", "vignetting", "specular_flecks", "bubbles",
                        "bubble_radius", "mucus", "noise", "blur", "jpeg_quality", "seed"}
    assert isinstance(rec["specular_flecks"], int) and isinstance(rec["jpeg_quality"], int)
    assert isinstance(rec["seed"], int) and isinstance(rec["gamma"], float)
    assert rec["blur"]["kind"] in ("motion", "defocus") and 0 <= rec["blur"]["angle_deg"] < 180
    assert all(round(v, 10) == v for v in (rec["gamma"], rec["noise"], rec["blur"]["px"]))


def test_same_record_same_output_and_input_untouched():
    img = _textured(96)
    before = img.copy()
    for seed in range(4):  # both blur kinds among them
        rec = ap.sample_appearance(_all_on(), np.random.default_rng(seed))
        a, b = ap.apply_appearance(img, rec), ap.apply_appearance(img, copy.deepcopy(rec))
        assert np.array_equal(a, b)
        assert not np.array_equal(a, img)
    assert np.array_equal(img, before)
    other = dict(rec, seed=rec["seed"] + 1)  # another pixel seed: other noise, flecks, bubbles
    assert not np.array_equal(ap.apply_appearance(img, other), ap.apply_appearance(img, rec))


def test_same_number_of_draws_whatever_the_settings():
    base = copy.deepcopy(ap.APPEARANCE_DEFAULTS)
    variants = [dict(base, noise=[0.0, 0.1]), dict(base, p_blur=1.0), dict(base, p_jpeg=1.0),
                dict(base, specular_flecks=[0, 50]), _all_on()]
    r0 = np.random.default_rng(7)
    rec0 = ap.sample_appearance(base, r0)
    after0 = r0.random()
    for settings in variants:
        r = np.random.default_rng(7)
        rec = ap.sample_appearance(settings, r)
        assert rec["seed"] == rec0["seed"]
        assert r.random() == after0  # the generator is left in the same state
    rec = ap.sample_appearance(variants[0], np.random.default_rng(7))  # one key changed: the others unchanged
    assert {k: v for k, v in rec.items() if k != "noise"} == {k: v for k, v in rec0.items() if k != "noise"}
    assert 0.0 <= rec["noise"] <= 0.1


def test_sampling_respects_ranges_and_probabilities():
    a = dict(_all_on(), specular_flecks=[0, 3], p_blur=0.5, p_jpeg=0.25, jpeg_quality=[40, 42])
    rng = np.random.default_rng(11)
    recs = [ap.sample_appearance(a, rng) for _ in range(600)]
    assert {r["specular_flecks"] for r in recs} == {0, 1, 2, 3}  # both ends of an integer range reachable
    assert {r["jpeg_quality"] for r in recs if r["jpeg_quality"] is not None} == {40, 41, 42}
    assert all(-1.0 <= r["exposure_stops"] <= 1.0 and 0.8 <= r["gamma"] <= 2.2 for r in recs)
    blurred = [r["blur"] for r in recs if r["blur"] is not None]
    assert 0.42 < len(blurred) / len(recs) < 0.58
    assert 0.18 < sum(r["jpeg_quality"] is not None for r in recs) / len(recs) < 0.32
    assert 0.38 < sum(b["kind"] == "motion" for b in blurred) / len(blurred) < 0.62
    assert all(1.0 <= b["px"] <= 3.0 for b in blurred)


def test_rejects_bad_images():
    with pytest.raises(ValueError, match="uint8 H x W x 3"):
        ap.apply_appearance(np.zeros((8, 8, 3), np.float32), _record(gamma=2.0))
    with pytest.raises(ValueError, match="uint8 H x W x 3"):
        ap.apply_appearance(np.zeros((8, 8), np.uint8), _record(gamma=2.0))


# ----------------------------------------------------------------------------- validation


@pytest.mark.parametrize("key, value, message", [
    ("gamma", [2.0, 1.0], "min <= max"),
    ("p_blur", 1.5, "probability"),
    ("specular_flecks", [0, 2.5], "integers"),
    ("bubbles", [0, 201], r"\[0, 200\]"),
    ("gamma", [0.0, 1.0], r"\(0.0, 5.0\]"),
    ("color_cast", [-1.5, 0.0], r"\[-1.0, 1.0\]"),
    ("noise", [0.0, 0.3], r"\[0.0, 0.2\]"),
    ("jpeg_quality", [30, 90.5], "integers"),
    ("vignetting", [0.5], "pair"),
    ("p_jpeg", True, "probability"),
])
def test_check_appearance_names_the_field(key, value, message):
    a = copy.deepcopy(ap.APPEARANCE_DEFAULTS)
    a[key] = value
    with pytest.raises(ValueError, match=rf"manifest field 'appearance\.{key}' must .*{message}") as e:
        ap.check_appearance("appearance", a)
    assert "\n" not in str(e.value)


def test_check_appearance_unknown_and_missing_keys():
    with pytest.raises(ValueError, match=r"unknown key 'appearance\.sharpen'"):
        ap.check_appearance("appearance", dict(ap.APPEARANCE_DEFAULTS, sharpen=[0, 1]))
    a = copy.deepcopy(ap.APPEARANCE_DEFAULTS)
    del a["mucus"]
    with pytest.raises(ValueError, match=r"manifest field 'appearance' is missing mucus"):
        ap.check_appearance("appearance", a)
    ap.check_appearance("appearance", _all_on())


# ----------------------------------------------------------------------------- effects


def test_exposure_brightens_monotonically_and_saturates():
    img = _textured()
    means = [ap.apply_appearance(img, _record(exposure_stops=s)).mean() for s in (-1.0, 0.0, 1.0)]
    assert means[0] < means[1] < means[2]
    assert abs(means[0] - img.mean() / 2) < 1.0  # -1 stop halves a linear image (no clipping below)
    saturated = [(ap.apply_appearance(img, _record(exposure_stops=s)) == 255).mean() for s in (0.0, 2.0)]
    assert saturated[0] == 0.0 and saturated[1] > 0.5


@pytest.mark.parametrize("g", [0.5, 1.8, 2.2])
def test_gamma_flat_images(g):
    for v in (10, 64, 128, 200):
        out = ap.apply_appearance(_flat(v, 16), _record(gamma=g))
        expected = round(255 * (v / 255) ** (1 / g))
        assert np.abs(out.astype(int) - expected).max() <= 1, (v, g)


@pytest.mark.parametrize("v", [0.2, 0.5, 0.9])
def test_vignetting_corner_to_centre(v):
    out = ap.apply_appearance(_flat(200, 65), _record(vignetting=v)).astype(float)
    assert out[32, 32, 0] == 200  # the centre pixel is untouched
    for corner in (out[0, 0], out[0, -1], out[-1, 0], out[-1, -1]):
        assert abs(corner[0] / out[32, 32, 0] - (1 - v)) < 0.01
    assert out[32, 0, 0] > out[0, 0, 0]  # the edge midpoint is brighter than the corner


def test_color_cast_definition():
    grey = _flat(128, 8)
    for c, end in ((1.0, ap.CAST_YELLOW), (-1.0, ap.CAST_PINK), (0.5, ap.CAST_YELLOW), (-0.3, ap.CAST_PINK)):
        out = ap.apply_appearance(grey, _record(color_cast=c))[0, 0].astype(int)
        expected = [round(128 * (1 + abs(c) * (e - 1))) for e in end]
        assert np.abs(out - expected).max() <= 1, (c, out, expected)
    r, g, b = ap.apply_appearance(grey, _record(color_cast=1.0))[0, 0].astype(int)
    assert (r + g) / 2 - b > 30  # yellowish: red and green above blue
    r, g, b = ap.apply_appearance(grey, _record(color_cast=-1.0))[0, 0].astype(int)
    assert (r + b) / 2 - g > 20  # pinkish-magenta: red and blue above green


def test_specular_flecks_saturate_on_bright_pixels():
    # a left-to-right ramp, no saturated pixel to start with
    ramp = np.tile(np.linspace(20, 220, 128)[None, :, None], (128, 1, 3)).astype(np.uint8)
    counts = []
    for n in (0, 5, 20, 80):
        out = ap.apply_appearance(ramp, _record(specular_flecks=n, seed=5))
        counts.append(int((out == 255).all(axis=2).sum()))
    assert counts[0] == 0 and counts[0] < counts[1] < counts[2] < counts[3]
    out = ap.apply_appearance(ramp, _record(specular_flecks=80, seed=5))
    hit = (out == 255).all(axis=2)
    bright = ramp[..., 0] > np.median(ramp[..., 0])
    assert hit[bright].sum() / hit.sum() > 0.7  # best of 4 candidates: ~94% expected, 50% if placed at random
    near = ndimage.binary_dilation(hit, iterations=2)
    assert np.array_equal(out[~near], ramp[~near])  # nothing changes away from the flecks (soft edges aside)


def test_fleck_size_scales_with_width():
    sizes = []
    for w in (128, 512):
        img = _flat(100, w)
        hit = (ap.apply_appearance(img, _record(specular_flecks=20, seed=2)) == 255).all(axis=2)
        sizes.append(hit.sum() / 20)
    assert 8 < sizes[1] / sizes[0] < 24  # area per fleck ~ (512 / 128)^2 = 16


def test_bubbles_are_rings():
    dark = _flat(30, 128)
    counts = [int((ap.apply_appearance(dark, _record(bubbles=n, seed=1)) > 120).any(axis=2).sum())
              for n in (0, 1, 4, 16)]
    assert counts[0] == 0 and counts[0] < counts[1] < counts[2] < counts[3]
    # one bubble of radius 0.1 x 128 = 12.8 px, fully in the frame: a ring around a dark centre
    for seed in range(100):
        out = ap.apply_appearance(dark, _record(bubbles=1, bubble_radius=[0.1, 0.1], seed=seed))
        ys, xs = np.nonzero((out > 120).any(axis=2))
        if ys.min() > 0 and xs.min() > 0 and ys.max() < 127 and xs.max() < 127:
            break
    cy, cx = (ys.min() + ys.max()) / 2, (xs.min() + xs.max()) / 2
    assert abs((ys.max() - ys.min()) - 2 * 12.8) <= 3 and abs((xs.max() - xs.min()) - 2 * 12.8) <= 3
    assert out[int(round(cy)), int(round(cx))].max() < 40  # the centre stays dark
    d = np.hypot(ys - cy, xs - cx)
    assert abs(np.median(d[d > 0.7 * 12.8]) - 12.8) < 1.0  # the rim lies on the radius
    assert out.max() == 255  # the small highlight saturates
    assert ((out > 120).any(axis=2).sum()) < 0.3 * np.pi * 12.8**2  # a thin ring, not a disc


def test_mucus_brightens_with_strength():
    img = _textured()
    means = [ap.apply_appearance(img, _record(mucus=m, seed=3)).mean() for m in (0.0, 0.3, 0.6, 1.0)]
    assert means[0] < means[1] < means[2] < means[3]
    out = ap.apply_appearance(img, _record(mucus=1.0, seed=3)).astype(int)
    assert (out >= img.astype(int) - 1).all()  # a sheen only adds light
    changed = np.abs(out - img).max(axis=2) > 2
    assert 0.05 < changed.mean() < 0.95  # patches, not a uniform veil
    # smooth, low-frequency patches: on a flat image a 5 x 5 mean explains the change almost entirely
    d = ap.apply_appearance(_flat(150, 128), _record(mucus=1.0, seed=3)).astype(float)[..., 0] - 150
    assert d.max() > 20
    assert ((d - ndimage.uniform_filter(d, 5, mode="nearest")) ** 2).mean() < 0.02 * d.var()


def test_noise_std_matches_sigma():
    for sigma in (0.02, 0.05):
        out = ap.apply_appearance(_flat(128, 128), _record(noise=sigma, seed=4)).astype(float)
        assert abs(out.std() / (sigma * 255) - 1) < 0.2
        assert abs(out.mean() - 128) < 0.5
        # independent per pixel and channel
        assert abs(np.corrcoef(out[:, :-1, 0].ravel(), out[:, 1:, 0].ravel())[0, 1]) < 0.05
        assert abs(np.corrcoef(out[..., 0].ravel(), out[..., 1].ravel())[0, 1]) < 0.05
    # additive in the output domain: the same std at every level (away from clipping)
    for level in (40, 200):
        out = ap.apply_appearance(_flat(level, 128), _record(noise=0.05, seed=4)).astype(float)
        assert abs(out.std() / (0.05 * 255) - 1) < 0.2
    z = ap.apply_appearance(_flat(128, 256), _record(noise=0.05, seed=9)).astype(float).ravel() - 128
    assert np.abs(z).max() < 3.6 * 0.05 * 255 + 1  # Irwin-Hall tails end at 3.46 std
    assert abs((np.abs(z) > 2 * 0.05 * 255).mean() - 0.046) < 0.015  # Gaussian-like: ~4.6% beyond 2 std


@pytest.mark.parametrize("kind", ["motion", "defocus"])
def test_blur_removes_high_frequencies(kind):
    yy, xx = np.mgrid[0:128, 0:128]
    checker = np.where((yy // 2 + xx // 2) % 2, 200, 50).astype(np.uint8)[..., None].repeat(3, axis=2)
    noise = np.random.default_rng(0).integers(50, 200, (128, 128, 3)).astype(np.uint8)
    for img, angle in ((checker, 0.0), (checker, 90.0), (noise, 30.0), (noise, 117.0)):
        hf = [_hf(ap.apply_appearance(img, _record(blur={"kind": kind, "px": px, "angle_deg": angle})))
              for px in (0.0, 2.0, 4.0)]
        assert hf[0] == _hf(img)  # px 0: no blur
        assert hf[0] > 1.3 * hf[1] and hf[1] > 1.2 * hf[2], (kind, angle, hf)
    out = ap.apply_appearance(checker, _record(blur={"kind": kind, "px": 3.0, "angle_deg": 75.0}))
    assert abs(out.astype(float).mean() - checker.mean()) < 1.0  # normalized kernel
    flat = _flat(90, 32)
    assert np.array_equal(ap.apply_appearance(flat, _record(blur={"kind": kind, "px": 3.0, "angle_deg": 10.0})), flat)


def test_motion_blur_follows_its_direction():
    stripes_h = np.where((np.arange(64) // 2) % 2, 200, 40).astype(np.uint8)[:, None, None].repeat(64, 1).repeat(3, 2)
    stripes_v = stripes_h.transpose(1, 0, 2).copy()
    horizontal = _record(blur={"kind": "motion", "px": 8.0, "angle_deg": 0.0})  # 4 px at width 64
    vertical = _record(blur={"kind": "motion", "px": 8.0, "angle_deg": 90.0})
    assert np.array_equal(ap.apply_appearance(stripes_h, horizontal), stripes_h)  # streaks along the stripes
    assert np.array_equal(ap.apply_appearance(stripes_v, vertical), stripes_v)
    assert _hf(ap.apply_appearance(stripes_v, horizontal)) < 0.6 * _hf(stripes_v)  # across the stripes
    assert _hf(ap.apply_appearance(stripes_h, vertical)) < 0.6 * _hf(stripes_h)


def test_jpeg_artefacts_grow_as_quality_drops():
    img = _textured(128, seed=1)
    err = {}
    for q in (30, 90):
        out = ap.apply_appearance(img, _record(jpeg_quality=q))
        assert out.shape == img.shape and out.dtype == np.uint8 and not np.array_equal(out, img)
        err[q] = np.abs(out.astype(float) - img).mean()
    assert err[30] > err[90] > 0


def test_every_effect_at_once_stays_in_range_and_changes_the_image():
    img = _textured(80)
    for seed in range(6):
        rec = ap.sample_appearance(_all_on(), np.random.default_rng(100 + seed))
        out = ap.apply_appearance(img, rec)
        assert out.shape == img.shape and out.dtype == np.uint8
        assert np.abs(out.astype(int) - img).mean() > 2
