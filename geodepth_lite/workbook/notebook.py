"""The set-up every numbered notebook starts with: check the common parameters, seed, run folder.

Papermill passes parameters as plain values, so a typo in a value (``case=5``, ``seed=-1``)
would otherwise surface deep inside a cell. ``setup`` checks the parameters all notebooks
share, by name, and resolves the folder their figures and tables go to the same way
everywhere (``reproduce.resolve_run_dir``)::

    prof, out = notebook.setup(profile, run_dir, seed=seed, case=case, n_examples=n_examples)

``save_table`` and ``save_figure`` write a notebook's tables and figures into that folder, where
``reproduce`` collects them into its report.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.evaluation.tables import markdown_table
from geodepth_lite.training import config
from geodepth_lite.workbook import reproduce


def check_int(name: str, value: Any, minimum: int = 0) -> int:
    """``value`` if it is an integer of at least ``minimum``, else a clear error naming the parameter."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        kind = {0: "a non-negative integer", 1: "a positive integer"}.get(minimum, f"an integer >= {minimum}")
        raise UserError(f"parameter {name} must be {kind}, got {value!r}")
    return value


def setup(profile: str, run_dir: str = "", *, seed: int | None = None, case: int | None = None,
          n_examples: int | None = None, **positive: int) -> tuple[config.Profile, Path]:
    """Check the notebook's parameters; seed python, numpy and torch; return (the profile, run folder).

    The profile (``config.Profile``, read like a dict: ``prof["predict_flips"]``) is made here, once
    for the notebook, and makes the configurations of the runs it loads (``prof.predict_run()``).

    profile: one of ``config.PROFILES``. run_dir: "" = ``runs/<profile>/`` in the workspace.
    seed: a non-negative integer, used to seed everything (0 when not given). case: an
    ablation case (Section 4.2.1). n_examples and any other keyword: positive integers.
    """
    prof = config.profile(profile)
    if case is not None and case not in config.ABLATION_CASES:
        raise UserError(f"parameter case must be one of {sorted(config.ABLATION_CASES)}, got {case!r}")
    if n_examples is not None:
        check_int("n_examples", n_examples, 1)
    for name, value in positive.items():
        check_int(name, value, 1)
    utils.seed_everything(check_int("seed", seed) if seed is not None else 0)
    return prof, reproduce.resolve_run_dir(prof, run_dir)


def save_table(run_dir: str | os.PathLike, name: str, columns: list[str], rows: list[list[Any]], *,
               title: str = "", notes: str = "", digits: int = 3) -> Path:
    """Write ``tables/<name>.json`` (+ ``.md``) under ``run_dir``; return the JSON path."""
    if not name or "/" in name or name.startswith("."):
        raise UserError(f"table name must be a plain file name, got {name!r}")
    if any(len(r) != len(columns) for r in rows):
        raise UserError(f"table {name!r}: every row needs {len(columns)} cells")
    table = {"name": name, "title": title, "columns": list(columns), "rows": [list(map(_plain, r)) for r in rows],
             "notes": notes}
    path = Path(run_dir) / "tables" / f"{name}.json"
    utils.write_json_atomic(path, table)
    md = ((f"**{title}**\n\n" if title else "") + markdown_table(columns, rows, digits)
          + (f"\n\n{notes}" if notes else ""))
    utils.write_bytes_atomic(path.with_suffix(".md"), (md + "\n").encode())
    return path


def save_figure(fig, run_dir: str | os.PathLike, name: str, dpi: int = 100) -> Path:
    """Write a matplotlib figure to ``figures/<name>.png`` under ``run_dir`` (atomically)."""
    path = Path(run_dir) / "figures" / f"{name}.png"
    with utils.atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight")
    return path


def save_record(run_dir: str | os.PathLike, name: str, record: dict[str, float]) -> Path:
    """Write a notebook's results record (every number that comes from trained weights, flat
    ``{key: number}``) to ``records/<name>.json`` under ``run_dir``, and say so in one line.

    ``tests/test_results.py`` compares it with the committed ``notebooks/records/<name>.json``
    within tolerances (trained weights differ between computers), so the notebook itself prints
    no long dump of numbers.
    """
    if not name or "/" in name or name.startswith("."):
        raise UserError(f"record name must be a plain file name, got {name!r}")
    bad = [k for k, v in record.items() if isinstance(v, bool) or not isinstance(_plain(v), (int, float))]
    if bad:
        raise UserError(f"record {name!r}: entries must be numbers, not {bad[:3]}")
    path = Path(run_dir) / "records" / f"{name}.json"
    utils.write_json_atomic(path, {k: _plain(record[k]) for k in sorted(record)})
    print(f"results record: {len(record)} numbers written to records/{name}.json in the run folder")
    return path


def _plain(x: Any) -> Any:
    """JSON-friendly cell: numpy scalars to python numbers."""
    if hasattr(x, "item") and callable(x.item):
        return x.item()
    return x


def evidence(name: str) -> list[dict]:
    """The rows of ``benchmarks/<name>.json``: the validation runs behind the teach recipe
    ("teach_recipe", "lambda_search", "view_evidence"; their prose is docs/teach_recipe.md)."""
    path = utils.checkout_path("benchmarks") / f"{name}.json"
    if not path.is_file():
        raise FileNotFoundError(f"no evidence table {name!r}: {path} is missing")
    return json.loads(path.read_text())["rows"]
