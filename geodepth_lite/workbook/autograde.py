"""``course autograde`` and ``course feedback``: each submission graded on its own, its kernel in a sandbox,
and feedback pages that name each exercise but keep the hidden tests hidden.

Autograde runs nbgrader's ``autograde <assignment> --student=<id>`` once per submission, in a process
of its own, with the notebook's kernel started in the sandbox of :mod:`geodepth_lite.workbook.sandbox` (the
course folder, the solutions and the gradebook out of its reach). A submission whose run fails (the
kernel died, nbgrader stopped, the whole run took longer than every cell's timeout together) is
recorded as *could not run* in ``COURSE/could_not_run.json`` with a one-line reason, and the class goes
on (the whole run's limit counts the course's cells, not the student's; only the tail of what it prints is
kept). Each graded submission's code cells then get the static review of :mod:`geodepth_lite.workbook.review`,
in this process: an exercise it flags is sent to manual grading (0 points until a hand grade) with the
reasons in ``COURSE/flagged.json``, on the command's output and in the grade table. A rerun skips what is
graded (``autograded/<student>/<assignment>/``) and what could not run
(unless ``retry``).

Feedback is written here, not by nbgrader's template (which prints the hidden tests and loads
MathJax from the web): one page per notebook, each exercise by its number and title with its
points, passed or failed, and the failed check's message (the exception's name and text, never the
check's source or its traceback; an error of the student's own answer cell, such as the cell timeout,
comes first); a flagged exercise is "held", with no message. A graded notebook that cannot be read back
gets a page saying so, and the class goes on. The page holds no script and no link: no prompt text is shown, so
there is no math to render.
"""

from __future__ import annotations

import html
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.workbook import exercises, review, sandbox

FAILURES = "could_not_run.json"  # (student, assignment) -> why the submission could not run
FLAGGED = "flagged.json"  # (student, assignment) -> exercises the static review sent to manual grading
KERNEL_START_S = 120  # on top of the cells' timeouts: starting the kernel and nbgrader itself
HEADING = re.compile(r"Exercise\s+(\d+\.\d+)\s*·\s*(.+?)\s*\((\w+),\s*([\d.]+)\s*points?\)")
MESSAGE_MAX = 400  # characters of a check's message on the page
HELD_MESSAGE = "your lecturer grades this exercise by hand (the static review flagged it); no check output is shown"
OUTPUT_TAIL_BYTES = 64 * 1024  # of nbgrader's output, read back to say why a submission could not run


# ----------------------------------------------------------------------------------------- could not run
def read_failures(course: Path) -> dict[tuple[str, str], str]:
    path = Path(course) / FAILURES
    if not path.is_file():
        return {}
    try:
        rows = json.loads(path.read_text())
        return {(r["student"], r["assignment"]): str(r["reason"]) for r in rows}
    except (ValueError, KeyError, TypeError) as exc:
        raise utils.FileProblem(f"cannot read {path}: damaged ({type(exc).__name__}); it lists the submissions "
                                "that could not run: fix or remove it", path) from None


def _write_failures(course: Path, failures: dict[tuple[str, str], str]) -> None:
    rows = [{"student": s, "assignment": a, "reason": r} for (s, a), r in sorted(failures.items())]
    utils.write_bytes_atomic(Path(course) / FAILURES, (json.dumps(rows, indent=1) + "\n").encode())


def failure_reason(output: str, returncode: int) -> str:
    """One line saying why nbgrader could not grade a submission, from its output."""
    lines = [ln.strip() for ln in output.splitlines() if ln.strip()]
    for pattern, why in (("DeadKernelError", "the kernel died (the notebook ended Python, crashed or ran out of "
                                             "memory)"),
                         ("Kernel died", "the kernel died"),
                         ("Timeout waiting for IOPub output", "a cell's output stopped reaching the grader (more "
                                                              f"than {sandbox.FRAME_BYTES >> 20} MiB printed at once "
                                                              "is dropped, with what follows it)"),
                         ("CellTimeoutError", "a cell ran past the timeout")):
        hit = next((ln for ln in reversed(lines) if pattern in ln), None)
        if hit:
            return f"{why}: {hit[-200:]}"
    errors = [ln for ln in lines if "Error" in ln or "[ERROR]" in ln] or lines
    return f"nbgrader exited with status {returncode}: {errors[-1][-200:] if errors else 'no output'}"


