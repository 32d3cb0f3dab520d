"""The loss explorer (notebook 03): perturbations, the loss report, and the live explorer's updates
(one reused figure, coalesced computes, one compute per reset, one number format)."""

import base64
import math

import numpy as np
import pytest

from geodepth_lite.core import camera
from geodepth_lite.workbook import widgets


def tube_like(H=32, W=32):
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    r = np.hypot(u - W / 2, v - H / 2) / W
    return 1.0 / (0.2 + r) + 0.3 * (u > W / 2)  # a lumen with a stepped edge


def test_perturbations_are_neutral_and_do_what_they_say():
    gt = tube_like()
    assert np.array_equal(widgets.perturb(gt, **widgets.neutral()), gt)
    assert np.allclose(widgets.perturb(gt, offset=0.25), gt + 0.25)
    assert np.allclose(widgets.perturb(gt, scale=1.5), gt * 1.5)
    a = widgets.perturb(gt, noise=0.05, seed=1)
    assert np.array_equal(a, widgets.perturb(gt, noise=0.05, seed=1)) and not np.array_equal(a, gt)


def test_loss_report_known_values():
    gt = tube_like()
    image = np.full((3, 32, 32), 0.5)
    K = camera.intrinsics(32)
    rep = widgets.loss_report(widgets.perturb(gt, offset=0.25), gt, image, K, grid=6)
    assert math.isclose(rep["depth"], 0.25, rel_tol=1e-9)
    assert rep["grad"] < 1e-12 and rep["normal"] < 1e-12 and rep["sdf"] > 0.05
    assert np.allclose(rep["maps"]["depth"], 0.25)
    assert rep["sdf_gt"].shape == (6, 6, 6)
    same = widgets.loss_report(gt, gt, image, K, grid=6)
    assert same["depth"] == same["grad"] == same["sdf"] == 0.0


def explorer_inputs(size=32):
    import matplotlib

    matplotlib.use("Agg")
    return tube_like(size, size), np.full((3, size, size), 0.5), camera.intrinsics(size)


def test_explorer_static_and_live(monkeypatch):
    gt, image, K = explorer_inputs()
    assert widgets.explorer(gt, image, K, grid=4, live=False) is None
    ex = widgets.explorer(gt, image, K, grid=4, live=True)
    grid, buttons = ex.ui.children[0].children  # the controls: sliders, then reset, status and losses
    assert [s.description for s in grid.children] == list(widgets.PERTURBATIONS)
    values = buttons.children[2]
    assert "depth 0.0000" in values.value
    bundle = ex._repr_mimebundle_()  # the widgets, and a line of text where widgets cannot show
    assert bundle["application/vnd.jupyter.widget-view+json"]["model_id"] == ex.ui.model_id
    assert "image/png" not in bundle and "live Jupyter kernel" in bundle["text/plain"]
    monkeypatch.setenv("GEODEPTH_LITE_WIDGETS", "static")
    assert widgets.has_live_frontend() is False
    with pytest.raises(ValueError, match="loss must be"):
        widgets.plot_loss_maps(gt, image, K, {"a": {}}, "bogus")


def test_a_slider_change_updates_the_reused_figure():
    gt, image, K = explorer_inputs()
    ex = widgets.LiveExplorer(gt, image, K, grid=4, background=False)
    fig, first = ex.figure.fig, bytes(ex.image_widget.value)
    n_axes = len(fig.axes)
    ex.sliders["offset"].value = 0.5  # the loss line and the figure follow the slider
    assert "depth 0.5000" in ex.values.value and "grad 0.0000" in ex.values.value
    assert bytes(ex.image_widget.value) != first and first.startswith(b"\x89PNG")
    assert ex.figure.fig is fig and len(fig.axes) == n_axes  # updated, not rebuilt
    assert np.allclose(ex.figure.artists[2].get_array(), gt + 0.5)
    assert ex.computes == ex.shown == [widgets.neutral(), {**widgets.neutral(), "offset": 0.5}]
    assert "updated in" in ex.status.value


def test_reset_recomputes_once():
    gt, image, K = explorer_inputs()
    ex = widgets.LiveExplorer(gt, image, K, grid=4, background=False)
    for name, value in (("blur", 1.0), ("scale", 1.2), ("offset", 0.3), ("noise", 0.02)):
        ex.sliders[name].value = value
    n = len(ex.computes)
    ex.reset()
    assert ex.computes[n:] == [widgets.neutral()] and ex.shown[-1] == widgets.neutral()
    assert ex.settings() == widgets.neutral() and "depth 0.0000" in ex.values.value
    ex.reset()  # nothing to change: nothing to compute
    assert len(ex.computes) == n + 1


