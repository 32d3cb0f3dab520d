"""3D reconstruction: PLY round trip, mesh topology and normals, and back-projection of a rendered frame."""

import numpy as np
import pytest

from geodepth_lite import camera, recon


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
    from geodepth_lite import render, tube

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


def test_show_static_views_and_a_clear_error_without_a_jupyter_backend(monkeypatch):
    import matplotlib.pyplot as plt

    depth, K, rgb = _step_scene()
    mesh = recon.depth_mesh(depth, K, rgb)
    assert recon.show(mesh, window_size=(64, 64)) is None
    assert len(plt.gcf().axes) == 2
    plt.close("all")
    monkeypatch.setattr(recon, "jupyter_backend_available", lambda: False)
    with pytest.raises(ValueError, match="pyvista Jupyter backend"):
        recon.show(mesh, interactive=True)
