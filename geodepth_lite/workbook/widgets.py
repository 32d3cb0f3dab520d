"""The interactive loss explorer of notebook 03: perturb a ground-truth depth map, watch the five losses.

A "prediction" is made from a ground-truth depth map by six perturbations, each a kind of
error a depth network makes (:func:`perturb`). :func:`loss_report` computes the five losses of
Sec. 3.C with :mod:`geodepth_lite.core.losses` (the same code that trains the network) and their
per-pixel maps; :func:`draw` draws them with the SDF grid slices (:class:`ExplorerFigure`);
:func:`explorer` wires sliders to one reused figure in a live Jupyter frontend
(:class:`LiveExplorer`) and falls back to a static figure where there is none (papermill,
nbval, nbconvert).
"""

from __future__ import annotations

import base64
import html
import io
import os
import threading
import time

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from geodepth_lite.core import losses
from geodepth_lite.data.datasets import SyntheticDepthDataset
from geodepth_lite.data.synth import ensure_dataset
from geodepth_lite.views.viz import DEPTH_CMAP, readable_pt

# slider name -> (min, max, step, neutral value, what it imitates)
PERTURBATIONS = {
    "blur": (0.0, 4.0, 0.25, 0.0, "Gaussian blur sigma (pixels): washed-out stepped edges"),
    "ripple": (0.0, 0.1, 0.005, 0.0, "ripple amplitude (fraction of depth), period 6 px: small structures"),
    "scale": (0.5, 1.5, 0.05, 1.0, "global scale factor: a wrong size of the lumen"),
    "tilt": (-0.5, 0.5, 0.05, 0.0, "depth tilt across the image (fraction of median depth): a wrong wall slope"),
    "offset": (-1.0, 1.0, 0.05, 0.0, "constant offset (scene units): the whole scene too near/far"),
    "noise": (0.0, 0.1, 0.005, 0.0, "per-pixel noise (fraction of depth): speckle"),
}
RIPPLE_PERIOD = 6.0  # pixels per ripple
MAP_TERMS = ("depth", "smooth", "grad", "normal")  # the terms drawn as per-pixel maps (the SDF is a 3D field)
READOUT_FORMAT = ".3f"  # every slider's number (d3 format) and the figure's title: each step above shows exactly
STATIC_FIGSIZE = (15, 6.2)  # inches of draw()'s figure (the notebook's static outputs)
LIVE_FIGSIZE = (12.8, 4.9)  # inches of the live figure: with the sliders it fits a 1400 x 1000 laptop window
LIVE_DPI = 90  # pixels per inch of the live figure's PNG (1152 x 441 px)
BUSY_HTML = '<span style="color:#b35c00"><b>&#8987; computing...</b></span>'
DEAD_TEXT = ("The kernel has stopped, so the sliders no longer change this figure: re-run this cell "
             "(after the cells above it) to use the explorer again.")  # shown instead of the sliders
# How the live explorer looks in JupyterLab (and Notebook 7) when its kernel is gone. ipywidgets marks
# the views of a restarted kernel's widgets with the class jupyter-widgets-disconnected (and a red
# broken-link sign, kept on the outer box only): the sliders and the status line then hide and DEAD_TEXT
# shows above the last figure. After a reload the widget's model is gone: the widget output (a Lumino
# panel saying "Error displaying widget: model not found") hides and the static copy of the figure
# saved beside it shows instead (hidden while the live explorer is in the same cell's output).
EXPLORER_CSS = """
.geodepth-explorer-dead { display: none; }
.geodepth-explorer.jupyter-widgets-disconnected .geodepth-explorer-controls { display: none; }
.geodepth-explorer.jupyter-widgets-disconnected .geodepth-explorer-dead { display: block; }
.jp-OutputArea:has(.geodepth-explorer) .geodepth-explorer-static { display: none; }
.geodepth-explorer .jupyter-widgets-disconnected::before { display: none; }
.jp-OutputArea:has(.geodepth-explorer-static)
  .jp-OutputArea-child:has(> .jp-OutputArea-output.lm-Panel):not(:has(.geodepth-explorer)) { display: none; }
"""


