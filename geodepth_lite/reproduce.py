"""``python -m geodepth_lite reproduce``: run the numbered notebooks, then write the report.

Each ``notebooks/NN_*.ipynb`` runs in order with papermill (parameters ``profile`` and
``run_dir``, plus any ``-p NAME VALUE`` the notebooks declare) into ``runs/<profile>/``.
Everything the user asked for is checked before the first notebook starts: the
profile, the notebook selection, and that every extra parameter is declared in the
``parameters`` cell of at least one selected notebook (with a value of the same type).

Output contract (what the notebooks write and the report reads), all under run_dir:
- ``notebooks/NN_topic.ipynb``: the executed notebooks;
- ``tables/<name>.json``: one table each, written by ``notebook.save_table``:
  {"name", "title", "columns": [...], "rows": [[...], ...], "notes": str};
  ``<name>`` starts with the notebook's number (``NN_name``) so the report can
  order them; a markdown copy ``tables/<name>.md`` sits beside it;
- ``figures/<name>.png``: figures, written by ``notebook.save_figure`` (same naming);
- ``.reproduce/NN_topic.json``: written after a notebook finished; a rerun skips
  notebooks whose marker matches the notebook's source and parameters, so an
  interrupted ``reproduce`` continues where it stopped (``--force`` reruns all);
- ``report.md`` and ``report.json``: every table and figure, grouped by notebook.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import functools
import hashlib
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

from geodepth_lite import config, run_cache, study, study2, utils
from geodepth_lite.tables import markdown_table

MARKER_DIR = ".reproduce"


class NotebookFailed(RuntimeError):
    """A notebook raised while running; the message names it and its executed copy."""


# --------------------------------------------------------------------------- the contract (used by notebooks)


def resolve_run_dir(profile: str, run_dir: str | os.PathLike = "") -> Path:
    """The notebooks' ``run_dir`` parameter: "" means ``runs/<profile>/`` in the workspace."""
    config.get_profile(profile)
    path = Path(run_dir).expanduser() if str(run_dir) else utils.runs_dir() / profile
    path.mkdir(parents=True, exist_ok=True)
    return path


# --------------------------------------------------------------------------- notebooks and parameters


def notebooks_dir() -> Path:
    root = utils.project_root()
    if root is None:
        raise FileNotFoundError("notebooks/ not found: run reproduce from a checkout of geodepth-lite")
    return root / "notebooks"


def list_notebooks(directory: Path | None = None) -> list[Path]:
    """The numbered notebooks ``NN_*.ipynb`` in order."""
    directory = directory or notebooks_dir()
    return sorted(p for p in directory.glob("[0-9][0-9]_*.ipynb") if p.is_file())


def notebook_parameters(path: Path) -> dict[str, Any]:
    """Names and default values of the ``parameters``-tagged cell (flat literal assignments)."""
    import nbformat  # heavy: needed only to read a notebook's parameters

    nb = nbformat.read(str(path), as_version=4)
    cells = [c for c in nb.cells if c.cell_type == "code" and "parameters" in c.get("metadata", {}).get("tags", [])]
    if len(cells) != 1:
        raise ValueError(f"{path.name}: expected exactly one cell tagged 'parameters', found {len(cells)}")
    params = {}
    for node in ast.parse(cells[0].source).body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            try:
                params[node.targets[0].id] = ast.literal_eval(node.value)
            except ValueError:
                params[node.targets[0].id] = None
    return params


def select_notebooks(only: list[str] | None, available: list[Path]) -> list[Path]:
    """``only`` entries are numbers ("NN", "N") or names ("NN_name", "NN_name.ipynb")."""
    if not only:
        return list(available)
    chosen = []
    for item in only:
        key = item.removesuffix(".ipynb")
        match = [p for p in available if p.stem == key or p.stem.split("_")[0] == key.zfill(2)]
        if not match:
            raise ValueError(f"--notebooks: no notebook {item!r}; available: {', '.join(p.stem for p in available)}")
        chosen += [p for p in match if p not in chosen]
    return sorted(chosen)


