"""``python -m geodepth_lite reproduce``: train the models, run the numbered notebooks, write the report.

Each ``notebooks/NN_*.ipynb`` runs with papermill (parameters ``profile`` and ``run_dir``, plus
any ``-p NAME VALUE`` the notebooks declare) into ``runs/<profile>/``. Everything the user asked
for is checked before anything starts: the profile, the notebook selection, and that every extra
parameter is declared in the ``parameters`` cell of at least one selected notebook (with a value
of the same type).

The work is a set of jobs, each in a process of its own (``ProcessJob``): one per model the
notebooks load that is not trained yet (``run_cache.train_run``), one per notebook. A notebook's
job needs the jobs of the models it declares in its metadata (``notebook_models``). ``run_jobs``
keeps as many jobs running as the cores hold at the profile's threads per run (two on two cores
under ``teach``): while a model is left to train one of them trains, the longest chain of work
first, and the others run the notebooks that are ready, so the notebooks that load no model run
beside the training and each other one starts as soon as its models are trained. One progress
line says what runs, how many jobs are done and about how long is left (``seconds_left``). A
failed job stops new ones from starting, the running ones finish, and the command ends with one
line naming it; everything finished is kept. The report is written after every job ended, from
what the notebooks wrote, in the notebooks' order, whatever order they finished in.

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
- ``.reproduce/logs/<job>.txt``: what each job's process printed (a failed one's traceback);
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
import multiprocessing
import os
import shutil
import signal
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, TextIO

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.data.datasets import resolve_dataset
from geodepth_lite.evaluation import study, study2
from geodepth_lite.evaluation.tables import markdown_table
from geodepth_lite.training import config, run_cache
from geodepth_lite.training.config import Profile, RunConfig

MARKER_DIR = ".reproduce"
JOB_POLL_S = 0.5  # seconds between two looks at the running jobs


class JobFailed(RuntimeError):
    """A job of ``reproduce`` (a training run or a notebook) failed; the one-line message names it."""


class NotebookFailed(JobFailed):
    """A notebook raised while running; the message names it and its executed copy."""


# --------------------------------------------------------------------------- the contract (used by notebooks)


def resolve_run_dir(prof: Profile, run_dir: str | os.PathLike = "") -> Path:
    """The notebooks' ``run_dir`` parameter: "" means ``runs/<profile>/`` in the workspace."""
    path = Path(run_dir).expanduser() if str(run_dir) else utils.runs_dir() / prof.name
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
        raise UserError(f"{path.name}: expected exactly one cell tagged 'parameters', found {len(cells)}")
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
            raise UserError(f"--notebooks: no notebook {item!r}; available: {', '.join(p.stem for p in available)}")
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
            raise UserError(f"notebook(s) {', '.join(lacking)} do not declare the parameter {name!r}")
    for name in ("profile", "run_dir"):
        if name in extra:
            raise UserError(f"-p {name}: use --profile / --out instead")
    per_nb: dict[Path, dict[str, Any]] = {nb: {} for nb in notebooks}
    for name, value in extra.items():
        owners = [nb for nb, ps in declared.items() if name in ps]
        if not owners:
            known = sorted({k for ps in declared.values() for k in ps} - {"profile", "run_dir"})
            raise UserError(f"unknown notebook parameter {name!r}: the selected notebooks declare "
                             f"{', '.join(known) or 'only profile and run_dir'}")
        for nb in owners:
            default = declared[nb][name]
            if default is not None and not _same_kind(default, value):
                raise UserError(f"parameter {name!r} of {nb.name} expects {type(default).__name__} "
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
SETTINGS = {"predict": Profile.predict_settings, "real": Profile.real_settings, "ablation": lambda prof: {}}


def notebook_models(nb: Path) -> list[dict]:
    """The models a notebook declares in its metadata (``metadata.geodepth_lite.models``).

    Each spec names the trained models by (case, seed): ``"case"``/``"seed"`` or ``"cases"``/
    ``"seeds"`` hold a number (or list) or the name of one of the notebook's parameters;
    ``"settings"`` is "predict" (the profile's ``predict`` model, ``Profile.predict_settings``),
    "real" (its model for real frames, ``Profile.real_settings``) or "ablation" (the profile's
    own settings); ``"workers"`` optionally names the parameter
    with the number of runs trained side by side. A notebook without the key loads no model.
    """
    meta = json.loads(nb.read_text()).get("metadata", {}).get(MODELS_KEY, {})
    specs = meta.get("models", [])
    for spec in specs:
        if spec.get("settings") not in SETTINGS:
            raise UserError(f"{nb.name}: metadata {MODELS_KEY}.models: settings must be one of {', '.join(SETTINGS)}, "
                             f"got {spec.get('settings')!r}")
    return specs


def notebook_runs(prof: Profile, nb: Path, given: dict) -> tuple[list[RunConfig], int | None]:
    """The models notebook ``nb`` loads with its parameters ``given`` (over its defaults), as run
    configurations, and the worker count it asks for (None: none asked)."""
    p = {**notebook_parameters(nb), **given}
    runs: list[RunConfig] = []
    workers = None
    for spec in notebook_models(nb):
        value = lambda key: p[spec[key]] if isinstance(spec.get(key), str) else spec[key]  # noqa: E731
        cases = value("cases") if "cases" in spec else [value("case")]
        seeds = value("seeds") if "seeds" in spec else [value("seed")]
        overrides = SETTINGS[spec["settings"]](prof)
        runs += [prof.run(int(c), int(s), **overrides) for c in cases for s in seeds]
        if "workers" in spec:
            workers = int(value("workers")) or None
    return runs, workers


def training_runs(prof: Profile, plan: list[tuple[Path, dict]]) -> tuple[list[RunConfig], int | None]:
    """The models that the notebooks of ``plan`` ([(notebook, its parameters)]) declare
    (``notebook_models``), as run configurations for ``run_cache.ensure_runs``, and the
    worker count a notebook asks for (None: one per core). Trained together before the notebooks
    run, the longest (the ``predict`` model) overlaps the ablation's runs instead of running alone."""
    runs: list[RunConfig] = []
    workers = None
    for nb, given in plan:
        nb_runs, nb_workers = notebook_runs(prof, nb, given)
        runs += nb_runs
        workers = nb_workers if nb_workers is not None else workers
    unique = [r for i, r in enumerate(runs) if r not in runs[:i]]
    return unique, workers


def reproduce(prof: Profile, *, notebooks: list[str] | None = None, params: dict[str, Any] | None = None,
              run_dir: str | os.PathLike | None = None, force: bool = False, progress: bool = True,
              dry_run: bool = False, start: Callable[[Job], Any] | None = None) -> Path:
    """Train the models the selected numbered notebooks load and run the notebooks into ``run_dir``
    (default runs/<profile>/), side by side (``plan_jobs``, ``run_jobs``), then write report.md /
    report.json there; returns the report.md path. Checks everything first. ``start``: how a job is
    started (default: ``ProcessJob``, a process of its own). ``prof``: ``config.profile(name)``."""
    selected = select_notebooks(notebooks, list_notebooks())
    if not selected:
        raise FileNotFoundError(f"no numbered notebooks (NN_*.ipynb) in {notebooks_dir()}")
    per_nb = check_parameters(selected, dict(params or {}))
    out = resolve_run_dir(prof, run_dir or "")
    plan = []
    for nb in selected:
        p = {"profile": prof.name, "run_dir": str(out), **per_nb[nb]}
        plan.append((nb, p, (not force) and _is_done(out, nb, p)))
    training_runs(prof, [(nb, p) for nb, p, _ in plan])  # a bad case or seed is refused now, dry run or not
    if dry_run:
        for nb, p, done in plan:
            print(f"{'skip' if done else 'run '} {nb.name} {p}")
        return out / "report.md"
    log = _read_json(out / "report.json").get("notebooks", {}) if (out / "report.json").exists() else {}
    for nb, _, done in plan:
        if done:
            print(f"[reproduce] {nb.name}: complete, skipped (--force reruns it)", flush=True)
    inject = not (run_dir is None and str(out) == str(resolve_run_dir(prof, "")))
    jobs, slots = plan_jobs(prof, plan, out, inject_run_dir=inject, progress=progress)
    if jobs:
        trains = sum(j.kind == "train" for j in jobs)
        print(f"[reproduce] {trains} model(s) to train and {len(jobs) - trains} notebook(s) to run, {slots} at a "
              f"time (an interrupted run continues from its last epoch; each job's output: "
              f"{out / MARKER_DIR / 'logs'})", flush=True)
        run_jobs(jobs, slots, start=start or functools.partial(ProcessJob, env=job_env(prof)),
                 show=JobProgress(len(jobs), slots, enabled=progress))
    ran = {nb.stem for nb, _, done in plan if not done}
    for nb, _, _ in plan:
        m = out / MARKER_DIR / f"{nb.stem}.json"
        if m.exists() and (nb.stem in ran or nb.stem not in log):
            log[nb.stem] = {"seconds": round(_read_json(m).get("seconds", float("nan")), 1)}
    return write_report(out, prof.name, log)


def job_env(prof: Profile) -> dict:
    """The environment of each job's process: where the profile fixes the threads per run, a
    notebook's kernel gets as many (training sets its own from the configuration)."""
    threads = prof.get("threads")
    return {"OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)} if threads else {}


def job_slots(prof: Profile, workers: int | None) -> int:
    """Jobs at once: ``workers`` when a notebook asks for it, else the cores over the profile's
    threads per run (one where the profile does not fix them)."""
    if workers:
        return workers
    threads = prof.get("threads")
    return max(1, (os.cpu_count() or 1) // threads) if threads else 1


def recorded_seconds(nb: Path, default: float = 60.0) -> float:
    """How long ``nb`` took when it was last executed: the duration papermill recorded in its
    metadata (``metadata.papermill.duration``, the record docs/timings.md states), else ``default``."""
    duration = json.loads(nb.read_text()).get("metadata", {}).get("papermill", {}).get("duration")
    return float(duration) if isinstance(duration, (int, float)) and duration > 0 else default


def run_label(prof: Profile, run: RunConfig) -> str:
    """A training job's name: "case 4 seed 0 (predict model, 96 px)", "case 1 seed 2 (64 px)"."""
    kind = next((k for k, f in SETTINGS.items() if k != "ablation" and run.overrides
                 and prof.run(run.case, run.seed, **f(prof)) == run), "")
    return f"case {run.case} seed {run.seed} ({kind + ' model, ' if kind else ''}{run['image_size']} px)"


def plan_jobs(prof: Profile, plan: list[tuple[Path, dict, bool]], out: Path, *, inject_run_dir: bool,
              progress: bool) -> tuple[list[Job], int]:
    """The jobs of ``plan`` ([(notebook, parameters, done)]) and how many run at once: one per model
    the notebooks not done load that is not trained yet (``run_cache.train_run``), then one per
    notebook not done (``run_notebook``), needing the jobs of the models it loads. Datasets (and
    the ablation's evaluation sets) are built here first, before any job starts."""
    todo = [(nb, p) for nb, p, done in plan if not done]
    runs, workers = training_runs(prof, todo)
    folders: dict[Path, str] = {}
    train = []
    for run in runs:
        folder = run_cache.checkpoint_dir(run)
        if folder not in folders and not run_cache.is_complete(run):
            name = run_label(prof, run)
            folders[folder] = name if name not in folders.values() else f"{name} [{folder.name}]"
            train.append((run, folder))
    scoring = any(spec["settings"] == "ablation" for nb, _ in todo for spec in notebook_models(nb))
    after = prepare_training(prof, [run for run, _ in train], progress=progress, sets=scoring)
    logs = out / MARKER_DIR / "logs"
    jobs = [Job(folders[folder], functools.partial(run_cache.train_run, run, after=after), (),
                60 * run_cache.estimated_minutes(run), "train", logs / f"{folder.name}.txt") for run, folder in train]
    for nb, p in todo:
        wanted = [run_cache.checkpoint_dir(run) for run in notebook_runs(prof, nb, p)[0]]
        needs = tuple(dict.fromkeys(folders[f] for f in wanted if f in folders))
        jobs.append(Job(nb.stem, functools.partial(run_notebook, nb, p, out, inject_run_dir=inject_run_dir,
                                                   progress=False), needs, recorded_seconds(nb), "notebook",
                        logs / f"{nb.stem}.txt"))
    if jobs:
        utils.make_dir(logs)
    return jobs, job_slots(prof, workers)


def prepare_training(prof: Profile, runs: list[RunConfig], *, progress: bool, sets: bool = False):
    """Before the ``runs`` train: each one's dataset found or built, and where one is a run of the
    ablation's default subset, the evaluation sets that its training process scores it on (with
    ``sets``, in any case: notebooks that score the ablation's runs read them, and jobs running side
    by side then never build one dataset twice at once). Returns the ``after`` hook for
    ``run_cache.train_run`` (None when no run is scored)."""
    for run in runs:
        resolve_dataset(run.as_dict(), progress=progress)
    scored = any(study.is_subset_run(prof, run) for run in runs)
    if scored or sets:
        study.evaluation_sets(prof, progress=progress)  # scored by the process that trains it, on these sets
    return functools.partial(study.score_if_subset_run, prof) if scored else None


def train_models(prof: Profile, runs: list[RunConfig], workers: int | None, *, progress: bool) -> None:
    """Train the runs that are not complete yet, side by side (``run_cache.ensure_runs``)."""
    folders = {run_cache.checkpoint_dir(run): run for run in runs}
    todo = [run for run in folders.values() if not run_cache.is_complete(run)]
    if not todo:
        return
    print(f"[reproduce] training {len(todo)} of the {len(folders)} models the notebooks use, side by side "
          "(an interrupted one continues from its last epoch) ...", flush=True)
    t0 = time.perf_counter()
    after = prepare_training(prof, todo, progress=progress)
    run_cache.ensure_runs(todo, workers=workers, progress=progress, after=after)
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


# --------------------------------------------------------------------------- the jobs and their scheduler


@dataclass
class Job:
    """One training run or one notebook execution. ``fn()`` does it (picklable: it runs in a process
    of its own); it starts once every job named in ``needs`` has finished. ``seconds``: its expected
    duration (the progress line's estimate); ``kind``: "train" or "notebook"; ``log``: where its
    process's output goes (None: the console)."""

    name: str
    fn: Callable[[], Any]
    needs: tuple[str, ...] = ()
    seconds: float = 0.0
    kind: str = "train"
    log: Path | None = None


def _job_main(name: str, fn: Callable[[], Any], conn, log: str | None, env: dict) -> None:
    """A job's process: its output into ``log``, ``env`` over the environment (a notebook's kernel
    inherits it), then ``fn()``; sends "" on success, else the one line naming the job."""
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # stopped: clean up (a notebook's kernel) and end
    os.environ.update(env)
    if log is not None:
        fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        os.dup2(fd, 1)
        os.dup2(fd, 2)
    try:
        fn()
    except BaseException as exc:  # noqa: BLE001 - every failure goes back as one line
        conn.send(failure_line(name, exc, log))
        traceback.print_exc()  # into its log
        sys.stderr.flush()
        raise SystemExit(1) from None
    conn.send("")


def failure_line(name: str, exc: BaseException, log: str | None = None) -> str:
    """One line naming the failed job: a notebook's own message, else the job, the error and its log."""
    if isinstance(exc, NotebookFailed):
        return " ".join(str(exc).split())
    first = (str(exc).strip().splitlines() or [""])[0]
    where = f"; its output: {log}" if log else ""
    return f"{name} failed ({type(exc).__name__}: {first}){where}"[:2000]


class ProcessJob:
    """A job running in a process of its own (spawned: no state shared with this one)."""

    def __init__(self, job: Job, env: dict | None = None):
        ctx = multiprocessing.get_context("spawn")
        self.job = job
        self._recv, send = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=_job_main, args=(job.name, job.fn, send, str(job.log) if job.log else None,
                                                        dict(env or {})), name=f"reproduce {job.name}")
        self.proc.start()
        send.close()

    def result(self) -> str | None:
        """None while it runs; "" once it finished; the one line that names it once it failed."""
        if self.proc.is_alive():
            return None
        self.proc.join()
        try:
            said = self._recv.recv() if self._recv.poll() else None
        except EOFError:  # it ended before it could say (e.g. it could not start)
            said = None
        if self.proc.exitcode == 0 and said == "":
            return ""
        return said or f"{self.job.name} failed: its process ended with exit code {self.proc.exitcode}"

    def stop(self) -> None:
        """Stop it (Ctrl-C or an error here): SIGTERM lets it clean up; SIGKILL after 30 s."""
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(30)
            if self.proc.is_alive():
                self.proc.kill()
                self.proc.join()


def chain_seconds(jobs: list[Job], own: dict[str, float]) -> dict[str, float]:
    """Per job, ``own`` seconds of it plus the longest chain of jobs that wait on it (critical path)."""
    after: dict[str, list[str]] = {j.name: [] for j in jobs}
    for j in jobs:
        for n in j.needs:
            after.setdefault(n, []).append(j.name)
    memo: dict[str, float] = {}

    def chain(name: str) -> float:
        if name not in memo:
            memo[name] = own.get(name, 0.0) + max((chain(n) for n in after.get(name, [])), default=0.0)
        return memo[name]

    return {j.name: chain(j.name) for j in jobs}


def pace(jobs: list[Job], took: dict[str, float]) -> dict[str, float]:
    """Per kind of job ("train", "notebook"), how much longer than expected the finished ones took on
    this machine (``took``: their seconds): their seconds over their expected seconds. A kind none of
    whose jobs has finished takes the pace of all finished jobs; 1.0 before any finished."""
    def ratio(kind: str | None) -> float | None:
        ended = [j for j in jobs if j.name in took and j.seconds > 0 and kind in (None, j.kind)]
        expected = sum(j.seconds for j in ended)
        return sum(took[j.name] for j in ended) / expected if expected > 0 else None

    overall = ratio(None) or 1.0
    return {kind: ratio(kind) or overall for kind in {j.kind for j in jobs}}


def seconds_left(jobs: list[Job], done: set[str], elapsed: dict[str, float], slots: int,
                 took: dict[str, float] | None = None) -> float:
    """About how long the jobs not done yet still take on ``slots`` workers: their expected seconds
    at this machine's :func:`pace` (from ``took``, the finished jobs' seconds; none: as expected), a
    running job's less its ``elapsed`` (at least 0), over the workers, or the longest chain of them
    where that is longer."""
    rate = pace(jobs, took or {})
    own = {j.name: 0.0 if j.name in done else max(j.seconds * rate[j.kind] - elapsed.get(j.name, 0.0), 0.0)
           for j in jobs}
    chains = chain_seconds(jobs, own)
    return max(sum(own.values()) / max(slots, 1), max(chains.values(), default=0.0))


def next_job(waiting: list[Job], done: set[str], running: list[Job], rank: dict[str, float]) -> Job | None:
    """The job to start next, of those ``waiting`` whose needs are ``done``: while no training run
    is ``running``, the training run with the longest chain of work (``rank``) waiting on it, so the
    models, which everything else waits for, always train; else the ready notebooks before the
    training runs, each by its chain (the longest first). None when none is ready."""
    ready = [j for j in waiting if set(j.needs) <= done]
    trains = [j for j in ready if j.kind == "train"]
    if trains and not any(j.kind == "train" for j in running):
        return min(trains, key=lambda j: -rank[j.name])
    return min(ready, key=lambda j: (j.kind != "notebook", -rank[j.name]), default=None)


def run_jobs(jobs: list[Job], slots: int, *, start: Callable[[Job], Any] = ProcessJob,
             show: JobProgress | None = None, poll_s: float | None = None) -> None:
    """Run ``jobs``, at most ``slots`` at once, each once the jobs it ``needs`` finished, in the
    order of ``next_job``. ``start(job)`` starts one and returns a handle with ``result()`` (None
    while running, "" done, else the failure's line) and ``stop()``. A failed job stops new ones
    from starting; the running ones finish, then :class:`JobFailed` names it. Ctrl-C (or an error
    here) stops the running jobs and is raised again."""
    names = [j.name for j in jobs]
    unknown = sorted({n for j in jobs for n in j.needs} - set(names))
    if len(set(names)) != len(names) or unknown:
        raise ValueError(f"jobs: names must be unique and every need a job's name (unknown: {unknown})")
    show = show or JobProgress(len(jobs), slots, enabled=False)
    rank = chain_seconds(jobs, {j.name: j.seconds for j in jobs})
    waiting = list(jobs)
    running: dict[str, tuple[Job, Any, float]] = {}
    done: set[str] = set()
    took: dict[str, float] = {}
    failed: list[str] = []
    try:
        while waiting or running:
            while not failed and len(running) < slots:
                job = next_job(waiting, done, [j for j, _, _ in running.values()], rank)
                if job is None:
                    break
                waiting.remove(job)
                running[job.name] = (job, start(job), time.monotonic())
                show.event(f"started {job.name}")
            if not running:  # a failure, or needs that can never be met
                break
            ended = [(name, h.result()) for name, (_, h, _) in list(running.items())]
            ended = [(name, r) for name, r in ended if r is not None]
            for name, reason in ended:
                job, _, t0 = running.pop(name)
                if reason:
                    failed.append(reason)
                    show.event(f"FAILED {name} after {time.monotonic() - t0:.0f} s")
                else:
                    done.add(name)
                    took[name] = time.monotonic() - t0
                    show.event(f"{name} done in {took[name]:.0f} s")
            now = time.monotonic()
            show.update(list(running), len(done), seconds_left(
                jobs, done, {n: now - t0 for n, (_, _, t0) in running.items()}, slots, took), changed=bool(ended))
            if not ended:
                time.sleep(JOB_POLL_S if poll_s is None else poll_s)
    except BaseException:
        for _, handle, _ in running.values():
            handle.stop()
        raise
    finally:
        show.close()
    if failed:
        raise JobFailed(failed[0] + (f" ({len(waiting)} job(s) not started; run the same command again to continue: "
                                     "finished work is kept)" if waiting else ""))
    if waiting:
        raise RuntimeError(f"jobs never ready: {', '.join(j.name for j in waiting)}")


class JobProgress:
    """One progress line: what runs, how many jobs of all are done, about how long is left. On a
    terminal it is rewritten in place (as tqdm does); elsewhere it is printed as a plain line when a
    job starts or ends and every ``every`` seconds. ``enabled`` False: only the started/done lines."""

    def __init__(self, total: int, slots: int, *, enabled: bool = True, stream: TextIO | None = None,
                 tty: bool | None = None, every: float = 60.0):
        self.total, self.slots, self.enabled, self.every = total, slots, enabled, every
        self.stream = stream or sys.stdout
        self.tty = self.stream.isatty() if tty is None else tty
        self.last, self.shown = 0.0, ""

    def line(self, running: list[str], done: int, left: float) -> str:
        when = "under a minute" if left < 60 else f"about {left / 60:.0f} min"
        return f"[reproduce] {done}/{self.total} done; running: {', '.join(running) or 'nothing'}; {when} left"

    def event(self, text: str) -> None:
        clear = "\r\x1b[K" if self.tty and self.shown else ""
        self.stream.write(f"{clear}[reproduce] {text}\n")
        if self.tty and self.shown:
            self.stream.write(self.shown)
        self.stream.flush()

    def update(self, running: list[str], done: int, left: float, *, changed: bool = False) -> None:
        if not self.enabled:
            return
        text, now = self.line(running, done, left), time.monotonic()
        if self.tty:
            width = shutil.get_terminal_size((120, 20)).columns - 1
            self.shown = "\r" + text[:width] + "\x1b[K"
            self.stream.write(self.shown)
        elif changed or now - self.last >= self.every:
            self.stream.write(text + "\n")
            self.last = now
        self.stream.flush()

    def close(self) -> None:
        if self.tty and self.shown:
            self.stream.write("\n")
            self.stream.flush()
            self.shown = ""


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


def run_study(prof: Profile, run_dir: str | os.PathLike | None = None, *, progress: bool = True,
              which=study, name: str = "study", title: str = "the study") -> Path:
    """Train (or reuse) a study's runs, score them and write its tables into ``<run folder>/<name>/``
    (``which.write_tables``; ``which`` is :mod:`study` or :mod:`study2`); returns that folder. An
    interrupted study continues: finished runs are reused, an unfinished one resumes from its last epoch."""
    out = resolve_run_dir(prof, run_dir or "") / name
    utils.check_can_create_dir(out)
    t0 = time.perf_counter()
    print(f"[reproduce] {title}: {len(which.study_runs(prof))} runs ({prof.name}) ...", flush=True)
    paths = which.train(prof, progress=progress)
    print(f"[reproduce] runs ready in {time.perf_counter() - t0:.0f} s; scoring them ...", flush=True)
    sets = study.evaluation_sets(prof, progress=progress)
    runs, frames = which.score(paths, sets, progress=progress)
    folder = which.write_tables(out, runs, frames, study.score_baselines(prof, sets), study.provenance_rows(paths))
    print(f"[reproduce] {title}'s tables: {folder} ({(time.perf_counter() - t0) / 60:.1f} min)", flush=True)
    return folder


def run_study2(prof: Profile, run_dir: str | os.PathLike | None = None, *, progress: bool = True) -> Path:
    """:func:`run_study` for the second study (docs/study_plan_2.md): its 24 runs into ``<run folder>/study2/``."""
    return run_study(prof, run_dir, progress=progress, which=study2, name="study2", title="the second study")


def _study_notebook_declares(name: str) -> None:
    """Refuse ``--study2`` before any training when notebook 05 has no parameter ``name``."""
    nb = [p for p in list_notebooks() if p.stem.startswith("05")]
    if nb and name not in notebook_parameters(nb[0]):
        raise UserError(f"{nb[0].name} does not declare the parameter {name!r}: it cannot read the tables "
                         "that --study2 writes")


def reproduce_locks(prof: Profile, run_dir: str | os.PathLike | None = None) -> contextlib.ExitStack:
    """The locks one ``reproduce`` holds while it trains and runs notebooks: the profile's folder
    ``runs/<profile>/`` (where its models are trained) and the run folder, if another, taken in one
    order (sorted paths), so two reproduces never hold one each and wait for the other. A busy one
    is waited for (``utils.wait_for_lock``: one line "waiting for reproduce (PID n) holding ..."),
    then this one goes on, finding the models the other trained."""
    folders = {(utils.runs_dir() / prof.name).resolve(), resolve_run_dir(prof, run_dir or "").resolve()}
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
            raise UserError(f"-p {name} given twice")
        params[name] = parse_value(value)
    prof = config.profile(args.profile)  # the run's profile, made once here and passed down
    if args.dry_run:
        return _run_reproduce(args, prof, params)
    study_run = args.study or getattr(args, "study2", False)
    if getattr(args, "study2", False):  # before the first study's runs too
        _study_notebook_declares("study2_tables")
    check_request(prof, ["05"] if study_run else args.notebooks, params)  # before any lock or folder
    with reproduce_locks(prof, args.out):
        return _run_reproduce(args, prof, params)


def check_request(prof: Profile, notebooks: list[str] | None, params: dict[str, Any]) -> None:
    """What ``reproduce`` checks before it writes anything (notebooks, parameters, the models' cases
    and seeds), without making a folder: refused requests take no lock either."""
    selected = select_notebooks(notebooks, list_notebooks())
    if not selected:
        raise FileNotFoundError(f"no numbered notebooks (NN_*.ipynb) in {notebooks_dir()}")
    per_nb = check_parameters(selected, dict(params))
    plan = [(nb, {"profile": prof.name, "run_dir": "", **per_nb[nb]}) for nb in selected]
    training_runs(prof, plan)  # each model's configuration made, so a bad case or seed is refused


def _run_reproduce(args: argparse.Namespace, prof: Profile, params: dict[str, Any]) -> int:
    t0 = time.perf_counter()
    studies = [(flag, which, fn) for flag, which, fn in (("study", study, run_study), ("study2", study2, run_study2))
               if getattr(args, flag, False)]
    if studies and args.notebooks:
        raise UserError(f"--{studies[0][0]} runs notebook 05 on the study's tables: leave out --notebooks")
    for flag, which, fn in studies:  # the study's tables first, then notebook 05 reads them
        if args.dry_run:
            runs = which.study_runs(prof)
            todo = sum(not run_cache.is_complete(run) for *_, run in runs)
            print(f"{flag}: {len(runs)} runs ({todo} to train), scored into "
                  f"{resolve_run_dir(prof, args.out or '') / flag}")
        else:
            params[f"{flag}_tables"] = str(fn(prof, args.out, progress=not args.no_progress))
    if studies:
        args.notebooks, args.force = ["05"], True
    try:
        report = reproduce(prof, notebooks=args.notebooks, params=params, run_dir=args.out,
                           force=args.force, progress=not args.no_progress, dry_run=args.dry_run)
    except JobFailed as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if not args.dry_run:
        print(f"report: {report} ({(time.perf_counter() - t0) / 60:.1f} min)")
    sys.stdout.flush()
    return 0
