"""Graded exercises: the instructor's notebooks hold them with their solutions; nbgrader makes
the student release.

Every numbered notebook 01-07 ends with a section "Exercises". Each exercise is a markdown
prompt followed by two code cells that carry nbgrader's cell metadata:

- the **answer** cell (``grade_id`` ``exNN-K-answer``, a solution cell): the solution sits between
  ``### BEGIN SOLUTION`` and ``### END SOLUTION``. nbgrader's ``generate_assignment`` replaces that
  region with ``raise NotImplementedError()`` in the student release;
- the **check** cell (``grade_id`` ``exNN-K-check``, a graded, locked cell with its points):
  assertions a student can run, and optionally more between ``### BEGIN HIDDEN TESTS`` and
  ``### END HIDDEN TESTS``, which the release leaves out and ``nbgrader autograde`` puts back.

An exercise is self-contained: its two cells import what they use and define their own data, so
it runs on its own (:func:`run_exercise`), in any order, and the tests can prove each check both
ways: it passes on the solution and fails on the student's unanswered stub.

``python -m geodepth_lite exercises --out DIR`` writes the student release of notebooks 01-07 to
DIR (nbgrader's ``generate_assignment`` in a temporary course folder; outputs cleared).
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import os
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError

NOTEBOOK_DIR = utils.package_parent() / "notebooks"
EXERCISE_NOTEBOOKS = ("01", "02", "03", "04", "05", "06", "07")  # notebooks with a graded section
GRADE_ID = re.compile(r"ex(\d\d)-(\d+)-(answer|check)")  # whole ids only: fullmatch
SOLUTION_MARKERS = ("### BEGIN SOLUTION", "### END SOLUTION")
HIDDEN_MARKERS = ("### BEGIN HIDDEN TESTS", "### END HIDDEN TESTS")
OPEN_LEVEL = re.compile(r"\(open,")  # the prompt's level marker of an open-ended exercise
ASSIGNMENT = "geodepth"  # nbgrader's assignment name inside the temporary course folder


@dataclass
class Exercise:
    """One exercise of a notebook: its id ("03-2"), prompt, answer and check cells' sources."""
    ident: str
    prompt: str = ""
    answer: str = ""
    check: str = ""
    points: float = 0.0
    cells: dict = field(default_factory=dict)  # "answer"/"check" -> the notebook cell


def _source(cell) -> str:
    src = cell.get("source", "")
    return "".join(src) if isinstance(src, list) else src


def notebook_paths(folder: Path = NOTEBOOK_DIR) -> list[Path]:
    """The notebooks with an exercise section, in order."""
    found = {p.name[:2]: p for p in Path(folder).glob("[0-9][0-9]_*.ipynb")}
    return [found[n] for n in EXERCISE_NOTEBOOKS if n in found]


def notebook_exercises(nb: dict) -> dict[str, Exercise]:
    """The exercises of a notebook (nbformat JSON as a dict), keyed by id, in notebook order.

    The prompt is the markdown cell just before an answer cell.
    """
    out: dict[str, Exercise] = {}
    cells = nb["cells"]
    for i, cell in enumerate(cells):
        grade_id = cell.get("metadata", {}).get("nbgrader", {}).get("grade_id", "")
        m = GRADE_ID.fullmatch(grade_id)
        if not m:
            continue
        ex = out.setdefault(f"{m.group(1)}-{m.group(2)}", Exercise(f"{m.group(1)}-{m.group(2)}"))
        ex.cells[m.group(3)] = cell
        if m.group(3) == "answer":
            ex.answer = _source(cell)
            if i > 0 and cells[i - 1]["cell_type"] == "markdown":
                ex.prompt = _source(cells[i - 1])
        else:
            ex.check = _source(cell)
            ex.points = float(cell["metadata"]["nbgrader"].get("points", 0))
    return out