# ----------------------------------------------------------------------------------------- the static review
def read_flags(course: Path) -> dict[tuple[str, str], list[dict]]:
    """(student, assignment) -> the flagged exercises (notebook, exercise, reasons) of ``COURSE/flagged.json``."""
    path = Path(course) / FLAGGED
    if not path.is_file():
        return {}
    try:
        out: dict[tuple[str, str], list[dict]] = {}
        for r in json.loads(path.read_text()):
            row = {"notebook": str(r["notebook"]), "exercise": str(r["exercise"]), "reasons": [str(x) for x in
                                                                                              r["reasons"]]}
            out.setdefault((r["student"], r["assignment"]), []).append(row)
        return out
    except (ValueError, KeyError, TypeError) as exc:
        raise utils.FileProblem(f"cannot read {path}: damaged ({type(exc).__name__}); it lists the answers the "
                                "static review sent to manual grading: fix or remove it", path) from None


def _write_flags(course: Path, flags: dict[tuple[str, str], list[dict]]) -> None:
    rows = [{"student": s, "assignment": a, **row} for (s, a), found in sorted(flags.items()) for row in found]
    utils.write_bytes_atomic(Path(course) / FLAGGED, (json.dumps(rows, indent=1) + "\n").encode())


def review_submission(course: Path, student: str, assignment: str) -> list[dict]:
    """The static review (:mod:`geodepth_lite.workbook.review`) of each returned notebook of a submission against
    the course's source: one row (notebook, exercise "02.2", its grade ids, reasons) per flagged exercise."""
    course = Path(course)
    rows = []
    for src in sorted((course / "source" / assignment).glob("*.ipynb")):
        returned = course / "submitted" / student / assignment / src.name
        if not returned.is_file():
            continue
        flagged = review.review_notebook(exercises.read_notebook(src, solutions=False),
                                         exercises.read_notebook(returned, solutions=False))
        for ident, found in flagged.items():
            rows.append({"notebook": src.stem, "exercise": ident.replace("-", "."),
                         "reasons": [f.text() for f in found]})
    return rows


def send_to_manual_grading(course: Path, student: str, assignment: str, rows: list[dict]) -> None:
    """In the gradebook, each flagged exercise's graded cells wait for a hand grade, at 0 points until it
    is given, and its answer cell carries the reasons as a comment (formgrader shows it)."""
    # nbgrader's gradebook (SQLAlchemy): heavy, needed by autograde only
    from nbgrader.api import Gradebook, MissingEntry

    with Gradebook(f"sqlite:///{(Path(course) / 'gradebook.db').resolve()}") as gb:
        for row in rows:
            stem = "ex" + row["exercise"].replace(".", "-")
            for part in ("answer", "check"):
                try:
                    grade = gb.find_grade(f"{stem}-{part}", row["notebook"], assignment, student)
                except MissingEntry:  # an answer cell that carries no points has no grade
                    continue
                grade.manual_score, grade.needs_manual_grade = 0.0, True
            try:
                comment = gb.find_comment(f"{stem}-answer", row["notebook"], assignment, student)
                comment.auto_comment = "Flagged by the static review, for a hand grade: " + "; ".join(row["reasons"])
            except MissingEntry:
                pass
        gb.db.commit()


# ----------------------------------------------------------------------------------------- one submission
def run_limit(folder: Path, cell_timeout: int) -> int:
    """Seconds one submission's whole run may take: every code cell at the cell timeout, plus a start.
    ``folder``: the assignment's notebooks in the course's ``source/``, so that cells a student adds do not
    lengthen it."""
    cells = 0
    for nb in folder.glob("*.ipynb"):
        try:
            cells += sum(c.get("cell_type") == "code" for c in exercises.read_notebook(nb, solutions=False)["cells"])
        except (ValueError, OSError):
            cells += 1
    return cell_timeout * max(cells, 1) + KERNEL_START_S


