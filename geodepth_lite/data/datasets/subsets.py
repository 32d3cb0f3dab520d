"""The paper's evaluation subsets (``data_manifests/eval_subsets/*.json``) counted in a user's copy.

A subset manifest names its public dataset and lists subsets, each a ``filter`` on the frame
records (``organ``, ``group``, ``sequence``) and the number of ``frames`` the paper used.
``count_subset_frames(manifest, root)`` counts each subset's frames under ``root``;
``check_eval_subsets(name, root)`` does so against a dataset's own manifest (its class's
``subset_manifest``); ``format_check`` prints the rows. ``python -m geodepth_lite evaluate
--dataset endoslam --root PATH --check`` prints that report.
"""

from __future__ import annotations

import json
from pathlib import Path

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.data.datasets.base import REGISTRY, PublicDepthDataset, as_set, dataset_class, open_dataset


def load_subset_manifest(manifest) -> dict:
    """A subset manifest: a dict, a path to JSON, or a name in ``data_manifests/eval_subsets/``."""
    if isinstance(manifest, dict):
        m = manifest
    else:
        p = Path(manifest)
        if not p.suffix:
            p = utils.manifests_dir() / "eval_subsets" / f"{manifest}.json"
        if not p.is_file():
            raise FileNotFoundError(f"subset manifest {manifest} not found ({p})")
        m = json.loads(p.read_text())
    for key in ("dataset", "subsets"):
        if key not in m:
            raise UserError(f"subset manifest lacks {key!r}")
    if m["dataset"] not in REGISTRY:
        raise UserError(f"subset manifest: unknown dataset {m['dataset']!r}")
    for s in m["subsets"]:
        for key in ("name", "filter", "frames"):
            if key not in s:
                raise UserError(f"subset manifest: a subset lacks {key!r}")
        if not isinstance(s["frames"], int) or s["frames"] <= 0:
            raise UserError(f"subset {s['name']}: frames must be a positive integer")
    return m


def count_subset_frames(manifest, root) -> list[dict]:
    """Count the frames of each paper subset in ``root``; one row per subset.

    Row: {"subset", "expected", "found", "status"} with status "ok" (counts equal),
    "more" (the copy holds more frames than the paper used: select as the manifest's
    notes say), "fewer" (frames missing) or "missing" (no frame of that subset).
    A root that is missing or in another layout raises the loader's error.
    """
    m = load_subset_manifest(manifest)
    ds = open_dataset(m["dataset"], root)
    rows = []
    for s in m["subsets"]:
        found = sum(all(f[k] in as_set(v, k) for k, v in s["filter"].items()) for f in ds.frames)
        exp = s["frames"]
        status = "ok" if found == exp else "missing" if found == 0 else "more" if found > exp else "fewer"
        rows.append({"subset": s["name"], "expected": exp, "found": found, "status": status})
    return rows


def check_eval_subsets(dataset: str | type[PublicDepthDataset], root, manifest=None) -> list[dict]:
    """``count_subset_frames`` of ``root`` against ``manifest`` (default: the ``subset_manifest`` of ``dataset``,
    a registered name or class)."""
    cls = dataset_class(dataset) if isinstance(dataset, str) else dataset
    if manifest is None:
        if cls.subset_manifest is None:
            have = ", ".join(n for n, c in REGISTRY.items() if c.subset_manifest)
            raise UserError(f"{cls.name} has no evaluation subset manifest (the paper's subsets: {have}); "
                             "give a manifest JSON to check against")
        manifest = cls.subset_manifest
    m = load_subset_manifest(manifest)
    if m["dataset"] != cls.name:
        raise UserError(f"subset manifest {manifest} describes {m['dataset']}, not {cls.name}")
    return count_subset_frames(m, root)


def format_check(rows: list[dict]) -> str:
    """``count_subset_frames``'s rows as a fixed-width table (subset, expected, found, status)."""
    lines = [f"{'subset':<18}{'expected':>9}{'found':>8}  status"]
    lines += [f"{r['subset']:<18}{r['expected']:>9}{r['found']:>8}  {r['status']}" for r in rows]
    return "\n".join(lines)
