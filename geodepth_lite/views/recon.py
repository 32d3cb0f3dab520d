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

import base64
import hashlib
import json
import math
from pathlib import Path

import numpy as np

from geodepth_lite import utils
from geodepth_lite.core import camera
from geodepth_lite.core.errors import UserError
from geodepth_lite.core.metrics import median_scale
from geodepth_lite.data import manifest as mf
from geodepth_lite.data import render
from geodepth_lite.data import tube as tube_mod
from geodepth_lite.data.images import encode_png
from geodepth_lite.views import viz

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
    """Write points (+ faces, "Normals", "rgb" point data) as PLY (``ply_bytes``), atomically."""
    path = Path(path)
    utils.write_bytes_atomic(path, ply_bytes(poly, binary))
    return path


def ply_bytes(poly, binary: bool = True) -> bytes:
    """The bytes of points (+ faces, "Normals", "rgb" point data) as a PLY file.

    Vertex properties: x y z (float32), nx ny nz (float32) when present, red green blue
    (uchar) when present; faces as uchar-counted int lists.
    """
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
    parts = [("\n".join(header) + "\nend_header\n").encode("ascii")]
    vert = np.empty(len(pts), dtype=[(name, t) for name, t, _ in cols])
    for name, _, v in cols:
        vert[name] = v
    if binary:
        parts.append(vert.tobytes())
        if len(faces):
            fb = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
            fb["n"], fb["i"] = 3, faces
            parts.append(fb.tobytes())
    else:
        fmt = " ".join("%.9g" if t == "<f4" else "%d" for _, t, _ in cols)
        parts += [(fmt % tuple(row) + "\n").encode("ascii") for row in vert]
        parts += [f"3 {tri[0]} {tri[1]} {tri[2]}\n".encode("ascii") for tri in faces]
    return b"".join(parts)


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


# Lighting of the rendered meshes: a light at the viewer (VTK lights both sides of a surface), enough
# ambient light that a wall turned away is still seen, a diffuse term that shows the relief.
LIGHTING = {"ambient": 0.35, "diffuse": 0.65, "specular": 0.1}
# The interactive view has one light on one side of each triangle (plotly): more ambient light, so
# that the wall's far side, seen when the reader turns the view, stays visible.
PLOTLY_LIGHTING = {"ambient": 0.65, "diffuse": 0.5, "specular": 0.1, "roughness": 0.6, "fresnel": 0.05}
SURFACE_RGB = (222, 160, 140)  # color_by="surface": one tissue tone, so that light alone shows the shape
COLOR_BY = ("image", "depth", "surface")


def depth_clim(poly) -> tuple[float, float]:
    """Colour range of a cloud's or mesh's "depth" point data: its 2nd and 98th percentiles (as 2D maps)."""
    return viz.depth_range(np.asarray(poly.point_data["depth"]))


def _check_color_by(poly, color_by: str) -> str:
    if color_by not in COLOR_BY:
        raise ValueError(f"color_by must be one of {', '.join(COLOR_BY)}, got {color_by!r}")
    if color_by == "image" and "rgb" not in poly.point_data:
        return "depth"  # a cloud without colours: depth is the only colour it has
    return color_by


def _view_frame(poly, reference_pose):
    """Points in the reference camera's frame (the points' own frame without a pose), the 5-95th
    percentile box's centre and its diagonal."""
    if poly.n_points == 0:
        raise ValueError("nothing to render: the cloud or mesh has no points")
    pts = np.asarray(poly.points, dtype=np.float64)
    if reference_pose is not None:
        pts = camera.transform(np.linalg.inv(np.asarray(reference_pose, dtype=np.float64)), pts)
    lo, hi = np.percentile(pts, 5, axis=0), np.percentile(pts, 95, axis=0)
    return pts, 0.5 * (lo + hi), float(np.linalg.norm(hi - lo)) or 1.0


def _view_direction(view: str) -> np.ndarray:
    """Unit viewing direction of ``view``: +z turned by yaw about y, then tilted down by pitch (y is down)."""
    if view not in VIEWS:
        raise ValueError(f"unknown view {view!r}: choose from {', '.join(VIEWS)}")
    yaw, pitch = (math.radians(a) for a in VIEWS[view])
    return np.array([math.sin(yaw) * math.cos(pitch), math.sin(pitch), math.cos(yaw) * math.cos(pitch)])