def _split_solutions(src: str) -> tuple[list[str], list[str]]:
    """(lines inside the solution regions, lines outside them); the marker lines are in neither."""
    regions: tuple[list[str], list[str]] = ([], [])
    inside = False
    for line in src.splitlines():
        if line.strip() in SOLUTION_MARKERS:
            inside = line.strip() == SOLUTION_MARKERS[0]
        else:
            regions[0 if inside else 1].append(line)
    return regions


def solution_lines(answer: str) -> list[str]:
    """The non-blank lines between the solution markers (what the release must not contain)."""
    return [line.strip() for line in _split_solutions(answer)[0] if line.strip()]


def new_namespace() -> dict:
    """A fresh namespace for an exercise's cells, with an input history ``In`` as IPython keeps one (the
    hidden tests run the answer cell again from it: :func:`geodepth_lite.workbook.grading.rerun_answer`)."""
    history = [""]
    return {"__name__": "__exercise__", "In": history, "_ih": history}


def run_cell(source: str, namespace: dict, name: str = "<cell>") -> None:
    """Execute one cell's source in ``namespace`` as a kernel would: its source enters ``In`` first."""
    namespace["In"].append(source)
    exec(compile(source, name, "exec"), namespace)  # noqa: S102 - the workbook's own cells


def visible_check(check: str) -> str:
    """A check cell's source as the student release shows it: without its hidden tests."""
    lines, hidden = [], False
    for line in check.splitlines(keepends=True):
        if line.strip() in HIDDEN_MARKERS:
            hidden = line.strip() == HIDDEN_MARKERS[0]
        elif not hidden:
            lines.append(line)
    return "".join(lines)


def run_exercise(answer: str, check: str) -> None:
    """Execute an exercise's answer then check cell in a fresh namespace, in a temporary working
    folder. Raises what the check raises, or an AssertionError when the exercise left files in
    its working folder (in a notebook that folder is ``notebooks/``)."""
    namespace = new_namespace()
    with tempfile.TemporaryDirectory(prefix="geodepth-exercise-") as tmp, contextlib.chdir(tmp):
        run_cell(answer, namespace, "<answer>")
        run_cell(check, namespace, "<check>")
        left = sorted(os.listdir(tmp))
    if left:  # in a notebook the working folder is notebooks/: an exercise must not write there
        raise AssertionError(f"the exercise wrote {left} into its working folder; use a temporary folder")


def stub_fails(answer_stub: str, check: str) -> tuple[bool, str]:
    """Run a student stub and the check: (True, why) when the check rejects the unanswered stub.

    The stub itself raises NotImplementedError where the solution was; the check then runs on
    whatever the stub left defined, and must raise an AssertionError or NotImplementedError (a
    NameError would mean the check tests nothing of the answer's own)."""
    namespace = new_namespace()
    with tempfile.TemporaryDirectory(prefix="geodepth-exercise-") as tmp, contextlib.chdir(tmp):
        try:
            run_cell(answer_stub, namespace, "<stub>")
        except NotImplementedError:
            pass
        try:
            run_cell(check, namespace, "<check>")
        except (AssertionError, NotImplementedError) as exc:
            return True, type(exc).__name__
        except Exception as exc:  # noqa: BLE001 - any other error is reported, not a pass
            return False, f"the check raised {type(exc).__name__}: {exc}"
    return False, "the check passed on the unanswered stub"


def _nbgrader_env() -> dict:
    """nbgrader runs its database migrations through the ``alembic`` script of its own
    environment: put this interpreter's scripts folder first on PATH."""
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    return env


def run_nbgrader(args: list[str], root: Path, what: str) -> subprocess.CompletedProcess:
    """``python -m nbgrader <args>`` in the course folder ``root`` (its ``nbgrader_config.py`` applies);
    a ValueError "cannot <what>: nbgrader <command> failed: <its last error lines>" when it fails."""
    cmd = [sys.executable, "-m", "nbgrader", *args, f"--CourseDirectory.root={root}", "--log-level=WARN"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=_nbgrader_env(), cwd=root)
    if proc.returncode != 0:
        lines = (proc.stderr or proc.stdout).strip().splitlines()
        errors = [ln for ln in lines if "[ERROR]" in ln or "Error" in ln] or lines
        raise UserError(f"cannot {what}: nbgrader {args[0]} failed: " + " | ".join(errors[-3:]))
    return proc