def example_frame(size: int = 128, index: int = 0, progress: bool = False) -> dict:
    """One frame (ground truth H x W, image 3 x H x W, K, organ) of a small synthetic set at ``size``.

    Built once with ``synth.ensure_dataset("scenario_smoke")`` at the requested resolution
    (a few seconds), then read from disk.
    """
    if size % 32 or size < 32:
        raise ValueError(f"frame size must be a positive multiple of 32, got {size}")
    n = 6
    if not 0 <= index < n:
        raise ValueError(f"frame index must be between 0 and {n - 1}, got {index}")
    overrides = {"camera": {"width": size, "height": size}, "splits": {"train": n, "val": 1, "test": 1},
                 "seed": 1, "frames_per_scene": 2}  # pinned: the notebook's frames stay the same
    item = SyntheticDepthDataset(ensure_dataset("scenario_smoke", overrides=overrides, progress=progress),
                                 "train")[index]
    return {"gt": item["depth"][0].numpy().astype(np.float64), "image": item["image"].numpy(),
            "K": item["K"].numpy().astype(np.float64), "organ": item["organ"]}


def neutral() -> dict:
    """Perturbation settings that leave the depth map unchanged."""
    return {k: v[3] for k, v in PERTURBATIONS.items()}


def perturb(gt: np.ndarray, *, blur=0.0, ripple=0.0, scale=1.0, tilt=0.0, offset=0.0, noise=0.0, seed=0) -> np.ndarray:
    """A prediction made from the H x W ground truth ``gt`` by the errors of :data:`PERTURBATIONS`.

    Applied in order: blur, ripple, scale, tilt, offset, noise; clipped to >= 0.01 (the network's
    smallest depth).
    """
    gt = np.asarray(gt, dtype=np.float64)
    H, W = gt.shape
    d = gaussian_filter(gt, sigma=blur, mode="nearest") if blur > 0 else gt.copy()
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    if ripple:
        k = 2 * np.pi / RIPPLE_PERIOD
        d = d * (1.0 + ripple * np.sin(k * u) * np.sin(k * v))
    d = d * scale
    med = float(np.median(gt))
    d = d + tilt * med * (u - (W - 1) / 2) / W
    d = d + offset
    if noise:
        d = d * (1.0 + noise * np.random.default_rng(seed).standard_normal(d.shape))
    return np.maximum(d, 0.01)


def _t(a) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a, dtype=np.float64))[None, None]


