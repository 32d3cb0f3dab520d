"""geodepth-lite: a workbook reproducing Yang et al. (2023), "A Geometry-Aware
Deep Network for Depth Estimation in Monocular Endoscopy".

The package holds what the notebooks reuse and the tests check; each module is
one arrow of the data flow (see README, "Architecture").
"""

import os as _os

__version__ = "0.1.0"

# Headless machines (CI, servers, most notebooks run by papermill) have no X display:
# ask VTK for its EGL window directly instead of trying X first and warning on stderr.
if not _os.environ.get("DISPLAY"):
    _os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
