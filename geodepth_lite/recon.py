"""Depth maps to 3D: coloured point clouds, surface meshes, PLY files and the paper's 3D views.

Section 4.2.3 ("Validation on clinical images"): "we transform each depth map into two 3D
views based on the calibrated endoscope parameters" (Fig. 9), and per-frame depth should
be temporally consistent over a sequence (Fig. 10). This module does the geometry:

- ``point_cloud``: every valid pixel back-projected with ``camera.backproject``, coloured
  by the image;
- ``depth_mesh``: the pixel grid as a triangle surface with normals, without triangles
  that span a depth discontinuity (an occluding fold edge is not a surface);
- ``save_ply`` / ``load_ply``: PLY files (binary or ASCII) any 3D viewer opens;
- ``render_views``: two headless views per depth map, as PNG-ready arrays;
- ``fuse_point_clouds`` and ``median_scale_ratios``: a sequence in world coordinates
  through the poses ``T_world_cam`` and the per-frame median-scale ratio (Fig. 10 claim).

Points are in the camera frame of ``camera`` (x right, y down, z forward) unless a
``T_world_cam`` moves them to the world; units are those of the depth map.
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
from PIL import Image

from . import camera, render, utils
from . import manifest as mf
from . import tube as tube_mod
from .metrics import median_scale

# A triangle between neighbouring pixels is kept only if a smooth surface could produce its
# depth spread: a surface seen at grazing angle a changes depth between pixels one ray step
# (1/f radians) apart by about z/(f tan a). Spreads above that for a below this angle are
# treated as jumps across an occluding edge.
MIN_GRAZING_DEG = 5.0


def _to_numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _as_hw(depth) -> np.ndarray:
    d = _to_numpy(depth).astype(np.float64)
    d = d.reshape(d.shape[-2:]) if d.ndim > 2 and int(np.prod(d.shape[:-2])) == 1 else d
    if d.ndim != 2:
        raise ValueError(f"depth must be H x W (or 1 x H x W), got shape {d.shape}")
    return d


def _as_rgb8(image, shape) -> np.ndarray | None:
    """H x W x 3 uint8 from uint8 HxWx3, float [0,1] HxWx3 or 3xHxW (numpy or torch)."""
    if image is None:
        return None
    im = _to_numpy(image)
    if im.ndim == 3 and im.shape[0] == 3 and im.shape[-1] != 3:
        im = im.transpose(1, 2, 0)
    if im.shape[:2] != tuple(shape) or im.ndim != 3 or im.shape[2] < 3:
        raise ValueError(f"image must be H x W x 3 or 3 x H x W matching depth {tuple(shape)}, got {im.shape}")
    im = im[..., :3]
    if im.dtype != np.uint8:
        im = np.clip(np.round(im.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    return im


def _valid_mask(d: np.ndarray, valid) -> np.ndarray:
    ok = np.isfinite(d) & (d > 0)
    if valid is not None:
        v = _to_numpy(valid).astype(bool)
        ok &= v.reshape(d.shape)
    return ok


def _subsample(d, K, rgb, ok, stride: int):
    if not isinstance(stride, int) or stride < 1:
        raise ValueError(f"stride must be a positive integer, got {stride!r}")
    if stride == 1:
        return d, np.asarray(K, dtype=np.float64), rgb, ok
    # Keeping every stride-th pixel maps pixel centre u to u / stride: K scales by 1/stride
    # about the pixel origin (not the image corner), so back-projection stays exact.
    K = np.array(K, dtype=np.float64)
    K[:2] /= stride
    sl = (slice(None, None, stride), slice(None, None, stride))
    return d[sl], K, (rgb[sl] if rgb is not None else None), ok[sl]


def point_cloud(depth, K, image=None, valid=None, T_world_cam=None, stride: int = 1):
    """Back-projected point cloud (pyvista PolyData) of the valid pixels.

    depth: H x W z-depth; K: 3x3 pixels; image: colours (uint8 or [0,1] float, HxWx3 or
    3xHxW); valid: H x W bool (pixels with depth <= 0 or non-finite are always dropped);
    T_world_cam: 4x4 to place the cloud in the world. Point data: "rgb" (uint8 N x 3) when
    an image is given, "depth" (float32 N).
    """
    import pyvista as pv  # VTK: heavy, needed only to build or render meshes

    d = _as_hw(depth)
    rgb = _as_rgb8(image, d.shape)
    d, K, rgb, ok = _subsample(d, K, rgb, _valid_mask(d, valid), stride)
    pts = camera.backproject(np.where(ok, d, 0.0), K)[ok]
    if T_world_cam is not None:
        pts = camera.transform(T_world_cam, pts)
    cloud = pv.PolyData(pts.astype(np.float32))
    cloud.point_data["depth"] = d[ok].astype(np.float32)
    if rgb is not None:
        cloud.point_data["rgb"] = rgb[ok]
    return cloud


def grid_triangles(depth: np.ndarray, ok: np.ndarray, K, min_grazing_deg: float = MIN_GRAZING_DEG) -> np.ndarray:
    """T x 3 indices into the H*W pixel grid: two triangles a 2x2 pixel block, kept when all
    three corners are valid and their depth spread max/min - 1 stays below the jump a
    surface at ``min_grazing_deg`` would make. Winding makes normals face the camera."""
    H, W = depth.shape
    if not 0.0 < min_grazing_deg < 90.0:
        raise ValueError(f"min_grazing_deg must be between 0 and 90, got {min_grazing_deg}")
    f = min(float(K[0][0]), float(K[1][1]))
    tol = 1.0 / (f * math.tan(math.radians(min_grazing_deg)))
    idx = np.arange(H * W).reshape(H, W)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()  # (u, v), (u+1, v)
    c, e = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()  # (u, v+1), (u+1, v+1)
    # With x right, y down, z forward, (a, c, b) turns counter-clockwise seen from the camera.
    tris = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, e], 1)])
    z = depth.ravel()[tris]
    okt = ok.ravel()[tris].all(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        spread = z.max(1) / z.min(1) - 1.0
    return tris[okt & (spread <= tol)]


def depth_mesh(depth, K, image=None, valid=None, T_world_cam=None, stride: int = 1,
               min_grazing_deg: float = MIN_GRAZING_DEG):
    """Triangle surface of the depth grid (pyvista PolyData) with point normals facing the camera.

    Arguments as ``point_cloud``; triangles across depth discontinuities are dropped
    (``grid_triangles``). Point data: "Normals", "depth", and "rgb" when an image is given.
    """
    import pyvista as pv  # VTK: heavy, needed only to build or render meshes

    d = _as_hw(depth)
    rgb = _as_rgb8(image, d.shape)
    d, K, rgb, ok = _subsample(d, K, rgb, _valid_mask(d, valid), stride)
    tris = grid_triangles(np.where(ok, d, 0.0), ok, K, min_grazing_deg)
    used = np.zeros(d.size, dtype=bool)
    used[tris.ravel()] = True
    remap = np.cumsum(used) - 1
    pts = camera.backproject(np.where(ok, d, 0.0), K).reshape(-1, 3)[used]
    if T_world_cam is not None:
        pts = camera.transform(T_world_cam, pts)
    mesh = pv.PolyData.from_regular_faces(pts.astype(np.float32), remap[tris])
    mesh.point_data["depth"] = d.ravel()[used].astype(np.float32)
    if rgb is not None:
        mesh.point_data["rgb"] = rgb.reshape(-1, 3)[used]
    if mesh.n_cells:
        mesh = mesh.compute_normals(cell_normals=False, point_normals=True, split_vertices=False,
                                    consistent_normals=False, auto_orient_normals=False)
    return mesh


# --------------------------------------------------------------------------- PLY
def save_ply(poly, path, binary: bool = True) -> Path:
    """Write points (+ faces, "Normals", "rgb" point data) as PLY, atomically.

    Vertex properties: x y z (float32), nx ny nz (float32) when present, red green blue
    (uchar) when present; faces as uchar-counted int lists.
    """
    path = Path(path)
    pts = np.asarray(poly.points, dtype=np.float32)
    cols = [("x", "<f4", pts[:, 0]), ("y", "<f4", pts[:, 1]), ("z", "<f4", pts[:, 2])]
    if "Normals" in poly.point_data:
        n = np.asarray(poly.point_data["Normals"], dtype=np.float32)
        cols += [("nx", "<f4", n[:, 0]), ("ny", "<f4", n[:, 1]), ("nz", "<f4", n[:, 2])]
    if "rgb" in poly.point_data:
        c = np.asarray(poly.point_data["rgb"], dtype=np.uint8)
        cols += [("red", "u1", c[:, 0]), ("green", "u1", c[:, 1]), ("blue", "u1", c[:, 2])]
    faces = _triangles(poly)
    ply_type = {"<f4": "float", "u1": "uchar"}
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
              "comment geodepth-lite depth reconstruction", f"element vertex {len(pts)}"]
    header += [f"property {ply_type[t]} {name}" for name, t, _ in cols]
    if len(faces):
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header_bytes = ("\n".join(header) + "\nend_header\n").encode("ascii")
    vert = np.empty(len(pts), dtype=[(name, t) for name, t, _ in cols])
    for name, _, v in cols:
        vert[name] = v
    with utils.atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header_bytes)
            if binary:
                fh.write(vert.tobytes())
                if len(faces):
                    fb = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
                    fb["n"], fb["i"] = 3, faces
                    fh.write(fb.tobytes())
            else:
                fmt = " ".join("%.9g" if t == "<f4" else "%d" for _, t, _ in cols)
                for row in vert:
                    fh.write((fmt % tuple(row) + "\n").encode("ascii"))
                for tri in faces:
                    fh.write(f"3 {tri[0]} {tri[1]} {tri[2]}\n".encode("ascii"))
    return path


def _triangles(poly) -> np.ndarray:
    if poly.n_cells == 0 or not poly.n_faces:
        return np.zeros((0, 3), dtype=np.int64)
    if not poly.is_all_triangles:
        raise ValueError("save_ply writes triangle meshes or point clouds only")
    return np.asarray(poly.regular_faces, dtype=np.int64)


def load_ply(path):
    """Read a PLY into pyvista PolyData (VTK's reader; colours land in point data "RGB")."""
    import pyvista as pv  # VTK: heavy, needed only to build or render meshes

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file not found: {path}")
    return pv.read(path)


# --------------------------------------------------------------------------- views
# View directions (yaw about the camera's y axis, pitch about its x axis, degrees) of the
# two 3D views of Fig. 9: "front" looks down the optical axis from behind and a little
# above and left of the endoscope; "side" looks across it, the optical axis running left
# to right, which shows the relief (lumen length, fold heights).
VIEWS = {"front": (20.0, 25.0), "side": (-80.0, 15.0)}
VIEW_NAMES = tuple(VIEWS)


def render_views(poly, window_size=(360, 360), views=VIEW_NAMES, point_size: float = 3.0, background="white",
                 reference_pose=None, zoom: float = 1.0, color_by: str = "image") -> list[np.ndarray]:
    """Headless renders (H x W x 3 uint8) of a cloud or mesh, one per view in ``views`` (Fig. 9).

    Views are set in a camera frame: the points' own frame, or the frame of
    ``reference_pose`` (a 4x4 T_world_cam) for world-frame clouds such as fused sequences.
    color_by: "image" (the "rgb" point data, when present) or "depth" (magma colour map).
    """
    if color_by not in ("image", "depth"):
        raise ValueError(f"color_by must be 'image' or 'depth', got {color_by!r}")
    import pyvista as pv  # VTK: heavy, needed only to build or render meshes

    if poly.n_points == 0:
        raise ValueError("nothing to render: the cloud or mesh has no points")
    if reference_pose is not None:
        poly = poly.copy()
        poly.points = camera.transform(np.linalg.inv(np.asarray(reference_pose, dtype=np.float64)),
                                       np.asarray(poly.points, dtype=np.float64)).astype(np.float32)
    pts = np.asarray(poly.points, dtype=np.float64)
    lo, hi = np.percentile(pts, 5, axis=0), np.percentile(pts, 95, axis=0)
    centre = 0.5 * (lo + hi)
    extent = float(np.linalg.norm(hi - lo)) or 1.0
    images = []
    for view in views:
        if view not in VIEWS:
            raise ValueError(f"unknown view {view!r}: choose from {', '.join(VIEWS)}")
        yaw, pitch = (math.radians(a) for a in VIEWS[view])
        # viewing direction: +z turned by yaw about y, then tilted down by pitch (y is down)
        direction = np.array([math.sin(yaw) * math.cos(pitch), math.sin(pitch), math.cos(yaw) * math.cos(pitch)])
        pl = pv.Plotter(off_screen=True, window_size=list(window_size))
        pl.set_background(background)
        kw = (dict(rgb=True, scalars="rgb") if color_by == "image" and "rgb" in poly.point_data
              else dict(scalars="depth", cmap="magma", show_scalar_bar=False))
        if poly.n_cells and poly.n_faces:
            pl.add_mesh(poly, smooth_shading=True, ambient=0.45, diffuse=0.7, specular=0.0, **kw)
        else:
            pl.add_points(poly, point_size=point_size, render_points_as_spheres=False, lighting=False, **kw)
        pos = centre - direction * extent * 1.8 / zoom
        pl.camera_position = [tuple(pos), tuple(centre), (0.0, -1.0, 0.0)]
        pl.camera.view_angle = 40.0
        images.append(np.asarray(pl.screenshot(return_img=True))[..., :3].copy())
        pl.close()
    return images


def jupyter_backend_available() -> bool:
    """True when a pyvista Jupyter backend (trame) is installed, so 3D views can be interactive."""
    return all(importlib.util.find_spec(m) is not None for m in ("trame", "trame_vtk"))


def show(poly, interactive: bool = False, titles=None, **kw):
    """Show a cloud or mesh in a notebook: interactive (pyvista's trame backend) when asked and
    available, else the two static views of ``render_views`` side by side (matplotlib)."""
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    if interactive:
        if not jupyter_backend_available():
            raise ValueError("interactive 3D needs a pyvista Jupyter backend: pip install 'pyvista[jupyter]' (trame)")
        import pyvista as pv  # VTK: heavy, needed only to build or render meshes

        pl = pv.Plotter(notebook=True)
        scalars = dict(rgb=True, scalars="rgb") if "rgb" in poly.point_data else dict(scalars="depth", cmap="magma")
        pl.add_mesh(poly, **scalars)
        return pl.show(jupyter_backend="trame")
    images = render_views(poly, **kw)
    fig, axes = plt.subplots(1, len(images), figsize=(3.5 * len(images), 3.5), squeeze=False)
    for ax, im, title in zip(axes[0], images, titles or kw.get("views", VIEW_NAMES)):
        ax.imshow(im)
        ax.set_title(title)
        ax.axis("off")
    plt.tight_layout()
    plt.show()
    return None


def save_png(image: np.ndarray, path) -> Path:
    """Write an H x W x 3 uint8 array as PNG, atomically."""
    path = Path(path)
    with utils.atomic_path(path) as tmp:
        Image.fromarray(np.asarray(image, dtype=np.uint8)).save(tmp, format="PNG")
    return path


# --------------------------------------------------------------------------- sequences (Fig. 10)
def synthetic_sequence(manifest: str = "heldout_T2L2", organ: str = "colon", n_frames: int = 12,
                       step: float = 0.25, width: int = 128, height: int = 128, seed: int = 0,
                       s_start: float = 0.25, offset=(0.3, 0.0)) -> dict:
    """Consecutive frames down a procedural tube with known poses (a stand-in for a clinical video).

    The tube, texture and lighting come from ``manifest`` (a data_manifests/ name): its
    organ preset ``organ``, its first texture and lighting family. The camera advances
    ``step`` scene units a frame from ``s_start`` (fraction of the tube length), ``offset``
    (fraction of the radius) off the centerline, lights fixed to the endoscope.
    Returns {"images": list of H x W x 3 uint8, "depths": list of H x W float32,
    "K": 3x3, "poses": list of 4x4 T_world_cam, "tube": tube.TubeMesh}.
    """
    if not isinstance(n_frames, int) or n_frames < 2:
        raise ValueError(f"n_frames must be an integer >= 2, got {n_frames!r}")
    if not step > 0:
        raise ValueError(f"step must be positive, got {step!r}")
    m = mf.load_manifest(manifest)
    if organ not in m["organ_presets"]:
        raise ValueError(f"organ {organ!r} is not in manifest {manifest} (has {', '.join(m['organ_presets'])})")
    preset = m["organ_presets"][organ]
    R = float(preset["radius"])
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5E0]))
    tb = tube_mod.build_tube(preset, int(rng.integers(2**31)), m["resolution"])
    if not 0.0 <= s_start * tb.length + step * (n_frames - 1) <= tb.length:
        raise ValueError(f"{n_frames} frames of step {step} from s_start={s_start} leave the tube "
                         f"(length {tb.length:.1f})")
    texture = render.make_texture(m["texture_sets"][m["textures"][0]], rng)
    lighting = m["lighting_sets"][m["lightings"][0]]
    lights, tint = render.sample_lighting(lighting, rng, R)
    poses = render.sequence_poses(tb, n_frames, s_start * tb.length, step, (offset[0] * R, offset[1] * R))
    K = camera.intrinsics_from_fov(width, height, m["camera"]["fov_x_deg"])
    images, depths = [], []
    with render.Renderer(width, height, K, near=m["camera"]["near"], far=m["camera"]["far"]) as r:
        r.set_tube(tb, texture, {k: lighting[k] for k in ("ambient", "diffuse", "specular", "specular_power")})
        r.set_tint(tint)
        for T in poses:
            rgb, d = r.render(T, lights)
            images.append(rgb)
            depths.append(d)
    return {"images": images, "depths": depths, "K": K, "poses": poses, "tube": tb}