def test_values_changed_during_a_compute_are_computed_once_and_the_stale_result_is_never_shown():
    gt, image, K = explorer_inputs()
    ex = widgets.LiveExplorer(gt, image, K, grid=4, background=False)
    compute = ex.compute

    def compute_while_the_student_moves_on(settings):
        if len(ex.computes) == 2:  # during the first update: two more changes arrive
            ex.sliders["offset"].value = 0.2
            ex.sliders["tilt"].value = 0.1
        return compute(settings)

    ex.compute = compute_while_the_student_moves_on
    ex.sliders["blur"].value = 1.0
    first, latest = {**widgets.neutral(), "blur": 1.0}, {**widgets.neutral(), "blur": 1.0, "offset": 0.2, "tilt": 0.1}
    assert ex.computes == [widgets.neutral(), first, latest]
    assert ex.shown == [widgets.neutral(), latest]  # the in-between result was dropped
    assert ex.figure.title.get_text().endswith("blur=1.000, tilt=0.100, offset=0.200")


def test_a_result_is_dropped_when_values_change_while_its_figure_is_drawn():
    gt, image, K = explorer_inputs()
    ex = widgets.LiveExplorer(gt, image, K, grid=4, background=False)
    png = ex.figure.png

    def png_while_the_student_moves_on():
        if len(ex.computes) == 2:
            ex.sliders["noise"].value = 0.01
        return png()

    ex.figure.png = png_while_the_student_moves_on
    ex.sliders["ripple"].value = 0.02
    latest = {**widgets.neutral(), "ripple": 0.02, "noise": 0.01}
    assert ex.computes[1:] == [{**widgets.neutral(), "ripple": 0.02}, latest]
    assert ex.shown == [widgets.neutral(), latest]


def test_the_worker_thread_coalesces_and_shows_a_busy_sign():
    import threading

    gt, image, K = explorer_inputs()
    ex = widgets.LiveExplorer(gt, image, K, grid=4)
    assert ex.background and "updated in" in ex.status.value
    started, release, compute = threading.Event(), threading.Event(), ex.compute

    def slow_compute(settings):
        started.set()
        assert release.wait(10)
        return compute(settings)

    ex.compute = slow_compute
    ex.sliders["scale"].value = 1.05  # returns at once: the kernel keeps taking slider changes
    assert started.wait(10)
    assert ex.status.value == widgets.BUSY_HTML
    for value in (1.1, 1.15, 1.2):  # quick key presses while the first change computes
        ex.sliders["scale"].value = value
    release.set()
    assert ex.wait(30)
    latest = {**widgets.neutral(), "scale": 1.2}
    assert ex.computes[1:] == [{**widgets.neutral(), "scale": 1.05}, latest]
    assert ex.shown == [widgets.neutral(), latest] and "updated in" in ex.status.value


def test_a_failing_compute_is_reported_and_the_explorer_goes_on():
    gt, image, K = explorer_inputs()
    ex = widgets.LiveExplorer(gt, image, K, grid=4, background=False)
    compute = ex.compute

    def failing(settings):
        raise RuntimeError("no memory")

    ex.compute = failing
    ex.sliders["blur"].value = 1.0
    assert "error: RuntimeError: no memory" in ex.status.value and ex.shown == [widgets.neutral()]
    ex.compute = compute
    ex.sliders["blur"].value = 2.0
    assert "updated in" in ex.status.value and ex.shown[-1]["blur"] == 2.0


def test_slider_numbers_share_one_format_that_shows_every_step_exactly():
    gt, image, K = explorer_inputs()
    ex = widgets.LiveExplorer(gt, image, K, grid=4, background=False)
    assert {s.readout_format for s in ex.sliders.values()} == {widgets.READOUT_FORMAT}
    numbers = [x for lo, hi, step, neutral, _ in widgets.PERTURBATIONS.values() for x in (lo, hi, step, neutral)]
    shown = [widgets.format_value(x) for x in numbers]
    assert all(math.isclose(float(t), x, abs_tol=1e-12) for t, x in zip(shown, numbers)), shown
    assert len({len(t.split(".")[1]) for t in shown}) == 1, shown  # as many decimals everywhere
    assert widgets.format_value(0) == "0.000" and widgets.format_value(0.5) == "0.500"
    assert widgets.describe({**widgets.neutral(), "noise": 0.02}).endswith("noise=0.020")