def render_views(poly, window_size=(360, 360), views=VIEW_NAMES, point_size: float = 3.0, background="white",
                 reference_pose=None, zoom: float = 1.0, color_by: str = "image", clim=None) -> list[np.ndarray]:
    """Headless renders (H x W x 3 uint8) of a cloud or mesh, one per view in ``views`` (Fig. 9).

    Views are set in a camera frame: the points' own frame, or the frame of
    ``reference_pose`` (a 4x4 T_world_cam) for world-frame clouds such as fused sequences.
    color_by: "image" (the "rgb" point data, when present), "depth" (the workbook's depth colours,
    near = bright, clipped to ``clim``, by default :func:`depth_clim`; draw its colour bar with
    ``viz.depth_colorbar``) or "surface" (one tissue tone: the light alone shows the shape).
    Meshes are lit by a light at the viewer (:data:`LIGHTING`); points are not lit.
    """
    color_by = _check_color_by(poly, color_by)
    import pyvista as pv  # VTK: heavy, needed only to build or render meshes

    pts, centre, extent = _view_frame(poly, reference_pose)
    poly = poly.copy()
    poly.points = pts.astype(np.float32)
    if color_by == "image":
        kw = dict(rgb=True, scalars="rgb")
    elif color_by == "depth":
        kw = dict(scalars="depth", cmap=viz.DEPTH_CMAP, clim=depth_clim(poly) if clim is None else clim,
                  show_scalar_bar=False)
    else:
        kw = dict(color=SURFACE_RGB)
    images = []
    for view in views:
        direction = _view_direction(view)
        pl = pv.Plotter(off_screen=True, window_size=list(window_size), lighting="none")
        pl.set_background(background)
        pl.add_light(pv.Light(light_type="headlight", intensity=1.0))
        if poly.n_cells and poly.n_faces:
            pl.add_mesh(poly, smooth_shading=True, ambient=LIGHTING["ambient"], diffuse=LIGHTING["diffuse"],
                        specular=LIGHTING["specular"], specular_power=10.0, **kw)
        else:
            pl.add_points(poly, point_size=point_size, render_points_as_spheres=False, lighting=False, **kw)
        pos = centre - direction * extent * 1.8 / zoom
        pl.camera_position = [tuple(pos), tuple(centre), (0.0, -1.0, 0.0)]
        pl.camera.view_angle = 40.0
        images.append(np.asarray(pl.screenshot(return_img=True))[..., :3].copy())
        pl.close()
    return images


# --------------------------------------------------------------------------- interactive 3D (plotly)
# A view a reader can turn: plotly's figure JSON, which JupyterLab draws through the extension the
# plotly package installs, and which ``plotly_html`` turns into HTML for a static page. Arrays travel
# as base64 typed arrays (compact, exact, the same bytes on every run); plotly itself is needed only
# to draw (its JupyterLab extension, or plotly.js for HTML), not to build the figure.
PLOTLY_MIME = "application/vnd.plotly.v1+json"
MAX_VIEW_POINTS = 20000  # vertices or points one interactive view may carry (about 0.1 MB each in a notebook)


def _typed_array(values, dtype: str) -> dict:
    """plotly's base64 typed array of ``values`` as little-endian ``dtype`` ("f4", "u2", "u4")."""
    a = np.ascontiguousarray(values, dtype=np.dtype("<" + dtype))
    return {"dtype": dtype, "bdata": base64.b64encode(a.tobytes()).decode("ascii")}


def _typed_length(spec: dict) -> int:
    return len(base64.b64decode(spec["bdata"])) // np.dtype(spec["dtype"]).itemsize


def _rgb_strings(rgb) -> list[str]:
    return [f"rgb({r},{g},{b})" for r, g, b in np.asarray(rgb, dtype=np.uint8).tolist()]


def depth_colorscale(n: int = 11) -> list:
    """The workbook's depth colours (``viz.DEPTH_CMAP``, near = bright) as a plotly colour scale."""
    import matplotlib  # heavy, needed only for its colour maps

    cmap = matplotlib.colormaps[viz.DEPTH_CMAP]
    return [[round(t, 4), "rgb({},{},{})".format(*(int(round(255 * c)) for c in cmap(t)[:3]))]
            for t in np.linspace(0.0, 1.0, n).tolist()]


