"""The interactive loss explorer of notebook 03: perturb a ground-truth depth map, watch the five losses.

A "prediction" is made from a ground-truth depth map by six perturbations, each a kind of
error a depth network makes (:func:`perturb`). :func:`loss_report` computes the five losses of
Sec. 3.C with :mod:`geodepth_lite.losses` (the same code that trains the network) and their
per-pixel maps; :func:`draw` draws them with the SDF grid slices; :func:`explorer` wires
sliders to :func:`draw` in a live Jupyter frontend and falls back to a static figure where
there is none (papermill, nbval, nbconvert).
"""

from __future__ import annotations

import os

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from . import losses
from .datasets import SyntheticDepthDataset
from .synth import ensure_dataset

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
    ("sdf_gt", "sdf_pred", shape r x r x r, axes x, y, z) and the grid bounds.
    """
    image = np.asarray(image, dtype=np.float64)
    if image.shape[-1] == 3 and image.shape[0] != 3:
        image = image.transpose(2, 0, 1)
    p, g, img = _t(pred), _t(gt), torch.as_tensor(image)[None]
    H, W = gt.shape
    r = (grid,) * 3 if isinstance(grid, int) else tuple(grid)
    inputs = losses.LossInputs(g, img, torch.as_tensor(np.asarray(K, dtype=np.float64)), None, r)
    out = {name: float(term.fn(p, inputs)) for name, term in losses.LOSS_TERMS.items()}  # every term, by name
    fields = losses.sdf_fields(p, g, K, grid=grid)[0]
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


def draw(gt, image, K, settings: dict | None = None, grid: int = 16, fig=None, seed: int = 0):
    """Draw the explorer's figure for perturbation ``settings``; returns (figure, loss report).

    Row 1: image, ground truth, prediction, per-pixel depth and smoothness terms.
    Row 2: per-pixel gradient and normal terms, and the x-z slice through the middle of the
    SDF grid for ground truth, prediction and their absolute difference (0-contour = surface).
    """
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    settings = {**neutral(), **(settings or {})}
    pred = perturb(gt, seed=seed, **settings)
    rep = loss_report(pred, gt, image, K, grid)
    if fig is None:
        fig = plt.figure(figsize=(15, 6.2))
    fig.clf()
    axs = fig.subplots(2, 5)
    img = np.asarray(image)
    img = img.transpose(1, 2, 0) if img.shape[0] == 3 else img
    vmin, vmax = float(np.min(gt)), float(np.max(gt))
    panels = [
        (img, "image", None, None, None),
        (gt, "ground truth depth", "magma", vmin, vmax),
        (pred, "prediction", "magma", vmin, vmax),
        (rep["maps"]["depth"], f"|D - D_gt|: depth {rep['depth']:.3f}"),
        (rep["maps"]["smooth"][:-1, :-1], f"smoothness {rep['smooth']:.4f}"),
        (rep["maps"]["grad"][:-1, :-1], f"|grad diff|: gradient {rep['grad']:.3f}"),
        (rep["maps"]["normal"][:-1, :-1], f"1 - cos: normal {rep['normal']:.4f}"),
    ]
    panels = panels[:3] + [(a, t, "viridis", 0.0, _vmax(a)) for a, t in panels[3:]]
    for ax, (a, title, cmap, lo, hi) in zip(axs.flat, panels):
        im = ax.imshow(a, cmap=cmap, vmin=lo, vmax=hi)
        ax.set_title(title, fontsize=9)
        ax.set_xticks([]), ax.set_yticks([])
        if cmap is not None:
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
    j = rep["sdf_gt"].shape[1] // 2
    lo, hi = rep["lower"], rep["upper"]
    ext = (lo[0], hi[0], lo[2], hi[2])  # x horizontal, z (depth) vertical
    lim = float(np.nanmax(np.abs(rep["sdf_gt"][:, j, :])))
    slices = [
        (rep["sdf_gt"][:, j, :], "SDF of ground truth (x-z slice)", "RdBu", -lim, lim),
        (rep["sdf_pred"][:, j, :], "SDF of prediction", "RdBu", -lim, lim),
        (np.abs(rep["sdf_pred"] - rep["sdf_gt"])[:, j, :], f"|SDF diff|: sdf {rep['sdf']:.3f}", "viridis", 0.0,
         _vmax(np.abs(rep["sdf_pred"] - rep["sdf_gt"])[:, j, :])),
    ]
    for ax, (a, title, cmap, vlo, vhi) in zip(axs.flat[7:], slices):
        im = ax.imshow(a.T, origin="lower", extent=ext, aspect="auto", cmap=cmap, vmin=vlo, vmax=vhi)
        if cmap == "RdBu":
            ax.contour(a.T, levels=[0.0], origin="lower", extent=ext, colors="k", linewidths=0.8)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x", fontsize=8), ax.set_ylabel("z (depth)", fontsize=8)
        ax.tick_params(labelsize=7)
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
    changed = ", ".join(f"{k}={v:g}" for k, v in settings.items() if v != PERTURBATIONS[k][3]) or "no perturbation"
    fig.suptitle(f"prediction = ground truth with {changed}", fontsize=11)
    fig.tight_layout()
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


def explorer(gt, image, K, grid: int = 16, live: bool | None = None, seed: int = 0):
    """Sliders for the six perturbations driving :func:`draw` (live), or its static figure.

    live=None guesses with :func:`has_live_frontend`. Live: returns an ipywidgets VBox (display
    it as the cell's last line); the figure updates when a slider is released. Static: shows
    the figure for the neutral settings, prints the loss values and returns None.
    """
    import matplotlib.pyplot as plt  # heavy, may pick a GUI backend: only when a figure is drawn

    live = has_live_frontend() if live is None else live
    if not live:
        fig, rep = draw(gt, image, K, None, grid, seed=seed)
        plt.show()
        print("static rendering (no live Jupyter frontend); losses:", format_losses(rep))
        return None
    import ipywidgets as w  # optional: needed only for live sliders in Jupyter
    from IPython.display import display  # optional: present only under Jupyter

    sliders = {
        k: w.FloatSlider(value=v[3], min=v[0], max=v[1], step=v[2], description=k, continuous_update=False,
                         tooltip=v[4], readout_format=".3g", layout=w.Layout(width="300px"))
        for k, v in PERTURBATIONS.items()
    }
    out = w.Output()
    values = w.HTML()

    def update(**settings):
        with out:
            out.clear_output(wait=True)
            fig, rep = draw(gt, image, K, settings, grid, seed=seed)
            display(fig)
            plt.close(fig)
        values.value = "<b>losses:</b> " + format_losses(rep)

    reset = w.Button(description="reset", layout=w.Layout(width="80px"))
    reset.on_click(lambda _: [setattr(sliders[k], "value", v[3]) for k, v in PERTURBATIONS.items()])
    for sl in sliders.values():
        sl.observe(lambda _change: update(**{k: s.value for k, s in sliders.items()}), names="value")
    update(**neutral())
    rows = [w.HBox(list(sliders.values())[i:i + 3]) for i in (0, 3)]
    return w.VBox([*rows, w.HBox([reset, values]), out])


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
    vmin, vmax = float(np.min(gt)), float(np.max(gt))
    values = {}
    for col, (name, s) in enumerate(cases.items()):
        pred = perturb(gt, seed=seed, **{**neutral(), **s})
        rep = loss_report(pred, gt, image, K, grid)
        values[name] = rep[loss]
        axs[0, col].imshow(pred, cmap="magma", vmin=vmin, vmax=vmax)
        axs[0, col].set_title(name, fontsize=9)
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
        axs[1, col].set_title(f"{loss} loss {rep[loss]:.4f}", fontsize=9)
        fig.colorbar(im, ax=axs[1, col], fraction=0.046, pad=0.02)
        for ax in axs[:, col]:
            ax.set_xticks([]), ax.set_yticks([])
    fig.tight_layout()
    return fig, values
