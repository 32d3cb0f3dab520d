"""View kinds of the camera path and papilla mounds: manifest field -> a measurable property of the frames."""

import json

import numpy as np
import pytest

from geodepth_lite.data import appearance, render, synth, tube
from geodepth_lite.data import manifest as mf


def _manifest(views, size=32, n=12, **extra):
    over = {"camera": {"width": size, "height": size}, "splits": {"test": n}, "frames_per_scene": 4,
            "camera_path": {"views": views}, "appearance": dict(appearance.APPEARANCE_DEFAULTS)}
    over.update(extra)
    return mf.load_manifest("scenario_smoke", over)


def _records(root, split="test"):
    return [json.loads(line) for line in (root / split / "frames.jsonl").read_text().splitlines()]


def test_closeup_share_gives_frames_with_no_lumen_in_view(tmp_path):
    """The share of frames whose every pixel is nearer than 4 radii follows camera_path.views."""
    lumen = _records(synth.generate(_manifest({"lumen": 1.0}), tmp_path / "lumen", progress=False))
    close = _records(synth.generate(_manifest({"closeup": 1.0}), tmp_path / "close", progress=False))
    assert {r["view"] for r in lumen} == {"lumen"} and {r["view"] for r in close} == {"closeup"}

    def no_lumen(recs):
        return np.mean([r["lumen_share"] == 0 for r in recs])

    assert no_lumen(lumen) <= 0.25  # looking down the lumen nearly always sees far pixels (bends hide some)
    assert no_lumen(close) >= 0.75  # facing the wall at 0.2-1 radius: the lumen is (nearly) never in view
    # lumen_share is recomputed from the depth files (the record is not decorative)
    root = tmp_path / "close"
    for r in close[:4]:
        radius = mf.load_manifest("scenario_smoke")["organ_presets"][r["organ"]]["radius"]
        assert r["lumen_share"] == synth.lumen_share(np.load(root / r["depth"]), radius)


def test_views_by_split_and_shares():
    """Per-split shares replace the global ones; drawn kinds follow the shares (binomial bounds)."""
    m = _manifest({"lumen": 1.0}, camera_path={"views": {"lumen": 1.0}, "views_by_split": {"test": {"oblique": 1.0}}})
    assert mf.split_path(m, "test")["views"] == {"oblique": 1.0}
    assert mf.split_path(m, "train")["views"] == {"lumen": 1.0}
    draws = [render.choose_view({"lumen": 3.0, "closeup": 1.0}, u) for u in np.random.default_rng(0).uniform(size=4000)]
    share = np.mean([d == "closeup" for d in draws])
    assert abs(share - 0.25) < 4 * np.sqrt(0.25 * 0.75 / 4000)
    assert render.choose_view({"papilla": 1.0}, 0.999) == "papilla"


def test_closeup_faces_the_wall_at_the_recorded_distance():
    """Known answer: the optical axis meets the wall point the camera faces, at the recorded distance."""
    preset = tube.PRESETS["small_intestine"]
    tm = tube.build_tube(preset, 3, {"n_theta": 128, "ring_step": 0.04})
    path = dict(mf.DEFAULTS["camera_path"], views={"closeup": 1.0})
    rng = np.random.default_rng(1)
    size = 33  # odd: a pixel centre on the principal point
    with render.Renderer(size, size) as r:
        r.set_tube(tm)
        for _ in range(5):
            T, info = render.sample_pose(tm, rng, path)
            assert info["view"] == "closeup" and 0.0 <= info["tilt_deg"] <= path["closeup_tilt_deg"]
            assert info["distance"] <= preset["radius"] * 1.3 * path["closeup_distance"][1]
            _, depth = r.render(T)
            assert depth[size // 2, size // 2] == pytest.approx(info["distance"], rel=0.03)


def test_papilla_is_a_mound_with_a_pit_and_papilla_views_face_it():
    preset = dict(tube.PRESETS["small_intestine"], papillae=[1, 1], papilla_size=[0.4, 0.4], polyps=[0, 0],
                  diverticula=[0, 0], ridges=[0, 0], fold_depth=0.0)
    tm = tube.build_tube(preset, 5, {"n_theta": 160, "ring_step": 0.03})
    (s, th, size), = tm.features.papillae
    plain = tube.WallFeatures(**{**tm.features.__dict__, "papillae": []})
    base = tube.radius_field(s, th, preset, plain)

    def r(ds):
        return float(tm.radius(s + ds, th))

    # a mound: the top stands PAPILLA_HEIGHT - PAPILLA_PIT_DEPTH radii of the mound into the lumen ...
    assert base - r(0.0) == pytest.approx((tube.PAPILLA_HEIGHT - tube.PAPILLA_PIT_DEPTH) * size, rel=1e-6)
    # ... with a pit: the rim around the centre is higher (nearer the axis) than the centre itself
    rim = r(0.35 * size)
    assert rim < r(0.0) and base - rim > 0.3 * size
    path = dict(mf.DEFAULTS["camera_path"], views={"papilla": 1.0})
    T, info = render.sample_pose(tm, np.random.default_rng(0), path)
    assert info["view"] == "papilla" and info["s"] == pytest.approx(s)
    # the optical axis points at the papilla's top
    target = tm.wall_point(s, th)
    axis = T[:3, 2]
    to_target = (target - T[:3, 3]) / np.linalg.norm(target - T[:3, 3])
    assert float(axis @ to_target) > 0.9999


def test_papilla_view_without_papillae_falls_back_to_a_closeup():
    tm = tube.build_tube(dict(tube.PRESETS["colon"], papillae=[0, 0]), 2, {"n_theta": 32, "ring_step": 0.3})
    path = dict(mf.DEFAULTS["camera_path"], views={"papilla": 1.0})
    T, info = render.sample_pose(tm, np.random.default_rng(0), path)
    assert info["view"] == "papilla" and info["distance"] is not None
    assert render.inside_tube(tm, T[:3, 3])


def test_exposure_setting_sets_the_mean_brightness_of_rendered_frames(tmp_path):
    """appearance.exposure_stops -> mean brightness of the same views, monotone."""
    means = []
    for stops in (-1.0, 0.0, 1.0):
        look = dict(appearance.APPEARANCE_DEFAULTS, exposure_stops=[stops, stops])
        m = _manifest({"lumen": 1.0, "closeup": 1.0}, n=4, appearance=look)
        root = synth.generate(m, tmp_path / f"e{stops}", progress=False)
        recs = _records(root)
        assert all(r["appearance"]["exposure_stops"] == stops for r in recs)
        from PIL import Image
        means.append(np.mean([np.asarray(Image.open(root / r["rgb"])).mean() for r in recs]))
    assert means[0] < means[1] < means[2]
    assert means[0] < 0.7 * means[1]  # one stop down roughly halves the signal (before gamma 1)
