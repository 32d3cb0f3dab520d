"""Shared test fixtures: every test writes into its own temporary workspace."""

import os
from pathlib import Path

import pytest

try:  # the CUDA tests run where matplotlib may be missing (a bare GPU machine: gpu-check)
    import matplotlib
except ImportError:
    matplotlib = None
else:
    matplotlib.use("Agg")

# the workspace the user chose (or "" for the checkout's), before unit tests isolate theirs:
# tests that must share checkpoints with the notebooks (tests/test_results.py) go back to it
os.environ.setdefault("GEODEPTH_LITE_TEST_REAL_HOME", os.environ.get("GEODEPTH_LITE_HOME", ""))


def pytest_collection_modifyitems(config, items):
    """Tests marked ``cuda`` run only where a CUDA device is available; elsewhere they skip, saying why."""
    marked = [item for item in items if "cuda" in item.keywords]
    if not marked:
        return
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason=f"needs a CUDA GPU: torch {torch.__version__} sees none "
                                   f"(built with CUDA {torch.version.cuda or 'none'})")
    for item in marked:
        item.add_marker(skip)


@pytest.fixture(autouse=True)
def _isolated_workspace(tmp_path, monkeypatch):
    """Keep generated datasets and runs of unit tests out of the checkout."""
    if "GEODEPTH_LITE_TEST_KEEP_HOME" not in os.environ:
        monkeypatch.setenv("GEODEPTH_LITE_HOME", str(tmp_path / "home"))
    yield


@pytest.fixture(scope="session")
def smoke_root(tmp_path_factory) -> Path:
    """The ``scenario_smoke`` dataset, generated once per test session in a folder of its own."""
    from geodepth_lite.data import synth

    return Path(synth.ensure_dataset("scenario_smoke", root=tmp_path_factory.mktemp("smoke_data"), progress=False))


def save_untrained_checkpoint(path: Path, cfg: dict | None = None) -> Path:
    """A seeded, untrained DepthNet in ``train``'s checkpoint format, so evaluation and prediction
    run end to end without training (network input 32 unless ``cfg`` says otherwise)."""
    import torch

    from geodepth_lite.core.model import DepthNet

    torch.manual_seed(0)
    torch.save({"model": DepthNet().state_dict(), "cfg": cfg or {"image_size": 32}, "epoch": 0}, path)
    return path


def save_nan_checkpoint(path: Path) -> Path:
    """An untrained checkpoint (``save_untrained_checkpoint``) with one weight tensor set to NaN."""
    import torch

    save_untrained_checkpoint(path)
    state = torch.load(path, weights_only=True)
    key = next(k for k, v in state["model"].items() if v.is_floating_point())
    state["model"][key] = state["model"][key].clone().fill_(float("nan"))
    torch.save(state, path)
    return path


@pytest.fixture(scope="module")
def untrained_checkpoint(tmp_path_factory) -> Path:
    return save_untrained_checkpoint(tmp_path_factory.mktemp("ckpt") / "checkpoint.pt")


def one_line_error(capsys, *needles) -> str:
    """The captured stderr is one ``error:`` line holding every needle, with no traceback; returns it."""
    err = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in err if line.startswith("error: ")]
    assert len(errors) == 1, err
    assert not any("Traceback" in line for line in err), err
    for needle in needles:
        assert str(needle) in errors[0], (needle, errors[0])
    return errors[0]