def _environment(scratch: Path, course: Path, memory: int) -> dict:
    env = dict(os.environ)  # nbgrader runs alembic from this interpreter's scripts folder: first on PATH
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    env[sandbox.SCRATCH_ENV] = str(scratch)
    env[sandbox.HIDDEN_ENV] = str(Path(course).resolve())
    env[sandbox.MEMORY_ENV] = str(int(memory))
    root = str(utils.package_parent())
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def grade_one(course: Path, student: str, assignment: str, sandboxed: bool, limit_s: float,
              memory: int = sandbox.KERNEL_MEMORY_BYTES) -> str | None:
    """nbgrader's autograde of one submission in a process of its own, the kernel's processes holding at most
    ``memory`` bytes (each of data, and all together: :class:`KernelWatch`); None when it is graded, else the
    reason it could not run (its partial ``autograded/`` folder, made by this run, is removed)."""
    course = Path(course)
    cmd = [sys.executable, "-m", "nbgrader", "autograde", assignment, f"--student={student}",
           f"--CourseDirectory.root={course.resolve()}", "--log-level=WARN"]
    if sandboxed:
        cmd.append("--Execute.kernel_manager_class=geodepth_lite.workbook.sandbox_kernel.SandboxKernelManager")
    scratch = Path(tempfile.mkdtemp(prefix="geodepth-grade-"))
    try:
        proc = subprocess.Popen(cmd, cwd=course, env=_environment(scratch, course, memory), stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, start_new_session=True)
        tail = bytearray()
        reader = threading.Thread(target=keep_tail, args=(proc.stdout, tail, OUTPUT_TAIL_BYTES), daemon=True)
        reader.start()
        watch = KernelWatch(proc.pid, memory, sockets=scratch / "kernel")
        watch.start()
        try:
            proc.wait(timeout=limit_s)
            reader.join(timeout=10)  # a process left holding the pipe open does not hold the class
            output = bytes(tail).decode("utf-8", "replace")
            reason = None if proc.returncode == 0 else failure_reason(output, proc.returncode)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # nbgrader, its kernel and what the kernel started
            proc.wait()
            reader.join(timeout=10)  # a process left holding the pipe open does not hold the class
            reason = f"stopped after {limit_s:.0f} s, every cell's timeout together: the kernel hung"
        finally:
            watch.stop()
        if watch.reason is not None:  # the kernel died because the watch stopped it: say why
            reason = f"the grader stopped the kernel: {watch.reason}"
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    if reason is not None:
        shutil.rmtree(course / "autograded" / student / assignment, ignore_errors=True)
    return reason


class KernelWatch(threading.Thread):
    """Every :data:`~geodepth_lite.workbook.sandbox.WATCH_S` seconds, what the processes under nbgrader's
    (``root``: the sandboxed kernel and whatever it started) hold together; past ``memory`` bytes or
    :data:`~geodepth_lite.workbook.sandbox.PROCESSES_MAX` processes, each is killed (bubblewrap first, which
    ends its PID namespace) and :attr:`reason` says why. RLIMIT_DATA bounds each process; this bounds their
    sum, from outside the sandbox, where the student's code cannot reach it. It stops them too where the
    folder of the kernel's sockets (``sockets``, on the grader's disk) holds more than its sockets need."""

    def __init__(self, root: int, memory: int, processes: int = sandbox.PROCESSES_MAX, sockets: Path | None = None):
        super().__init__(daemon=True)
        self.root, self.memory, self.processes, self.sockets = root, memory, processes, sockets
        self.reason: str | None = None
        self._done = threading.Event()

    def run(self) -> None:
        while not self._done.wait(sandbox.WATCH_S):
            pids = sandbox.descendants(self.root)
            why = sandbox.over_limits(pids, self.memory, self.processes)
            if why is None and self.sockets is not None:
                why = sandbox.sockets_over(self.sockets)
            if why is None:
                continue
            self.reason = self.reason or why
            for pid in pids:
                try:
                    os.kill(pid, signal.SIGKILL)
                except OSError:
                    pass  # ended already

    def stop(self) -> None:
        self._done.set()
        self.join(timeout=10)


