"""The set-up every numbered notebook starts with: check the common parameters, seed, run folder.

Papermill passes parameters as plain values, so a typo in a value (``case=5``, ``seed=-1``)
would otherwise surface deep inside a cell. ``setup`` checks the parameters all notebooks
share, by name, and resolves the folder their figures and tables go to the same way
everywhere (``reproduce.resolve_run_dir``)::

    prof, out = notebook.setup(profile, run_dir, seed=seed, case=case, n_examples=n_examples)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from geodepth_lite import config, reproduce, utils


def check_int(name: str, value: Any, minimum: int = 0) -> int:
    """``value`` if it is an integer of at least ``minimum``, else a clear error naming the parameter."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        kind = {0: "a non-negative integer", 1: "a positive integer"}.get(minimum, f"an integer >= {minimum}")
        raise ValueError(f"parameter {name} must be {kind}, got {value!r}")
    return value


def setup(profile: str, run_dir: str = "", *, seed: int | None = None, case: int | None = None,
          n_examples: int | None = None, **positive: int) -> tuple[dict, Path]:
    """Check the notebook's parameters; seed python, numpy and torch; return (profile settings, run folder).

    profile: one of ``config.PROFILES``. run_dir: "" = ``runs/<profile>/`` in the workspace.
    seed: a non-negative integer, used to seed everything (0 when not given). case: an
    ablation case (Section 4.3). n_examples and any other keyword: positive integers.
    """
    prof = config.get_profile(profile)
    if case is not None and case not in config.ABLATION_CASES:
        raise ValueError(f"parameter case must be one of {sorted(config.ABLATION_CASES)}, got {case!r}")
    if n_examples is not None:
        check_int("n_examples", n_examples, 1)
    for name, value in positive.items():
        check_int(name, value, 1)
    utils.seed_everything(check_int("seed", seed) if seed is not None else 0)
    return prof, reproduce.resolve_run_dir(profile, run_dir)