def _trace_3d(poly, pts: np.ndarray, color_by: str, clim, max_points: int, scene: str, colorbar: bool,
              light: dict) -> dict:
    """One plotly trace: a Mesh3d lit from ``light`` (a position) for a mesh, a Scatter3d of markers for a cloud."""
    is_mesh = bool(poly.n_cells and poly.n_faces)
    keep = np.arange(len(pts))
    if len(pts) > max_points:
        if is_mesh:
            raise ValueError(f"the mesh has {len(pts)} vertices, more than max_points={max_points}: "
                             "build it with a larger stride")
        keep = np.unique(np.round(np.linspace(0, len(pts) - 1, max_points)).astype(np.int64))
    xyz = {a: _typed_array(pts[keep, i], "f4") for i, a in enumerate("xyz")}
    if color_by == "depth":
        colour = {"colorscale": depth_colorscale(), "cmin": float(clim[0]), "cmax": float(clim[1]),
                  "showscale": colorbar, "colorbar": {"title": {"text": "z-depth, near = bright<br>(clipped to "
                                                                         f"{clim[0]:.3g}-{clim[1]:.3g})"},
                                                      "len": 0.8}}
        values = _typed_array(np.asarray(poly.point_data["depth"])[keep], "f4")
    else:
        colour = {}
        values = (_rgb_strings(np.asarray(poly.point_data["rgb"])[keep]) if color_by == "image"
                  else "rgb({},{},{})".format(*SURFACE_RGB))
    if is_mesh:
        faces = np.asarray(poly.regular_faces)
        idx = "u2" if len(pts) < 2**16 else "u4"
        trace = {"type": "mesh3d", **xyz, **{a: _typed_array(faces[:, i], idx) for i, a in enumerate("ijk")},
                 "lighting": dict(PLOTLY_LIGHTING), "lightposition": light,
                 "flatshading": False, "hoverinfo": "skip", **colour}
        trace.update({"intensity": values} if color_by == "depth" else
                     {"vertexcolor": values} if color_by == "image" else {"color": values})
        return {**trace, "scene": scene}
    marker = {"size": 2, "color": values, **colour}
    return {"type": "scatter3d", "mode": "markers", **xyz, "marker": marker, "hoverinfo": "skip", "scene": scene}


def figure_3d(panels, color_by: str = "depth", clim=None, reference_pose=None, view: str = "front",
              max_points: int = MAX_VIEW_POINTS, height: int = 420) -> dict:
    """A plotly figure (a JSON-ready dict) of one or more clouds or meshes side by side, to turn and zoom.

    panels: a cloud or mesh, or {title: cloud or mesh}. Meshes are lit by a light behind the
    camera (:data:`LIGHTING`); clouds are markers. color_by as :func:`render_views`; with
    "depth" all panels share one colour range (``clim``, by default :func:`depth_clim` of the
    first panel) and one colour bar that states its clip. Points are shown in the frame of
    ``reference_pose`` (a 4x4 T_world_cam) when given; the camera starts at ``view`` (:data:`VIEWS`).
    A cloud over ``max_points`` is thinned evenly; a mesh over it is refused (build it with a
    larger stride).
    """
    panels = panels if isinstance(panels, dict) else {"": panels}
    if not panels:
        raise ValueError("figure_3d needs at least one cloud or mesh")
    first = next(iter(panels.values()))
    color_by = _check_color_by(first, color_by)
    if color_by == "depth" and clim is None:
        clim = depth_clim(first)
    eye = -_view_direction(view) * 2.2
    n, traces, layout = len(panels), [], {"height": int(height), "margin": {"l": 0, "r": 0, "t": 30, "b": 0},
                                          "showlegend": False, "annotations": []}
    for k, (title, poly) in enumerate(panels.items()):
        pts, centre, _ = _view_frame(poly, reference_pose)
        scene = "scene" if k == 0 else f"scene{k + 1}"
        light = dict(zip("xyz", (centre + eye * 1e4).round(1).tolist()))  # far out where the reader's eye starts
        traces.append(_trace_3d(poly, pts, _check_color_by(poly, color_by), clim, max_points, scene, k == n - 1,
                                light))
        axis = {"showspikes": False}
        layout[scene] = {"domain": {"x": [k / n, (k + 1) / n], "y": [0, 1]}, "aspectmode": "data",
                         "xaxis": axis, "yaxis": axis, "zaxis": axis,
                         "camera": {"eye": dict(zip("xyz", eye.round(4).tolist())), "up": {"x": 0, "y": -1, "z": 0},
                                    "center": {"x": 0, "y": 0, "z": 0}}}
        if title:
            layout["annotations"].append({"text": title, "x": (k + 0.5) / n, "y": 1.0, "xref": "paper",
                                          "yref": "paper", "showarrow": False, "yanchor": "bottom"})
    return {"data": traces, "layout": layout}


