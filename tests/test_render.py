"""Renderer: exact pinhole geometry (analytic cylinder), pixel alignment, back-projection onto the mesh."""

import numpy as np
import pytest

from geodepth_lite.core import camera
from geodepth_lite.data import manifest as mf
from geodepth_lite.data import render, tube


def _cylinder_check(K, width, height, poses_s=(3.0, 12.0)):
    m = mf.load_manifest("check_cylinder")
    tm = tube.build_tube(m["organ_presets"]["cylinder"], 0, m["resolution"])
    R, L = tm.preset["radius"], tm.length
    worst = 0.0
    with render.Renderer(width, height, K) as r:
        r.set_tube(tm)
        for s in poses_s:
            T = render.sequence_poses(tm, 1, s, 0.0)[0]
            rgb, depth = r.render(T)
            assert rgb.shape == (height, width, 3) and rgb.dtype == np.uint8
            assert depth.shape == (height, width) and depth.dtype == np.float32
            xn, yn = camera.normalized_grid(K, height, width).numpy()
            with np.errstate(divide="ignore"):
                expected = R / np.sqrt(xn**2 + yn**2)
            wall = expected < 0.95 * (L - s)  # pixels whose ray meets the wall before the far end cap
            assert wall.mean() > 0.9
            rel = np.abs(depth[wall] / expected[wall] - 1.0)
            worst = max(worst, float(rel.max()))
    return worst


def test_straight_tube_depth_matches_the_analytic_cylinder_with_the_shipped_manifest():
    m = mf.load_manifest("check_cylinder")
    K = mf.intrinsics_of(m)
    assert K[0, 2] == 0.5 * m["camera"]["width"]  # cx = 0.5 W: not VTK's image centre (W - 1) / 2
    assert _cylinder_check(K, m["camera"]["width"], m["camera"]["height"]) < 0.005


def test_arbitrary_intrinsics_are_honoured_exactly():
    # non-square image, fx != fy, principal point far off-centre
    K = np.array([[41.0, 0.0, 23.7], [0.0, 52.5, 38.2], [0.0, 0.0, 1.0]])
    assert _cylinder_check(K, 56, 72) < 0.005


def test_projection_matrix_maps_pixel_centres_to_ndc_centres():
    K = np.array([[50.0, 0.0, 20.0], [0.0, 60.0, 10.0], [0.0, 0.0, 1.0]])
    W, H = 40, 30
    P = render.projection_matrix(K, W, H, 0.1, 10.0)
    u, v, z = 7.0, 21.0, 2.5
    X = np.array([(u - 20.0) / 50.0 * z, -(v - 10.0) / 60.0 * z, -z, 1.0])  # VTK eye: y up, looking down -z
    clip = P @ X
    ndc = clip[:3] / clip[3]
    assert ndc[0] == pytest.approx(2 * (u + 0.5) / W - 1)
    row_from_bottom = H - 1 - v
    assert ndc[1] == pytest.approx(2 * (row_from_bottom + 0.5) / H - 1)


def test_rendered_depth_back_projects_onto_the_mesh():
    import pyvista as pv

    preset = tube.PRESETS["colon"]
    tm = tube.build_tube(preset, 11, {"n_theta": 96, "ring_step": 0.08})
    K = camera.intrinsics(80, 64)
    rng = np.random.default_rng(0)
    path = dict(mf.DEFAULTS["camera_path"], views={"lumen": 1, "wall": 1, "oblique": 1, "closeup": 1})
    with render.Renderer(80, 64, K) as r:
        r.set_tube(tm, render.make_texture(render.TEXTURES["pink"], rng))
        for _ in range(3):
            T, _info = render.sample_pose(tm, rng, path)
            lights, tint = render.sample_lighting(render.LIGHTINGS["white_dual"], rng, preset["radius"])
            r.set_tint(tint)
            rgb, depth = r.render(T, lights)
            valid = depth > 0
            assert valid.mean() > 0.99
            pts_cam = camera.backproject(depth, K)[valid]
            pts_world = camera.transform(T, pts_cam)
            dist = np.abs(pv.PolyData(pts_world).compute_implicit_distance(tm.mesh)["implicit_distance"])
            assert np.all(dist < 0.01 * depth[valid])
            assert rgb.mean() > 10  # lit


def test_point_light_at_the_lens_has_inverse_square_falloff():
    # light on the axis of a cylinder of radius R: a wall point at depth z is d = sqrt(R^2 + z^2)
    # away and lit at incidence cos = R / d, so Lambertian radiance = I * albedo * R / d^3
    tm = tube.build_tube("cylinder", 0, {"n_theta": 128, "ring_step": 1.0})
    K = camera.intrinsics(64)
    T = render.sequence_poses(tm, 1, 5.0, 0.0)[0]
    with render.Renderer(64, 64, K) as r:
        r.set_tube(tm, material={"ambient": 0.0, "diffuse": 1.0, "specular": 0.0})
        r.set_tint((1.0, 1.0, 1.0))
        rgb, depth = r.render(T, [render.Light((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 2.0)])
    d = np.sqrt(1.0 + depth.astype(np.float64) ** 2)
    predicted = 2.0 * 1.0 / d**3 * 255.0
    lit = (depth > 0) & (predicted > 20) & (predicted < 250)
    assert lit.sum() > 200
    ratio = rgb[..., 0][lit] / predicted[lit]  # red channel, white albedo
    assert np.median(ratio) == pytest.approx(1.0, rel=0.05)
    assert np.percentile(np.abs(ratio / np.median(ratio) - 1), 90) < 0.05


def _sphere_depth(K, size, centre, radius, inside=False):
    xn, yn = camera.normalized_grid(K, size, size).numpy()
    rays = np.stack([xn, yn, np.ones_like(xn)], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    b = rays @ centre
    root = np.sqrt(np.clip(b * b - (centre @ centre - radius**2), 0.0, None))  # rays that miss: unused
    return (b + root if inside else b - root) * rays[..., 2]


def test_shape_index_of_analytic_surfaces():
    from geodepth_lite.views import viz

    K = camera.intrinsics(48)
    cap = _sphere_depth(K, 48, np.array([0.0, 0.0, 5.0]), 3.0)          # dome towards the camera
    cup = _sphere_depth(K, 48, np.array([0.0, 0.0, 0.5]), 8.0, True)    # inside a sphere: a pocket
    xn, yn = camera.normalized_grid(K, 48, 48).numpy()
    a = xn**2 + 1.0
    ridge = (5.0 - np.sqrt(np.clip(25.0 - a * 16.0, 0.0, None))) / a  # cylinder x^2 + (z - 5)^2 = 9, z along each ray
    centre = (slice(16, 32), slice(16, 32))
    for depth, expected in ((cap, 1.0), (cup, -1.0), (ridge, 0.5)):
        si = viz.shape_index(depth, K, smooth=0)
        assert np.nanmedian(si[centre]) == pytest.approx(expected, abs=0.02)
    assert viz.shape_index_classes(viz.shape_index(cap, K, smooth=0)[centre])["cap"] > 0.9
    img = viz.colorize_depth(cap)
    assert img.shape == (48, 48, 3) and img.dtype == np.uint8
