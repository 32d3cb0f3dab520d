"""geodepth-lite: a workbook reproducing Yang et al. (2023), "A Geometry-Aware
Deep Network for Depth Estimation in Monocular Endoscopy".

The package holds what the notebooks reuse and the tests check; each module is
one arrow of the data flow (see README, "Architecture").
"""

import importlib as _importlib
import importlib.abc as _abc
import importlib.util as _util
import os as _os
import sys as _sys
import warnings as _warnings

__version__ = "0.1.0"

# Headless machines (CI, servers, most notebooks run by papermill) have no X display:
# ask VTK for its EGL window directly instead of trying X first and warning on stderr.
if not _os.environ.get("DISPLAY"):
    _os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

# The package is in wings (see docs/architecture.md): the paper's method in ``core``, then ``data``,
# ``training``, ``evaluation``, ``views``, ``apps`` and ``workbook``. The former flat names
# (geodepth_lite.camera, geodepth_lite.train, geodepth_lite.datasets.c3vd, ...) still import, with a
# DeprecationWarning that names the new place, for notebooks written against the previous release.
# They go in the next one.
_WINGS = {
    "core": "camera errors losses metrics model nnsearch nnsearch_triton sdf",
    "data": "analytic appearance augment datasets fov images integrity manifest render render_agreement "
            "render_torch synth tube",
    "training": "checkpoint config distributed inference provenance run_cache train train_cli train_many",
    "evaluation": "ablation baselines border evaluate evaluate_cli exploratory external gallery run_scores "
                  "study study2 tables",
    "views": "recon viz",
    "apps": "bundle gpu_check predict",
    "workbook": "autograde book book_reader course exercises grading lesson_guard notebook reproduce review "
                "sandbox sandbox_kernel widgets",
}
MOVED = {leaf: f"{__name__}.{wing}.{leaf}" for wing, leaves in _WINGS.items() for leaf in leaves.split()}


class _MovedModule(_abc.Loader):
    def __init__(self, target: str):
        self.target = target

    def create_module(self, spec):
        return None

    def exec_module(self, module):
        _warnings.warn(f"{module.__name__} moved to {self.target}; the old name goes in the next release",
                       DeprecationWarning, stacklevel=2)
        _sys.modules[module.__name__] = _importlib.import_module(self.target)


class _MovedFinder(_abc.MetaPathFinder):
    """Finds a former flat name (and the modules inside a moved package) before the path finder does,
    so that an old name gives the very module object of the new one, never a second copy."""

    def find_spec(self, name, path=None, target=None):
        parts = name.split(".")
        if len(parts) < 2 or parts[0] != __name__ or parts[1] not in MOVED:
            return None
        target = ".".join([MOVED[parts[1]]] + parts[2:])
        if _util.find_spec(target) is None:
            return None  # not a module there either: the import fails as for any missing name, with no warning
        return _util.spec_from_loader(name, _MovedModule(target))


if not any(isinstance(f, _MovedFinder) for f in _sys.meta_path):
    _sys.meta_path.insert(0, _MovedFinder())
