"""Tables and result files of an evaluation: what ``evaluate.evaluate_predictor`` writes, and what the
notebooks print.

``markdown_table`` and ``metrics_table`` lay out the seven metrics (Section 4.2.1) per set, group or
method. ``write_results`` writes ``metrics.json``, ``frames.csv`` (one row per frame), ``tables.md``
and error-map PNGs laid out like the paper's Fig. 7 (``viz.error_map_figure``) as one set: all of
them or, on a failure, none (an earlier set in that folder is kept whole). ``flat_record`` flattens
the numbers a notebook shows into the record that ``tests/test_results.py`` compares.
"""

from __future__ import annotations

import contextlib
import csv
import gzip
import io
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from geodepth_lite import utils
from geodepth_lite.core.metrics import EVAL_MAX_DEPTH, EVAL_MIN_DEPTH, METRIC_NAMES
from geodepth_lite.views.viz import error_map_figure

# the seven metrics of Section 4.2.1 (``metrics.METRIC_NAMES``) as the tables head them
METRIC_LABELS = {"abs_rel": "Abs Rel", "sq_rel": "Sq Rel", "rmse": "RMSE", "rmse_log": "RMSE log",
                 "a1": "a1", "a2": "a2", "a3": "a3"}


# --------------------------------------------------------------------------- tables


def fmt(x: Any, digits: int = 3) -> str:
    """A table cell: floats rounded to ``digits`` decimals, the rest as text."""
    if isinstance(x, (float, np.floating)):
        return "nan" if not np.isfinite(x) else f"{x:.{digits}f}"
    return str(x)


def markdown_table(columns: list[str], rows: Iterable[Iterable[Any]], digits: int = 3) -> str:
    """A GitHub-flavoured markdown table (floats rounded to ``digits``)."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(fmt(c, digits) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def metrics_table(result: dict, by: str | None = None) -> dict:
    """{"columns", "rows"} of the seven metrics: one row overall (plus one per baseline in
    ``result["baselines"]``), or one per group/organ."""
    columns = [by or "set", "frames"] + [METRIC_LABELS[k] for k in METRIC_NAMES]
    baselines = result.get("baselines") or {}
    if by is None and baselines:  # the model's row, then one row per baseline on the same frames
        columns[0] = "method"
        parts = {f"model ({result['name']})" if result.get("name") else "model": result["overall"]}
        parts.update({f"baseline: {k}": b["overall"] for k, b in baselines.items()})
    elif by is None:
        parts = {result.get("name") or "all": result["overall"]}
    else:
        parts = result[f"by_{by}"]
    rows = [[g, s["n"]] + [s[k] for k in METRIC_NAMES] for g, s in parts.items()]
    return {"columns": columns, "rows": rows}


# --------------------------------------------------------------------------- result files, one set or none


OUTPUT_SET = ("metrics.json", "frames.csv", "tables.md", "error_maps")  # one evaluation's files, replaced whole
MARKER = ".evaluate"  # marks an output folder as evaluate's (utils.claim_folder): it may write there again
STAGING_PREFIX = ".eval-staging-"  # hidden folder in the output folder where a new set is written first
PREVIOUS_PREFIX = ".eval-previous-"  # hidden folder that holds the replaced set until the new one is in place
TABLES_BYTES = 4 * 2**20  # room asked for metrics.json, frames.csv and tables.md before any work (a few kB each)
ERROR_MAP_BYTES = 2**20  # and per error-map PNG (about 0.1-0.3 MB at dpi 80)



def csv_bytes(rows: list[dict]) -> bytes:
    """``rows`` (dicts with the same keys, in order) as CSV: a header line, then one line each."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue().encode()