def loss_report(pred: np.ndarray, gt: np.ndarray, image: np.ndarray, K, grid: int = 16) -> dict:
    """The five loss values and their per-pixel maps (H x W numpy; the last row and column of the
    smoothness, gradient and normal maps are NaN: forward differences need a neighbour).

    image: H x W x 3 or 3 x H x W in [0, 1]. Also returns the SDF fields on the r^3 grid
    ("sdf_gt", "sdf_pred", shape r x r x r, axes x, y, z) and the grid bounds. The ground
    truth's field comes from ``geodepth_lite.core.sdf.GT_FIELD_CACHE`` after the first call for a frame, so a
    call searches the prediction's field only, once (the SDF loss is the mean of the fields'
    difference, as :func:`geodepth_lite.core.losses.sdf_loss` computes it).
    """
    image = np.asarray(image, dtype=np.float64)
    if image.shape[-1] == 3 and image.shape[0] != 3:
        image = image.transpose(2, 0, 1)
    p, g, img = _t(pred), _t(gt), torch.as_tensor(image)[None]
    H, W = gt.shape
    options = losses.SDFOptions(grid=grid)  # the paper's term on this grid, the ground truth's field cached
    r = options.grid
    inputs = losses.LossInputs(gt=g, image=img, K=torch.as_tensor(np.asarray(K, dtype=np.float64)),
                               spec=losses.LossSpec(sdf=options))
    fields = losses.sdf_fields(p, g, K, options)[0]
    out = {name: float(term.fn(p, inputs)) for name, term in losses.LOSS_TERMS.items()  # every term, by name
           if name != "sdf"}  # the SDF term from the fields below: one nearest-point search, not two
    out["sdf"] = float((torch.stack([fields["pred"]]) - torch.stack([fields["gt"]])).abs().mean())
    # per-pixel maps from the losses' own map functions (the loss is their mean)
    maps = {k: np.full((H, W), np.nan) for k in MAP_TERMS}
    maps["depth"] = np.abs(pred - gt)
    sx, sy = losses.smoothness_maps(p, img)  # (1, 1, H, W-1), (1, 1, H-1, W)
    maps["smooth"][:-1, :-1] = (sx[0, 0, :-1, :] + sy[0, 0, :, :-1]).numpy()
    (gx, _), (gy, _) = losses.gradient_maps(p, g)
    maps["grad"][:-1, :-1] = (gx[0, 0, :-1, :] + gy[0, 0, :, :-1]).numpy()
    maps["normal"][:-1, :-1] = losses.normal_map(p, g)[0][0, 0].numpy()
    out["maps"] = maps
    out["sdf_gt"] = fields["gt"].reshape(r).numpy()
    out["sdf_pred"] = fields["pred"].reshape(r).numpy()
    out["lower"], out["upper"] = fields["lower"].numpy(), fields["upper"].numpy()
    return out


def _vmax(a, floor: float = 1e-3) -> float:
    """Colour-scale top for an error map: its maximum, but at least ``floor`` (zero maps stay dark)."""
    m = float(np.nanmax(a)) if np.isfinite(a).any() else 0.0
    return max(m, floor)


def format_losses(rep: dict) -> str:
    """One line with the five loss values."""
    return "  ".join(f"{k} {rep[k]:.4f}" for k in losses.term_names())


def format_value(value: float) -> str:
    """A perturbation value as the sliders show it (:data:`READOUT_FORMAT`, fixed point): "0.250"."""
    return format(float(value), READOUT_FORMAT)


def describe(settings: dict) -> str:
    """The figure's title: the perturbations that differ from neutral, in the sliders' number format."""
    changed = [f"{k}={format_value(v)}" for k, v in settings.items() if v != PERTURBATIONS[k][3]]
    return "prediction = ground truth with " + (", ".join(changed) or "no perturbation")


def _panels(gt, image, pred, rep: dict) -> list[tuple]:
    """The figure's ten panels in order, as (array, title, colour map, vmin, vmax, colour bar label);
    the last three are x-z slices (x along the first axis) through the middle of the SDF grid. The
    prediction's depth and SDF use the ground truth's colour range and clip to it: their labels say
    so (and their colour bars end in arrows, :data:`CLIPPED`)."""
    img = np.asarray(image)
    img = img.transpose(1, 2, 0) if img.shape[0] == 3 else img
    vmin, vmax = float(np.min(gt)), float(np.max(gt))
    maps = [
        (rep["maps"]["depth"], f"|D - D_gt|: depth {rep['depth']:.3f}"),
        (rep["maps"]["smooth"][:-1, :-1], f"smoothness {rep['smooth']:.4f}"),
        (rep["maps"]["grad"][:-1, :-1], f"|grad diff|: gradient {rep['grad']:.3f}"),
        (rep["maps"]["normal"][:-1, :-1], f"1 - cos: normal {rep['normal']:.4f}"),
    ]
    j = rep["sdf_gt"].shape[1] // 2
    lim = float(np.nanmax(np.abs(rep["sdf_gt"][:, j, :])))
    diff = np.abs(rep["sdf_pred"] - rep["sdf_gt"])[:, j, :]
    return [
        (img, "image", None, None, None, None),
        (gt, "ground truth depth (near = bright)", DEPTH_CMAP, vmin, vmax, "depth"),
        (pred, "prediction", DEPTH_CMAP, vmin, vmax, f"clipped to {vmin:.3g}..{vmax:.3g}"),
        *[(a, t, "viridis", 0.0, _vmax(a), None) for a, t in maps],
        (rep["sdf_gt"][:, j, :], "SDF of ground truth (x-z slice)", "RdBu", -lim, lim, "signed distance"),
        (rep["sdf_pred"][:, j, :], "SDF of prediction", "RdBu", -lim, lim,
         f"clipped to \u00b1{lim:.3g}"),
        (diff, f"|SDF diff|: sdf {rep['sdf']:.3f}", "viridis", 0.0, _vmax(diff), None),
    ]


