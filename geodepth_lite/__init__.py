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

# The paper's method moved into geodepth_lite.core; the old names (geodepth_lite.camera, ...) still
# import, with a DeprecationWarning, for notebooks written against the previous release. They go in
# the next one.
_MOVED_TO_CORE = ("camera", "errors", "losses", "metrics", "model", "nnsearch", "nnsearch_triton", "sdf")


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
    def find_spec(self, name, path=None, target=None):
        package, _, leaf = name.rpartition(".")
        if package != __name__ or leaf not in _MOVED_TO_CORE:
            return None
        return _util.spec_from_loader(name, _MovedModule(f"{__name__}.core.{leaf}"))


if not any(isinstance(f, _MovedFinder) for f in _sys.meta_path):
    _sys.meta_path.append(_MovedFinder())