def read_csv(path: str | os.PathLike, missing: str = "") -> list[dict]:
    """The rows of a CSV file (``.gz``: gzip-compressed) as dicts of strings; a missing file is a
    FileNotFoundError naming it, followed by ``missing`` (what writes it)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"table not found: {path}{missing}")
    data = gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()
    return list(csv.DictReader(io.StringIO(data.decode())))


def output_bytes_needed(error_maps: int) -> int:
    """A generous estimate of the bytes one evaluation writes: its tables and ``error_maps`` PNGs."""
    return TABLES_BYTES + max(0, int(error_maps)) * ERROR_MAP_BYTES


def _problem_reason(exc: utils.FileProblem) -> str:
    """The reason part of a :class:`utils.FileProblem` ("no space left on device"), without its path."""
    cause = exc.__cause__
    if isinstance(cause, OSError) and not isinstance(cause, utils.FileProblem):
        return utils.os_reason(cause)
    text = str(exc)
    prefix = f"{exc.path}: " if exc.path is not None else ""
    return text.split(prefix, 1)[1] if prefix and prefix in text else text


def prepare_output_dir(out: str | os.PathLike, need_bytes: int = 0) -> Path:
    """``out`` as a writable folder with ``need_bytes`` free, checked before any work (``utils.check_output_dir``).

    Any refusal is a :class:`utils.FileProblem` reading "cannot write <out>: <reason>" (a file of
    that name, a read-only or full disk, no permission), and the folders this call created are
    removed again.
    """
    out = Path(out)
    if os.path.lexists(out) and not out.is_dir():
        raise utils.FileProblem(f"cannot write {out}: a file of that name exists (the output must be a folder)", out)
    try:
        return utils.check_output_dir(out, need_bytes)
    except utils.FileProblem as exc:
        raise utils.FileProblem(f"cannot write {out}: {_problem_reason(exc)}", out) from exc


def _hidden_folder(out: Path, prefix: str) -> Path:
    """A new empty hidden folder in ``out`` (same file system, so renames out of it are atomic)."""
    try:
        return Path(tempfile.mkdtemp(prefix=prefix, dir=out))
    except OSError as exc:
        raise utils.FileProblem(f"cannot write {out}: {utils.os_reason(exc)}", out) from exc


def _remove_stale_sets(out: Path) -> None:
    """Delete the hidden staging / previous-set folders an evaluation killed mid-write left in ``out``."""
    for prefix in (STAGING_PREFIX, PREVIOUS_PREFIX):
        for folder in out.glob(prefix + "*"):
            if folder.is_dir() and not folder.is_symlink():
                shutil.rmtree(folder, ignore_errors=True)


def _remove_path(path: Path) -> None:
    """Delete a file or a folder tree, if present."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif os.path.lexists(path):
        path.unlink()


@contextlib.contextmanager
def _staged_file(staging: Path, out: Path, name: str) -> Iterator[Path]:
    """A temporary path for ``staging/name`` (``utils.atomic_path``: flushed, renamed when complete); a
    failure is a :class:`utils.FileProblem` naming the file's final place ``out/name``."""
    try:
        with utils.atomic_path(staging / name) as tmp:
            yield tmp
    except utils.FileProblem as exc:
        raise utils.FileProblem(f"cannot write {out / name}: {_problem_reason(exc)}", out / name) from exc


def _results_files(result: dict) -> dict[str, bytes]:
    """The text files of a result: {"metrics.json": ..., "frames.csv": ..., "tables.md": ...} as bytes."""
    summary = {k: v for k, v in result.items() if k != "frames"}
    if result.get("baselines"):
        summary["baselines"] = {name: {k: v for k, v in b.items() if k != "frames"}
                                for name, b in result["baselines"].items()}
    fields = ["index", "organ", "group", *METRIC_NAMES, "ratio", "skipped"]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for r in result["frames"]:
        w.writerow({k: (f"{r[k]:.6g}" if isinstance(r[k], float) else r[k]) for k in fields if k in r})
    skipped = result.get("skipped", [])
    md = [f"# Evaluation {result.get('name', '')}".rstrip(), "", f"{result['n']} frames; median scaling per frame."
          + (f" {len(skipped)} skipped (no valid ground-truth pixel): {', '.join(skipped)}." if skipped else ""), ""]
    for by in (None, "organ", "group"):
        t = metrics_table(result, by)
        title = "Overall" if by is None else f"By {by}" + (" (model)" if result.get("baselines") else "")
        md += [f"## {title}", "", markdown_table(t["columns"], t["rows"]), ""]
        if by is None and result.get("baselines"):
            md += ["Baselines: trivial predictors scored on the same frames with the same protocol; "
                   "a model must beat them for its numbers to mean anything.", ""]
            for name, b in result["baselines"].items():
                md.append(f"- `{name}`: {b.get('description', '')}".rstrip())
                md += [f"  - {note}" for note in b.get("notes", [])]
            md.append("")
    return {"metrics.json": (json.dumps(summary, indent=2) + "\n").encode(), "frames.csv": buf.getvalue().encode(),
            "tables.md": "\n".join(md).encode()}


def _stage_results(result: dict, staging: Path, out: Path, examples: Iterable[dict] = (), *,
                   min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH) -> None:
    """Write the whole set (``_results_files`` and one error-map PNG per example) into ``staging``."""
    for name, data in _results_files(result).items():
        with _staged_file(staging, out, name) as tmp:
            tmp.write_bytes(data)
    examples = list(examples)
    if examples:
        # heavy, needed only for error maps; no backend switch: a notebook's inline figures must keep showing
        import matplotlib.pyplot as plt

        for ex in examples:
            fig = error_map_figure([ex], min_depth=min_depth, max_depth=max_depth)
            try:
                with _staged_file(staging, out, f"error_maps/{ex['index']:06d}.png") as tmp:
                    fig.savefig(tmp, format="png", dpi=80, bbox_inches="tight")
            finally:
                plt.close(fig)