class ExplorerFigure:
    """The explorer's figure, built once; :meth:`update` changes its image data, colour limits,
    titles and the prediction's 0-contour only (no new axes, colour bars or layout).

    Row 1: image, ground truth, prediction, per-pixel depth and smoothness terms.
    Row 2: per-pixel gradient and normal terms, and the x-z slice through the middle of the
    SDF grid for ground truth, prediction and their absolute difference (0-contour = surface).
    """

    SDF_PANELS = (7, 8, 9)  # indices of the SDF slices among the ten panels
    CLIPPED = (2, 8)  # panels drawn in the ground truth's fixed colour range: values beyond it are clipped
    CHANGING = (2, 3, 4, 5, 6, 8, 9)  # panels whose data and title follow the sliders
    RESCALED = (3, 4, 5, 6, 9)  # panels whose colour limits follow the data (their colour bars are redrawn)

    def __init__(self, fig, gt, image, pred, rep: dict, settings: dict):
        self.fig, self.gt, self.image = fig, gt, image
        fig.clf()
        lo, hi = rep["lower"], rep["upper"]
        self.extent = (lo[0], hi[0], lo[2], hi[2])  # x horizontal, z (depth) vertical
        self.artists, self.colorbars, self.contours = [], {}, {}
        self._background = None  # the canvas without the changing artists, once png() has run
        self.pt = pt = readable_pt(fig.get_figwidth(), least=7.0)  # every text readable as the book shows the figure
        for i, (ax, (a, title, cmap, vlo, vhi, label)) in enumerate(zip(fig.subplots(2, 5).flat,
                                                                         _panels(gt, image, pred, rep))):
            if i in self.SDF_PANELS:
                im = ax.imshow(a.T, origin="lower", extent=self.extent, aspect="auto", cmap=cmap, vmin=vlo, vmax=vhi)
                ax.set_xlabel("x", fontsize=pt), ax.set_ylabel("z (depth)", fontsize=pt)
                ax.tick_params(labelsize=pt)
            else:
                im = ax.imshow(a, cmap=cmap, vmin=vlo, vmax=vhi)
                ax.set_xticks([]), ax.set_yticks([])
            ax.set_title(title, fontsize=pt + 1)
            if cmap is not None:  # arrows at both ends where values beyond the range are clipped
                extend = "both" if i in self.CLIPPED else "neither"
                cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02, extend=extend)
                if label:
                    cb.set_label(label, fontsize=pt)
                cb.ax.tick_params(labelsize=pt)
                self.colorbars[i] = cb
            if cmap == "RdBu":
                self._contour(i, ax, a)
            self.artists.append(im)
        self.title = fig.suptitle(describe(settings), fontsize=pt + 3)
        fig.tight_layout()

    def _contour(self, i: int, ax, a: np.ndarray) -> None:
        """Panel ``i``'s 0-contour of the SDF slice ``a`` (the surface), replacing its former one;
        none where the slice does not change sign."""
        if i in self.contours:
            self.contours.pop(i).remove()
        if np.nanmin(a) < 0.0 < np.nanmax(a):
            self.contours[i] = ax.contour(a.T, levels=[0.0], origin="lower", extent=self.extent, colors="k",
                                          linewidths=0.8)

    def update(self, pred, rep: dict, settings: dict) -> None:
        """Show the prediction ``pred`` with its loss report ``rep`` for perturbation ``settings``."""
        panels = _panels(self.gt, self.image, pred, rep)
        for i in self.CHANGING:
            a, title, cmap, vlo, vhi, _label = panels[i]
            im = self.artists[i]
            im.set_data(a.T if i in self.SDF_PANELS else a)
            im.set_clim(vlo, vhi)
            im.axes.set_title(title, fontsize=self.pt + 1)
            if cmap == "RdBu":
                self._contour(i, im.axes, a)
        self.title.set_text(describe(settings))

    def _changing_artists(self) -> list:
        """What :meth:`update` changes, in drawing order: images, their axes' frames and the
        prediction's 0-contour, titles, rescaled colour bars, the figure's title."""
        axes = [self.artists[i].axes for i in self.CHANGING]
        return ([self.artists[i] for i in self.CHANGING] + [sp for ax in axes for sp in ax.spines.values()]
                + [c for i, c in self.contours.items() if i in self.CHANGING] + [ax.title for ax in axes]
                + [self.colorbars[i].ax for i in self.RESCALED] + [self.title])

    def _draw_background(self) -> None:
        """Draw the figure without the changing artists and keep it (:meth:`png`)."""
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # heavy: only when a live figure is rendered

        canvas = FigureCanvasAgg(self.fig)  # becomes fig.canvas
        canvas.draw()  # a full drawing places the titles (above tick labels); a drawing without them would not
        titles = [self.artists[i].axes.title for i in self.CHANGING]
        placed = [t.get_position() for t in titles]
        changing = self._changing_artists()
        for a in changing:
            a.set_visible(False)
        canvas.draw()
        self._background = canvas.copy_from_bbox(self.fig.bbox)
        for a in changing:
            a.set_visible(True)
        for t, xy in zip(titles, placed):
            t.set_position(xy)

    def png(self) -> bytes:
        """The figure as PNG bytes, fast: the first call draws everything but what :meth:`update`
        changes and keeps that as the background; each call restores it and draws only the
        changing artists on it (blitting), then encodes with a fast zlib level. For a figure
        outside pyplot (the live explorer's): it gets its own Agg canvas."""
        import matplotlib.image as mimage  # heavy: only when a live figure is rendered

        if self._background is None:
            self._draw_background()
        self.fig.canvas.restore_region(self._background)
        for a in self._changing_artists():
            self.fig.draw_artist(a)
        buf = io.BytesIO()
        rgb = np.asarray(self.fig.canvas.buffer_rgba())[..., :3]
        mimage.imsave(buf, rgb, format="png", pil_kwargs={"compress_level": 1})
        return buf.getvalue()