def test_the_blitted_png_is_the_full_drawing(tmp_path):
    import io

    from PIL import Image

    def blitted_and_full():
        blit = np.asarray(Image.open(io.BytesIO(ex.image_widget.value)).convert("RGB"))
        ex.figure.fig.canvas.draw()  # everything drawn again from scratch
        return blit, np.asarray(ex.figure.fig.canvas.buffer_rgba())[..., :3]

    gt, image, K = explorer_inputs()
    ex = widgets.LiveExplorer(gt, image, K, grid=6, background=False)
    blit, full = blitted_and_full()  # the first figure: background and changing parts drawn apart
    assert blit.shape == full.shape and np.array_equal(blit, full)
    for settings in ({"blur": 1.5, "noise": 0.03}, {"scale": 1.3, "ripple": 0.05}):
        for name, value in settings.items():
            ex.sliders[name].value = value
    blit, full = blitted_and_full()
    assert blit.shape == full.shape and np.array_equal(blit, full)


def test_the_live_figure_fits_a_laptop_window_and_the_static_one_keeps_its_shape():
    w, h = (round(x * widgets.LIVE_DPI) for x in widgets.LIVE_FIGSIZE)
    assert w <= 1200 and h <= 450  # + sliders (~110 px): well inside a 1400 x 1000 window's notebook area
    gt, image, K = explorer_inputs()
    fig, _ = widgets.draw(gt, image, K, {"scale": 1.2}, grid=4)
    assert repr(fig) == "<Figure size 1500x620 with 19 Axes>"  # the notebook's stored outputs (nbval) say so


def test_loss_report_searches_the_ground_truth_field_once(monkeypatch):
    import torch

    from geodepth_lite.core import losses, sdf

    gt, image, K = explorer_inputs()
    gt = gt + 0.123  # a frame no other test has cached
    searches = []
    search = sdf.nearest_indices
    monkeypatch.setattr(sdf, "nearest_indices", lambda *a, **k: searches.append(1) or search(*a, **k))
    pred = widgets.perturb(gt, blur=1.0)
    rep = widgets.loss_report(pred, gt, image, K, grid=5)
    assert len(searches) == 2  # ground truth and prediction
    rep2 = widgets.loss_report(widgets.perturb(gt, scale=1.1), gt, image, K, grid=5)
    assert len(searches) == 3  # the prediction only: the ground truth's field is cached
    t = lambda a: torch.as_tensor(a)[None, None]  # noqa: E731
    options = losses.SDFOptions(grid=(5, 5, 5))
    assert math.isclose(rep["sdf"], float(losses.sdf_loss(t(pred), t(gt), torch.as_tensor(K), options)),
                        rel_tol=1e-12)
    assert rep2["sdf"] > 0


def test_the_cell_shows_a_static_figure_beside_the_widgets_for_when_the_kernel_is_gone():
    from IPython.core.interactiveshell import InteractiveShell

    gt, image, K = explorer_inputs()
    ex = widgets.LiveExplorer(gt, image, K, grid=4, background=False)
    ex.sliders["offset"].value = 0.5
    shown = []
    InteractiveShell.instance().display_pub.publish = lambda data, **kw: shown.append(data)
    try:
        ex._ipython_display_()
    finally:
        InteractiveShell.clear_instance()
    assert [sorted(d) for d in shown] == [["text/html", "text/plain"],
                                          ["application/vnd.jupyter.widget-view+json", "text/plain"]]
    static = shown[0]["text/html"]  # the figure the widgets show now, the "re-run this cell" line and the styles
    png = static.split('src="data:image/png;base64,', 1)[1].split('"', 1)[0]
    assert base64.b64decode(png) == bytes(ex.image_widget.value)
    assert 'class="geodepth-explorer-static"' in static and "re-run this cell" in static
    assert ".jupyter-widgets-disconnected .geodepth-explorer-controls { display: none; }" in static
    # the classes the styles rely on: the sliders' box hides and the dead-kernel line shows
    controls, dead, figure = ex.ui.children
    assert "geodepth-explorer" in ex.ui._dom_classes and "geodepth-explorer-controls" in controls._dom_classes
    assert "geodepth-explorer-dead" in dead._dom_classes and "re-run this cell" in dead.value
    assert figure is ex.image_widget and ex.sliders["blur"] in controls.children[0].children