NOTEBOOK_MAX_BYTES = 64 * 2**20  # a lesson notebook with its figures is a few MB


def read_notebook(path: Path, solutions: bool = True) -> dict:
    """A notebook's JSON, checked to be a notebook whose exercises can be collected; a ValueError
    "cannot read <path>: <reason>" for a damaged, oversized or tampered file. ``solutions``: each
    answer cell must hold matched solution markers (an instructor's notebook; not a released one)."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > NOTEBOOK_MAX_BYTES:
            raise UserError(f"cannot read {path}: {size / 2**20:.0f} MB, more than a notebook's "
                             f"{NOTEBOOK_MAX_BYTES / 2**20:.0f} MB")
        nb = json.loads(path.read_bytes())
    except OSError as exc:
        raise utils.FileProblem(f"cannot read {path}: {utils.os_reason(exc)}", path) from exc
    except (UnicodeDecodeError, RecursionError) as exc:
        raise UserError(f"cannot read {path}: not a notebook ({type(exc).__name__})") from None
    except json.JSONDecodeError as exc:
        raise UserError(f"cannot read {path}: damaged notebook, not valid JSON ({exc})") from None
    cells = nb.get("cells") if isinstance(nb, dict) else None
    if not isinstance(cells, list) or not all(isinstance(c, dict) for c in cells):
        raise UserError(f"cannot read {path}: not a notebook (no list of cells)")
    for i, c in enumerate(cells):
        src = c.get("source", "")
        meta = c.get("metadata", {})
        if not isinstance(c.get("cell_type"), str) or not isinstance(meta, dict) or not (
                isinstance(src, str) or (isinstance(src, list) and all(isinstance(x, str) for x in src))):
            raise UserError(f"cannot read {path}: cell {i} is damaged (cell_type, metadata or source)")
        grading = meta.get("nbgrader", {})
        if not isinstance(grading, dict) or not isinstance(grading.get("grade_id", ""), str):
            raise UserError(f"cannot read {path}: cell {i} has damaged nbgrader metadata")
        if GRADE_ID.fullmatch(str(grading.get("grade_id", ""))):
            try:
                float(grading.get("points", 0))
            except (TypeError, ValueError):
                raise UserError(f"cannot read {path}: cell {i} ({grading['grade_id']}) has points "
                                 f"{grading.get('points')!r}, not a number") from None
            if solutions and grading["grade_id"].endswith("answer"):
                regions = [ln.strip() for ln in _source(c).splitlines() if ln.strip() in SOLUTION_MARKERS]
                if regions != list(SOLUTION_MARKERS) * (len(regions) // 2) or not regions:
                    raise UserError(f"cannot read {path}: exercise {grading['grade_id']} has unmatched "
                                     f"solution markers ({' / '.join(SOLUTION_MARKERS)})")
    return nb


def git_tracked(folder: Path) -> list[str] | None:
    """The files git tracks in ``folder`` (or under it), where ``folder`` lies in a git work tree; None
    where there is no git, or no work tree around it."""
    existing = folder.absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return None
    try:
        top = subprocess.run(["git", "-C", str(existing), "rev-parse", "--show-toplevel"],
                             capture_output=True, text=True, timeout=30)
        if top.returncode != 0 or not top.stdout.strip():
            return None
        listed = subprocess.run(["git", "-C", top.stdout.strip(), "ls-files", "-z", "--",
                                 str(folder.resolve())], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None
    if listed.returncode != 0:
        return None
    return [n for n in listed.stdout.split("\0") if n]


def checkout_around(folder: Path) -> Path | None:
    """The nearest folder holding ``folder`` (itself included) that looks like a git checkout (it holds a
    ``.git`` folder or file), found without git; None when there is none."""
    for candidate in (folder.resolve(), *folder.resolve().parents):
        if os.path.lexists(candidate / ".git"):
            return candidate
    return None


def check_release_folder(out: Path, force: bool = False) -> None:
    """Refuse a folder the release must not write into, before anything is made: the notebooks folder
    (or one inside it, or one holding it), a folder holding files git tracks (any folder inside a
    checkout when git cannot list them), and, without ``force``, any folder that is not empty (the
    student may have edited a notebook there)."""
    out = Path(out)
    target = out.resolve()
    notebooks = NOTEBOOK_DIR.resolve()
    if target == notebooks or notebooks in target.parents or target in notebooks.parents:
        raise utils.FileProblem(f"cannot write the student release into {out}: that is (or holds) the "
                                f"notebooks folder {NOTEBOOK_DIR}, whose solutions it would replace; choose "
                                "another --out", out)
    if os.path.lexists(out) and not out.is_dir():
        raise utils.FileProblem(f"cannot write the student release into {out}: a file of that name exists", out)
    tracked = git_tracked(out) if out.exists() else None
    top = checkout_around(out) if out.exists() and tracked is None else None
    if top is not None:  # git cannot say which files are tracked there: nothing is written inside a checkout
        raise utils.FileProblem(f"cannot write the student release into {out}: it lies in the checkout {top} "
                                "(which holds .git), and git could not list the files it tracks there (git not "
                                "on PATH, or refusing that checkout); choose a folder outside it", out)
    if tracked:
        raise utils.FileProblem(f"cannot write the student release into {out}: it holds {len(tracked)} file(s) "
                                f"of the checkout tracked by git (first {tracked[0]}); choose another --out "
                                "(even --force never writes there)", out)
    if not force and out.is_dir():
        present = sorted(p.name for p in out.iterdir() if p.name != utils.LOCK_NAME)
        if present:
            raise utils.FileProblem(f"cannot write the student release into {out}: the folder is not empty "
                                    f"(first {present[0]}); a student may have edited a notebook there: choose "
                                    "an empty or new folder, or pass --force to replace the released notebooks",
                                    out)


def write_release(out: Path, notebooks: list[Path] | None = None, *, force: bool = False) -> list[Path]:
    """Write the student release of ``notebooks`` (default: 01-07) to ``out``; returns the files.

    ``out`` is checked first (:func:`check_release_folder`: never the notebooks folder nor a folder of
    tracked files; a non-empty one only with ``force``) and locked for the run (``utils.FolderLock``).
    Each notebook is read and checked (:func:`read_notebook`), then nbgrader's ``generate_assignment``
    runs in a temporary course folder: solutions become stubs, hidden tests go, outputs are cleared,
    graded cells are locked. Each released notebook is then checked to hold no solution line and no
    hidden-test marker; ``out`` is written only when every notebook passes.
    """
    notebooks = notebook_paths() if notebooks is None else [Path(p) for p in notebooks]
    if not notebooks:
        raise FileNotFoundError(f"no notebook with exercises under {NOTEBOOK_DIR}")
    out = Path(out)
    check_release_folder(out, force)
    sources = {nb: read_notebook(nb) for nb in notebooks}
    created = utils.missing_dirs(out)
    utils.check_output_dir(out)
    lock = utils.FolderLock(out, "output folder", remove_file=True)
    try:
        lock.acquire()
        check_release_folder(out, force)  # again, under the lock: what another writer left meanwhile
        written = _release_into(out, sources)
    except BaseException:
        lock.release()
        utils.remove_empty_dirs(created)
        raise
    lock.release()
    return written


def _release_into(out: Path, sources: dict[Path, dict]) -> list[Path]:
    """nbgrader's release of ``sources`` (notebook path -> its JSON), checked, then copied into ``out``."""
    with tempfile.TemporaryDirectory(prefix="geodepth-release-") as tmp:
        source = Path(tmp, "source", ASSIGNMENT)
        source.mkdir(parents=True)
        for nb, content in sources.items():  # open-ended exercises graded by hand, as in a course
            marked = copy.deepcopy(content)
            grade_by_hand(marked)
            student_wording(marked)
            (source / nb.name).write_text(json.dumps(marked, indent=1, ensure_ascii=False) + "\n")
        names = ", ".join(nb.name for nb in sources)
        run_nbgrader(["generate_assignment", ASSIGNMENT, "--force"], Path(tmp), f"release {names}")
        released = Path(tmp, "release", ASSIGNMENT)
        if not released.is_dir():
            raise UserError(f"cannot release {names}: nbgrader generate_assignment wrote no release folder")
        for nb, source_nb in sources.items():
            problems = leaks(source_nb, read_notebook(released / nb.name, solutions=False))
            if problems:
                raise UserError(f"cannot release {nb}: the release still holds solution text: {problems[0]}")
        written = []
        for nb in sources:
            utils.write_bytes_atomic(out / nb.name, (released / nb.name).read_bytes())
            written.append(out / nb.name)
    return written