def keep_tail(stream, tail: bytearray, keep: int) -> None:
    """Read ``stream`` to its end, keeping only its last ``keep`` bytes in ``tail``: what a notebook prints
    to its standard error (which nbgrader passes on) cannot fill the grader's memory."""
    with stream:
        for chunk in iter(lambda: stream.read(65536), b""):
            tail += chunk
            del tail[:max(0, len(tail) - keep)]


# ----------------------------------------------------------------------------------------- the class
def submissions(course: Path, names: list[str]) -> list[tuple[str, str]]:
    """(student, assignment) of every collected submission of the ``names`` assignments, in order."""
    folder = Path(course) / "submitted"
    found = [(p.parent.name, p.name) for p in folder.glob("*/*") if p.is_dir() and p.name in names]
    return sorted(found, key=lambda sa: (names.index(sa[1]), sa[0]))


def grade_class(course: Path, names: list[str], cell_timeout: int, *, sandboxed: bool = True, retry: bool = False,
                echo=None, memory: int = sandbox.KERNEL_MEMORY_BYTES) -> dict:
    """Grade every collected submission not graded yet (see the module docstring); the caller holds the
    course lock. ``cell_timeout``: the course's, in seconds; ``echo``: called with one line per
    submission that could not run and per exercise the static review flagged. Each submission graded is
    reviewed (:func:`review_submission`): a flagged exercise waits for a hand grade at 0 points
    (:func:`send_to_manual_grading`) and is recorded in ``COURSE/flagged.json``. Returns the submissions
    graded now, those that could not run (with the reason), those skipped, and the flagged exercises."""
    course = Path(course)
    if sandboxed:
        why = sandbox.unavailable()
        if why:
            raise UserError(f"cannot autograde {course}: no sandbox for the students' code ({why}); install "
                             "bubblewrap (apt-get install bubblewrap) or, knowing that each notebook then runs "
                             "with your rights, pass --unsafe-no-sandbox")
    failures, flags = read_failures(course), read_flags(course)
    graded, failed, skipped = [], [], []
    for student, assignment in submissions(course, names):
        key = (student, assignment)
        if (course / "autograded" / student / assignment).is_dir() or (key in failures and not retry):
            skipped.append(key)
            continue
        folder = course / "submitted" / student / assignment
        limit = run_limit(course / "source" / assignment, cell_timeout)
        reason = grade_one(course, student, assignment, sandboxed, limit, memory)
        failures.pop(key, None)
        if reason is None:
            graded.append(key)
            _flag(course, key, flags, echo)
        else:
            notebooks = ", ".join(p.name for p in sorted(folder.glob("*.ipynb"))) or assignment
            failures[key] = reason
            failed.append((student, assignment, reason))
            if echo:
                echo(f"could not run: {student}, {notebooks}: {reason}")
        _write_failures(course, failures)
    flagged = [(s, a, row) for (s, a) in graded for row in flags.get((s, a), [])]
    return {"graded": graded, "could_not_run": failed, "skipped": skipped, "flagged": flagged}


def _flag(course: Path, key: tuple[str, str], flags: dict, echo) -> None:
    """Review a submission just graded; send its flagged exercises to manual grading and record them."""
    rows = review_submission(course, *key)
    if flags.pop(key, None) is None and not rows:
        return
    if rows:
        send_to_manual_grading(course, *key, rows)
        flags[key] = rows
        for row in rows:
            if echo:
                echo(f"flagged for review: {key[0]}, {row['notebook']}.ipynb exercise {row['exercise']}: "
                     f"{row['reasons'][0]}" + (f" (and {len(row['reasons']) - 1} more)" if len(row["reasons"]) > 1
                                               else ""))
    _write_flags(course, flags)


