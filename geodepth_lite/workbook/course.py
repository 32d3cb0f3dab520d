"""A course a lecturer runs with nbgrader: set it up, release, collect, autograde, feedback, grades.

``python -m geodepth_lite course <action>``, each action in a course folder of nbgrader's layout::

    COURSE/nbgrader_config.py          course id and the cell timeout (init)
    COURSE/source/<assignment>/        the notebooks with their solutions (init)
    COURSE/release/<assignment>/       what students get (release)
    COURSE/submitted/<student>/<assignment>/   what they returned (collect)
    COURSE/autograded/, feedback/, gradebook.db   (autograde, feedback)

One assignment per notebook, named after it (``04_training``). ``init`` copies the notebooks and
marks each open-ended exercise ("(open, N points)" in its prompt) as a manually graded answer: its
answer cell carries the points and is graded by hand (nbgrader's formgrader); its check cell stays
a graded cell worth 0 points, so it still runs, hidden tests included, and shows the lecturer
whether the answer meets the stated conditions. The cell timeout is the slowest code cell that the
committed notebooks record (papermill's ``duration``, else the kernel's execution timestamps) times
``TIMEOUT_FACTOR``, rounded up to a minute. Every action locks the course folder; ``collect`` checks
every returned notebook before copying any and never replaces a collected one.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import re
import shutil
import stat
import sys
from datetime import datetime, timezone
from pathlib import Path

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.workbook import autograde as grading_run
from geodepth_lite.workbook import exercises, sandbox

COURSE_ID = "geodepth"
TIMEOUT_FACTOR = 3.0  # a student's laptop may be three times slower than the machine that executed notebooks/
TIMEOUT_MIN_S = 120  # a notebook without execution records (or only fast cells) still gets two minutes a cell
STUDENT_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")  # whole names only: fullmatch
CONFIG = "nbgrader_config.py"
GRADE_COLUMNS = ["student", "assignment", "points", "max_points", "needs_manual_grading", "pending_max_points",
                 "could_not_run", "flagged_for_review"]


# ----------------------------------------------------------------------------------------- the timeout
def _stamp(text) -> datetime | None:
    try:
        return datetime.fromisoformat(str(text).replace("Z", "+00:00"))
    except ValueError:
        return None


def cell_seconds(cell: dict) -> float | None:
    """How long a committed code cell took to run: papermill's ``duration``, else the kernel's
    ``execution`` timestamps (``shell.execute_reply`` - ``iopub.execute_input``); None if unrecorded."""
    meta = cell.get("metadata", {})
    duration = meta.get("papermill", {}).get("duration") if isinstance(meta.get("papermill"), dict) else None
    if isinstance(duration, (int, float)) and not isinstance(duration, bool) and math.isfinite(duration):
        return float(duration)
    stamps = meta.get("execution", {}) if isinstance(meta.get("execution"), dict) else {}
    start, end = _stamp(stamps.get("iopub.execute_input")), _stamp(stamps.get("shell.execute_reply"))
    if start is None or end is None or (start.tzinfo is None) != (end.tzinfo is None):
        return None
    return (end - start).total_seconds()


def slowest_cell(notebooks: dict[Path, dict]) -> tuple[float, str]:
    """(seconds, notebook name) of the slowest recorded code cell; (0, "") when none is recorded."""
    best = (0.0, "")
    for path, nb in notebooks.items():
        for cell in nb["cells"]:
            s = cell_seconds(cell) if cell["cell_type"] == "code" else None
            if s is not None and s > best[0]:
                best = (s, path.name)
    return best


def cell_timeout(slowest_s: float) -> int:
    """Seconds nbgrader allows a cell: the slowest recorded cell times TIMEOUT_FACTOR, up to a minute."""
    return max(TIMEOUT_MIN_S, int(math.ceil(slowest_s * TIMEOUT_FACTOR / 60.0)) * 60)


# ----------------------------------------------------------------------------------------- init
def assignment_name(notebook: Path) -> str:
    return Path(notebook).stem




def _config_text(course_id: str, timeout: int, slowest: tuple[float, str]) -> str:
    seconds, name = slowest
    why = (f"the slowest recorded cell ({seconds:.0f} s, {name}) x {TIMEOUT_FACTOR:g}, rounded up to a minute"
           if name else f"no cell recorded its run time: the minimum, {TIMEOUT_MIN_S} s")
    return (f"# nbgrader's settings for this course (python -m geodepth_lite course init)\n"
            f"c = get_config()  # noqa: F821 - nbgrader provides it\n"
            f"c.CourseDirectory.course_id = {course_id!r}\n"
            f"# seconds a cell may run when autograding: {why}\n"
            f"c.Execute.timeout = {timeout}\n")


def check_new_folder(out: Path, what: str) -> None:
    """Refuse an ``out`` that exists and is not an empty folder, or that lies in the notebooks folder."""
    notebooks = exercises.NOTEBOOK_DIR.resolve()
    target = out.resolve()
    if target == notebooks or notebooks in target.parents or target in notebooks.parents:
        raise utils.FileProblem(f"cannot write the {what} into {out}: that is (or holds) the notebooks folder "
                                f"{exercises.NOTEBOOK_DIR}; choose another folder", out)
    if out.exists() and (not out.is_dir() or any(p.name != utils.LOCK_NAME for p in out.iterdir())):
        raise utils.FileProblem(f"cannot write the {what} into {out}: it exists and is not an empty folder; "
                                "choose a new folder (nothing there is ever replaced)", out)


def _write_source(out: Path, nb: Path, content: dict) -> list[str]:
    """``source/<assignment>/<notebook>`` of the course: open-ended exercises graded by hand, outputs
    cleared (nothing of a run goes to students). Returns the hand-graded exercises."""
    manual = exercises.grade_by_hand(content)  # the release and the course mark open answers alike
    for cell in content["cells"]:
        if cell["cell_type"] == "code":
            cell["outputs"], cell["execution_count"] = [], None
    target = out / "source" / assignment_name(nb) / nb.name
    utils.write_bytes_atomic(target, (json.dumps(content, indent=1, ensure_ascii=False) + "\n").encode())
    return manual


def init(out: Path, notebooks: list[Path] | None = None, course_id: str = COURSE_ID) -> dict:
    """Write a new course folder ``out``: ``nbgrader_config.py`` and ``source/<assignment>/<notebook>``
    for each notebook (default 01-07), open-ended exercises marked for hand grading. Returns a summary."""
    notebooks = exercises.notebook_paths() if notebooks is None else [Path(p) for p in notebooks]
    if not notebooks:
        raise FileNotFoundError(f"no notebook with exercises under {exercises.NOTEBOOK_DIR}")
    if not isinstance(course_id, str) or not re.fullmatch(r"[A-Za-z0-9_-]{1,64}", course_id):
        raise UserError(f"course id must be 1-64 letters, digits, '_' or '-', got {course_id!r}")
    names = [assignment_name(nb) for nb in notebooks]
    if len(set(names)) != len(names):
        twice = next(nb for nb in notebooks if names.count(assignment_name(nb)) > 1)
        raise UserError(f"cannot make a course of {twice}: two notebooks named {twice.name} would be one assignment")
    out = Path(out)
    check_new_folder(out, "course")
    sources = {nb: exercises.read_notebook(nb) for nb in notebooks}
    slowest = slowest_cell(sources)
    timeout = cell_timeout(slowest[0])
    created = utils.missing_dirs(out)
    utils.check_output_dir(out)
    try:
        with utils.FolderLock(out, "course folder", remove_file=True):
            check_new_folder(out, "course")  # again, under the lock: empty, so all in it is ours
            try:
                manual = {nb.name: _write_source(out, nb, content) for nb, content in sources.items()}
                utils.write_bytes_atomic(out / CONFIG, _config_text(course_id, timeout, slowest).encode())
            except BaseException:
                shutil.rmtree(out / "source", ignore_errors=True)
                (out / CONFIG).unlink(missing_ok=True)
                raise
    except BaseException:
        utils.remove_empty_dirs(created)
        raise
    return {"assignments": [assignment_name(nb) for nb in notebooks], "timeout": timeout, "slowest": slowest,
            "manual": manual}


# ----------------------------------------------------------------------------------------- the course folder
def open_course(course: Path) -> list[str]:
    """The assignments of a course folder made by ``init`` (each ``source/<assignment>/``); a FileProblem
    naming the folder when it is not one."""
    course = Path(course)
    if not (course / CONFIG).is_file() or not (course / "source").is_dir():
        raise utils.FileProblem(f"cannot use {course} as a course folder: no {CONFIG} or source/ in it; "
                                "make one with `course init --out FOLDER`", course)
    names = sorted(p.name for p in (course / "source").iterdir() if p.is_dir() and not p.name.startswith("."))
    if not names:
        raise utils.FileProblem(f"cannot use {course} as a course folder: source/ holds no assignment", course)
    return names


def course_lock(course: Path) -> utils.FolderLock:
    return utils.FolderLock(course, "course folder", remove_file=True)


def release(course: Path) -> list[Path]:
    """nbgrader's ``generate_assignment`` for every assignment of the course (it also enters them into
    the gradebook); each released notebook is checked to hold no solution text. Returns the notebooks."""
    course = Path(course)
    names = open_course(course)
    written = []
    with course_lock(course):
        for name in names:
            exercises.run_nbgrader(["generate_assignment", name, "--force"], course, f"release {name}")
            for src in sorted((course / "source" / name).glob("*.ipynb")):
                out = course / "release" / name / src.name
                problems = exercises.leaks(exercises.read_notebook(src), exercises.read_notebook(out, solutions=False))
                if problems:
                    raise UserError(f"cannot release {out}: it still holds solution text: {problems[0]}")
                written.append(out)
    return written


# ----------------------------------------------------------------------------------------- the student edition
def holds_solutions(path: Path) -> bool:
    """Whether a notebook has a solution region (a line that is a solution marker) in any cell."""
    nb = exercises.read_notebook(path, solutions=False)
    return any(ln.strip() in exercises.SOLUTION_MARKERS for c in nb["cells"] for ln in
               "".join(c.get("source", "")).splitlines())


# tracked files that hold answers outside the notebooks: the tests that play shortcuts and wrong answers
# against every check (their answers overlap the solutions), kept by the lecturer
LECTURER_FILES = frozenset({"tests/test_exercise_shortcuts.py"})


def edition_files(root: Path) -> tuple[list[str], list[str]]:
    """(files of the checkout ``root`` that the student edition copies, files it leaves out): every
    file git tracks but the notebooks that hold solutions and :data:`LECTURER_FILES`."""
    tracked = exercises.git_tracked(root)
    if not tracked:
        raise FileNotFoundError(f"cannot list the files of {root}: the student edition is made from a git "
                                "checkout of geodepth-lite (git ls-files)")
    keep, dropped = [], []
    for rel in tracked:
        is_solution = rel in LECTURER_FILES or (
            rel.endswith(".ipynb") and (root / rel).is_file() and holds_solutions(root / rel))
        (dropped if is_solution else keep).append(rel)
    return keep, dropped


def edition(course: Path, out: Path) -> dict:
    """Write the student edition to the new folder ``out``: the checkout this package runs from (the
    files git tracks, as they are in the work tree) without any notebook that holds solutions, and
    the course's released notebooks in ``notebooks/`` in their place. Returns a summary."""
    course, out = Path(course), Path(out)
    names = open_course(course)
    released = sorted(p for name in names for p in (course / "release" / name).glob("*.ipynb"))
    if not released:
        raise utils.FileProblem(f"cannot write the student edition from {course}: nothing is released yet; run "
                                "`course release` first", course)
    root = utils.project_root()
    if root is None:
        raise FileNotFoundError("cannot write the student edition: this package does not run from a checkout")
    if out.resolve() == root or root in out.resolve().parents:
        raise utils.FileProblem(f"cannot write the student edition into {out}: it lies inside the checkout {root}; "
                                "choose a folder outside it", out)
    check_new_folder(out, "student edition")
    keep, dropped = edition_files(root)
    for nb in released:
        if holds_solutions(nb):
            raise UserError(f"cannot hand out {nb}: it holds a solution region")
    created = utils.missing_dirs(out)
    utils.check_output_dir(out)
    try:
        with utils.FolderLock(out, "output folder", remove_file=True), course_lock(course):
            check_new_folder(out, "student edition")  # again, under the lock: empty, so all in it is ours
            try:
                for rel in keep:
                    if (root / rel).is_file() and not (root / rel).is_symlink():
                        utils.write_bytes_atomic(out / rel, (root / rel).read_bytes())
                for nb in released:
                    utils.write_bytes_atomic(out / "notebooks" / nb.name, nb.read_bytes())
            except BaseException:
                for child in out.iterdir():
                    if child.name != utils.LOCK_NAME:
                        shutil.rmtree(child) if child.is_dir() else child.unlink()
                raise
    except BaseException:
        utils.remove_empty_dirs(created)
        raise
    return {"copied": len(keep), "left_out": dropped, "released": [nb.name for nb in released]}


