"""Named constants: one scene depth range for renderer and network, shape coefficients that drive the tube."""

import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from geodepth_lite.core import camera, model
from geodepth_lite.data import render, tube


def test_render_and_model_use_cameras_depth_range():
    assert camera.DEPTH_RANGE == (camera.MIN_DEPTH, camera.MAX_DEPTH) == (0.01, 100.0)
    assert render.NEAR is camera.MIN_DEPTH and render.FAR is camera.MAX_DEPTH
    assert model.MIN_DEPTH is camera.MIN_DEPTH and model.MAX_DEPTH is camera.MAX_DEPTH
    # the defaults that follow from them: the projection's near/far planes and the head's output range
    P = render.projection_matrix(camera.intrinsics(8), 8, 8)
    n, f = camera.DEPTH_RANGE
    assert P[2, 2] == -(f + n) / (f - n) and P[2, 3] == -2.0 * f * n / (f - n)
    d = model.sigmoid_to_depth(torch.tensor([0.0, 1.0], dtype=torch.float64))
    assert d.tolist() == pytest.approx([n, f], rel=1e-12)


def _plain(**overrides) -> dict:
    """The cylinder preset (nothing on the wall) with some keys overridden."""
    return dict(tube.PRESETS["cylinder"], **overrides)


def test_radius_wave_is_the_named_sines():
    preset = _plain(radius=2.0, length=40.0, radius_var=0.15)
    phases = np.array([0.3, 1.1, 2.0])
    feats = tube.WallFeatures(base_phases=phases)
    s = np.array([0.0, 3.7, 11.0, 25.5, 39.0])
    R, L, var = 2.0, 40.0, 0.15
    (a0, a1), (p0, p1) = tube.RADIUS_WAVE_AMPLITUDE, tube.RADIUS_WAVE_PERIOD
    expected = R * (1.0 + var * (a0 * np.sin(2 * math.pi * s / (p0 * L) + phases[0])
                                 + a1 * np.sin(2 * math.pi * s / (p1 * L) + phases[1])))
    got = tube.radius_field(s, np.zeros_like(s), preset, feats)
    np.testing.assert_allclose(got, expected, rtol=1e-13)
    # the name really drives the field: another amplitude, another radius
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(tube, "RADIUS_WAVE_AMPLITUDE", (a0 + 0.2, a1))
        assert not np.allclose(tube.radius_field(s, np.zeros_like(s), preset, feats), expected)


def test_dome_heights_and_minimum_radius_clamp():
    R = 1.0
    feats = tube.WallFeatures(base_phases=np.zeros(3), polyps=[(10.0, 1.0, 0.3)], diverticula=[(20.0, 2.0, 0.25)])
    r = tube.radius_field(np.array([10.0, 20.0]), np.array([1.0, 2.0]), _plain(radius=R), feats)
    # at a dome's centre (d = 0) the profile is 1: the radius moves by exactly height x size
    assert r.tolist() == pytest.approx([R - tube.POLYP_HEIGHT * 0.3, R + tube.DIVERTICULUM_DEPTH * 0.25], abs=1e-12)
    # an absurdly deep circular fold would close the lumen: the radius stops at MIN_RADIUS_FRACTION x R
    deep = _plain(radius=R, fold_kind="circular", fold_depth=50.0, fold_width=0.2)
    feats = tube.WallFeatures(base_phases=np.zeros(3), folds=[(30.0, 0.0, -1, 1.0)])
    r = tube.radius_field(np.array([30.0, 45.0]), np.array([0.0, 0.0]), deep, feats)
    assert r[0] == tube.MIN_RADIUS_FRACTION * R
    assert r[1] == pytest.approx(R, abs=1e-9)  # far from the fold: the plain wall


# --------------------------------------------------------------------------- the bounds the docs state

BOUNDS_DOC = Path(__file__).resolve().parent.parent / "docs" / "errors_and_files.md"


def _stated(value: int) -> str:
    """How the docs write a bound: bytes in whole KiB/MiB/GiB, counts with a space every three digits."""
    for unit, size in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if value >= size and value % size == 0:
            return f"{value // size} {unit}"
    return f"{value:,}".replace(",", " ")


def bound_mismatches(text: str, modules: dict) -> list[str]:
    """Each row of the docs' bounds table that names a constant (`module.NAME`) without stating its value."""
    wrong = []
    for row in (line for line in text.splitlines() if line.startswith("| ")):
        for mod, name in re.findall(r"`(\w+)\.(MAX_\w+)`", row):
            value = getattr(modules[mod], name)
            if _stated(value) not in row:
                wrong.append(f"{mod}.{name} = {value} ({_stated(value)}) not in: {row[:80]}")
    return wrong


def test_the_bounds_the_docs_state_are_the_codes(monkeypatch):
    from geodepth_lite.data import bounds, frames, integrity, manifest

    modules = {"bounds": bounds, "frames": frames, "integrity": integrity, "manifest": manifest}
    text = BOUNDS_DOC.read_text()
    assert len(re.findall(r"`\w+\.MAX_\w+`", text)) >= 6  # every bound of the table is checked
    assert bound_mismatches(text, modules) == []
    monkeypatch.setattr(frames, "MAX_INTRINSICS_BYTES", 32 * 2**10)  # a bound changed without the docs
    wrong = bound_mismatches(text, modules)
    assert len(wrong) == 1 and wrong[0].startswith("frames.MAX_INTRINSICS_BYTES = 32768 (32 KiB) not in: "), wrong