def fuse_point_clouds(depths, Ks, T_world_cams, images=None, valids=None, stride: int = 2):
    """One world-frame cloud from per-frame depth maps and camera-to-world poses.

    depths: sequence of H x W; Ks: one 3x3 or one per frame; T_world_cams: one 4x4 per
    frame. Point data "frame" (int32) says which frame each point came from. Depth maps
    that are temporally consistent give overlapping surfaces; a per-frame scale error
    shows up as shells at different radii.
    """
    import pyvista as pv  # VTK: heavy, needed only to build or render meshes

    n = len(depths)
    if len(T_world_cams) != n:
        raise ValueError(f"need one pose a frame: {n} depth maps, {len(T_world_cams)} poses")
    Ks = [Ks] * n if np.asarray(Ks).ndim == 2 else list(Ks)
    clouds = []
    for i in range(n):
        c = point_cloud(depths[i], Ks[i], None if images is None else images[i],
                        None if valids is None else valids[i], T_world_cams[i], stride)
        c.point_data["frame"] = np.full(c.n_points, i, dtype=np.int32)
        clouds.append(c)
    fused = pv.merge(clouds, merge_points=False) if clouds else pv.PolyData()
    return fused


def median_scale_ratios(preds, gts, valids=None) -> np.ndarray:
    """Per-frame median(gt) / median(pred) over valid pixels (the scale of Section 4.2.1's median scaling).

    A network whose depth is temporally consistent needs nearly the same ratio for every
    frame of a sequence; the spread of these ratios is what Fig. 10 shows qualitatively.
    """
    ratios = []
    for i, (p, g) in enumerate(zip(preds, gts)):
        p, g = _as_hw(p), _as_hw(g)
        ok = _valid_mask(g, None if valids is None else valids[i]) & np.isfinite(p) & (p > 0)
        if not ok.any():
            raise ValueError(f"frame {i}: no pixel with valid ground truth and positive prediction")
        ratios.append(median_scale(p[ok], g[ok]))
    return np.asarray(ratios)


def plot_scale_ratios(ratios, ax=None, label: str | None = None):
    """Per-frame median-scale ratio normalised by its mean, with the coefficient of variation."""
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    r = np.asarray(ratios, dtype=np.float64)
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 3))
    cv = r.std() / r.mean()
    ax.plot(np.arange(len(r)), r / r.mean(), marker="o", label=f"{label or 'ratio'} (CV {cv:.3f})")
    ax.axhline(1.0, color="gray", lw=0.8, ls="--")
    ax.set_xlabel("frame")
    ax.set_ylabel("median ratio / mean")
    ax.legend(loc="best")
    return ax