def _roll_back(out: Path, previous: Path, moved_aside: list[str], placed: list[str]) -> bool:
    """Undo a half-done ``_commit_results``: remove the new files put in ``out``, move the old ones back.

    Returns whether every old file is back in place (else some are still in ``previous``)."""
    ok = True
    for name in placed:
        with contextlib.suppress(OSError):
            _remove_path(out / name)
    for name in moved_aside:
        try:
            os.replace(previous / name, out / name)
        except OSError:
            ok = False
    return ok


def _commit_results(staging: Path, out: Path) -> None:
    """Swap the set in ``staging`` for the one in ``out``: every name of ``OUTPUT_SET``, new or old, at once.

    The old set's entries are first moved aside into a hidden folder, then the new ones moved
    in, by renames within one file system (no data is written in this phase). If any rename
    fails, the new entries are removed and the old ones moved back, and a
    :class:`utils.FileProblem` is raised; on success the old set is deleted.
    """
    previous = _hidden_folder(out, PREVIOUS_PREFIX)
    moved_aside: list[str] = []
    placed: list[str] = []
    try:
        for name in OUTPUT_SET:
            if os.path.lexists(out / name):
                os.replace(out / name, previous / name)
                moved_aside.append(name)
        for name in OUTPUT_SET:
            if os.path.lexists(staging / name):
                os.replace(staging / name, out / name)
                placed.append(name)
        utils.fsync_dir(out)
    except BaseException as exc:
        restored = _roll_back(out, previous, moved_aside, placed)
        if restored:
            shutil.rmtree(previous, ignore_errors=True)
        if not isinstance(exc, OSError):
            raise
        kept = "the previous results are kept" if restored else f"the previous results are in {previous}"
        raise utils.FileProblem(f"cannot write {out}: {utils.os_reason(exc)} ({kept})", out) from exc
    shutil.rmtree(previous, ignore_errors=True)


def write_results(result: dict, out_dir: str | os.PathLike, examples: Iterable[dict] = (), *,
                  min_depth: float = EVAL_MIN_DEPTH, max_depth: float = EVAL_MAX_DEPTH) -> None:
    """metrics.json, frames.csv, tables.md and error_maps/*.png in ``out_dir``, as one set or none.

    Guarantee: when this returns, ``out_dir`` holds exactly the new set (``OUTPUT_SET``; the
    error_maps folder holds this run's PNGs only, none if there are no examples); when it raises
    (full or read-only disk, an interrupt...), ``out_dir`` holds what it held before, an earlier
    run's set untouched and nothing new, and folders this call created are removed again.

    How: every file is first written and flushed into a hidden staging folder inside
    ``out_dir``; only then is the set swapped in by renames (``_commit_results``), which move no
    data and are undone if one fails. Other files in ``out_dir`` are left alone. Not covered:
    a power loss or kill -9 during the swap itself (a few renames) can leave part of either
    set, the rest being in a hidden ``.eval-previous-*`` folder; the next write_results into
    that folder deletes such leftovers. Two evaluations writing into one folder at the same time
    are not supported here: the ``evaluate`` command holds the folder's lock (``utils.FolderLock``).
    """
    out = Path(out_dir)
    created = utils.missing_dirs(out)
    try:
        prepare_output_dir(out)
        _remove_stale_sets(out)
        staging = _hidden_folder(out, STAGING_PREFIX)
        try:
            _stage_results(result, staging, out, examples, min_depth=min_depth, max_depth=max_depth)
            _commit_results(staging, out)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    except BaseException:
        utils.remove_empty_dirs(created)
        raise


# --------------------------------------------------------------------------- the notebooks' record


def flat_record(tree: dict, digits: int = 4, keys: Iterable[str] = METRIC_NAMES) -> dict[str, float]:
    """A nested dict ending in metric dicts, flattened to {"a | b | metric": value rounded to ``digits``}.

    The notebooks print such a record of every number that comes from trained weights, so a
    test can compare a fresh run with the committed one within a tolerance.
    """
    out: dict[str, float] = {}

    def walk(node: dict, path: list[str]) -> None:
        if any(k in node for k in keys):
            for k in keys:
                if k in node:
                    out[" | ".join(path + [k])] = round(float(node[k]), digits)
            return
        for name, child in node.items():
            if isinstance(child, dict):
                walk(child, path + [str(name)])

    walk(tree, [])
    return out