# ----------------------------------------------------------------------------------------- feedback
def _message(cell: dict) -> str | None:
    """A cell's error as one line (exception name and text), or None if it ran without one. The last
    error counts: after a cell timeout, the kernel's KeyboardInterrupt comes before nbgrader's
    CellTimeoutError."""
    errors = [out for out in cell.get("outputs", []) if out.get("output_type") == "error"]
    if not errors:
        return None
    name = str(errors[-1].get("ename", "Error"))
    text = " ".join(str(errors[-1].get("evalue", "")).split())
    if name == "CellTimeoutError" and not text:
        text = "the cell ran longer than the course's cell timeout and was stopped"
    text = text if len(text) <= MESSAGE_MAX else text[:MESSAGE_MAX] + "..."
    return f"{name}: {text}" if text else name


def _score(grades: dict, cell: dict) -> tuple[float | None, float, bool]:
    """(points given or None, max points, waits for a hand grade) of a graded cell."""
    grade_id = cell.get("metadata", {}).get("nbgrader", {}).get("grade_id", "")
    got = grades.get(grade_id)
    if got is None:
        return None, float(cell.get("metadata", {}).get("nbgrader", {}).get("points", 0) or 0), False
    return got


def exercise_rows(nb: dict, grades: dict, held: frozenset[str] = frozenset()) -> list[dict]:
    """One row per exercise of a graded notebook: number, title, points, max points, outcome, message.
    ``held``: the exercises ("99.2") the static review flagged: what their checks printed ran beside code
    the review could not vouch for (it may carry the hidden tests), so their row says "held" and no more."""
    rows = []
    for ex in exercises.notebook_exercises(nb).values():
        m = HEADING.search(ex.prompt)
        number, title = (m.group(1), m.group(2)) if m else (ex.ident.replace("-", "."), "")
        points, max_points, waits = 0.0, 0.0, False
        for part in ("answer", "check"):
            cell = ex.cells.get(part)
            meta = (cell or {}).get("metadata", {}).get("nbgrader", {})
            if cell is None or not (meta.get("grade") or meta.get("grade_id") in grades):
                continue
            got, most, hand = _score(grades, cell)
            points += got or 0.0
            max_points += most
            waits = waits or hand
        stopped = _message(ex.cells["answer"]) if "answer" in ex.cells else None  # the student's own cell
        failed = _message(ex.cells["check"]) if "check" in ex.cells else None
        outcome = "failed" if failed else "passed"
        message = "; ".join(m for m in (stopped and f"your answer cell stopped: {stopped}", failed) if m) or None
        if ex.ident.replace("-", ".") in held:
            outcome, message = "held", HELD_MESSAGE
        rows.append({"number": number, "title": title, "points": points, "max_points": max_points,
                     "outcome": outcome, "message": message, "waits": waits})
    return rows


def notebook_grades(course: Path, student: str, assignment: str, notebook: str) -> dict:
    """grade_id -> (points, max points, waits for a hand grade) from the gradebook."""
    # nbgrader's gradebook (SQLAlchemy): heavy, needed by this command only
    from nbgrader.api import Gradebook, MissingEntry

    out = {}
    with Gradebook(f"sqlite:///{(Path(course) / 'gradebook.db').resolve()}") as gb:
        try:
            nb = gb.find_submission_notebook(notebook, assignment, student)
        except MissingEntry:
            return {}
        for g in nb.grades:
            out[g.name] = (None if g.score is None else float(g.score), float(g.max_score), bool(g.needs_manual_grade))
    return out


PAGE_CSS = ("body{font-family:sans-serif;max-width:46em;margin:2em auto;padding:0 1em;color:#222}"
            "table{border-collapse:collapse;width:100%}td,th{border-bottom:1px solid #ccc;padding:.4em;"
            "text-align:left;vertical-align:top}.failed{color:#a00}.passed{color:#060}.held{color:#850}"
            ".could-not-run{border:2px solid #a00;padding:.6em 1em}")


