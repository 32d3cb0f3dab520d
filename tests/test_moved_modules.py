"""The paper's method moved into ``geodepth_lite.core``. Notebooks written against the previous
release import the old names (``from geodepth_lite import camera``, ``geodepth_lite.losses``):
those still give the same module, with a DeprecationWarning that names the new place."""

import importlib
import sys

import pytest

import geodepth_lite

MOVED = ("camera", "errors", "losses", "metrics", "model", "nnsearch", "nnsearch_triton", "sdf")


@pytest.fixture
def forget_old_names():
    """The old names are imported afresh in each test and forgotten after it."""
    def drop():
        for name in MOVED:
            sys.modules.pop(f"geodepth_lite.{name}", None)
    drop()
    yield
    drop()


@pytest.mark.parametrize("name", MOVED)
def test_an_old_name_imports_the_moved_module_with_a_warning(name, forget_old_names):
    with pytest.warns(DeprecationWarning, match=rf"geodepth_lite\.{name} moved to geodepth_lite\.core\.{name};"):
        old = importlib.import_module(f"geodepth_lite.{name}")
    assert old is importlib.import_module(f"geodepth_lite.core.{name}")


def test_every_form_of_the_old_import_works(forget_old_names):
    from geodepth_lite.core import losses

    with pytest.warns(DeprecationWarning):
        import geodepth_lite.sdf as sdf_old
        from geodepth_lite import camera  # noqa: F401
        from geodepth_lite.losses import total_loss
    assert total_loss is losses.total_loss and sdf_old.__name__ == "geodepth_lite.core.sdf"
    assert geodepth_lite.camera.__name__ == "geodepth_lite.core.camera"


def test_a_name_that_never_existed_is_still_missing():
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("geodepth_lite.no_such_module")
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("geodepth_lite.core.camera_x")
