"""The datasets: the synthetic set, and the public endoscopy depth datasets, one small class each.

Laid out as monodepth2's ``datasets/`` (one module per dataset):

- ``synthetic``: the generated set as a torch Dataset (``SyntheticDepthDataset``), the one resize
  recipe (``resize_image``, ``resize_frame``), ``resolve_dataset`` and the training splits kept in
  memory (``load_split``, ``MemoryDataset``, ``MEMORY_CACHE``) or on a CUDA device (``DeviceSplit``,
  ``DeviceBatches``);
- ``base``: what the public datasets share: ``PublicDepthDataset`` (the torch Dataset and the
  description of a dataset in one), the registry (``REGISTRY``, ``register``, ``dataset_class``)
  and ``open_dataset``;
- ``endoslam``, ``colondepth``: the two the paper evaluates on (Section 4.1); ``simcol3d``,
  ``c3vd``: two more. Each holds its class (``EndoSLAMDataset``, ``ColonDepthDataset``,
  ``SimCol3DDataset``, ``C3VDDataset``) and its constants (``ENDOSLAM_*``, ...);
- ``subsets``: the paper's evaluation subsets (``data_manifests/eval_subsets/*.json``) counted
  in a user's copy (``count_subset_frames``, ``check_eval_subsets``, ``format_check``).

This module registers the public datasets: ``REGISTRY`` ({name: class}) is the only list of
dataset names, in the order below (``DATASETS`` is ``tuple(REGISTRY)``). A class holds its
``name``, ``layout`` (the folder layout quoted in errors), ``depth_units``, ``max_depth`` (the
largest depth its encoding holds: the evaluation mask's bound, Section 4.2.1) and
``subset_manifest`` (its paper subsets in ``data_manifests/eval_subsets/``, or None), and says
how frames are found under a root (``find_frames``, with the poses where the dataset has them),
how a depth file is decoded (``decode_depth``) and its intrinsics at native size (``intrinsics``).

``open_dataset(name, root, **filters)`` reads a user's copy of EndoSLAM (UnityCam),
ColonDepth, SimCol3D or C3VD in its original layout and depth encoding and returns an
instance of that class, whose items look like the synthetic set's (``SyntheticDepthDataset``)::

    {"image": float32 3xHxW in [0, 1], "depth": float32 1xHxW z-depth (0 where invalid),
     "K": float32 3x3 pixels, "organ": str, "group": str, "index": int,
     "valid": bool 1xHxW (pixels with a usable ground-truth depth)}

Depth stays in each dataset's own unit (``ds.depth_units``; EndoSLAM is relative, so
evaluation must median-scale, as the paper does, Section 4.2.1). ``ds.frames`` lists one
record per item (file paths, sequence, frame number, ``T_world_cam`` where the dataset
has poses). Every fact in a dataset's module that the datasets' documentation does not pin
down is one named constant marked UNVERIFIED, so a user whose copy differs changes one line.

``count_subset_frames(manifest, root)`` counts the frames of the paper's evaluation subsets in a
user's copy and reports mismatches; ``python -m geodepth_lite evaluate --dataset endoslam
--root PATH --check`` prints that report.
"""

from geodepth_lite.data.datasets.base import REGISTRY, PublicDepthDataset, dataset_class, open_dataset, register
from geodepth_lite.data.datasets.c3vd import C3VDDataset
from geodepth_lite.data.datasets.colondepth import ColonDepthDataset
from geodepth_lite.data.datasets.endoslam import EndoSLAMDataset
from geodepth_lite.data.datasets.simcol3d import SimCol3DDataset
from geodepth_lite.data.datasets.subsets import check_eval_subsets, count_subset_frames, format_check, load_subset_manifest
from geodepth_lite.data.datasets.synthetic import CACHE_LIMIT_BYTES, MEMORY_CACHE, DeviceBatches, DeviceSplit, MemoryDataset, SyntheticDepthDataset, load_split, read_frames, resize_frame, resize_image, resolve_dataset

# The public datasets, in the order REGISTRY lists them: the paper's two test sets first.
for cls in (EndoSLAMDataset, ColonDepthDataset, SimCol3DDataset, C3VDDataset):
    register(cls)
del cls

DATASETS = tuple(REGISTRY)  # the registered names, for compatibility

__all__ = [
    "CACHE_LIMIT_BYTES", "DATASETS", "MEMORY_CACHE", "REGISTRY", "C3VDDataset", "ColonDepthDataset",
    "DeviceBatches", "DeviceSplit", "EndoSLAMDataset", "MemoryDataset", "PublicDepthDataset", "SimCol3DDataset",
    "SyntheticDepthDataset",
    "check_eval_subsets", "count_subset_frames", "dataset_class", "format_check", "load_split", "load_subset_manifest",
    "open_dataset", "read_frames", "register", "resize_frame", "resize_image", "resolve_dataset",
]
