"""3D reconstruction: PLY round trip, mesh topology and normals, and back-projection of a rendered frame."""

import base64
import io
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from geodepth_lite.core import camera
from geodepth_lite.views import recon


def _step_scene(H=24, W=32):
    K = camera.intrinsics(W, H)
    depth = np.full((H, W), 2.0)
    depth[:, W // 2:] = 4.0  # a fronto-parallel step: an occluding edge between columns W/2-1 and W/2
    rgb = np.random.default_rng(0).integers(0, 256, size=(H, W, 3), dtype=np.uint8)
    return depth, K, rgb


def test_mesh_drops_triangles_across_the_step_and_faces_the_camera():
    depth, K, rgb = _step_scene()
    H, W = depth.shape
    valid = np.ones_like(depth, dtype=bool)
    valid[0, 0] = False
    mesh = recon.depth_mesh(depth, K, rgb, valid)
    # every 2x2 block gives two triangles, except the block column across the step (H-1 blocks)
    # and the two triangles of block (0, 0) that use the invalid pixel (only one of them does:
    # (a, c, b) uses it, (b, c, e) does not).
    assert mesh.n_cells == 2 * (H - 1) * (W - 1) - 2 * (H - 1) - 1
    assert mesh.n_points == H * W - 1
    n = np.asarray(mesh.point_data["Normals"])
    np.testing.assert_allclose(n, np.tile([0.0, 0.0, -1.0], (len(n), 1)), atol=1e-6)
    # vertices are the back-projected pixels (camera.backproject), coloured by the image
    pts = camera.backproject(depth, K).reshape(-1, 3)[valid.ravel()]
    np.testing.assert_allclose(np.asarray(mesh.points), pts, rtol=1e-6)
    np.testing.assert_array_equal(mesh.point_data["rgb"], rgb.reshape(-1, 3)[valid.ravel()])


def test_a_steep_but_smooth_surface_is_kept():
    # a plane tilted 60 degrees to the view: depth changes smoothly, no triangle may be dropped
    H, W = 16, 16
    K = camera.intrinsics(W, H)
    xn = (np.arange(W) - K[0, 2]) / K[0, 0]
    z = 3.0 / (1.0 - np.tan(np.radians(60.0)) * 0.3 * xn)  # plane z = 3 + tan(60) * 0.3 * x
    depth = np.tile(z, (H, 1))
    mesh = recon.depth_mesh(depth, K)
    assert mesh.n_cells == 2 * (H - 1) * (W - 1)


def test_point_cloud_stride_keeps_exact_geometry():
    depth, K, rgb = _step_scene()
    full = camera.backproject(depth, K)
    cloud = recon.point_cloud(depth, K, rgb, stride=3)
    np.testing.assert_allclose(np.asarray(cloud.points), full[::3, ::3].reshape(-1, 3), rtol=1e-6)
    np.testing.assert_array_equal(cloud.point_data["rgb"], rgb[::3, ::3].reshape(-1, 3))


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("kind", ["mesh", "cloud"])
def test_ply_round_trip_through_vtks_reader(tmp_path, binary, kind):
    depth, K, rgb = _step_scene()
    poly = recon.depth_mesh(depth, K, rgb) if kind == "mesh" else recon.point_cloud(depth, K, rgb)
    path = recon.save_ply(poly, tmp_path / f"x_{kind}_{binary}.ply", binary=binary)
    head = path.read_bytes()[:120]
    assert (b"binary_little_endian" in head) == binary
    back = recon.load_ply(path)
    np.testing.assert_allclose(np.asarray(back.points), np.asarray(poly.points), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(back.point_data["RGB"]), poly.point_data["rgb"])
    if kind == "mesh":
        np.testing.assert_array_equal(back.regular_faces, poly.regular_faces)
        np.testing.assert_allclose(back.point_data["Normals"], poly.point_data["Normals"], atol=1e-6)
    else:
        assert back.n_faces == 0
    assert not list(tmp_path.glob(".*.tmp"))  # written atomically, nothing left over


def test_rendered_frames_back_project_onto_the_mesh_and_fuse_with_their_poses():
    """A synthetic frame (tube mesh + renderer): every back-projected pixel lies on the wall
    within 1% of its depth, and two consecutive frames fused with T_world_cam do too."""
    from geodepth_lite.data import render, tube

    tb = tube.build_tube("colon", seed=3, resolution={"n_theta": 64, "ring_step": 0.15})
    K = camera.intrinsics(48, 48)
    poses = render.sequence_poses(tb, 2, 5.0, 0.6, offset=(0.4, -0.2))
    with render.Renderer(48, 48, K) as r:
        r.set_tube(tb)
        frames = [r.render(T) for T in poses]
    depths = [d for _, d in frames]
    assert all((d > 0).mean() > 0.99 for d in depths)
    fused = recon.fuse_point_clouds(depths, K, poses, images=[rgb for rgb, _ in frames], stride=1)
    assert fused.n_points == sum(int((d > 0).sum()) for d in depths)
    dist = np.abs(fused.compute_implicit_distance(tb.mesh)["implicit_distance"])
    rel = dist / fused.point_data["depth"]
    assert rel.max() <= 0.01
    # the same points in the camera frame (no pose) are far from the wall: the test can fail
    cam_only = recon.point_cloud(depths[1], K)
    assert np.median(np.abs(cam_only.compute_implicit_distance(tb.mesh)["implicit_distance"])) > 0.05


def test_median_scale_ratios_known_answer():
    rng = np.random.default_rng(1)
    gts = [rng.uniform(1, 5, size=(8, 8)) for _ in range(4)]
    scales = [0.5, 1.0, 2.0, 4.0]
    preds = [g * s for g, s in zip(gts, scales)]
    valids = [np.ones((8, 8), bool) for _ in gts]
    valids[2][:4] = False
    np.testing.assert_allclose(recon.median_scale_ratios(preds, gts, valids), [2.0, 1.0, 0.5, 0.25])
    with pytest.raises(ValueError, match="frame 0: no pixel"):
        recon.median_scale_ratios([preds[0]], [np.zeros((8, 8))])


def test_render_views_are_two_nonblank_images():
    depth, K, rgb = _step_scene()
    images = recon.render_views(recon.depth_mesh(depth, K, rgb), window_size=(96, 80))
    assert len(images) == 2
    for im in images:
        assert im.shape == (80, 96, 3) and im.dtype == np.uint8
        assert (im != 255).any(axis=-1).mean() > 0.02  # something drawn on the white background
    with pytest.raises(ValueError, match="unknown view 'top'"):
        recon.render_views(recon.point_cloud(depth, K), views=("top",))


def test_render_views_colour_modes_and_a_clear_error():
    H, W = 24, 32
    K = camera.intrinsics(W, H)
    xn = (np.arange(W) - K[0, 2]) / K[0, 0]
    depth = np.tile(3.0 / (1.0 - np.tan(np.radians(50.0)) * 0.5 * xn), (H, 1))  # a plane turned 50 degrees
    mesh = recon.depth_mesh(depth, K)
    surface = recon.render_views(mesh, window_size=(64, 64), views=("side",), color_by="surface")[0]
    drawn = surface[(surface != 255).any(axis=-1)].astype(float)
    assert len(drawn) > 100
    # one tissue tone, lit: no drawn pixel near black or washed out to white, the tone kept (red > green > blue)
    assert drawn.mean(axis=-1).min() > 60 and drawn[:, 2].max() < 235
    assert np.all(drawn[:, 0] > drawn[:, 1]) and np.all(drawn[:, 1] > drawn[:, 2])
    with pytest.raises(ValueError, match="color_by must be one of image, depth, surface"):
        recon.render_views(mesh, color_by="height")


def test_show_gives_static_views_or_an_interactive_view():
    import matplotlib.pyplot as plt

    depth, K, rgb = _step_scene()
    mesh = recon.depth_mesh(depth, K, rgb)
    assert recon.show(mesh, window_size=(64, 64)) is None
    assert len(plt.gcf().axes) == 2
    plt.close("all")
    view = recon.show(mesh, interactive=True, color_by="surface")
    assert isinstance(view, recon.View3D) and view.figure["data"][0]["type"] == "mesh3d"


# --------------------------------------------------------------------------- interactive 3D views
def _decode(spec: dict) -> np.ndarray:
    return np.frombuffer(base64.b64decode(spec["bdata"]), dtype=np.dtype("<" + spec["dtype"]))


def test_interactive_mesh_is_lit_and_carries_every_vertex_and_triangle():
    depth, K, rgb = _step_scene()
    H, W = depth.shape
    valid = np.ones_like(depth, dtype=bool)
    valid[0, 0] = False
    mesh = recon.depth_mesh(depth, K, rgb, valid)
    fig = recon.figure_3d({"step": mesh}, color_by="surface")
    (trace,) = fig["data"]
    assert trace["type"] == "mesh3d" and trace["scene"] == "scene"
    xyz = np.stack([_decode(trace[a]) for a in "xyz"], axis=1)
    assert len(xyz) == H * W - 1  # every valid pixel, as in the mesh test above
    np.testing.assert_array_equal(xyz, np.asarray(mesh.points, dtype=np.float32))
    ijk = np.stack([_decode(trace[a]) for a in "ijk"], axis=1)
    assert len(ijk) == 2 * (H - 1) * (W - 1) - 2 * (H - 1) - 1
    np.testing.assert_array_equal(ijk, mesh.regular_faces)
    assert trace["lighting"] == recon.PLOTLY_LIGHTING
    assert trace["lighting"]["ambient"] >= 0.5 and trace["lighting"]["diffuse"] > 0  # the far side stays visible
    assert trace["color"] == "rgb(222,160,140)" and "intensity" not in trace and "colorbar" not in trace
    assert fig["layout"]["scene"]["camera"]["up"] == {"x": 0, "y": -1, "z": 0}  # y points down in the camera frame
    assert [a["text"] for a in fig["layout"]["annotations"]] == ["step"]


def test_depth_coloured_clouds_share_one_range_and_one_colour_bar_that_states_the_clip():
    K = camera.intrinsics(20, 10)
    depth = np.arange(1, 201, dtype=np.float64).reshape(10, 20) / 10.0  # 0.1 .. 20.0
    cloud = recon.point_cloud(depth, K)
    assert recon.depth_clim(cloud) == pytest.approx((np.percentile(depth, 2), np.percentile(depth, 98)))
    assert recon.depth_clim(cloud) == pytest.approx((0.498, 19.602))  # known answer: 0.1 + 0.02 * 199 * 0.1 ...
    fig = recon.figure_3d({"a": cloud, "b": recon.point_cloud(depth * 2, K)})
    a, b = fig["data"]
    assert a["type"] == b["type"] == "scatter3d" and (a["scene"], b["scene"]) == ("scene", "scene2")
    np.testing.assert_array_equal(_decode(a["marker"]["color"]), depth.ravel().astype(np.float32))
    for t in (a, b):  # one range for both panels: the first panel's
        assert (t["marker"]["cmin"], t["marker"]["cmax"]) == pytest.approx((0.498, 19.602))
    assert a["marker"]["showscale"] is False and b["marker"]["showscale"] is True  # one colour bar
    assert "clipped to 0.498-19.6" in b["marker"]["colorbar"]["title"]["text"]
    scale = a["marker"]["colorscale"]
    assert scale[0][0] == 0 and scale[-1][0] == 1 and scale[0][1] == "rgb(252,253,191)"  # near = bright (magma_r)
    assert fig["layout"]["scene2"]["domain"]["x"] == [0.5, 1.0]


def test_large_clouds_are_thinned_evenly_and_large_meshes_refused():
    K = camera.intrinsics(50, 40)
    depth = np.linspace(1.0, 5.0, 2000).reshape(40, 50)
    fig = recon.figure_3d(recon.point_cloud(depth, K), max_points=500)
    z = _decode(fig["data"][0]["z"])
    assert len(z) == 500 and z[0] == np.float32(1.0) and z[-1] == np.float32(5.0) and np.all(np.diff(z) > 0)
    with pytest.raises(ValueError, match="2000 vertices, more than max_points=500: build it with a larger stride"):
        recon.figure_3d(recon.depth_mesh(depth, K), max_points=500)
    with pytest.raises(ValueError, match="at least one"):
        recon.figure_3d({})


def test_view_3d_is_a_plotly_bundle_plotly_accepts_and_the_same_bytes_every_time():
    go = pytest.importorskip("plotly.graph_objects")
    depth, K, rgb = _step_scene()
    mesh, cloud = recon.depth_mesh(depth, K, rgb), recon.point_cloud(depth, K, rgb)
    view = recon.view_3d({"mesh": mesh, "cloud": cloud}, color_by="image")
    bundle = view._repr_mimebundle_()
    assert set(bundle) == {recon.PLOTLY_MIME, "text/plain"}
    assert bundle["text/plain"].startswith(f"interactive 3D view (mesh: mesh of {mesh.n_points} vertices and "
                                           f"{mesh.n_cells} triangles; cloud: cloud of {cloud.n_points} points)")
    mesh_trace, cloud_trace = bundle[recon.PLOTLY_MIME]["data"]
    assert mesh_trace["vertexcolor"][:2] == [f"rgb({r},{g},{b})" for r, g, b in rgb.reshape(-1, 3)[:2].tolist()]
    go.Figure(bundle[recon.PLOTLY_MIME])  # plotly validates every property name and value
    with pytest.raises(ValueError):
        go.Figure({"data": [{**mesh_trace, "lightning": {}}]})  # and would catch a misspelt one
    again = recon.view_3d({"mesh": mesh, "cloud": cloud}, color_by="image")
    assert json.dumps(again.figure, sort_keys=True) == json.dumps(view.figure, sort_keys=True)
    html = view.html()
    assert html == again.html() and html.count("geodepth3d-") == 2 and "<script" in html
    assert "</" not in html[html.index("var fig="):html.rindex("</script>")]  # the JSON cannot close its script


def test_save_html_is_a_standalone_page_with_plotly_inlined(tmp_path):
    pytest.importorskip("plotly")
    depth, K, rgb = _step_scene()
    path = recon.save_html(recon.view_3d(recon.depth_mesh(depth, K, rgb)), tmp_path / "view.html")
    page = path.read_text()
    assert page.startswith("<!DOCTYPE html>") and len(page) > 1_000_000  # plotly.js itself, no network needed
    assert "https://cdn" not in page[:200] and not list(tmp_path.glob(".*.tmp"))


@pytest.mark.slow
def test_the_standalone_page_draws_a_lit_mesh_in_a_browser(tmp_path):
    """Chromium (headless, software WebGL) opens the page: a WebGL canvas appears and the mesh is drawn
    in the tissue tone, neither blank nor black."""
    sync_api = pytest.importorskip("playwright.sync_api")
    chromium = Path("/usr/bin/chromium")
    if not chromium.exists():
        pytest.skip("no chromium at /usr/bin/chromium")
    depth, K, rgb = _step_scene()
    depth = depth + np.linspace(0, 1, depth.shape[1])[None, :]  # a slanted step: shading varies
    path = recon.save_html(recon.view_3d(recon.depth_mesh(depth, K, rgb), color_by="surface"), tmp_path / "v.html")
    args = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync"]
    with sync_api.sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(str(tmp_path / "profile"), executable_path=str(chromium),
                                                   args=args, headless=True, viewport={"width": 600, "height": 500})
        try:
            page = ctx.new_page()
            errors = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(path.as_uri())
            page.wait_for_selector(".geodepth-3d canvas", timeout=30_000)
            page.wait_for_timeout(1500)
            shot = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB")).astype(int)
        finally:
            ctx.close()
    assert not errors, errors
    assert _lit_mesh_seen(shot)
    black = shot.copy()
    black[np.abs(shot - np.array(recon.SURFACE_RGB)).max(axis=-1) < 90] = 20  # the same picture with a black mesh
    assert not _lit_mesh_seen(black) and not _lit_mesh_seen(np.full_like(shot, 255))  # the check can fail


def _lit_mesh_seen(shot: np.ndarray) -> bool:
    """At least 2% of the screenshot in the tissue tone (lit or in shade), and under 1% near black."""
    tone = np.abs(shot - np.array(recon.SURFACE_RGB)).max(axis=-1) < 90
    return bool(tone.mean() > 0.02 and (shot.max(axis=-1) < 40).mean() < 0.01)