def draw(gt, image, K, settings: dict | None = None, grid: int = 16, fig=None, seed: int = 0):
    """Draw the explorer's figure (:class:`ExplorerFigure`) for perturbation ``settings``;
    returns (figure, loss report). A new pyplot figure unless ``fig`` is given (then cleared)."""
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    settings = {**neutral(), **(settings or {})}
    pred = perturb(gt, seed=seed, **settings)
    rep = loss_report(pred, gt, image, K, grid)
    if fig is None:
        fig = plt.figure(figsize=STATIC_FIGSIZE)
    ExplorerFigure(fig, gt, image, pred, rep, settings)
    return fig, rep


def has_live_frontend() -> bool:
    """True in a kernel started by a Jupyter server (JupyterLab/Notebook), False under papermill/nbval.

    ``GEODEPTH_LITE_WIDGETS=live|static`` overrides the guess.
    """
    force = os.environ.get("GEODEPTH_LITE_WIDGETS", "").lower()
    if force in ("live", "static"):
        return force == "live"
    try:
        from IPython import get_ipython  # optional: present only under Jupyter

        ip = get_ipython()
    except ImportError:  # pragma: no cover
        return False
    return ip is not None and getattr(ip, "kernel", None) is not None and "JPY_SESSION_NAME" in os.environ