LECTURER_NOTE = ("This copy shows the solutions; a class gets the student version without them "
                 "(`python -m geodepth_lite exercises`), and nbgrader grades it, with a few more checks kept hidden "
                 "until grading.")
STUDENT_NOTE = ("This is the student version: the answer cells are yours to fill in, and nbgrader grades them, "
                "with a few more checks kept hidden until grading.")


def student_wording(nb: dict) -> int:
    """Replace (in place) the lessons' sentence that says the copy shows the solutions with the student
    version's; returns how many markdown cells changed."""
    changed = 0
    for cell in nb.get("cells", []):
        src = "".join(cell.get("source", ""))
        if cell.get("cell_type") == "markdown" and LECTURER_NOTE in src:
            cell["source"] = src.replace(LECTURER_NOTE, STUDENT_NOTE).splitlines(keepends=True)
            changed += 1
    return changed


def grade_by_hand(nb: dict) -> list[str]:
    """Mark each open-ended exercise of ``nb`` (in place) as manually graded: the answer cell becomes a
    graded solution cell with the exercise's points, the check cell a graded cell worth 0. Returns the ids."""
    marked = []
    for ex in notebook_exercises(nb).values():
        if not OPEN_LEVEL.search(ex.prompt) or set(ex.cells) != {"answer", "check"}:
            continue
        answer, check = ex.cells["answer"]["metadata"]["nbgrader"], ex.cells["check"]["metadata"]["nbgrader"]
        answer.update(grade=True, solution=True, locked=False, points=float(check.get("points", 0)))
        check.update(grade=True, solution=False, locked=True, points=0.0)
        marked.append(ex.ident)
    return marked