def test_colour_bars_of_the_clipped_panels_have_arrows_and_say_the_range():
    gt, image, K = explorer_inputs()
    fig, _ = widgets.draw(gt, image, K, {"scale": 1.5}, grid=4)
    bars = widgets.ExplorerFigure.CLIPPED
    fig_bars = {i: cb for i, cb in _colourbars(fig).items()}
    for i, cb in fig_bars.items():
        assert (cb.extend == "both") == (i in bars), i
    lo, hi = float(gt.min()), float(gt.max())
    assert fig_bars[2].ax.get_ylabel() == f"clipped to {lo:.3g}..{hi:.3g}"
    assert fig_bars[8].ax.get_ylabel().startswith("clipped to \u00b1")
    assert float(np.max(widgets.perturb(gt, scale=1.5))) > hi  # the prediction really goes beyond the range


def _colourbars(fig):
    """{panel index: colour bar} of an explorer figure (the panels are its first ten axes)."""
    panels = fig.axes[:10]
    return {panels.index(im.colorbar.mappable.axes): im.colorbar for ax in panels for im in ax.images
            if im.colorbar is not None}


def test_readable_pt_is_the_size_that_the_book_shows_at_the_least_height():
    """Hand-computed at 100 px per inch and an 800 px column: a figure 8 in wide is shown as it is, so
    8 px is 8 x 72 / 100 = 5.76 pt (6 in half points); one 16 in wide is shown at half its size, 11.52 pt
    (12); and text of that size measures at least 8 px as shown."""
    from matplotlib.figure import Figure

    from geodepth_lite.views import viz

    assert (viz.FIGURE_DPI, viz.BOOK_COLUMN_PX, viz.MIN_TEXT_PX) == (100, 800, 8.0)
    assert viz.readable_pt(8) == 6.0 and viz.readable_pt(16) == 12.0 and viz.shown_scale(16) == 0.5
    fig = Figure(figsize=(16, 4))
    fig.subplots().set_title("a title", fontsize=viz.readable_pt(16))
    assert [t for t, px in viz.text_heights_px(fig) if px < viz.MIN_TEXT_PX] == ["0.0", "0.2", "0.4", "0.6", "0.8",
                                                                                 "1.0"] * 2  # default ticks: 10 pt
    assert dict(viz.text_heights_px(fig))["a title"] == pytest.approx(12 * 100 / 72 / 2)


@pytest.mark.parametrize("which", ["static", "live", "loss maps"])
def test_every_text_of_the_explorer_and_the_loss_maps_is_readable(which):
    """The explorer's labels and the loss maps' colour-bar captions, as the book shows them: at least
    viz.MIN_TEXT_PX tall. The same figure with the former 7 pt captions fails the check."""
    from matplotlib.figure import Figure

    from geodepth_lite.views import viz

    gt, image, K = explorer_inputs()
    if which == "static":
        fig, _ = widgets.draw(gt, image, K, {"scale": 1.2}, grid=4)
    elif which == "live":
        fig = Figure(figsize=widgets.LIVE_FIGSIZE, dpi=widgets.LIVE_DPI)
        pred = widgets.perturb(gt, scale=1.2)
        widgets.ExplorerFigure(fig, gt, image, pred, widgets.loss_report(pred, gt, image, K, 4), {"scale": 1.2})
    else:
        cases = {"offset": {"offset": 0.2}, "scale": {"scale": 1.1}, "blur": {"blur": 1.0}, "ripple": {"ripple": 0.03}}
        fig, _ = widgets.plot_loss_maps(gt, image, K, cases, "depth", grid=4)  # as notebook 03 draws them
    heights = viz.text_heights_px(fig)
    assert len(heights) > 10 and heights[0][1] >= viz.MIN_TEXT_PX, heights[:3]
    fig.axes[-1].set_ylabel("a caption at 7 pt", fontsize=7)  # as the colour bars' captions were
    assert viz.text_heights_px(fig)[0][0] == "a caption at 7 pt"
    assert viz.text_heights_px(fig)[0][1] < viz.MIN_TEXT_PX