class View3D:
    """An interactive 3D view in a notebook: JupyterLab draws its plotly figure through plotly's
    extension (``PLOTLY_MIME``); ``text/plain`` says what it shows where nothing can draw it;
    :meth:`html` gives the HTML for a static page."""

    def __init__(self, figure: dict, summary: str):
        self.figure, self.summary = figure, summary

    def _repr_mimebundle_(self, include=None, exclude=None):
        return {PLOTLY_MIME: self.figure, "text/plain": self.summary}

    def html(self, plotly_js: bool = False) -> str:
        return plotly_html(self.figure, plotly_js)


def view_3d(panels, color_by: str = "depth", **kw) -> View3D:
    """:func:`figure_3d` as a :class:`View3D` whose text says what it shows: panels, sizes, colours."""
    fig = figure_3d(panels, color_by=color_by, **kw)
    parts = []
    for trace, title in zip(fig["data"], panels if isinstance(panels, dict) else [""]):
        n = _typed_length(trace["x"])
        what = (f"mesh of {n} vertices and {_typed_length(trace['i'])} triangles" if trace["type"] == "mesh3d"
                else f"cloud of {n} points")
        parts.append(f"{title + ': ' if title else ''}{what}")
    colour = fig["data"][0].get("marker", fig["data"][0])
    by = (f"coloured by depth ({colour['cmin']:.3g}-{colour['cmax']:.3g}, colour bar)" if "cmin" in colour
          else f"coloured by {color_by}")
    return View3D(fig, f"interactive 3D view ({'; '.join(parts)}), {by}: drag to turn, scroll to zoom")


def plotly_html(figure: dict, plotly_js: bool = False) -> str:
    """HTML that draws ``figure`` with plotly.js, for a page without a Jupyter kernel (a static book).

    plotly_js=True inlines plotly.js (about 4.8 MB, from the plotly package: offline, self-contained;
    once per page is enough); False expects it on the page and waits up to 30 s for ``window.Plotly``.
    The element id is a hash of the figure, so the same figure gives the same bytes.
    """
    text = json.dumps(figure, separators=(",", ":"), sort_keys=True)
    div = "geodepth3d-" + hashlib.sha256(text.encode()).hexdigest()[:12]
    height = int(figure.get("layout", {}).get("height", 420))
    lib = ""
    if plotly_js:
        from plotly.offline import get_plotlyjs  # optional: only pages that carry plotly.js need it

        lib = f"<script type=\"text/javascript\">{get_plotlyjs()}</script>\n"
    safe = text.replace("</", "<\\/")  # no "</script>" inside the script
    draw = (f"(function(){{var fig={safe};"
            f"function draw(){{window.Plotly.newPlot(\"{div}\",fig.data,fig.layout,"
            "{responsive:true,displaylogo:false});}"
            "(function wait(n){if(window.Plotly){draw();}else if(n>0){setTimeout(function(){wait(n-1);},100);}})(300);"
            "})();")
    return (f"<div id=\"{div}\" class=\"geodepth-3d\" style=\"width:100%;height:{height}px;\"></div>\n"
            f"{lib}<script type=\"text/javascript\">{draw}</script>\n")


def save_html(view, path) -> Path:
    """A standalone HTML page of a :class:`View3D` (or a figure dict) with plotly.js inlined: opens
    offline in any browser. Written atomically."""
    figure = view.figure if isinstance(view, View3D) else view
    page = ("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>geodepth-lite 3D view</title></head>\n"
            f"<body>\n{plotly_html(figure, plotly_js=True)}</body></html>\n")
    path = Path(path)
    with utils.atomic_path(path) as tmp:
        Path(tmp).write_text(page, encoding="utf-8")
    return path


def show(poly, interactive: bool = False, titles=None, **kw):
    """Show a cloud or mesh in a notebook: an interactive :class:`View3D` (returned; ``kw`` go to
    :func:`view_3d`), else the two static views of :func:`render_views` side by side (matplotlib)."""
    if interactive:
        return view_3d(poly, **kw)
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

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
    """Write an H x W x 3 uint8 array as PNG (``images.encode_png``), atomically."""
    path = Path(path)
    utils.write_bytes_atomic(path, encode_png(image))
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
        raise UserError(f"organ {organ!r} is not in manifest {manifest} (has {', '.join(m['organ_presets'])})")
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
