"""Figures: colorized depth, sample grids (paper Fig. 3), depth histograms, shape-index maps (Fig. 5), 3D views.

Everything returns numpy images or matplotlib figures; nothing needs a display.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter

from geodepth_lite.core import camera as cam
from geodepth_lite.core.metrics import EVAL_MAX_DEPTH, EVAL_MIN_DEPTH, eval_mask

DEPTH_CMAP = "magma_r"  # the workbook's one depth convention: near = bright, far = dark (as the paper's figures)
ERROR_CMAP = "inferno"  # error maps: 0 = black, large = bright
CBAR = dict(fraction=0.046, pad=0.02)  # colour bars as tall as their panel

# Readable figure text: the notebooks draw inline figures at FIGURE_DPI pixels per inch, and the web book
# shows a figure at most BOOK_COLUMN_PX wide (its text column at a 1366 px screen), scaled down when
# wider; every text of a figure should then be at least MIN_TEXT_PX pixels tall (readable_pt).
FIGURE_DPI = 100
BOOK_COLUMN_PX = 800
MIN_TEXT_PX = 8.0


def shown_scale(fig_width_in: float) -> float:
    """How much the book scales a figure ``fig_width_in`` inches wide (1 when it fits its column)."""
    return min(1.0, BOOK_COLUMN_PX / (fig_width_in * FIGURE_DPI))


def readable_pt(fig_width_in: float, px: float = MIN_TEXT_PX, least: float = 0.0) -> float:
    """The least font size (points, in half points) whose text is ``px`` pixels tall as the book shows a
    figure ``fig_width_in`` inches wide, and at least ``least`` points (a narrow figure keeps its size)."""
    return max(least, math.ceil(2 * px * 72 / (FIGURE_DPI * shown_scale(fig_width_in))) / 2)


def text_heights_px(fig) -> list[tuple[str, float]]:
    """(text, pixels tall as the book shows the figure) of every visible, non-empty text of ``fig``
    (titles, labels, tick labels, colour bars' captions and ticks), least first."""
    fig.draw_without_rendering()  # tick labels exist once drawn
    scale = shown_scale(fig.get_figwidth())
    texts = fig.findobj(lambda a: hasattr(a, "get_text") and hasattr(a, "get_fontsize"))
    out = [(t.get_text(), t.get_fontsize() * FIGURE_DPI / 72 * scale) for t in texts
           if t.get_visible() and t.get_text().strip()]
    return sorted(out, key=lambda x: x[1])


def colorize_depth(depth, vmin=None, vmax=None, cmap: str = "magma") -> np.ndarray:
    """H x W depth -> H x W x 3 uint8 through a matplotlib colormap, reversed so that near = bright
    (the workbook's convention, :data:`DEPTH_CMAP`; :func:`relative_depth_colorbar` is its colour bar).

    vmin/vmax default to the 2nd/98th percentiles of the valid (finite, > 0) pixels;
    invalid pixels are black: NaN marks pixels outside an endoscope's field of view (``predict``),
    which thus neither get a colour nor move the range. Accepts numpy or torch (1 x H x W or H x W).
    """
    import matplotlib  # heavy, needed only for its colour maps

    d = depth.detach().cpu().numpy() if hasattr(depth, "detach") else np.asarray(depth)
    d = np.squeeze(d).astype(np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be H x W (or 1 x H x W), got shape {np.shape(depth)}")
    valid = np.isfinite(d) & (d > 0)
    if valid.any():
        lo = np.percentile(d[valid], 2) if vmin is None else float(vmin)
        hi = np.percentile(d[valid], 98) if vmax is None else float(vmax)
    else:
        lo, hi = 0.0, 1.0
    t = np.clip((d - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    rgba = matplotlib.colormaps[cmap](1.0 - t)  # near = bright, as in the paper's figures
    out = (rgba[..., :3] * 255.0 + 0.5).astype(np.uint8)
    out[~valid] = 0
    return out


def depth_range(depth, lo_pct: float = 2.0, hi_pct: float = 98.0) -> tuple[float, float]:
    """The 2nd and 98th percentiles of the valid (finite, > 0) pixels: the default colour range."""
    d = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    if not valid.any():
        return 0.0, 1.0
    return float(np.percentile(d[valid], lo_pct)), float(np.percentile(d[valid], hi_pct))


def show_depth(ax, depth, vmin=None, vmax=None, *, label: str = "z-depth", colorbar: bool = True,
               bad: str = "black"):
    """Draw a depth map in the workbook's convention (:data:`DEPTH_CMAP`, near = bright) with a colour
    bar that states its clip: the 2nd-98th percentile by default, else ``vmin``-``vmax``.
    Invalid pixels (not finite, <= 0; NaN outside an endoscope's field of view) are drawn in the
    colour ``bad`` and never enter the range. Returns the image artist."""
    import matplotlib  # heavy, needed only for its colour maps

    d = np.squeeze(np.asarray(depth, dtype=np.float64))
    auto = vmin is None and vmax is None
    lo, hi = depth_range(d)
    vmin, vmax = (lo if vmin is None else float(vmin)), (hi if vmax is None else float(vmax))
    cmap = matplotlib.colormaps[DEPTH_CMAP].with_extremes(bad=bad)
    im = ax.imshow(np.ma.masked_where(~(np.isfinite(d) & (d > 0)), d), cmap=cmap, vmin=vmin, vmax=vmax)
    ax.set_xticks([]), ax.set_yticks([])
    if colorbar:
        cb = ax.figure.colorbar(im, ax=ax, extend="both", **CBAR)
        clip = "2nd-98th percentile" if auto else f"{vmin:.3g}-{vmax:.3g}"
        pt = readable_pt(ax.figure.get_figwidth(), least=7.0)
        cb.set_label(f"{label}, near = bright\n(clipped to {clip})", fontsize=pt)
        cb.ax.tick_params(labelsize=pt)
    return im


def show_error(ax, err, vmax: float, *, label: str = "Abs Rel error"):
    """Draw an error map (:data:`ERROR_CMAP`, NaN = black) with a colour bar clipped at ``vmax``,
    the clip written on the bar. Returns the image artist."""
    import matplotlib  # heavy, needed only for its colour maps

    cmap = matplotlib.colormaps[ERROR_CMAP].with_extremes(bad="black")
    im = ax.imshow(np.ma.masked_invalid(np.asarray(err, dtype=np.float64)), cmap=cmap, vmin=0, vmax=vmax)
    ax.set_xticks([]), ax.set_yticks([])
    cb = ax.figure.colorbar(im, ax=ax, extend="max", **CBAR)
    pt = readable_pt(ax.figure.get_figwidth(), least=7.0)
    cb.set_label(f"{label}\n(clipped at {vmax:g})", fontsize=pt)
    cb.ax.tick_params(labelsize=pt)
    return im


RELATIVE_LABEL = "depth, each panel from its own\n2nd (near) to 98th (far) percentile"


def relative_depth_colorbar(fig, axes, label: str = RELATIVE_LABEL):
    """One colour bar for panels drawn with :func:`colorize_depth` (each scaled to its own range)."""
    import matplotlib  # heavy, needed only for its colour maps

    sm = matplotlib.cm.ScalarMappable(norm=matplotlib.colors.Normalize(0, 1), cmap=DEPTH_CMAP)
    cb = fig.colorbar(sm, ax=axes, extend="both", fraction=0.03, pad=0.02, ticks=[0, 1])
    pt = readable_pt(fig.get_figwidth(), least=7.0)
    cb.ax.set_yticklabels(["near", "far"], fontsize=pt)
    cb.set_label(label, fontsize=pt)
    return cb


# ----------------------------------------------------------------------------- shape index (Fig. 5)


def principal_curvatures(points: np.ndarray, valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Principal curvatures k1 <= k2 (1/scene units) of a surface given as an H x W x 3 point grid.

    From the first and second fundamental forms with central differences over the
    pixel grid: E, F, G from the tangents X_u, X_v; e, f, g from the second derivatives
    along the unit normal n = X_u x X_v / |X_u x X_v| oriented away from the camera
    (n_z > 0, into the tissue), so a bump towards the camera (a cap) has positive
    curvatures and a pocket (a cup) negative ones.
    Pixels next to invalid ones (or the border) are NaN.
    """
    P = np.asarray(points, dtype=np.float64)
    Xu = 0.5 * (np.roll(P, -1, 1) - np.roll(P, 1, 1))
    Xv = 0.5 * (np.roll(P, -1, 0) - np.roll(P, 1, 0))
    Xuu = np.roll(P, -1, 1) - 2 * P + np.roll(P, 1, 1)
    Xvv = np.roll(P, -1, 0) - 2 * P + np.roll(P, 1, 0)
    Xuv = 0.25 * (np.roll(np.roll(P, -1, 0), -1, 1) - np.roll(np.roll(P, -1, 0), 1, 1)
                  - np.roll(np.roll(P, 1, 0), -1, 1) + np.roll(np.roll(P, 1, 0), 1, 1))
    n = np.cross(Xu, Xv)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-30
    n *= np.sign(n[..., 2:3] + 1e-30)  # away from the camera
    E, F, G = (Xu * Xu).sum(-1), (Xu * Xv).sum(-1), (Xv * Xv).sum(-1)
    e, f, g = (Xuu * n).sum(-1), (Xuv * n).sum(-1), (Xvv * n).sum(-1)
    denom = E * G - F * F
    with np.errstate(divide="ignore", invalid="ignore"):
        K = (e * g - f * f) / denom
        H = (e * G - 2 * f * F + g * E) / (2 * denom)
        disc = np.sqrt(np.clip(H * H - K, 0.0, None))
        k1, k2 = H - disc, H + disc
    bad = np.zeros(P.shape[:2], dtype=bool)
    bad[0, :] = bad[-1, :] = bad[:, 0] = bad[:, -1] = True
    if valid is not None:
        v = np.asarray(valid, dtype=bool)
        near_bad = ~v
        for ax, sh in ((0, 1), (0, -1), (1, 1), (1, -1)):
            near_bad |= ~np.roll(v, sh, ax)
        bad |= near_bad
    k1[bad] = np.nan
    k2[bad] = np.nan
    return k1, k2


def shape_index(depth: np.ndarray, K: np.ndarray, smooth: float = 1.0, max_step: float = 0.1) -> np.ndarray:
    """Koenderink's shape index S = (2/pi) arctan((k2 + k1) / (k2 - k1)) of a depth map (paper Fig. 5).

    The depth (H x W z-depth) is back-projected with ``camera.backproject`` and, if
    ``smooth`` > 0, Gaussian-smoothed (sigma in pixels) to suppress pixel noise.
    S lies in [-1, 1]: -1 cup (diverticulum), -0.5 rut, 0 saddle, +0.5 ridge (folds,
    rugae), +1 cap (polyp, papilla), with curvature signs seen from the camera.
    Occlusion edges (a relative depth step above ``max_step`` between neighbours) are not
    surfaces: they are excluded like invalid pixels, and smoothing does not cross them.
    Undefined (umbilic planes, excluded pixels) -> NaN.
    """
    d = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    dd = np.where(valid, d, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        for ax in (0, 1):
            a, b = np.delete(dd, -1, axis=ax), np.delete(dd, 0, axis=ax)
            edge = ~(np.abs(a - b) <= max_step * np.minimum(a, b))  # NaN neighbours count as edges
            before, after = [(0, 0), (0, 0)], [(0, 0), (0, 0)]
            before[ax], after[ax] = (0, 1), (1, 0)
            valid &= ~np.pad(edge, before) & ~np.pad(edge, after)
    if smooth > 0:
        w = gaussian_filter(valid.astype(np.float64), smooth)
        d = np.where(valid, gaussian_filter(np.where(valid, d, 0.0), smooth) / np.maximum(w, 1e-12), 0.0)
    pts = cam.backproject(d, K)
    k1, k2 = principal_curvatures(pts, valid)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (2.0 / math.pi) * np.arctan((k2 + k1) / (k2 - k1))
    return s


# ----------------------------------------------------------------------------- figures


def sample_grid(cells: list[list[tuple]], row_labels: list[str], col_labels: list[str], *, cmap: str = "magma",
                cell_inches: float = 1.6):
    """Paper Fig. 3 style grid: for every (row, column) cell an RGB frame above its depth map.

    cells[r][c] = (rgb H x W x 3 uint8, depth H x W). Returns the matplotlib figure.
    """
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    n_rows, n_cols = len(cells), len(cells[0])
    fig, axes = plt.subplots(2 * n_rows, n_cols, figsize=(cell_inches * n_cols, 2 * cell_inches * n_rows),
                             squeeze=False)
    pt = readable_pt(fig.get_figwidth(), least=8.0)
    for r, row in enumerate(cells):
        for c, (rgb, depth) in enumerate(row):
            axes[2 * r, c].imshow(rgb)
            axes[2 * r + 1, c].imshow(colorize_depth(depth, cmap=cmap))
            if r == 0:
                axes[0, c].set_title(col_labels[c], fontsize=pt)
        axes[2 * r, 0].set_ylabel(f"{row_labels[r]}\nRGB", fontsize=pt)
        axes[2 * r + 1, 0].set_ylabel("depth", fontsize=pt)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    relative_depth_colorbar(fig, axes[1::2].ravel().tolist())
    return fig


def depth_histogram(depths: dict, bins: int = 50, ax=None, log: bool = True):
    """Histograms of valid depth values (> 0), one per label: {label: array of depths}. Returns the axes."""
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    if ax is None:
        _, ax = plt.subplots(figsize=(5, 3))
    values = {k: np.asarray(v, dtype=np.float64).ravel() for k, v in depths.items()}
    values = {k: v[np.isfinite(v) & (v > 0)] for k, v in values.items()}
    hi = max(float(v.max()) for v in values.values() if len(v))
    edges = np.geomspace(0.05, hi * 1.05, bins + 1) if log else np.linspace(0.0, hi * 1.05, bins + 1)
    for label, v in values.items():
        ax.hist(v, bins=edges, histtype="step", density=True, label=label, linewidth=1.4)
    if log:
        ax.set_xscale("log")
    ax.set_xlabel("z-depth (scene units)")
    ax.set_ylabel("density")
    ax.legend(fontsize=readable_pt(ax.figure.get_figwidth(), least=8.0))
    return ax


SHAPE_CLASSES = (  # Koenderink's scale as in the paper's Fig. 5 (upper bounds of each class)
    (-5 / 8, "cup"), (-3 / 8, "rut"), (-1 / 8, "saddle rut"), (1 / 8, "saddle"),
    (3 / 8, "saddle ridge"), (5 / 8, "ridge"), (1.0, "cap"),
)


def shape_index_classes(si: np.ndarray) -> dict:
    """Fraction of defined pixels in each shape class of Fig. 5 (cup ... cap)."""
    s = si[np.isfinite(si)]
    out, lo = {}, -1.0 - 1e-9
    for hi, name in SHAPE_CLASSES:
        out[name] = float(np.mean((s > lo) & (s <= hi))) if len(s) else 0.0
        lo = hi
    return out


def plot_shape_index(rgb, depth, si, axes=None):
    """RGB, depth and its shape-index map side by side (cup = blue ... cap = red). Returns the figure."""
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    if axes is None:
        fig, axes = plt.subplots(1, 3, figsize=(10, 3.4))
    else:
        fig = axes[0].figure
    axes[0].imshow(rgb)
    axes[0].set_title("RGB")
    axes[1].imshow(colorize_depth(depth))
    axes[1].set_title("depth")
    im = axes[2].imshow(np.ma.masked_invalid(si), cmap="RdBu_r", vmin=-1, vmax=1)
    axes[2].set_title("shape index")
    cb = fig.colorbar(im, ax=axes[2], ticks=[-1, -0.5, 0, 0.5, 1], fraction=0.046)
    cb.ax.set_yticklabels(["cup", "rut", "saddle", "ridge", "cap"])
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    return fig


def tube_view(tube, poses=(), size=(800, 320), frustum: float | None = None, camera_position=None,
              connect: bool = False) -> np.ndarray:
    """Off-screen 3D view of a tube mesh (cut open) with the centerline and camera poses; H x W x 3 uint8.

    poses: T_world_cam matrices (OpenCV frame); each is drawn as a small frustum
    (length ``frustum``, default 0.3 x radius); ``connect`` joins their centres (a camera path).
    The half of the wall facing the viewer is clipped away so the lumen is visible.
    """
    import pyvista as pv  # VTK: heavy, needed only to build or render meshes
    import vtk  # VTK: heavy, needed only for the 3D view

    vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
    R = float(tube.preset["radius"])
    frustum = 0.3 * R if frustum is None else frustum
    pts = tube.points
    centre = pts.mean(axis=0)
    # viewing direction: perpendicular to the tube's overall direction
    axis = pts[-1] - pts[0]
    axis /= np.linalg.norm(axis)
    side = np.cross(axis, [0.0, 1.0, 0.0] if abs(axis[1]) < 0.9 else [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    pl = pv.Plotter(off_screen=True, window_size=list(size))
    try:
        pl.set_background("white")
        mesh = tube.mesh.copy()
        radial = mesh.points - tube.centerline(mesh.point_data["s"].astype(np.float64))
        mesh.point_data["facing"] = radial @ side  # > 0: the half of the wall between viewer and lumen
        cut = mesh.clip_scalar(scalars="facing", value=0.0, invert=True)
        pl.add_mesh(cut, color=(0.85, 0.55, 0.5), smooth_shading=True, specular=0.3)
        pl.add_mesh(pv.lines_from_points(pts), color="black", line_width=2)
        if len(poses):
            centres = np.array([np.asarray(T)[:3, 3] for T in poses])
            if connect and len(centres) > 1:
                pl.add_mesh(pv.lines_from_points(centres), color="royalblue", line_width=3)
            for T in poses:
                T = np.asarray(T)
                o = T[:3, 3]
                corners = [o + frustum * (T[:3, 2] + a * 0.6 * T[:3, 0] + b * 0.6 * T[:3, 1])
                           for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
                lines = ([np.array([o, c]) for c in corners]
                         + [np.array([corners[k], corners[(k + 1) % 4]]) for k in range(4)])
                for seg in lines:
                    pl.add_mesh(pv.lines_from_points(seg), color="navy", line_width=2)
        length = float(np.linalg.norm(pts[-1] - pts[0]))
        pos = centre + side * length if camera_position is None else np.asarray(camera_position)
        up = np.cross(side, axis)
        pl.camera_position = [tuple(pos), tuple(centre), tuple(up)]
        if camera_position is None:
            pl.reset_camera()
            pl.camera.zoom(1.15)
        img = pl.screenshot(return_img=True)
    finally:
        pl.close()
    return np.asarray(img)[..., :3].copy()


# ----------------------------------------------------------------------------- error maps (Fig. 7), border maps


def abs_rel_map(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None, min_depth: float = EVAL_MIN_DEPTH,
                max_depth: float = EVAL_MAX_DEPTH) -> np.ndarray:
    """Per-pixel |gt - pred| / gt (NaN outside the valid mask) of a median-scaled prediction."""
    mask = eval_mask(gt, min_depth, max_depth, valid)
    err = np.abs(gt - np.clip(pred, min_depth, max_depth)) / np.where(mask, gt, 1.0)
    return np.where(mask, err, np.nan)


def error_map_figure(examples: list[dict], columns: tuple[str, ...] = ("input", "ground truth", "prediction", "error"),
                     min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH, err_max: float = 0.5,
                     row_labels: list[str] | None = None):
    """The paper's Fig. 7 layout: one row per frame, input | GT | (median-scaled) prediction | Abs Rel map.

    Each example: {"image": HxWx3 in [0,1], "gt": HxW, "pred": HxW already median-scaled,
    optional "preds": {label: HxW} for extra prediction columns (ablation), "valid"}.
    """
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    extra = list(examples[0].get("preds", {}))
    cols = ["input", "ground truth"] + (extra if extra else ["prediction"]) + (["error"] if "error" in columns else [])
    fig, axes = plt.subplots(len(examples), len(cols), figsize=(2.2 * len(cols), 2.2 * len(examples)), squeeze=False)
    for i, ex in enumerate(examples):
        gt = ex["gt"]
        finite = gt[np.isfinite(gt) & (gt > min_depth)]
        vmin, vmax = (np.percentile(finite, 2), np.percentile(finite, 98)) if finite.size else (0, 1)
        preds = ex.get("preds") or {"prediction": ex["pred"]}
        panels = [("input", ex["image"]), ("ground truth", gt), *preds.items()]
        if "error" in cols:
            last = list(preds.values())[-1]
            panels.append(("Abs Rel error", abs_rel_map(last, gt, ex.get("valid"), min_depth, max_depth)))
        for j, (title, img) in enumerate(panels):
            ax = axes[i, j]
            if title == "input":
                ax.imshow(np.clip(img, 0, 1)), ax.set_xticks([]), ax.set_yticks([])
            elif title == "Abs Rel error":
                show_error(ax, img, err_max)
            else:  # depth panels share the ground truth's range; the last one carries the colour bar
                show_depth(ax, img, vmin, vmax, colorbar=j == len(preds) + 1)
            if i == 0:
                ax.set_title(title, fontsize=readable_pt(fig.get_figwidth(), least=9.0))
        if row_labels:
            axes[i, 0].set_ylabel(row_labels[i], fontsize=readable_pt(fig.get_figwidth(), least=8.0))
    fig.tight_layout()
    return fig


def border_map_figure(maps: dict, title: str = ""):
    """Two panels of ``border.border_error_map``'s result: the mean signed log error (diverging colours)
    and the mean |log error| per pixel."""
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    fig, axes = plt.subplots(1, 2, figsize=(8.4, 3.6))
    lim = float(np.nanmax(np.abs(maps["signed"]))) or 1.0
    im = axes[0].imshow(maps["signed"], cmap="RdBu_r", vmin=-lim, vmax=lim)
    axes[0].set_title("mean signed log error\n(red: too far, blue: too near)")
    pt = readable_pt(fig.get_figwidth(), least=8.0)
    fig.colorbar(im, ax=axes[0], fraction=0.046).set_label("log(pred / gt), mean over frames", fontsize=pt)
    im = axes[1].imshow(maps["abs"], cmap=ERROR_CMAP, vmin=0)
    ratios = ", ".join(f"{k} {v:.2f}" for k, v in maps["ratios"].items())
    axes[1].set_title(f"mean |log error|\nborder / centre: {ratios}", fontsize=pt + 1)
    fig.colorbar(im, ax=axes[1], fraction=0.046).set_label("|log(pred / gt)|, mean over frames", fontsize=pt)
    for ax in axes:
        ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def depth_colorbar(fig, axes, vmin: float, vmax: float, *, label: str = "z-depth"):
    """The colour bar of 3D views coloured by depth (``recon.render_views(color_by="depth")`` with
    ``clim=(vmin, vmax)``): the workbook's colours (:data:`DEPTH_CMAP`, near = bright), the clip
    written on the bar."""
    import matplotlib  # heavy, needed only for its colour maps

    sm = matplotlib.cm.ScalarMappable(norm=matplotlib.colors.Normalize(vmin, vmax), cmap=DEPTH_CMAP)
    cb = fig.colorbar(sm, ax=axes, extend="both", fraction=0.046, pad=0.02)
    pt = readable_pt(fig.get_figwidth(), least=7.0)
    cb.set_label(f"{label}, near = bright\n(clipped to {vmin:.3g}-{vmax:.3g})", fontsize=pt)
    cb.ax.tick_params(labelsize=pt)
    return cb
