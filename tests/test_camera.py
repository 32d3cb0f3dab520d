import math

import numpy as np
import pytest
import torch

from geodepth_lite.core import camera


def test_default_intrinsics_match_the_authors_blender_set():
    K = camera.intrinsics(320)
    assert K[0, 0] == pytest.approx(0.5556 * 320)
    assert K[1, 1] == pytest.approx(0.5556 * 320)
    assert (K[0, 2], K[1, 2]) == (160.0, 160.0)
    assert camera.fov_x_deg(K, 320) == pytest.approx(2 * math.degrees(math.atan(0.5 / 0.5556)))
    assert 83.5 < camera.fov_x_deg(K, 320) < 84.5


def test_fov_roundtrip_and_bad_values():
    K = camera.intrinsics_from_fov(100, 80, 90.0)
    assert K[0, 0] == pytest.approx(50.0)
    assert camera.fov_x_deg(K, 100) == pytest.approx(90.0)
    for bad in (0.0, 180.0, 200.0):
        with pytest.raises(ValueError, match="field of view"):
            camera.intrinsics_from_fov(100, 80, bad)


def test_backproject_then_project_is_identity():
    rng = np.random.default_rng(0)
    K = camera.intrinsics(7, 5)
    depth = rng.uniform(0.5, 3.0, size=(5, 7))
    pts = camera.backproject(depth, K)
    uv, z = camera.project(pts.reshape(-1, 3), K)
    v, u = np.mgrid[0:5, 0:7]
    np.testing.assert_allclose(uv[:, 0], u.ravel(), atol=1e-9)
    np.testing.assert_allclose(uv[:, 1], v.ravel(), atol=1e-9)
    np.testing.assert_allclose(z, depth.ravel())


def test_backproject_principal_point_is_on_axis_and_batched_matches():
    K = np.array([[10.0, 0, 2.0], [0, 10.0, 1.0], [0, 0, 1]])
    depth = torch.full((2, 1, 3, 5), 4.0, dtype=torch.float64)
    pts = camera.backproject(depth, K)  # B x HW x 3
    assert pts.shape == (2, 15, 3)
    np.testing.assert_allclose(pts[0, 1 * 5 + 2].numpy(), [0.0, 0.0, 4.0])
    np.testing.assert_allclose(pts[1, 0].numpy(), [-0.8, -0.4, 4.0])
    single = camera.backproject(depth[0, 0].numpy(), K).reshape(-1, 3)
    np.testing.assert_allclose(pts[0].numpy(), single)


def test_scale_intrinsics_keeps_the_image_centre():
    K = camera.intrinsics(64)
    K2 = camera.scale_intrinsics(K, 5.0)
    # the continuous centre of a 64-pixel image (31.5 in pixel-centre coordinates) maps to that of 320
    assert (K[0, 2] - 31.5) * 5 == pytest.approx(K2[0, 2] - 159.5)
    assert K2[0, 0] == pytest.approx(5 * K[0, 0])