# ----------------------------------------------------------------------------------------- collect
def _files_under(folder: Path) -> list[Path]:
    """The files under ``folder`` (hidden names skipped), never following a link to a folder: such a
    link comes back as an entry, for the caller to refuse."""
    found = []
    for top, dirs, files in os.walk(folder, followlinks=False):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        found += [Path(top, d) for d in dirs if Path(top, d).is_symlink()]
        found += [Path(top, f) for f in sorted(files) if not f.startswith(".")]
    return found


def _returned_notebooks(subs: Path, course: Path, names: list[str]) -> tuple[list[tuple[Path, Path]], list[Path]]:
    """(source file, target in submitted/) for each returned notebook, all checked; and the files skipped
    (not a notebook of the course). A ValueError or FileProblem names the first file refused."""
    expected = {p.name: name for name in names for p in (course / "source" / name).glob("*.ipynb")}
    root = subs.resolve()
    pairs, skipped = [], []
    for student_dir in sorted(subs.iterdir()):
        if student_dir.name.startswith("."):
            continue
        if student_dir.is_symlink() or not student_dir.is_dir():
            raise utils.FileProblem(f"cannot collect {student_dir}: expected a folder named after a student "
                                    "(a link or a file is refused)", student_dir)
        if not STUDENT_ID.fullmatch(student_dir.name):  # the name quoted: it may hold a newline
            raise utils.FileProblem(f"cannot collect {str(student_dir)!r}: a student folder is named by 1-64 "
                                    "letters, digits, '_' or '-'", student_dir)
        for path in _files_under(student_dir):
            if path.is_symlink() or root not in path.resolve().parents:
                raise utils.FileProblem(f"cannot collect {path}: a link, or a file outside {subs}", path)
            if path.name not in expected:
                skipped.append(path)
                continue
            if not path.is_file():  # checked by stat, not by opening: a FIFO would block the first read
                raise utils.FileProblem(f"cannot collect {path}: not a regular file (a FIFO, socket or device "
                                        "named like a notebook is refused)", path)
            exercises.read_notebook(path, solutions=False)  # bounded, JSON, cells intact
            target = course / "submitted" / student_dir.name / expected[path.name] / path.name
            if any(t == target for _, t in pairs):
                raise utils.FileProblem(f"cannot collect {path}: {student_dir.name} returned {path.name} twice", path)
            pairs.append((path, target))
    return pairs, skipped


