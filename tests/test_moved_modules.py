"""The package moved into wings (``core``, ``data``, ``training``, ``evaluation``, ``views``, ``apps``,
``workbook``). Notebooks written against the previous release import the former flat names
(``from geodepth_lite import camera``, ``geodepth_lite.train``, ``geodepth_lite.datasets.c3vd``): those
still give the very same module, with a DeprecationWarning that names the new place."""

import importlib
import pkgutil
import re
import sys
from pathlib import Path

import pytest

import geodepth_lite

PACKAGE = Path(geodepth_lite.__file__).parent
WINGS = ("core", "data", "training", "evaluation", "views", "apps", "workbook")
OLD_NAMES = sorted(geodepth_lite.MOVED)


@pytest.fixture
def forget_old_names():
    """The old names are imported afresh in each test and forgotten after it."""
    def drop():
        for name in list(sys.modules):
            parts = name.split(".")
            if parts[0] == "geodepth_lite" and len(parts) > 1 and parts[1] in geodepth_lite.MOVED:
                sys.modules.pop(name)
    drop()
    yield
    drop()


@pytest.mark.parametrize("name", OLD_NAMES)
def test_an_old_name_imports_the_moved_module_with_a_warning(name, forget_old_names):
    target = geodepth_lite.MOVED[name]
    with pytest.warns(DeprecationWarning, match=re.escape(f"geodepth_lite.{name} moved to {target};")):
        old = importlib.import_module(f"geodepth_lite.{name}")
    assert old is importlib.import_module(target)


def test_every_form_of_the_old_import_works(forget_old_names):
    from geodepth_lite.core import losses
    from geodepth_lite.data.datasets import c3vd
    from geodepth_lite.training import train

    with pytest.warns(DeprecationWarning):
        import geodepth_lite.datasets.c3vd as c3vd_old
        import geodepth_lite.sdf as sdf_old
        from geodepth_lite import camera  # noqa: F401
        from geodepth_lite import train as train_old
        from geodepth_lite.losses import total_loss
    assert total_loss is losses.total_loss and sdf_old.__name__ == "geodepth_lite.core.sdf"
    assert geodepth_lite.camera.__name__ == "geodepth_lite.core.camera"
    assert train_old is train and c3vd_old is c3vd  # the module inside a moved package: no second copy


def test_the_table_of_old_names_is_every_module_of_the_wings():
    """Each module a wing holds has its former flat name in the table, except the ones new in the wings'
    release (predict's reading and writing rooms had no flat name) and the bounds on files from elsewhere
    (formerly part of ``utils``), and the table names nothing else."""
    new_in_wings = {"frames", "depth_files", "bounds"}
    in_wings = {m.name: f"geodepth_lite.{wing}.{m.name}" for wing in WINGS
                for m in pkgutil.iter_modules([str(PACKAGE / wing)]) if m.name not in new_in_wings}
    assert geodepth_lite.MOVED == in_wings


def test_a_name_that_never_existed_is_still_missing(recwarn):
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("geodepth_lite.no_such_module")
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("geodepth_lite.core.camera_x")
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("geodepth_lite.datasets.no_such_loader")
    assert not [w for w in recwarn if issubclass(w.category, DeprecationWarning) and "no_such" in str(w.message)]