def leaks(source_nb: dict, released_nb: dict) -> list[str]:
    """What of the solutions and hidden tests is still in a released notebook (empty: none)."""
    text = "\n".join(_source(c) for c in released_nb["cells"])
    found = [m for m in (*SOLUTION_MARKERS, *HIDDEN_MARKERS) if m in text]
    released_lines = {ln.strip() for ln in text.splitlines()}
    exercises = notebook_exercises(source_nb).values()
    # a line that the source also has outside any solution (an import, a blank return) is no leak
    public = {ln.strip() for c in source_nb["cells"] for ln in _split_solutions(_source(c))[1]}
    for ex in exercises:
        found += [f"exercise {ex.ident}: {ln!r}" for ln in solution_lines(ex.answer)
                  if ln in released_lines and ln not in public]
    return found


def add_arguments_exercises(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("student-release"),
                   help="folder for the student notebooks (default: student-release); never the notebooks "
                   "folder or a folder of files git tracks; it must be new or empty unless --force")
    p.add_argument("--force", action="store_true",
                   help="write into a folder that is not empty, replacing the released notebooks there")


def run_exercises(args) -> int:
    written = write_release(args.out, force=args.force)
    counts = {p.name: len(notebook_exercises(read_notebook(p))) for p in notebook_paths()}
    print(f"student release: {len(written)} notebooks, {sum(counts.values())} exercises, in {args.out}")
    print("solutions stay in notebooks/: do not hand that folder out; a whole course (student edition, collect, "
          "autograde, grades): python -m geodepth_lite course --help, docs/teaching.md")
    return 0