def _number(x: float) -> str:
    return f"{x:g}" if math.isfinite(x) else "?"


def page(student: str, assignment: str, notebook: str, rows: list[dict] | None, reason: str | None,
         unreadable: str | None = None) -> str:
    """The feedback page: the exercises' table, or what stopped the notebook, or (``unreadable``) why its
    graded copy could not be read back."""
    e = html.escape
    head = (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>Feedback: {e(notebook)}"
            f"</title><style>{PAGE_CSS}</style></head><body>\n<h1>Feedback on {e(notebook)}</h1>\n"
            f"<p>Student {e(student)}, assignment {e(assignment)}.</p>\n")
    if reason is not None:
        body = (f"<div class=\"could-not-run\"><p><strong>Your notebook could not run</strong>, so none of its "
                f"exercises was graded: {e(reason)}.</p><p>Run it from the top in a fresh kernel (Kernel &gt; "
                "Restart &amp; Run All) and make sure it ends without stopping Python (no <code>exit()</code>); "
                "then ask your lecturer to grade it again.</p></div>\n")
        return head + body + "</body></html>\n"
    if unreadable is not None:
        body = (f"<div class=\"could-not-run\"><p><strong>Your notebook ran, but its graded copy could not be "
                f"read back</strong>: {e(unreadable)}. Make its outputs smaller (print less) and ask your lecturer "
                "to grade it again; your grade is in the lecturer's gradebook.</p></div>\n")
        return head + body + "</body></html>\n"
    total = sum(r["points"] for r in rows)
    most = sum(r["max_points"] for r in rows)
    lines = ["<table><tr><th>exercise</th><th>points</th><th>check</th><th>message</th></tr>"]
    for r in rows:
        pts = f"{_number(r['points'])} / {_number(r['max_points'])}" + (" (graded by hand, pending)"
                                                                       if r["waits"] else "")
        lines.append(f"<tr><td>{e(r['number'])} {e(r['title'])}</td><td>{e(pts)}</td>"
                     f"<td class=\"{r['outcome']}\">{r['outcome']}</td><td>{e(r['message'] or '')}</td></tr>")
    lines.append("</table>")
    summary = f"<p><strong>{_number(total)} of {_number(most)} points</strong> so far.</p>\n"
    return head + summary + "\n".join(lines) + "\n</body></html>\n"


def write_feedback(course: Path, names: list[str], echo=None) -> list[Path]:
    """One page per notebook graded or that could not run, ``feedback/<student>/<assignment>/<notebook>.html``
    (the caller holds the course lock); returns the pages written. A graded notebook that cannot be read
    back (over the size a notebook may have, damaged) gets a page saying so, and a line to ``echo``; the
    class goes on."""
    course = Path(course)
    failures, flags = read_failures(course), read_flags(course)
    written = []
    for student, assignment in submissions(course, names):
        graded = course / "autograded" / student / assignment
        reason = failures.get((student, assignment))
        if reason is None and not graded.is_dir():
            continue
        for src in sorted((course / "source" / assignment).glob("*.ipynb")):
            rows = unreadable = None
            if reason is None:
                if not (graded / src.name).is_file():
                    continue
                held = frozenset(r["exercise"] for r in flags.get((student, assignment), [])
                                 if r["notebook"] == src.stem)
                try:
                    nb = exercises.read_notebook(graded / src.name, solutions=False)
                    rows = exercise_rows(nb, notebook_grades(course, student, assignment, src.stem), held)
                except (ValueError, OSError) as exc:
                    unreadable = str(exc).replace(str(graded / src.name), "it").splitlines()[0][:300]
                    if echo:
                        echo(f"feedback: {student}, {src.name}: {exc}")
            target = course / "feedback" / student / assignment / f"{src.stem}.html"
            text = page(student, assignment, src.name, rows, reason, unreadable)
            utils.write_bytes_atomic(target, text.encode())
            written.append(target)
    return written