def parse_value(text: str) -> Any:
    """A ``-p`` value: a Python literal (3, 0.5, True, [0, 1], "x") or else the text itself."""
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def check_parameters(notebooks: list[Path], extra: dict[str, Any]) -> dict[Path, dict[str, Any]]:
    """Per notebook, the extra parameters it declares; a clear error for an undeclared name or wrong type."""
    declared = {nb: notebook_parameters(nb) for nb in notebooks}
    for name in ("profile", "run_dir"):
        lacking = [nb.name for nb, ps in declared.items() if name not in ps]
        if lacking:
            raise ValueError(f"notebook(s) {', '.join(lacking)} do not declare the parameter {name!r}")
    for name in ("profile", "run_dir"):
        if name in extra:
            raise ValueError(f"-p {name}: use --profile / --out instead")
    per_nb: dict[Path, dict[str, Any]] = {nb: {} for nb in notebooks}
    for name, value in extra.items():
        owners = [nb for nb, ps in declared.items() if name in ps]
        if not owners:
            known = sorted({k for ps in declared.values() for k in ps} - {"profile", "run_dir"})
            raise ValueError(f"unknown notebook parameter {name!r}: the selected notebooks declare "
                             f"{', '.join(known) or 'only profile and run_dir'}")
        for nb in owners:
            default = declared[nb][name]
            if default is not None and not _same_kind(default, value):
                raise ValueError(f"parameter {name!r} of {nb.name} expects {type(default).__name__} "
                                 f"(default {default!r}), got {value!r}")
            per_nb[nb][name] = value
    return per_nb


def _same_kind(default: Any, value: Any) -> bool:
    if isinstance(default, bool) or isinstance(value, bool):
        return isinstance(default, bool) and isinstance(value, bool)
    if isinstance(default, (int, float)):
        return isinstance(value, (int, float)) and (isinstance(default, float) or isinstance(value, int))
    return isinstance(value, type(default))


def _marker(nb: Path, params: dict) -> dict:
    return {"source_sha256": hashlib.sha256(nb.read_bytes()).hexdigest(),
            "parameters": json.loads(json.dumps(params, default=str))}


def _is_done(run_dir: Path, nb: Path, params: dict) -> bool:
    mpath = run_dir / MARKER_DIR / f"{nb.stem}.json"
    if not mpath.exists() or not (run_dir / "notebooks" / nb.name).exists():
        return False
    try:
        m = json.loads(mpath.read_text())
    except ValueError:
        return False
    want = _marker(nb, params)
    return all(m.get(k) == v for k, v in want.items())


# --------------------------------------------------------------------------- running and the report


MODELS_KEY = "geodepth_lite"  # notebook metadata: {"models": [spec, ...]}, the models the notebook loads
# a spec's "settings": the training settings beyond (case, seed) of each kind of model
SETTINGS = {"predict": run_cache.predict_settings, "real": run_cache.real_settings, "ablation": lambda profile: {}}


def notebook_models(nb: Path) -> list[dict]:
    """The models a notebook declares in its metadata (``metadata.geodepth_lite.models``).

    Each spec names the trained models by (case, seed): ``"case"``/``"seed"`` or ``"cases"``/
    ``"seeds"`` hold a number (or list) or the name of one of the notebook's parameters;
    ``"settings"`` is "predict" (the profile's ``predict`` model, ``run_cache.predict_settings``),
    "real" (its model for real frames, ``run_cache.real_settings``) or "ablation" (the profile's
    own settings); ``"workers"`` optionally names the parameter
    with the number of runs trained side by side. A notebook without the key loads no model.
    """
    meta = json.loads(nb.read_text()).get("metadata", {}).get(MODELS_KEY, {})
    specs = meta.get("models", [])
    for spec in specs:
        if spec.get("settings") not in SETTINGS:
            raise ValueError(f"{nb.name}: metadata {MODELS_KEY}.models: settings must be one of {', '.join(SETTINGS)}, "
                             f"got {spec.get('settings')!r}")
    return specs


