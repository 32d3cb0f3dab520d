"""The loss explorer's building blocks (notebook 03): perturbations and the loss report."""

import math

import numpy as np
import pytest

from geodepth_lite import camera, widgets


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


def test_explorer_static_and_live(monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    gt = tube_like()
    image = np.full((3, 32, 32), 0.5)
    K = camera.intrinsics(32)
    assert widgets.explorer(gt, image, K, grid=4, live=False) is None
    ui = widgets.explorer(gt, image, K, grid=4, live=True)
    sliders = [c for row in ui.children[:2] for c in row.children]
    assert [s.description for s in sliders] == list(widgets.PERTURBATIONS)
    values = ui.children[2].children[1]
    assert "depth 0.0000" in values.value
    sliders[4].value = 0.5  # offset: the loss line follows the slider
    assert "depth 0.5000" in values.value and "grad 0.0000" in values.value
    monkeypatch.setenv("GEODEPTH_LITE_WIDGETS", "static")
    assert widgets.has_live_frontend() is False
    with pytest.raises(ValueError, match="loss must be"):
        widgets.plot_loss_maps(gt, image, K, {"a": {}}, "bogus")
