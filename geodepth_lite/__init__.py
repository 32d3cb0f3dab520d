"""geodepth-lite: a workbook reproducing Yang et al. (2023), "A Geometry-Aware
Deep Network for Depth Estimation in Monocular Endoscopy".

The package holds what the notebooks reuse and the tests check; each module is
one arrow of the data flow (see README, "Architecture").
"""

__version__ = "0.1.0"