@pytest.mark.parametrize("width", [6.0, 10.0, 15.0])
def test_the_lessons_figure_helpers_write_readable_text_at_any_width(width):
    """viz's colour bars (show_depth, show_error, relative_depth_colorbar, depth_colorbar) and the
    error-map and border-map figures, on figures as wide as the lessons draw them: every text at least
    viz.MIN_TEXT_PX tall as the book shows it (the colour bars' former 7 pt captions fail at 15 in)."""
    import matplotlib.pyplot as plt

    from geodepth_lite.views import viz

    explorer_inputs()  # the Agg backend
    rng = np.random.default_rng(0)
    depth = 1.0 + rng.random((16, 16))
    fig, axes = plt.subplots(1, 4, figsize=(width, width / 4))
    viz.show_depth(axes[0], depth)
    viz.show_error(axes[1], rng.random((16, 16)), 0.5)
    viz.relative_depth_colorbar(fig, axes[2])
    viz.depth_colorbar(fig, axes[3], 1.0, 2.0)
    for ax in axes:
        ax.set_xticks([]), ax.set_yticks([])
    figs = [fig]
    ex = {"image": rng.random((16, 16, 3)), "gt": depth, "pred": depth * 1.1}
    figs.append(viz.error_map_figure([ex, ex], row_labels=["a", "b"]))
    figs.append(viz.border_map_figure({"signed": rng.random((16, 16)) - 0.5, "abs": rng.random((16, 16)),
                                       "ratios": {"test": 1.2}}))
    from geodepth_lite.evaluation import gallery

    row = {"image": rng.random((16, 16, 3)), "depth": depth, "prior": depth, "view": "close-up",
           "file": "a_long_file_name_of_a_frame.png", "r": 0.63, "far_share": 0.04}
    figs.append(gallery.gallery_figure([row] * 4))  # notebook 07's gallery: 12.6 in wide
    try:
        for f in figs:
            least = viz.text_heights_px(f)[0]
            assert least[1] >= viz.MIN_TEXT_PX, (f.get_size_inches(), least)
        if width == 15.0:  # the former captions, planted back, are caught
            cb = axes[0].images[0].colorbar
            cb.set_label("z-depth, near = bright", fontsize=7)
            assert viz.text_heights_px(fig)[0] == ("z-depth, near = bright", pytest.approx(7 * 100 / 72 * 800 / 1500))
    finally:
        for f in figs:
            plt.close(f)


def figure_text_problems(record: dict, names: list[str]) -> list[str]:
    """What breaks the book's rule in benchmarks/figure_text.json for the lessons ``names``: a figure
    with text under the record's min_text_px, a failed measurement, a lesson not measured."""
    out = []
    for name in names:
        r = record["notebooks"].get(name)
        if r is None:
            out.append(f"{name}: not measured")
            continue
        out += [f"{name}: figure {i} has {f['below']} text(s) under {record['min_text_px']} px"
                for i, f in enumerate(r["figures"]) if f.get("below")]
        out += [f"{name}: figure {i} not measured ({f['error']})" for i, f in enumerate(r["figures"]) if "error" in f]
    return out


def test_the_lessons_that_docs_name_draw_readable_text_by_their_record():
    """docs/book.md says which lessons draw no text under 8 px and the least height: both from the
    record benchmarks/figure_text.py wrote; a planted small text in the record is caught."""
    import json
    import re
    from pathlib import Path

    from geodepth_lite.views import viz

    root = Path(__file__).resolve().parents[1]
    record = json.loads((root / "benchmarks" / "figure_text.json").read_text())
    text = " ".join((root / "docs" / "book.md").read_text().split())
    said = r"notebooks ((?:\d\d, )*\d\d) and (\d\d) draw no text under (\d+) px \(the least, ([\d.]+) px\)"
    m = re.search(said, text)
    assert m, "docs/book.md states no measured lessons"
    nums = [*m.group(1).split(", "), m.group(2)]
    names = [n for n in record["notebooks"] if n[:2] in nums]
    assert len(names) == len(nums) and float(m.group(3)) == record["min_text_px"] == viz.MIN_TEXT_PX
    assert figure_text_problems(record, names) == []
    assert float(m.group(4)) == min(record["notebooks"][n]["least_px"] for n in names)
    planted = json.loads(json.dumps(record))
    planted["notebooks"][names[0]]["figures"][0]["below"] = 3
    assert figure_text_problems(planted, names) == [f"{names[0]}: figure 0 has 3 text(s) under 8.0 px"]
