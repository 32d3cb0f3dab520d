"""Shared test fixtures: every test writes into its own temporary workspace."""

import os

import matplotlib
import pytest

matplotlib.use("Agg")


@pytest.fixture(autouse=True)
def _isolated_workspace(tmp_path, monkeypatch):
    """Keep generated datasets and runs of unit tests out of the checkout."""
    if "GEODEPTH_LITE_TEST_KEEP_HOME" not in os.environ:
        monkeypatch.setenv("GEODEPTH_LITE_HOME", str(tmp_path / "home"))
    yield