def training_runs(profile: str, plan: list[tuple[Path, dict]]) -> tuple[list[tuple[int, int, dict]], int | None]:
    """The models that the notebooks of ``plan`` ([(notebook, its parameters)]) declare
    (``notebook_models``), as (case, seed, overrides) runs for ``run_cache.ensure_runs``, and the
    worker count a notebook asks for (None: one per core). Trained together before the notebooks
    run, the longest (the ``predict`` model) overlaps the ablation's runs instead of running alone."""
    runs: list[tuple[int, int, dict]] = []
    workers = None
    for nb, given in plan:
        p = {**notebook_parameters(nb), **given}
        for spec in notebook_models(nb):
            value = lambda key: p[spec[key]] if isinstance(spec.get(key), str) else spec[key]  # noqa: E731
            cases = value("cases") if "cases" in spec else [value("case")]
            seeds = value("seeds") if "seeds" in spec else [value("seed")]
            overrides = SETTINGS[spec["settings"]](profile)
            runs += [(int(c), int(s), dict(overrides)) for c in cases for s in seeds]
            if "workers" in spec:
                workers = int(value("workers")) or None
    unique = [r for i, r in enumerate(runs) if r not in runs[:i]]
    return unique, workers


def reproduce(profile: str = "teach", *, notebooks: list[str] | None = None, params: dict[str, Any] | None = None,
              run_dir: str | os.PathLike | None = None, force: bool = False, progress: bool = True,
              dry_run: bool = False) -> Path:
    """Run the selected numbered notebooks into ``run_dir`` (default runs/<profile>/) and write
    report.md / report.json there; returns the report.md path. Checks everything first."""
    config.get_profile(profile)
    selected = select_notebooks(notebooks, list_notebooks())
    if not selected:
        raise FileNotFoundError(f"no numbered notebooks (NN_*.ipynb) in {notebooks_dir()}")
    per_nb = check_parameters(selected, dict(params or {}))
    out = resolve_run_dir(profile, run_dir or "")
    plan = []
    for nb in selected:
        p = {"profile": profile, "run_dir": str(out), **per_nb[nb]}
        plan.append((nb, p, (not force) and _is_done(out, nb, p)))
    for c, s, o in training_runs(profile, [(nb, p) for nb, p, _ in plan])[0]:
        config.make_config(profile, c, s, **o)  # a bad case or seed is refused now, dry run or not
    if dry_run:
        for nb, p, done in plan:
            print(f"{'skip' if done else 'run '} {nb.name} {p}")
        return out / "report.md"
    log = _read_json(out / "report.json").get("notebooks", {}) if (out / "report.json").exists() else {}
    train_models(profile, *training_runs(profile, [(nb, p) for nb, p, done in plan if not done]), progress=progress)
    for nb, p, done in plan:
        if done:
            print(f"[reproduce] {nb.name}: complete, skipped (--force reruns it)", flush=True)
            continue
        seconds = run_notebook(nb, p, out, inject_run_dir=not (run_dir is None and str(out) == str(
            resolve_run_dir(profile, ""))), progress=progress)
        log[nb.stem] = {"seconds": round(seconds, 1)}
    for nb, _, _ in plan:
        m = out / MARKER_DIR / f"{nb.stem}.json"
        if m.exists() and nb.stem not in log:
            log[nb.stem] = {"seconds": round(_read_json(m).get("seconds", float("nan")), 1)}
    return write_report(out, profile, log)


