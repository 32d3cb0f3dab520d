"""Procedural tube: closed wall, consistent inward normals, twist-free frames, determinism."""

import numpy as np
import pytest

from geodepth_lite.data import tube

LOW_RES = {"n_theta": 48, "ring_step": 0.15}


@pytest.mark.parametrize("organ", ["colon", "small_intestine", "stomach", "cylinder"])
def test_wall_is_closed_and_normals_point_into_the_lumen(organ):
    tm = tube.build_tube(organ, seed=5, resolution=LOW_RES)
    merged = tm.mesh.clean()  # merge the duplicated texture seam
    assert merged.n_open_edges == 0
    assert merged.is_manifold
    # consistently oriented: on a closed surface every directed edge occurs exactly once
    tris = merged.faces.reshape(-1, 4)[:, 1:]
    edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    assert np.unique(edges, axis=0).shape[0] == edges.shape[0]
    # ... and facing inwards: the signed volume (sum of det(v0, v1, v2) / 6) is negative
    P = merged.points.astype(np.float64)
    signed = np.einsum("ij,ij->i", P[tris[:, 0]], np.cross(P[tris[:, 1]], P[tris[:, 2]])).sum() / 6
    assert signed == pytest.approx(-merged.volume, rel=1e-6)
    # the wall's stored point normals agree with the winding of every wall triangle
    wall_tris = tm.mesh.faces.reshape(-1, 4)[:, 1:]
    wall_tris = wall_tris[np.all(wall_tris < tm.mesh.n_points - 2, axis=1)]
    Q = tm.mesh.points.astype(np.float64)
    face_n = np.cross(Q[wall_tris[:, 1]] - Q[wall_tris[:, 0]], Q[wall_tris[:, 2]] - Q[wall_tris[:, 0]])
    assert np.all(np.sum(face_n * tm.mesh.point_data["Normals"][wall_tris].mean(axis=1), axis=1) > 0)
    # wall normals point towards the centerline (into the lumen, where the camera is)
    s = tm.mesh.point_data["s"][:-2].astype(np.float64)
    radial = tm.mesh.points[:-2] - tm.centerline(s)
    assert np.all(np.sum(tm.mesh.point_data["Normals"][:-2] * radial, axis=1) < 0)
    # a closed, inward-facing surface encloses a positive volume roughly pi r^2 L
    R, L = tm.preset["radius"], tm.preset["length"]
    assert 0.5 < merged.volume / (np.pi * R**2 * L) < 1.5
    assert tm.mesh.active_texture_coordinates.shape == (tm.mesh.n_points, 2)


def test_cylinder_preset_is_a_straight_tube_of_constant_radius():
    tm = tube.build_tube("cylinder", seed=1, resolution=LOW_RES)
    s = np.linspace(0, tm.length, 50)
    th = np.linspace(0, 2 * np.pi, 40)
    assert np.allclose(tm.radius(s[:, None], th[None, :]), 1.0)
    c = tm.centerline(s)
    assert np.allclose(c[:, :2], 0.0) and np.allclose(c[:, 2], s)
    wall = tm.wall_point(s[:, None], th[None, :])
    assert np.allclose(np.linalg.norm(wall[..., :2], axis=-1), 1.0)


def test_parallel_transport_frames_do_not_twist():
    # a planar curve (in x-z): the rotation-minimizing frame keeps its out-of-plane vector constant
    t = np.linspace(0, 20, 400)
    planar = np.stack([3 * np.sin(t / 4), np.zeros_like(t), t], axis=1)
    T, N, B = tube.parallel_transport_frames(planar)
    out_of_plane = np.where(np.abs(N[:, 1]) > 0.5, N[:, 1], B[:, 1])
    assert np.allclose(np.abs(out_of_plane), 1.0, atol=1e-9)
    # a 3D curve: orthonormal frames, and N never turns about T (N_{i+1} . B_i = O(ds^2))
    helixish = np.stack([2 * np.cos(t / 3), 1.5 * np.sin(t / 2), t], axis=1)
    T, N, B = tube.parallel_transport_frames(helixish)
    for a, b in ((T, N), (T, B), (N, B)):
        assert np.abs(np.sum(a * b, axis=1)).max() < 1e-9
    ds = np.linalg.norm(np.diff(helixish, axis=0), axis=1)
    twist = np.abs(np.sum(N[1:] * B[:-1], axis=1)) / ds
    assert twist.max() < 1e-2  # twist rate per unit length vanishes with ds


def test_tube_frames_are_orthonormal_and_build_is_deterministic():
    a = tube.build_tube("colon", seed=3, resolution=LOW_RES)
    b = tube.build_tube("colon", seed=3, resolution=LOW_RES)
    c = tube.build_tube("colon", seed=4, resolution=LOW_RES)
    assert np.array_equal(a.mesh.points, b.mesh.points)
    assert not np.array_equal(a.mesh.points, c.mesh.points)
    T, N, B = a.frame(np.array([0.0, 7.3, 21.1]))
    assert np.allclose(np.sum(T * N, -1), 0) and np.allclose(np.linalg.norm(B, axis=-1), 1)
    assert np.allclose(np.cross(T, N), B)


def test_local_structure_counts_follow_the_preset():
    preset = dict(tube.PRESETS["colon"], polyps=[2, 2], diverticula=[1, 1], ridges=[3, 3])
    tm = tube.build_tube(preset, seed=0, resolution=LOW_RES)
    assert (len(tm.features.polyps), len(tm.features.diverticula), len(tm.features.ridges)) == (2, 1, 3)
    # a polyp (cap) pulls the wall into the lumen, a diverticulum (cup) pushes it out
    s, th, size = tm.features.polyps[0]
    plain = dict(preset, polyps=[0, 0], diverticula=[0, 0], ridges=[0, 0])
    feats_plain = tube.WallFeatures(**{**tm.features.__dict__, "polyps": [], "diverticula": [], "ridges": []})
    assert tm.radius(s, th) < tube.radius_field(s, th, plain, feats_plain)
    s, th, size = tm.features.diverticula[0]
    assert tm.radius(s, th) > tube.radius_field(s, th, plain, feats_plain)


def test_unknown_preset_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown organ preset 'liver'"):
        tube.build_tube("liver", seed=0)