class LiveExplorer:
    """The live explorer: six sliders, a reset button, a busy sign, the loss line and one figure
    (:class:`ExplorerFigure`, shown as a PNG in an ipywidgets Image) that is updated, never rebuilt.

    Updates are coalesced. A slider change asks for one (:meth:`request`); the compute runs in a
    worker thread (``background=True``), so the kernel keeps taking slider changes meanwhile and the
    busy sign shows at once. When values change during a compute, its result is dropped (never
    shown) and one more compute runs with the latest values only. :meth:`reset` sets every slider
    with updates held, then asks for ONE update. ``background=False`` computes in the caller's
    thread (tests, scripts). ``computes`` and ``shown`` list the settings of every compute and of
    every figure shown, in order. Display :attr:`ui`.
    """

    def __init__(self, gt, image, K, grid: int = 16, seed: int = 0, background: bool = True):
        from matplotlib.figure import Figure  # heavy; a Figure outside pyplot: no GUI backend, never auto-shown

        self.gt, self.image, self.K, self.grid, self.seed = gt, image, K, grid, seed
        self.background = background
        self.computes: list[dict] = []
        self.shown: list[dict] = []
        self.error: BaseException | None = None  # the last compute's error, shown in the status line
        self._lock = threading.Lock()
        self._idle = threading.Event()
        self._idle.set()
        self._busy = self._dirty = self._held = False
        self._build_widgets()
        settings = self.settings()
        self.computes.append(settings)
        start = time.perf_counter()
        pred, rep = self.compute(settings)
        self.figure = ExplorerFigure(Figure(figsize=LIVE_FIGSIZE, dpi=LIVE_DPI), gt, image, pred, rep, settings)
        self._show(self.figure.png(), rep, settings, start)
        self.status.value = self._status_html()

    def _build_widgets(self) -> None:
        import ipywidgets as w  # optional: needed only for live sliders in Jupyter

        self.sliders = {
            k: w.FloatSlider(value=v[3], min=v[0], max=v[1], step=v[2], description=k, continuous_update=False,
                             tooltip=v[4], readout_format=READOUT_FORMAT, style={"description_width": "48px"},
                             layout=w.Layout(width="auto", min_width="0"))
            for k, v in PERTURBATIONS.items()
        }
        for sl in self.sliders.values():
            sl.observe(self._changed, names="value")
        self.reset_button = w.Button(description="reset", tooltip="every slider back to no perturbation",
                                     layout=w.Layout(width="80px"))
        self.reset_button.on_click(lambda _button: self.reset())
        self.status = w.HTML(layout=w.Layout(min_width="150px"))
        self.values = w.HTML()
        width = f"{round(LIVE_FIGSIZE[0] * LIVE_DPI)}px"  # the figure's; narrower windows scale both down
        self.image_widget = w.Image(format="png", layout=w.Layout(width="100%", max_width=width))
        grid = w.GridBox(list(self.sliders.values()),  # three columns sharing the width
                         layout=w.Layout(grid_template_columns="repeat(3, minmax(0, 1fr))", max_width=width))
        controls = w.VBox([grid, w.HBox([self.reset_button, self.status, self.values])])
        controls.add_class("geodepth-explorer-controls")  # hidden when the kernel is gone (EXPLORER_CSS)
        self.dead = w.HTML(f'<b style="color:#b00020">{html.escape(DEAD_TEXT)}</b>')
        self.dead.add_class("geodepth-explorer-dead")  # shown when the kernel is gone
        self.ui = w.VBox([controls, self.dead, self.image_widget])
        self.ui.add_class("geodepth-explorer")

    def settings(self) -> dict:
        """The sliders' current values: {perturbation: value}."""
        return {k: s.value for k, s in self.sliders.items()}

    def compute(self, settings: dict) -> tuple[np.ndarray, dict]:
        """The prediction for ``settings`` and its loss report (the slow part, run in the worker)."""
        pred = perturb(self.gt, seed=self.seed, **settings)
        return pred, loss_report(pred, self.gt, self.image, self.K, self.grid)

    def _changed(self, _change) -> None:
        if not self._held:
            self.request()

    def request(self) -> None:
        """Ask for an update with the sliders' latest values (coalesced: see the class)."""
        with self._lock:
            self._dirty = True
            if self._busy:
                return  # the running worker computes once more when its compute ends
            self._busy = True
            self._idle.clear()
            self.status.value = BUSY_HTML
        if self.background:
            threading.Thread(target=self._work, name="geodepth-explorer", daemon=True).start()
        else:
            self._work()

    def _work(self) -> None:
        """Compute until no request is pending; show a result only if no value changed meanwhile."""
        while True:
            with self._lock:
                if not self._dirty:
                    self._busy = False
                    self.status.value = self._status_html()
                    self._idle.set()
                    return
                self._dirty = False
                settings = self.settings()
            self.computes.append(settings)
            start = time.perf_counter()
            try:
                pred, rep = self.compute(settings)
                self.figure.update(pred, rep, settings)
                png = self.figure.png()
                with self._lock:
                    if not self._dirty:  # else values changed meanwhile: drop this result, compute again
                        self._show(png, rep, settings, start)
            except Exception as exc:  # shown in the status line: a worker thread has no traceback display
                self.error = exc

    def _show(self, png: bytes, rep: dict, settings: dict, start: float) -> None:
        """Show the figure ``png`` and the losses of a compute started at ``start`` (perf_counter)."""
        self.image_widget.value = png
        self.values.value = "<b>losses:</b> " + format_losses(rep)
        self.seconds = time.perf_counter() - start  # compute and drawing, as the status line says
        self.error = None
        self.shown.append(settings)

    def _status_html(self) -> str:
        if self.error is not None:
            what = html.escape(f"{type(self.error).__name__}: {self.error}")
            return f'<span style="color:#b00020">error: {what}</span>'
        return f'<span style="color:#2e7d32">updated in {self.seconds:.1f} s</span>'

    def reset(self) -> None:
        """Every slider back to its neutral value with updates held, then ONE update (none when
        nothing changed)."""
        changed = self.settings() != neutral()
        self._held = True
        try:
            for k, s in self.sliders.items():
                s.value = PERTURBATIONS[k][3]
        finally:
            self._held = False
        if changed:
            self.request()

    def wait(self, timeout: float = 60.0) -> bool:
        """Block until no update is pending (tests, scripts); False if still busy after ``timeout`` s."""
        return self._idle.wait(timeout)

    def static_html(self) -> str:
        """The figure shown now as a static HTML output (a PNG) with :data:`DEAD_TEXT` and the
        :data:`EXPLORER_CSS`: what the cell shows once its kernel and widget models are gone."""
        png = base64.b64encode(bytes(self.image_widget.value)).decode("ascii")
        return (f"<style>{EXPLORER_CSS}</style><div class=\"geodepth-explorer-static\">"
                f'<p><b style="color:#b00020">{html.escape(DEAD_TEXT)}</b></p>'
                f'<img src="data:image/png;base64,{png}" alt="the explorer figure" style="max-width:100%"></div>')

    def _repr_mimebundle_(self, **kwargs) -> dict:
        """The widgets (:attr:`ui`), with a line of text where widgets cannot show (nbviewer, a notebook
        reopened untrusted). :meth:`_ipython_display_` shows the static figure beside them."""
        bundle = dict(self.ui._repr_mimebundle_(**kwargs) or {})
        bundle["text/plain"] = "loss explorer (its sliders need this cell run in a live Jupyter kernel)"
        return bundle

    def _ipython_display_(self) -> None:
        """Two outputs: the static figure (:meth:`static_html`, hidden while the widgets live) and the
        widgets. A saved notebook keeps both, so a reload without the kernel shows the figure and
        the "re-run this cell" line, not "Error displaying widget: model not found"."""
        from IPython.display import HTML, display  # optional: only under IPython

        display(HTML(self.static_html()))
        display(self._repr_mimebundle_(), raw=True)