def train_models(profile: str, runs: list[tuple[int, int, dict]], workers: int | None, *, progress: bool) -> None:
    """Train the runs that are not complete yet, side by side (``run_cache.ensure_runs``)."""
    folders = {run_cache.checkpoint_dir(profile, c, s, **o): (c, s, o) for c, s, o in runs}
    todo = [r for r in folders.values() if not run_cache.is_complete(profile, r[0], r[1], **r[2])]
    if not todo:
        return
    print(f"[reproduce] training {len(todo)} of the {len(folders)} models the notebooks use, side by side "
          "(an interrupted one continues from its last epoch) ...", flush=True)
    t0 = time.perf_counter()
    after = None
    if any(study.is_subset_run(profile, *r) for r in todo):  # scored by the process that trains it, on these sets
        study.evaluation_sets(profile, progress=progress)
        after = functools.partial(study.score_if_subset_run, profile)
    run_cache.ensure_runs(profile, todo, workers=workers, progress=progress, after=after)
    print(f"[reproduce] models ready in {time.perf_counter() - t0:.0f} s", flush=True)


def run_notebook(nb: Path, params: dict, out: Path, *, inject_run_dir: bool, progress: bool) -> float:
    """Execute ``nb`` with papermill into ``out/notebooks/``, then mark it done; returns its seconds."""
    import papermill  # heavy: imported only when a notebook runs

    # papermill's own guess at the parameters cell trips over comments with quotes and
    # warns about parameters it missed; they were checked (ast), so keep it quiet
    logging.getLogger("papermill").setLevel(logging.ERROR)
    print(f"[reproduce] {nb.name} ...", flush=True)
    t0 = time.perf_counter()
    target = out / "notebooks" / nb.name
    target.parent.mkdir(parents=True, exist_ok=True)
    (out / MARKER_DIR / f"{nb.stem}.json").unlink(missing_ok=True)
    # only what differs from the notebook's own defaults is injected, so a default run's
    # executed notebook is the notebook itself, outputs filled in (no injected cell)
    defaults = notebook_parameters(nb)
    given = {k: v for k, v in params.items() if not (k in defaults and defaults[k] == v)}
    if not inject_run_dir:
        given.pop("run_dir", None)  # "" resolves to the same folder in the kernel
    try:
        papermill.execute_notebook(str(nb), str(target), parameters=given, kernel_name="python3",
                                   cwd=str(nb.parent), progress_bar=progress)
    except papermill.PapermillExecutionError as exc:
        raise NotebookFailed(f"{nb.name} failed ({exc.ename}: {exc.evalue}); the executed copy with the "
                             f"traceback is {target}. Fix it and run the same command again: completed "
                             "notebooks are skipped.") from None
    seconds = time.perf_counter() - t0
    utils.write_json_atomic(out / MARKER_DIR / f"{nb.stem}.json", {**_marker(nb, params), "seconds": seconds})
    print(f"[reproduce] {nb.name} done in {seconds:.0f} s", flush=True)
    return seconds


def _read_json(path: Path) -> dict:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}


def write_report(run_dir: Path, profile: str, notebook_log: dict | None = None) -> Path:
    """Collect ``tables/*.json`` and ``figures/*.png`` under ``run_dir`` into report.md and report.json."""
    run_dir = Path(run_dir)
    tables = {p.stem: _read_json(p) for p in sorted((run_dir / "tables").glob("*.json"))}
    figures = sorted(p.relative_to(run_dir).as_posix() for p in (run_dir / "figures").glob("*.png"))
    notebook_log = notebook_log or {}
    prefixes = sorted({n.split("_")[0] for n in list(tables) + [Path(f).stem for f in figures]})
    try:
        names = {nb.stem.split("_")[0]: nb.stem for nb in list_notebooks()}
    except FileNotFoundError:  # installed without the notebooks: headings by number
        names = {}
    names.update({nb.split("_")[0]: nb for nb in notebook_log})
    md = [f"# geodepth-lite report: profile `{profile}`", "",
          "Tables and figures written by the notebooks of this run (executed copies in `notebooks/`).", ""]
    if notebook_log:
        md += ["| notebook | minutes |", "|---|---|"]
        md += [f"| {k} | {v.get('seconds', float('nan')) / 60:.1f} |" for k, v in sorted(notebook_log.items())]
        md.append("")
    for prefix in prefixes:
        md += [f"## {names.get(prefix, prefix)}", ""]
        for name, t in tables.items():
            if name.split("_")[0] != prefix or "columns" not in t:
                continue
            md += [f"### {t.get('title') or name}", "", markdown_table(t["columns"], t["rows"]), ""]
            if t.get("notes"):
                md += [t["notes"], ""]
        for f in figures:
            if Path(f).stem.split("_")[0] == prefix:
                md += [f"![{Path(f).stem}]({f})", ""]
    report = {"profile": profile, "notebooks": notebook_log, "tables": tables, "figures": figures,
              "written": time.strftime("%Y-%m-%dT%H:%M:%S")}
    utils.write_json_atomic(run_dir / "report.json", report)
    utils.write_bytes_atomic(run_dir / "report.md", "\n".join(md).encode())
    return run_dir / "report.md"