def _read_regular(path: Path) -> bytes:
    """The bytes of ``path``, opened without following a link and without blocking (O_NONBLOCK), and
    read only if it is a regular file: a file swapped for a FIFO after the checks cannot hang collect."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(path, flags)
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise utils.FileProblem(f"cannot collect {path}: not a regular file", path)
            return f.read()
    except utils.FileProblem:
        raise
    except OSError as exc:
        raise utils.FileProblem(f"cannot collect {path}: {utils.os_reason(exc)}", path) from exc


def collect(course: Path, submissions: Path) -> dict:
    """Copy the students' returned notebooks (``submissions/<student>/**/<notebook>.ipynb``) into
    ``submitted/<student>/<assignment>/``. Every file is checked before the first copy; a notebook
    already collected is skipped when identical and refused when different (never replaced)."""
    course, submissions = Path(course), Path(submissions)
    names = open_course(course)
    if not submissions.is_dir():
        raise utils.FileProblem(f"cannot collect {submissions}: not a folder", submissions)
    with course_lock(course):
        pairs, skipped = _returned_notebooks(submissions, course, names)
        new = []
        for src, target in pairs:
            if target.exists():
                if _read_regular(target) != _read_regular(src):
                    raise utils.FileProblem(f"cannot collect {src}: {target} already holds a different copy "
                                            "(nothing was collected; remove that copy by hand to replace it)", src)
                continue
            new.append((src, target))
        stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M:%S.%f UTC")
        for src, target in new:
            utils.write_bytes_atomic(target, _read_regular(src))
            if not (target.parent / "timestamp.txt").exists():
                utils.write_bytes_atomic(target.parent / "timestamp.txt", (stamp + "\n").encode())
    return {"collected": [t for _, t in new], "already": len(pairs) - len(new), "skipped": skipped}


# ----------------------------------------------------------------------------------------- grade
def autograde(course: Path, *, sandboxed: bool = True, retry: bool = False, echo=None,
              memory_gib: float = sandbox.KERNEL_MEMORY_GIB) -> dict:
    """nbgrader's ``autograde`` of each collected submission on its own, its kernel in a sandbox (see
    :mod:`geodepth_lite.workbook.autograde`): hidden tests put back, the notebook executed with the course's cell
    timeout. A submission graded before is left as it is; one whose kernel dies or hangs is recorded as
    "could not run" (``echo`` gets one line naming it) and the others are graded. Without bubblewrap it
    refuses unless ``sandboxed`` is False. A sandboxed kernel holds at most ``memory_gib`` GiB, its processes
    together and each of them (:mod:`geodepth_lite.workbook.sandbox`). Returns graded, could_not_run and
    skipped submissions."""
    course = Path(course)
    memory = sandbox.memory_bytes(memory_gib)
    names = open_course(course)
    if not (course / "gradebook.db").is_file():
        raise utils.FileProblem(f"cannot autograde {course}: no gradebook yet; run `course release` first", course)
    with course_lock(course):
        return grading_run.grade_class(course, names, configured_timeout(course), sandboxed=sandboxed, retry=retry,
                                       echo=echo, memory=memory)


def configured_timeout(course: Path) -> int:
    """The cell timeout in the course's ``nbgrader_config.py`` (``c.Execute.timeout``, as ``init`` wrote it
    or the lecturer set it); ``TIMEOUT_MIN_S`` where none is set."""
    m = re.search(r"^c\.Execute\.timeout\s*=\s*(\d+)\s*$", (Path(course) / CONFIG).read_text(), re.M)
    return int(m.group(1)) if m else TIMEOUT_MIN_S


def feedback(course: Path, echo=None) -> list[Path]:
    """One HTML page per graded notebook (or per notebook that could not run) in
    ``feedback/<student>/<assignment>/``: each exercise by number and title, its points, passed or failed
    and the check's message; never the hidden tests (see :mod:`geodepth_lite.workbook.autograde`).
    ``echo``: called with one line per graded notebook that could not be read back."""
    course = Path(course)
    names = open_course(course)
    with course_lock(course):
        return grading_run.write_feedback(course, names, echo)


def grade_rows(course: Path) -> list[dict]:
    """One row per student and assignment from the gradebook: points (auto and hand grades so far), max
    points, how many answers still need a hand grade and the points they are worth."""
    # nbgrader's gradebook (SQLAlchemy): heavy, needed by this command only
    import sqlalchemy.exc
    from nbgrader.api import Gradebook, MissingEntry  # nbgrader: only the course commands need it

    course = Path(course)
    db = course / "gradebook.db"
    if not db.is_file():
        raise utils.FileProblem(f"cannot read the grades of {course}: no gradebook.db; run `course release` and "
                                "`course autograde` first", course)
    _check_gradebook(db)
    try:
        rows, most = _rows(Gradebook, MissingEntry, db)
    except sqlalchemy.exc.SQLAlchemyError as exc:  # a damaged database, or not nbgrader's
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise utils.FileProblem(f"cannot read the grades from {db}: not nbgrader's gradebook ({first[:160]})",
                                db) from None
    return with_flags(with_could_not_run(rows, grading_run.read_failures(course), most),
                      grading_run.read_flags(course))


def with_flags(rows: list[dict], flags: dict[tuple[str, str], list[dict]]) -> list[dict]:
    """The grade rows with the ``flagged_for_review`` column: empty, or each exercise the static review sent
    to manual grading with its reasons ("02.2: line 3: import inspect: reads ... | 02.3: ...")."""
    for row in rows:
        found = flags.get((row["student"], row["assignment"]), [])
        row["flagged_for_review"] = " | ".join(f"{f['exercise']}: {'; '.join(f['reasons'])}" for f in found)
    return rows


SQLITE_HEADER = b"SQLite format 3\x00"  # the first 16 bytes of every SQLite database file


def _check_gradebook(db: Path) -> None:
    """A FileProblem naming ``db`` unless it begins as an SQLite database does (nbgrader's gradebook is one)."""
    try:
        with open(db, "rb") as f:
            head = f.read(len(SQLITE_HEADER))
    except OSError as exc:
        raise utils.FileProblem(f"cannot read {db}: {utils.os_reason(exc)}", db) from exc
    if head != SQLITE_HEADER:
        raise utils.FileProblem(f"cannot read the grades from {db}: not an SQLite database (nbgrader's gradebook); "
                                "it is left as it is", db)


def _rows(gradebook_class, missing_entry, db: Path) -> tuple[list[dict], dict[str, float]]:
    """The gradebook's rows of ``grade_rows`` and each assignment's max points (nbgrader's classes passed
    in: imported only by that command)."""
    rows = []
    with gradebook_class(f"sqlite:///{db.resolve()}") as gb:
        for assignment in sorted(gb.assignments, key=lambda a: a.name):
            for student in sorted(gb.students, key=lambda s: s.id):
                try:
                    sub = gb.find_submission(assignment.name, student.id)
                except missing_entry:
                    continue
                pending = [g for nb in sub.notebooks for g in nb.grades if g.needs_manual_grade]
                rows.append({"student": student.id, "assignment": assignment.name, "points": round(sub.score, 4),
                             "max_points": round(sub.max_score, 4), "needs_manual_grading": len(pending),
                             "pending_max_points": round(sum(g.max_score for g in pending), 4)})
        most = {a.name: round(a.max_score, 4) for a in gb.assignments}
    return rows, most


def with_could_not_run(rows: list[dict], failures: dict[tuple[str, str], str], most: dict[str, float]) -> list[dict]:
    """The grade rows with the ``could_not_run`` column: empty for a graded submission; the reason for one
    whose notebook could not run, which then has 0 points and nothing waiting for a hand grade (a row is
    added where the gradebook has none; ``most``: each assignment's max points)."""
    failures = dict(failures)
    for row in rows:
        reason = failures.pop((row["student"], row["assignment"]), "")
        row["could_not_run"] = reason
        if reason:
            row.update(points=0.0, needs_manual_grading=0, pending_max_points=0.0)
    for (student, assignment), reason in sorted(failures.items()):
        rows.append({"student": student, "assignment": assignment, "points": 0.0,
                     "max_points": most.get(assignment, 0.0), "needs_manual_grading": 0, "pending_max_points": 0.0,
                     "could_not_run": reason})
    return sorted(rows, key=lambda r: (r["assignment"], r["student"]))


def write_grades(course: Path, out: Path) -> list[dict]:
    """The grade table as CSV (``GRADE_COLUMNS``); ``out`` must not exist (never replaced)."""
    out = Path(out)
    if out.exists() or out.is_symlink():
        raise utils.FileProblem(f"cannot write {out}: it exists; choose another name (a grade table is never "
                                "replaced)", out)
    with course_lock(Path(course)):
        rows = grade_rows(course)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=GRADE_COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    utils.check_output_dir(out.parent if str(out.parent) else Path("."))
    utils.write_bytes_atomic(out, buf.getvalue().encode())
    return rows


# ----------------------------------------------------------------------------------------- command line
def add_arguments_course(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="<action>", required=True)
    a = sub.add_parser("init", help="make a course folder (nbgrader's layout) from notebooks 01-07")
    a.add_argument("--out", type=Path, default=Path("course"), help="the new course folder (default: course)")
    a.add_argument("--course-id", default=COURSE_ID, help=f"nbgrader's course id (default: {COURSE_ID})")
    a.add_argument("--notebooks", nargs="+", type=Path, default=None,
                   help="the notebooks that become assignments (default: 01-07 of notebooks/)")
    helps = {"release": "write the student release (release/<assignment>/) and enter it into the gradebook",
             "edition": "write the student edition: the checkout without solution notebooks, the release in its place",
             "collect": "copy returned notebooks SUBMISSIONS/<student>/... into submitted/<student>/<assignment>/",
             "autograde": "autograde every collected submission in a sandbox (hidden tests put back)",
             "feedback": "write an HTML feedback page per graded notebook (feedback/)",
             "grades": "write the grade table: points and max points per student and assignment"}
    for action, text in helps.items():
        a = sub.add_parser(action, help=text, description=text)
        a.add_argument("--course", type=Path, default=Path("course"), help="the course folder (default: course)")
        if action == "collect":
            a.add_argument("submissions", type=Path, help="a folder holding one folder per student")
        if action == "autograde":
            a.add_argument("--unsafe-no-sandbox", action="store_true",
                           help="run the students' notebooks with your own rights where bubblewrap is missing "
                                "(they can then read the solutions and the gradebook: see docs/teaching.md)")
            a.add_argument("--retry", action="store_true",
                           help="grade again the submissions that could not run before")
            a.add_argument("--kernel-memory", type=float, default=sandbox.KERNEL_MEMORY_GIB, metavar="GIB",
                           help="the most memory (GiB) a student's kernel may hold in the sandbox, its processes "
                                f"together (default: {sandbox.KERNEL_MEMORY_GIB:g})")
        if action == "grades":
            a.add_argument("--out", type=Path, default=Path("grades.csv"), help="the CSV (default: grades.csv)")
        if action == "edition":
            a.add_argument("--out", type=Path, default=Path("student-edition"),
                           help="the new folder for the student edition (default: student-edition)")


def _report(args) -> str:
    if args.action == "init":
        info = init(args.out, args.notebooks, args.course_id)
        manual = sum(len(v) for v in info["manual"].values())
        return (f"course {args.out}: {len(info['assignments'])} assignments ({', '.join(info['assignments'])}); "
                f"{manual} open-ended exercises graded by hand; cell timeout {info['timeout']} s")
    if args.action == "release":
        return f"released {len(release(args.course))} notebooks into {args.course / 'release'}"
    if args.action == "edition":
        info = edition(args.course, args.out)
        return (f"student edition {args.out}: {info['copied']} files of the checkout, without "
                f"{', '.join(info['left_out']) or 'no notebook'}; {len(info['released'])} released notebooks in "
                f"{args.out / 'notebooks'}")
    if args.action == "collect":
        info = collect(args.course, args.submissions)
        note = f"; skipped {len(info['skipped'])} other files (first {info['skipped'][0]})" if info["skipped"] else ""
        return f"collected {len(info['collected'])} notebooks ({info['already']} already there){note}"
    if args.action == "autograde":
        return _autograde_report(args)
    if args.action == "feedback":
        pages = feedback(args.course, echo=lambda line: print(line, file=sys.stderr))
        return f"{len(pages)} feedback pages under {args.course / 'feedback'}"
    rows = write_grades(args.course, args.out)
    pending = sum(r["needs_manual_grading"] > 0 for r in rows)
    flagged = [f"flagged for review: {r['student']}, {r['assignment']}, {part}" for r in rows
               for part in r["flagged_for_review"].split(" | ") if part]
    return "\n".join([*flagged, f"{len(rows)} grades in {args.out}; {pending} still need a hand grade (formgrader)"
                       + (f"; {len(flagged)} answers flagged by the static review (column flagged_for_review)"
                          if flagged else "")])


def _autograde_report(args) -> str:
    if args.unsafe_no_sandbox:
        print("WARNING: autograding WITHOUT a sandbox (--unsafe-no-sandbox): every student's notebook runs with "
              "your rights and can read the solutions in source/, the hidden tests in gradebook.db and the other "
              "submissions, and change them", file=sys.stderr)
    info = autograde(args.course, sandboxed=not args.unsafe_no_sandbox, retry=args.retry,
                     echo=lambda line: print(line, file=sys.stderr), memory_gib=args.kernel_memory)
    if not info["graded"] and not info["could_not_run"]:
        return (f"nothing to autograde: {len(info['skipped'])} submissions graded before" if info["skipped"]
                else "nothing to autograde: no submission collected")
    flagged = f"; {len(info['flagged'])} answers flagged for review (manual grading)" if info["flagged"] else ""
    return (f"autograded {len(info['graded'])} submissions; {len(info['could_not_run'])} could not run; "
            f"{len(info['skipped'])} graded before{flagged}")


def run_course(args) -> int:
    print(_report(args))
    return 0