def explorer(gt, image, K, grid: int = 16, live: bool | None = None, seed: int = 0):
    """Sliders for the six perturbations driving one reused figure (live), or its static figure.

    live=None guesses with :func:`has_live_frontend`. Live: returns a :class:`LiveExplorer`
    (display it as the cell's last line: it shows as its widgets, :attr:`LiveExplorer.ui`); the
    figure updates in the background when a slider is released, with a busy sign meanwhile.
    Static: shows the figure (:func:`draw`) for the neutral settings, prints the loss values and
    returns None.
    """
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    live = has_live_frontend() if live is None else live
    if not live:
        fig, rep = draw(gt, image, K, None, grid, seed=seed)
        plt.show()
        print("static figure (its sliders need this cell run in JupyterLab); losses:", format_losses(rep))
        return None
    return LiveExplorer(gt, image, K, grid, seed)


def sensitivity_table(gt, image, K, settings: dict[str, dict], grid: int = 16, seed: int = 0) -> dict[str, dict]:
    """Loss values for several named perturbation settings: {name: {loss: value}}."""
    table = {}
    for name, s in settings.items():
        rep = loss_report(perturb(gt, seed=seed, **{**neutral(), **s}), gt, image, K, grid)
        table[name] = {k: rep[k] for k in losses.term_names()}
    return table