# --------------------------------------------------------------------------- CLI


def add_arguments_reproduce(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", default="teach", help="smoke | teach | paper (default teach)")
    parser.add_argument("--notebooks", nargs="+", default=None, metavar="NN",
                        help="run only these notebooks (numbers like 04 05, or names); default all")
    parser.add_argument("-p", "--parameter", nargs=2, action="append", default=[], metavar=("NAME", "VALUE"),
                        help="extra notebook parameter (must be declared in a selected notebook's parameters cell)")
    parser.add_argument("--out", default=None, help="run folder (default runs/<profile>/)")
    parser.add_argument("--force", action="store_true", help="rerun notebooks that already completed")
    parser.add_argument("--dry-run", action="store_true", help="check everything and show the plan; run nothing")
    parser.add_argument("--study", action="store_true",
                        help="the confirmatory ablation study (docs/study_plan.md): train its 48 runs, score them "
                             "into <run folder>/study/, then run notebook 05 on those tables")
    parser.add_argument("--study2", action="store_true",
                        help="the second study (docs/study_plan_2.md): train its 24 runs, score them into "
                             "<run folder>/study2/, then run notebook 05 on those tables")
    parser.add_argument("--no-progress", action="store_true")


def run_study(profile: str, run_dir: str | os.PathLike | None = None, *, progress: bool = True,
              which=study, name: str = "study", title: str = "the study") -> Path:
    """Train (or reuse) a study's runs, score them and write its tables into ``<run folder>/<name>/``
    (``which.write_tables``; ``which`` is :mod:`study` or :mod:`study2`); returns that folder. An
    interrupted study continues: finished runs are reused, an unfinished one resumes from its last epoch."""
    out = resolve_run_dir(profile, run_dir or "") / name
    utils.check_can_create_dir(out)
    t0 = time.perf_counter()
    print(f"[reproduce] {title}: {len(which.study_runs(profile))} runs ({profile}) ...", flush=True)
    paths = which.train(profile, progress=progress)
    print(f"[reproduce] runs ready in {time.perf_counter() - t0:.0f} s; scoring them ...", flush=True)
    sets = study.evaluation_sets(profile, progress=progress)
    runs, frames = which.score(paths, sets, progress=progress)
    folder = which.write_tables(out, runs, frames, study.score_baselines(profile, sets), study.provenance_rows(paths))
    print(f"[reproduce] {title}'s tables: {folder} ({(time.perf_counter() - t0) / 60:.1f} min)", flush=True)
    return folder


def run_study2(profile: str, run_dir: str | os.PathLike | None = None, *, progress: bool = True) -> Path:
    """:func:`run_study` for the second study (docs/study_plan_2.md): its 24 runs into ``<run folder>/study2/``."""
    return run_study(profile, run_dir, progress=progress, which=study2, name="study2", title="the second study")


def _study_notebook_declares(name: str) -> None:
    """Refuse ``--study2`` before any training when notebook 05 has no parameter ``name``."""
    nb = [p for p in list_notebooks() if p.stem.startswith("05")]
    if nb and name not in notebook_parameters(nb[0]):
        raise ValueError(f"{nb[0].name} does not declare the parameter {name!r}: it cannot read the tables "
                         "that --study2 writes")


def reproduce_locks(profile: str, run_dir: str | os.PathLike | None = None) -> contextlib.ExitStack:
    """The locks one ``reproduce`` holds while it trains and runs notebooks: the profile's folder
    ``runs/<profile>/`` (where its models are trained) and the run folder, if another, taken in one
    order (sorted paths), so two reproduces never hold one each and wait for the other. A busy one
    is waited for (``utils.wait_for_lock``: one line "waiting for reproduce (PID n) holding ..."),
    then this one goes on, finding the models the other trained."""
    folders = {(utils.runs_dir() / profile).resolve(), resolve_run_dir(profile, run_dir or "").resolve()}
    stack = contextlib.ExitStack()
    try:
        for folder in sorted(folders):
            lock = utils.wait_for_lock(utils.FolderLock(folder), "reproduce")
            stack.callback(lock.release)
    except BaseException:
        stack.close()
        raise
    return stack


def run_reproduce(args: argparse.Namespace) -> int:
    params: dict[str, Any] = {}
    for name, value in args.parameter:
        if name in params:
            raise ValueError(f"-p {name} given twice")
        params[name] = parse_value(value)
    if args.dry_run:
        return _run_reproduce(args, params)
    study_run = args.study or getattr(args, "study2", False)
    if getattr(args, "study2", False):  # before the first study's runs too
        _study_notebook_declares("study2_tables")
    check_request(args.profile, ["05"] if study_run else args.notebooks, params)  # before any lock or folder
    with reproduce_locks(args.profile, args.out):
        return _run_reproduce(args, params)


def check_request(profile: str, notebooks: list[str] | None, params: dict[str, Any]) -> None:
    """What ``reproduce`` checks before it writes anything (profile, notebooks, parameters, the
    models' cases and seeds), without making a folder: refused requests take no lock either."""
    config.get_profile(profile)
    selected = select_notebooks(notebooks, list_notebooks())
    if not selected:
        raise FileNotFoundError(f"no numbered notebooks (NN_*.ipynb) in {notebooks_dir()}")
    per_nb = check_parameters(selected, dict(params))
    plan = [(nb, {"profile": profile, "run_dir": "", **per_nb[nb]}) for nb in selected]
    for c, s, o in training_runs(profile, plan)[0]:
        config.make_config(profile, c, s, **o)


def _run_reproduce(args: argparse.Namespace, params: dict[str, Any]) -> int:
    t0 = time.perf_counter()
    studies = [(flag, which, fn) for flag, which, fn in (("study", study, run_study), ("study2", study2, run_study2))
               if getattr(args, flag, False)]
    if studies and args.notebooks:
        raise ValueError(f"--{studies[0][0]} runs notebook 05 on the study's tables: leave out --notebooks")
    for flag, which, fn in studies:  # the study's tables first, then notebook 05 reads them
        if args.dry_run:
            runs = which.study_runs(args.profile)
            todo = sum(not run_cache.is_complete(args.profile, c, s, **o) for _, c, s, o in runs)
            print(f"{flag}: {len(runs)} runs ({todo} to train), scored into "
                  f"{resolve_run_dir(args.profile, args.out or '') / flag}")
        else:
            params[f"{flag}_tables"] = str(fn(args.profile, args.out, progress=not args.no_progress))
    if studies:
        args.notebooks, args.force = ["05"], True
    try:
        report = reproduce(args.profile, notebooks=args.notebooks, params=params, run_dir=args.out,
                           force=args.force, progress=not args.no_progress, dry_run=args.dry_run)
    except NotebookFailed as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if not args.dry_run:
        print(f"report: {report} ({(time.perf_counter() - t0) / 60:.1f} min)")
    sys.stdout.flush()
    return 0