def plot_loss_maps(gt, image, K, cases: dict[str, dict], loss: str, grid: int = 16, seed: int = 0):
    """One row per case: the prediction and the per-pixel map of ``loss`` (depth, smooth, grad,
    normal; for "sdf" the x-z slice of |SDF diff|), with the loss value in the title."""
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    if loss not in MAP_TERMS:
        raise ValueError(f"loss must be one of {', '.join(MAP_TERMS)}, got {loss!r}")
    fig, axs = plt.subplots(2, len(cases), figsize=(3.2 * len(cases), 6.0), squeeze=False)
    pt = readable_pt(fig.get_figwidth(), least=7.0)  # every text readable as the book shows the figure
    vmin, vmax = float(np.min(gt)), float(np.max(gt))
    values = {}
    for col, (name, s) in enumerate(cases.items()):
        pred = perturb(gt, seed=seed, **{**neutral(), **s})
        rep = loss_report(pred, gt, image, K, grid)
        values[name] = rep[loss]
        shown = axs[0, col].imshow(pred, cmap=DEPTH_CMAP, vmin=vmin, vmax=vmax)
        cb = fig.colorbar(shown, ax=axs[0, col], fraction=0.046, pad=0.02, extend="both")
        cb.set_label("depth, near = bright", fontsize=pt)
        cb.ax.tick_params(labelsize=pt)
        axs[0, col].set_title(name, fontsize=pt + 1)
        if loss == "sdf":
            j = rep["sdf_gt"].shape[1] // 2
            lo, hi = rep["lower"], rep["upper"]
            a = np.abs(rep["sdf_pred"] - rep["sdf_gt"])[:, j, :].T
            im = axs[1, col].imshow(a, origin="lower", extent=(lo[0], hi[0], lo[2], hi[2]), aspect="auto",
                                    vmin=0.0, vmax=_vmax(a))
        else:
            m = rep["maps"][loss]
            m = m if loss == "depth" else m[:-1, :-1]
            im = axs[1, col].imshow(m, cmap="viridis", vmin=0.0, vmax=_vmax(m))
        axs[1, col].set_title(f"{loss} loss {rep[loss]:.4f}", fontsize=pt + 1)
        fig.colorbar(im, ax=axs[1, col], fraction=0.046, pad=0.02).ax.tick_params(labelsize=pt)
        for ax in axs[:, col]:
            ax.set_xticks([]), ax.set_yticks([])
    fig.suptitle(f"top: the predictions, clipped to the ground truth's depths {vmin:.2g}-{vmax:.2g} (arrows: "
                 f"beyond it); bottom: the per-pixel {loss} term", fontsize=pt + 1)
    fig.tight_layout()
    return fig, values
