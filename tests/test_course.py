"""The lecturer's course (``course init / release / collect / autograde / feedback / grades``): the
cell timeout taken from the notebooks' own execution records, open-ended exercises graded by hand,
returned notebooks collected without replacing one, and a round trip through nbgrader in which
three students (all right, all wrong, the release untouched) get known scores.

The round trip grades a tiny notebook built here in the project's exercise conventions (executing
notebooks 01-07 would take many minutes): an answer cell with a solution region and a locked check
cell with hidden tests per exercise, the last one open-ended."""

import csv
import errno
import hashlib
import html
import io
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from conftest import one_line_error

from geodepth_lite import cli, utils
from geodepth_lite.workbook import autograde, course, exercises, review, sandbox

TINY = "99_tiny"


def _cell(kind, source, grade_id=None, points=None, **extra):
    meta = {}
    if grade_id:
        answer = grade_id.endswith("answer")
        meta["nbgrader"] = {"grade": not answer, "grade_id": grade_id, "locked": not answer, "schema_version": 3,
                            "solution": answer, "task": False}
        if points is not None:
            meta["nbgrader"]["points"] = points
    meta.update(extra)
    cell = {"cell_type": kind, "metadata": meta, "source": source}
    if kind == "code":
        cell.update(outputs=[], execution_count=None)
    return cell


def _exercise(n, title, level, points, answer, check):
    return [_cell("markdown", f"### Exercise 99.{n} · {title} ({level}, {points} points)\n\nDo it."),
            _cell("code", answer, f"ex99-{n}-answer"), _cell("code", check, f"ex99-{n}-check", points)]


ANSWERS = {  # exercise -> (the source's answer cell, a plausible wrong answer a student returns)
    1: ("my_sum = None\n### BEGIN SOLUTION\nmy_sum = 2 + 3\n### END SOLUTION",
        "import time\n\ntime.sleep(40)  # a loop that takes too long: the cell timeout stops it\nmy_sum = 2 + 3"),
    2: ("def square(x):\n    ### BEGIN SOLUTION\n    return x * x\n    ### END SOLUTION",
        "def square(x):\n    return 3 * x  # right for 3 only: the hidden test catches it"),
    3: ("why = None\n### BEGIN SOLUTION\nwhy = 'a square multiplies a number by itself, so it outgrows a sum'\n"
        "### END SOLUTION", "why = 'I am not sure why, but it works.'  # eight words, no reason"),
}


def tiny_notebook(path: Path) -> Path:
    cells = [_cell("markdown", "# A tiny lesson\n\n## Exercises")]
    cells += _exercise(1, "Add", "recall", 2, ANSWERS[1][0],
                       "assert my_sum == 5, 'my_sum'\n### BEGIN HIDDEN TESTS\nassert isinstance(my_sum, int)\n"
                       "### END HIDDEN TESTS")
    cells += _exercise(2, "Square", "apply", 3, ANSWERS[2][0],
                       "assert square(3) == 9\n### BEGIN HIDDEN TESTS\nassert square(-4) == 16\n### END HIDDEN TESTS")
    cells += _exercise(3, "Why", "open", 4, ANSWERS[3][0],
                       "assert isinstance(why, str) and len(why.split()) >= 8, 'explain in why'")
    nb = {"cells": cells, "metadata": {"kernelspec": {"name": "python3", "display_name": "Python 3",
                                                      "language": "python"}}, "nbformat": 4, "nbformat_minor": 5}
    path.write_text(json.dumps(nb, indent=1))
    return path


def _returned(release_nb: Path, answers: dict[int, str] | None) -> bytes:
    """The released notebook with each answer cell replaced by ``answers[n]`` (None: untouched)."""
    nb = json.loads(release_nb.read_text())
    for cell in nb["cells"]:
        gid = cell["metadata"].get("nbgrader", {}).get("grade_id", "")
        if answers and gid.endswith("answer"):
            cell["source"] = answers[int(gid.split("-")[1])]
    return json.dumps(nb).encode()


def _solution(answer: str) -> str:
    return "\n".join(ln for ln in answer.splitlines() if ln.strip() not in exercises.SOLUTION_MARKERS)


@pytest.fixture
def needs_sandbox():
    """Autograding runs each kernel in bubblewrap: skipped, saying why, where it cannot; with
    GEODEPTH_REQUIRE_SANDBOX=1 (CI) it fails instead."""
    why = sandbox.unavailable()
    if why and os.environ.get(sandbox.REQUIRE_ENV) == "1":
        pytest.fail(f"no sandbox for autograding: {why}")
    if why:
        pytest.skip(f"no sandbox for autograding: {why}")


@pytest.fixture
def tiny_course(tmp_path):
    root = tmp_path / "course"
    course.init(root, [tiny_notebook(tmp_path / f"{TINY}.ipynb")])
    return root


# ----------------------------------------------------------------------------------------- the timeout
def test_cell_timeout_comes_from_the_committed_notebooks_records():
    assert course.cell_seconds({"metadata": {"papermill": {"duration": 12.5}}}) == 12.5
    stamps = {"iopub.execute_input": "2026-11-24T04:34:52.612586Z",
              "shell.execute_reply": "2026-11-24T04:35:02.612586Z"}
    assert course.cell_seconds({"metadata": {"execution": stamps}}) == pytest.approx(10.0)
    assert course.cell_seconds({"metadata": {}}) is None
    assert course.cell_timeout(348.1) == 1080 and course.cell_timeout(0.0) == course.TIMEOUT_MIN_S
    committed = {p: json.loads(p.read_text()) for p in exercises.notebook_paths()}
    seconds, name = course.slowest_cell(committed)
    assert name == "06_generalization.ipynb" and 300 < seconds < 400  # its held-out training cell
    assert course.cell_timeout(seconds) > 2 * seconds


def test_init_writes_nbgrader_layout_config_and_hand_graded_open_exercises(tmp_path, capsys):
    out = tmp_path / "course"
    assert cli.main(["course", "init", "--out", str(out), "--course-id", "depth101"]) == 0
    assert "7 assignments" in capsys.readouterr().out
    config = (out / "nbgrader_config.py").read_text()
    assert "c.CourseDirectory.course_id = 'depth101'" in config and "c.Execute.timeout = 1080" in config
    assert "06_generalization.ipynb" in config
    for p in exercises.notebook_paths():
        src = json.loads((out / "source" / p.stem / p.name).read_text())
        before, after = exercises.notebook_exercises(json.loads(p.read_text())), exercises.notebook_exercises(src)
        assert not any(c.get("outputs") for c in src["cells"] if c["cell_type"] == "code")
        for ident, ex in after.items():
            answer, check = ex.cells["answer"]["metadata"]["nbgrader"], ex.cells["check"]["metadata"]["nbgrader"]
            if "(open," in ex.prompt:  # points move to the hand-graded answer; the check still runs, for 0
                assert answer["grade"] and answer["solution"] and answer["points"] == before[ident].points
                assert check["grade"] and check["points"] == 0
            else:
                assert not answer["grade"] and check["points"] == before[ident].points
        assert sum(ex.points for ex in before.values()) == sum(
            ex.cells["answer"]["metadata"]["nbgrader"].get("points", 0) + ex.points for ex in after.values())
    # a second init never writes into it
    assert cli.main(["course", "init", "--out", str(out)]) == 2
    one_line_error(capsys, str(out), "not an empty folder")
    assert cli.main(["course", "init", "--out", str(exercises.NOTEBOOK_DIR / "c")]) == 2
    one_line_error(capsys, "notebooks folder")
    assert not (exercises.NOTEBOOK_DIR / "c").exists()


# ----------------------------------------------------------------------------------------- collect
def _submissions(tmp_path, files: dict[str, bytes]) -> Path:
    subs = tmp_path / "returned"
    for rel, data in files.items():
        (subs / rel).parent.mkdir(parents=True, exist_ok=True)
        (subs / rel).write_bytes(data)
    return subs


def test_collect_copies_into_submitted_and_never_replaces(tiny_course, tmp_path, capsys):
    nb = (tmp_path / f"{TINY}.ipynb").read_bytes()
    subs = _submissions(tmp_path, {f"ana/{TINY}.ipynb": nb, f"bo/{TINY}/{TINY}.ipynb": nb, "bo/notes.txt": b"hi"})
    assert cli.main(["course", "collect", str(subs), "--course", str(tiny_course)]) == 0
    out = capsys.readouterr().out
    assert "collected 2 notebooks" in out and "skipped 1" in out
    for student in ("ana", "bo"):
        folder = tiny_course / "submitted" / student / TINY
        assert (folder / f"{TINY}.ipynb").read_bytes() == nb and (folder / "timestamp.txt").is_file()
    assert cli.main(["course", "collect", str(subs), "--course", str(tiny_course)]) == 0  # the same again: skipped
    assert "collected 0 notebooks (2 already there)" in capsys.readouterr().out
    (subs / "ana" / f"{TINY}.ipynb").write_bytes(nb.replace(b"A tiny", b"My tiny"))
    (subs / "cy").mkdir()
    (subs / "cy" / f"{TINY}.ipynb").write_bytes(nb)
    assert cli.main(["course", "collect", str(subs), "--course", str(tiny_course)]) == 2
    one_line_error(capsys, str(subs / "ana" / f"{TINY}.ipynb"), "different copy")
    assert not (tiny_course / "submitted" / "cy").exists()  # refused before the first copy
    assert (tiny_course / "submitted" / "ana" / TINY / f"{TINY}.ipynb").read_bytes() == nb


@pytest.mark.parametrize("case", ["link", "outside", "linked folder", "damaged", "student name", "no course"])
def test_collect_refuses_with_one_line_naming_the_file(tiny_course, tmp_path, capsys, case):
    secret = tmp_path / "secret.ipynb"
    secret.write_text("{}")
    subs = _submissions(tmp_path, {f"ana/{TINY}.ipynb": (tmp_path / f"{TINY}.ipynb").read_bytes()})
    named, target = subs / "bo" / f"{TINY}.ipynb", str(tiny_course)
    (subs / "bo").mkdir()
    if case == "link":
        named.symlink_to(secret)
    elif case == "outside":
        named = subs / "cy"
        named.symlink_to(tmp_path, target_is_directory=True)
    elif case == "linked folder":  # a folder inside a student's folder that links back up: never walked
        named = subs / "bo" / TINY
        named.symlink_to(subs, target_is_directory=True)
    elif case == "damaged":
        named.write_bytes(b'{"cells": [1, 2')
    elif case == "student name":
        named = subs / "bo b"
        named.mkdir()
    else:
        named, target = tmp_path / "nowhere", str(tmp_path / "nowhere")
    assert cli.main(["course", "collect", str(subs), "--course", target]) == 2
    one_line_error(capsys, str(named))
    assert not (tiny_course / "submitted").exists()


def test_collect_refuses_a_fifo_named_like_a_notebook_without_hanging(tiny_course, tmp_path, capsys):
    """A FIFO (as a tar archive can deliver one) named like a returned notebook: one line naming it, exit 2,
    nothing collected, the course lock released; an alarm turns a hang into a failure."""
    subs = _submissions(tmp_path, {f"ana/{TINY}.ipynb": (tmp_path / f"{TINY}.ipynb").read_bytes()})
    (subs / "bo").mkdir()
    fifo = subs / "bo" / f"{TINY}.ipynb"
    os.mkfifo(fifo)

    def hung(*_):
        raise TimeoutError("collect blocked on the FIFO")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(15)
    try:
        assert cli.main(["course", "collect", str(subs), "--course", str(tiny_course)]) == 2
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    one_line_error(capsys, str(fifo), "not a regular file")
    assert not (tiny_course / "submitted").exists() and not (tiny_course / utils.LOCK_NAME).exists()
    with course.course_lock(tiny_course):  # free again: the next action is not told the course is busy
        pass
    with pytest.raises(utils.FileProblem, match="not a regular file"):  # swapped for a FIFO after the checks
        course._read_regular(fifo)


def test_an_identifier_with_a_trailing_newline_is_refused(tiny_course, tmp_path, capsys):
    """``^...$`` with ``re.match`` lets a name end in a newline ('$' matches before it): ids are fullmatched."""
    subs = _submissions(tmp_path, {f"ana\n/{TINY}.ipynb": (tmp_path / f"{TINY}.ipynb").read_bytes()})
    assert cli.main(["course", "collect", str(subs), "--course", str(tiny_course)]) == 2
    one_line_error(capsys, repr(str(subs / "ana\n")), "a student folder is named by")
    assert not (tiny_course / "submitted").exists()
    out = tmp_path / "new-course"
    assert cli.main(["course", "init", "--out", str(out), "--course-id", "a\n"]) == 2
    one_line_error(capsys, "course id must be", repr("a\n"))
    assert not out.exists()
    assert course.STUDENT_ID.fullmatch("ana") and exercises.GRADE_ID.fullmatch("ex01-2-answer")  # the plain ids pass
    assert not exercises.GRADE_ID.fullmatch("ex01-2-answer\n")


@pytest.mark.parametrize("content, needle", [(b"grades, not a database\n" * 4, "not an SQLite database"),
                                             (course.SQLITE_HEADER + b"\xff" * 200, "not nbgrader's gradebook")])
def test_grades_from_a_gradebook_that_is_not_a_database_is_one_line(tiny_course, tmp_path, capsys, content, needle):
    db = tiny_course / "gradebook.db"
    db.write_bytes(content)
    out = tmp_path / "grades.csv"
    assert cli.main(["course", "grades", "--course", str(tiny_course), "--out", str(out)]) == 2
    one_line_error(capsys, str(db), needle)
    assert not out.exists() and db.read_bytes() == content


# ----------------------------------------------------------------------------------------- the round trip
@pytest.mark.slow
def test_three_students_through_nbgrader_get_known_scores(tiny_course, tmp_path, capsys, needs_sandbox):
    """release -> collect -> autograde -> feedback -> grades, with nbgrader itself (about a minute)."""
    run = ["--course", str(tiny_course)]
    config = tiny_course / course.CONFIG
    assert f"c.Execute.timeout = {course.TIMEOUT_MIN_S}\n" in config.read_text()
    config.write_text(config.read_text().replace(f"timeout = {course.TIMEOUT_MIN_S}", "timeout = 8"))
    assert cli.main(["course", "release", *run]) == 0
    released = tiny_course / "release" / TINY / f"{TINY}.ipynb"
    text = released.read_text()
    assert "BEGIN SOLUTION" not in text and "HIDDEN" not in text and "square(-4)" not in text
    right = {n: _solution(a) for n, (a, _) in ANSWERS.items()}
    wrong = {n: w for n, (_, w) in ANSWERS.items()}
    subs = _submissions(tmp_path, {f"{who}/{TINY}.ipynb": _returned(released, answers)
                                   for who, answers in (("right", right), ("wrong", wrong), ("untouched", None))})
    assert cli.main(["course", "collect", str(subs), *run]) == 0
    assert cli.main(["course", "autograde", *run]) == 0
    assert cli.main(["course", "feedback", *run]) == 0
    pages = {who: (tiny_course / "feedback" / who / TINY / f"{TINY}.html").read_text()
             for who in ("right", "wrong", "untouched")}
    assert feedback_leaks(pages, tiny_course) == []
    assert "99.2 Square</td><td>3 / 3</td><td class=\"passed\">" in pages["right"]
    assert "99.2 Square</td><td>0 / 3</td><td class=\"failed\">failed</td><td>AssertionError</td>" in pages["wrong"]
    assert ("99.1 Add</td><td>0 / 2</td><td class=\"failed\">failed</td><td>your answer cell stopped: "
            "CellTimeoutError: the cell ran longer than the course&#x27;s cell timeout and was stopped; "
            "NameError: name &#x27;my_sum&#x27; is not defined</td>") in pages["wrong"]
    assert "0 / 4 (graded by hand, pending)" in pages["wrong"]
    assert "CellTimeoutError" in (tiny_course / "autograded" / "wrong" / TINY / f"{TINY}.ipynb").read_text()
    assert cli.main(["course", "grades", "--out", str(tmp_path / "grades.csv"), *run]) == 0
    rows = {r["student"]: r for r in csv.DictReader((tmp_path / "grades.csv").open())}
    # all right: 2 + 3 automatically, the open answer (4) waits for a hand grade; all wrong: 0 (the
    # course's 8 s timeout stops the 40 s answer, which nbgrader's default 30 s would have let finish
    # right; the hidden test catches 3 * x), its eight-word "why" earns nothing automatically;
    # untouched: 0, and its unchanged open answer is a 0 nobody needs to grade
    assert {who: (float(r["points"]), float(r["max_points"]), int(r["needs_manual_grading"]),
                  float(r["pending_max_points"])) for who, r in rows.items()} == {
        "right": (5.0, 9.0, 1, 4.0), "wrong": (0.0, 9.0, 1, 4.0), "untouched": (0.0, 9.0, 0, 0.0)}
    assert all(r["assignment"] == TINY and r["could_not_run"] == "" for r in rows.values())
    _grade_by_hand(tiny_course, "right", "ex99-3-answer", 4.0)  # what formgrader does
    rows = course.grade_rows(tiny_course)
    assert [(r["student"], r["points"], r["needs_manual_grading"]) for r in rows if r["student"] == "right"] == [
        ("right", 9.0, 0)]
    # the table is never replaced
    assert cli.main(["course", "grades", "--out", str(tmp_path / "grades.csv"), *run]) == 2
    one_line_error(capsys, str(tmp_path / "grades.csv"), "exists")
    # a rerun grades nothing again
    assert cli.main(["course", "autograde", *run]) == 0
    assert "nothing to autograde: 3 submissions graded before" in capsys.readouterr().out
    # nbgrader's own feedback template prints the hidden tests and loads MathJax from the web: the scan sees both
    exercises.run_nbgrader(["generate_feedback", TINY, "--force"], tiny_course, "write nbgrader's feedback")
    leaks = feedback_leaks({"wrong": (tiny_course / "feedback" / "wrong" / TINY / f"{TINY}.html").read_text()},
                           tiny_course)
    assert any("square(-4)" in x for x in leaks) and any("http" in x for x in leaks)


def hidden_test_lines(root: Path) -> list[str]:
    """Each line inside the hidden-test regions of the course's source notebooks."""
    lines = []
    for nb in (root / "source").glob("*/*.ipynb"):
        for cell in json.loads(nb.read_text())["cells"]:
            inside = False
            for ln in "".join(cell["source"]).splitlines():
                if ln.strip() in exercises.HIDDEN_MARKERS:
                    inside = ln.strip() == exercises.HIDDEN_MARKERS[0]
                elif inside and ln.strip():
                    lines.append(ln.strip())
    assert lines, "the course has hidden tests"
    return lines


def feedback_leaks(pages: dict[str, str], root: Path) -> list[str]:
    """What of the hidden tests, or a web address (a CDN's script or style), the feedback pages hold."""
    found = []
    for name, page in pages.items():  # read as text: tags (a highlighter's spans) removed, entities decoded
        text = " ".join(html.unescape(re.sub(r"<[^>]*>", "", page)).split())
        found += [f"{name}: {ln}" for ln in (*hidden_test_lines(root), *exercises.HIDDEN_MARKERS)
                  if " ".join(ln.split()) in text]
        found += [f"{name}: {m}" for m in ("http://", "https://", "//cdn", "<script") if m in page]
    return found


def hostile_answer(root: Path, victim: str, port: int) -> str:
    """An answer to 99.1 (right: my_sum = 5) that first tries to read the solutions, the gradebook and
    another student's notebook, to list and write into the course folder, to reach a port listening
    on this machine's loopback, to find the hidden tests in a file of its working folder and to hold
    more memory than a 1 GiB limit allows; it prints one line per attempt, "done" or "blocked"."""
    victim_nb = root / "submitted" / victim / TINY / f"{TINY}.ipynb"
    attempts = {"read source": f"open({str(root / 'source' / TINY / f'{TINY}.ipynb')!r}, 'rb').read()",
                "read gradebook": f"open({str(root / 'gradebook.db')!r}, 'rb').read()",
                "read other student": f"open({str(victim_nb)!r}, 'rb').read()",
                "list course": f"assert os.listdir({str(root)!r})",
                "rewrite other student": f"open({str(victim_nb)!r}, 'wb').write(b'{{}}')",
                "write gradebook": f"open({str(root / 'gradebook.db')!r}, 'ab').write(b'x')",
                "write course": f"open({str(root / 'planted.txt')!r}, 'w').write('x')",
                "network": f"socket.create_connection(('127.0.0.1', {port}), timeout=2).close()",
                "hidden tests in the working folder": "assert [f for f in os.listdir('.') if os.path.isfile(f) "
                                                      "and b'square(-4)' in open(f, 'rb').read()]",
                "hold 1.5 GiB": "bytearray(1536 << 20)"}
    lines = ["import os", "import socket", ""]
    for what, code in attempts.items():
        lines += ["try:", f"    {code}", f"    print('done: {what}')", "except Exception:",
                  f"    print('blocked: {what}')"]
    return "\n".join(lines + ["my_sum = 2 + 3"])


# 99.2 answered with a value equal to anything: it passes both checks, and the static review flags it
ALWAYS_EQUAL = ("class Always(int):\n    def __eq__(self, other):\n        return True\n\n    __hash__ = int.__hash__\n"
                "\n\ndef square(x):\n    return Always(0)")


def _printed(notebook: Path) -> str:
    nb = json.loads(notebook.read_text())
    return "".join("".join(o.get("text", "")) for c in nb["cells"] for o in c.get("outputs", []))


@pytest.mark.slow
def test_a_dead_kernel_and_a_hostile_notebook_fail_only_themselves(tiny_course, tmp_path, capsys, needs_sandbox):
    """Three students: ana all right; bo's notebook ends Python (exit()) in exercise 99.2; cy's 99.1 is
    right, but first tries to read the solutions, the gradebook and ana's notebook, to write into
    the course folder and to hold 1.5 GiB (the kernels may hold 1 GiB), and cy's 99.2 returns a value equal
    to anything. ana and cy are graded, bo could not
    run; cy's every attempt fails in the sandbox, and the static review sends cy's 99.1 (it imports socket),
    99.2 (a class defining __eq__, and the socket of 99.1 in the same kernel) and 99.3 (what 99.1 and 99.2
    left in the kernel) to manual grading, with the reasons in the grade table; cy's page shows their rows
    as held, without the checks' messages."""
    run = ["--course", str(tiny_course)]
    config = tiny_course / course.CONFIG
    config.write_text(config.read_text().replace(f"timeout = {course.TIMEOUT_MIN_S}", "timeout = 8"))
    course.release(tiny_course)
    released = tiny_course / "release" / TINY / f"{TINY}.ipynb"
    right = {n: _solution(a) for n, (a, _) in ANSWERS.items()}
    dead = {**right, 2: "exit()  # Python ends once the cell is done\nimport time\n\ntime.sleep(1)\n" + right[2]}
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    hostile = {**right, 1: hostile_answer(tiny_course, "ana", port), 2: ALWAYS_EQUAL}
    subs = _submissions(tmp_path, {f"{who}/{TINY}.ipynb": _returned(released, answers)
                                   for who, answers in (("ana", right), ("bo", dead), ("cy", hostile))})
    course.collect(tiny_course, subs)
    # the attempts are real: run in this process, outside the sandbox, on a copy of the course, each succeeds
    copy = tmp_path / "copy"
    shutil.copytree(tiny_course, copy)
    outside = subprocess.run([sys.executable, "-c", hostile_answer(copy, "ana", port)], capture_output=True,
                             text=True, cwd=copy / "source" / TINY)  # a folder holding the hidden tests
    assert [ln.split(":")[0] for ln in outside.stdout.splitlines()] == ["done"] * 10, outside.stdout
    ana_nb = (tiny_course / "submitted" / "ana" / TINY / f"{TINY}.ipynb").read_bytes()
    protected = {p: p.read_bytes() for p in tiny_course.rglob("*") if p.is_file() and "gradebook" not in p.name}
    capsys.readouterr()

    with listener:
        assert cli.main(["course", "autograde", "--kernel-memory", "1", *run]) == 0
    captured = capsys.readouterr()
    assert "autograded 2 submissions; 1 could not run; 0 graded before; 3 answers flagged for review" in captured.out
    (line,) = [ln for ln in captured.err.splitlines() if ln.startswith("could not run")]
    assert line.startswith(f"could not run: bo, {TINY}.ipynb: the kernel died")
    assert [ln.split(":")[1] for ln in captured.err.splitlines() if ln.startswith("flagged for review")] == [
        f" cy, {TINY}.ipynb exercise 99.1", f" cy, {TINY}.ipynb exercise 99.2", f" cy, {TINY}.ipynb exercise 99.3"]
    printed = _printed(tiny_course / "autograded" / "cy" / TINY / f"{TINY}.ipynb")
    assert [ln for ln in printed.splitlines() if ln.startswith(("done", "blocked"))] == [
        f"blocked: {what}" for what in ("read source", "read gradebook", "read other student", "list course",
                                        "rewrite other student", "write gradebook", "write course", "network",
                                        "hidden tests in the working folder", "hold 1.5 GiB")]
    assert (tiny_course / "submitted" / "ana" / TINY / f"{TINY}.ipynb").read_bytes() == ana_nb
    assert all(p.read_bytes() == data for p, data in protected.items()) and not (tiny_course / "planted.txt").exists()
    assert cli.main(["course", "feedback", *run]) == 0
    pages = {who: (tiny_course / "feedback" / who / TINY / f"{TINY}.html").read_text() for who in ("ana", "bo", "cy")}
    assert "could not run" in pages["bo"] and "kernel died" in pages["bo"] and "0 of 9 points" in pages["cy"]
    assert "99.2 Square</td><td>0 / 3 (graded by hand, pending)</td><td class=\"held\">" in pages["cy"]
    assert pages["cy"].count(autograde.HELD_MESSAGE) == 3 and "passed" not in pages["cy"].split("<table>")[1]
    assert feedback_leaks(pages, tiny_course) == []
    assert cli.main(["course", "grades", "--out", str(tmp_path / "grades.csv"), *run]) == 0
    report = capsys.readouterr().out
    assert (f"flagged for review: cy, {TINY}, 99.2: line 2: class Always defines __eq__: "
            f"{review.RULES['special-method']}") in report
    assert "3 grades in" in report and "3 answers flagged by the static review" in report
    rows = {r["student"]: r for r in csv.DictReader((tmp_path / "grades.csv").open())}
    # cy's checks passed (the always-equal square fooled them), but the flagged exercises' four graded cells
    # (99.1's and 99.2's checks, 99.3's answer and check) wait for a hand grade
    assert {who: (float(r["points"]), int(r["needs_manual_grading"]), r["could_not_run"][:15])
            for who, r in rows.items()} == {"ana": (5.0, 1, ""), "bo": (0.0, 0, "the kernel died"), "cy": (0.0, 4, "")}
    assert rows["ana"]["flagged_for_review"] == rows["bo"]["flagged_for_review"] == ""
    assert rows["cy"]["flagged_for_review"].startswith("99.1: line 2: import socket: runs code where the grading ")
    assert "99.2: line 2: class Always defines __eq__" in rows["cy"]["flagged_for_review"]
    assert [(r["student"], r["exercise"]) for r in json.loads((tiny_course / autograde.FLAGGED).read_text())] == [
        ("cy", "99.1"), ("cy", "99.2"), ("cy", "99.3")]
    from nbgrader.api import Gradebook

    with Gradebook(f"sqlite:///{tiny_course / 'gradebook.db'}") as gb:  # what formgrader shows the lecturer
        grade = gb.find_grade("ex99-2-check", TINY, TINY, "cy")
        assert (grade.auto_score, grade.manual_score, grade.needs_manual_grade) == (3.0, 0.0, True)
        assert gb.find_comment("ex99-2-answer", TINY, TINY, "cy").auto_comment.startswith(
            "Flagged by the static review, for a hand grade: line 2: class Always defines __eq__")
        assert gb.find_grade("ex99-2-check", TINY, TINY, "ana").needs_manual_grade is False
    graded_cy = json.loads((tiny_course / "autograded" / "cy" / TINY / f"{TINY}.ipynb").read_text())
    (check,) = [c for c in graded_cy["cells"] if c["metadata"].get("nbgrader", {}).get("grade_id") == "ex99-2-check"]
    assert not [o for o in check["outputs"] if o["output_type"] == "error"]  # it passed: the review held the points
    # a rerun grades nothing again: bo waits for --retry
    assert cli.main(["course", "autograde", *run]) == 0
    assert "nothing to autograde: 3 submissions graded before" in capsys.readouterr().out


@pytest.mark.slow
def test_what_a_kernel_prints_is_bounded_in_the_grader_and_the_grade_holds(tiny_course, tmp_path, capsys,
                                                                           needs_sandbox):
    """The kernel's output reaches nbgrader's process (the lecturer's), which kept all of it: 600 MB printed
    took it to 2,700 MB. pat's right 99.1 prints 20 MiB in 1 MiB messages: graded as ana (all right), the
    graded copy keeps 16 MiB of that cell's output and says it cut the rest. flo's prints 40 MiB at once,
    a message over sandbox.FRAME_BYTES: zmq drops it unread, flo's run could not finish, and says why."""
    config = tiny_course / course.CONFIG
    config.write_text(config.read_text().replace(f"timeout = {course.TIMEOUT_MIN_S}", "timeout = 20"))
    course.release(tiny_course)
    released = tiny_course / "release" / TINY / f"{TINY}.ipynb"
    right = {n: _solution(a) for n, (a, _) in ANSWERS.items()}
    flood = "line = 'x' * (1 << 20)\nfor _ in range(20):\n    print(line, flush=True)\n"
    burst = f"print('x' * ({sandbox.FRAME_BYTES} + (8 << 20)))\n"
    subs = _submissions(tmp_path, {f"{who}/{TINY}.ipynb": _returned(released, answers) for who, answers in
                                   (("ana", right), ("pat", {**right, 1: flood + right[1]}),
                                    ("flo", {**right, 1: burst + right[1]}))})
    course.collect(tiny_course, subs)
    capsys.readouterr()
    assert cli.main(["course", "autograde", "--course", str(tiny_course)]) == 0
    captured = capsys.readouterr()
    assert "autograded 2 submissions; 1 could not run" in captured.out
    (line,) = [ln for ln in captured.err.splitlines() if ln.startswith("could not run")]
    assert line.startswith(f"could not run: flo, {TINY}.ipynb: a cell's output stopped reaching the grader")
    graded = tiny_course / "autograded" / "pat" / TINY / f"{TINY}.ipynb"
    assert graded.stat().st_size < sandbox.CELL_OUTPUT_BYTES + (1 << 20)
    assert sandbox.OUTPUT_CUT.format(limit=sandbox.CELL_OUTPUT_BYTES >> 20) in _printed(graded)
    assert cli.main(["course", "grades", "--out", str(tmp_path / "grades.csv"), "--course", str(tiny_course)]) == 0
    rows = {r["student"]: r for r in csv.DictReader((tmp_path / "grades.csv").open())}
    assert rows["pat"]["points"] == rows["ana"]["points"] == "5.0" and rows["flo"]["points"] == "0.0"


def _grade_by_hand(root: Path, student: str, grade_id: str, score: float) -> None:
    from nbgrader.api import Gradebook

    with Gradebook(f"sqlite:///{root / 'gradebook.db'}") as gb:
        grade = gb.find_grade(grade_id, TINY, TINY, student)
        grade.manual_score = score
        grade.needs_manual_grade = False  # as formgrader's grade handler sets it
        gb.db.commit()


def test_a_busy_course_folder_is_refused_before_any_work(tiny_course, tmp_path, capsys):
    from geodepth_lite import utils

    subs = _submissions(tmp_path, {f"ana/{TINY}.ipynb": (tmp_path / f"{TINY}.ipynb").read_bytes()})
    with utils.FolderLock(tiny_course, "course folder"):
        assert cli.main(["course", "collect", str(subs), "--course", str(tiny_course)]) == 2
    one_line_error(capsys, str(tiny_course), "in use by process")
    assert not (tiny_course / "submitted").exists()


def test_autograde_without_a_release_is_one_line(tiny_course, capsys):
    assert cli.main(["course", "autograde", "--course", str(tiny_course)]) == 2
    one_line_error(capsys, str(tiny_course), "course release")
    assert sorted(os.listdir(tiny_course)) == ["nbgrader_config.py", "source"]  # no gradebook made, no lock left


# ----------------------------------------------------------------------------------------- what students get
# Lines of the notebooks' solutions that the package (or a test) holds as its own code: the library the
# lessons use implements what some exercises ask for (02-2 and 02-4 in core/model.py, 05-2's Holm rule in
# ablation.py, 06-1's bands in border.py; 01-3/01-4's pixel grid in a test). Pinned by the SHA-256 of
# the line (this file ships to students too, so it must not hold the lines themselves): any other
# solution line in what students get fails the tests below.
SHARED_WITH_THE_PROJECT = {
    "320c96563e2be11a": {"tests/test_render.py"},
    "603da3fc218796a7": {"geodepth_lite/core/model.py"},
    "03d402e8058d6f40": {"geodepth_lite/core/model.py"},
    "ac6de9fa23fc3050": {"geodepth_lite/evaluation/ablation.py"},
    "b332d63d46722f4b": {"geodepth_lite/evaluation/border.py"},
    "693a347d777327f5": {"geodepth_lite/evaluation/border.py"},
}


def _digest(line: str) -> str:
    return hashlib.sha256(line.encode()).hexdigest()[:16]


def solution_texts() -> dict[str, str]:
    """Each non-trivial line of every solution region of notebooks 01-07 (not a comment, 12 characters or
    more, not given away by the lessons' own text outside the solutions) -> its exercise."""
    books = {p: json.loads(p.read_text()) for p in exercises.notebook_paths()}
    public = "\n".join(ln for nb in books.values() for c in nb["cells"] for ln in "".join(c["source"]).splitlines()
                       if ln.strip() not in exercises.SOLUTION_MARKERS and not _in_solution(c, ln))
    out = {}
    for p, nb in books.items():
        for ex in exercises.notebook_exercises(nb).values():
            for ln in exercises.solution_lines(ex.answer):
                if not ln.startswith("#") and len(ln) >= 12 and ln not in public:
                    out[ln] = f"{p.name} exercise {ex.ident}"
    return out


def _in_solution(cell, line) -> bool:
    return line.strip() in {ln.strip() for ln in exercises._split_solutions("".join(cell["source"]))[0]}


def solution_leaks(files: dict[str, str]) -> list[str]:
    """What of the solutions ``files`` (name -> text) hold: marker lines, and solution lines (whole
    lines, or inside a line for those of 20 characters or more) beyond SHARED_WITH_THE_PROJECT."""
    found = []
    texts = solution_texts()
    for name, text in files.items():
        lines = {ln.strip() for ln in text.splitlines()}
        found += [f"{name}: {m}" for m in (*exercises.SOLUTION_MARKERS, *exercises.HIDDEN_MARKERS) if m in lines]
        for ln, where in texts.items():
            if (ln in lines or (len(ln) >= 20 and ln in text)) and name not in SHARED_WITH_THE_PROJECT.get(
                    _digest(ln), ()):
                found.append(f"{name}: {where}: {ln!r}")
    return found


def notebook_strings(obj) -> list[str]:
    """Every string in a notebook's JSON (sources, outputs, metadata)."""
    if isinstance(obj, str):
        return [obj]
    if isinstance(obj, dict):
        return [s for v in obj.values() for s in notebook_strings(v)]
    if isinstance(obj, list):
        return [s for v in obj for s in notebook_strings(v)]
    return []


def _text_files(folder: Path) -> dict[str, str]:
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name != ".lock":
            raw = p.read_bytes()
            if p.suffix == ".ipynb":
                out[str(p.relative_to(folder))] = "\n".join(notebook_strings(json.loads(raw)))
            elif b"\0" not in raw[:4096]:
                out[str(p.relative_to(folder))] = raw.decode("utf-8", errors="replace")
    return out


def test_the_leak_scan_finds_a_solution_line_and_a_marker():
    texts = solution_texts()
    assert len(texts) > 100  # 26 exercises' solutions
    line = next(iter(texts))
    assert solution_leaks({"notes.md": f"x\n    {line}\n"}) and solution_leaks({"a.py": "### BEGIN SOLUTION\n"})
    shared = next(ln for ln in texts if _digest(ln) in SHARED_WITH_THE_PROJECT)
    assert solution_leaks({"geodepth_lite/new.py": shared})  # shared only where pinned
    assert solution_leaks({name: shared for name in SHARED_WITH_THE_PROJECT[_digest(shared)]}) == []
    assert {_digest(ln) for ln in texts} >= set(SHARED_WITH_THE_PROJECT)  # each pin is still a solution line


def test_the_package_pip_installs_holds_no_notebook_and_no_solution(tmp_path):
    """Build the wheel `python -m pip install .` would install (offline, from a copy of the sources)."""
    pytest.importorskip("setuptools")
    root = exercises.NOTEBOOK_DIR.parent
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        (src / name).write_bytes((root / name).read_bytes())
    shutil.copytree(root / "geodepth_lite", src / "geodepth_lite", ignore=shutil.ignore_patterns("__pycache__"))
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                           "-q", ".", "-w", str(tmp_path / "wheel")], cwd=src, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    (wheel,) = (tmp_path / "wheel").glob("*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        files = {n: zf.read(n).decode("utf-8", errors="replace") for n in names}
    assert not [n for n in names if n.endswith(".ipynb")]
    assert all(n.startswith(("geodepth_lite/", "geodepth_lite-")) for n in names), names
    assert "geodepth_lite/workbook/course.py" in names and "geodepth_lite/workbook/exercises.py" in names
    assert solution_leaks(files) == []


@pytest.mark.slow
def test_the_student_edition_holds_no_solution(tiny_course, tmp_path, capsys):
    """course edition: the checkout without the notebooks that hold solutions, the release in their place."""
    course.release(tiny_course)
    out = tmp_path / "edition"
    assert cli.main(["course", "edition", "--course", str(tiny_course), "--out", str(out)]) == 0
    assert "without notebooks/01_synthetic_dataset.ipynb" in capsys.readouterr().out
    notebooks = sorted(p.name for p in (out / "notebooks").glob("*.ipynb"))
    assert notebooks == ["00_overview.ipynb", f"{TINY}.ipynb"]  # 01-07 left out: they hold the solutions
    assert (out / "data_manifests").is_dir() and (out / "geodepth_lite" / "workbook" / "course.py").is_file()
    assert not any(course.holds_solutions(p) for p in out.rglob("*.ipynb"))
    assert solution_leaks(_text_files(out)) == []
    assert not (out / ".lock").exists()
    assert cli.main(["course", "edition", "--course", str(tiny_course), "--out", str(out)]) == 2  # never again
    one_line_error(capsys, str(out), "not an empty folder")
    inside = exercises.NOTEBOOK_DIR.parent / "student-edition-test"
    assert cli.main(["course", "edition", "--course", str(tiny_course), "--out", str(inside)]) == 2
    one_line_error(capsys, str(inside), "inside the checkout")
    assert not inside.exists()


# ----------------------------------------------------------------------------------------- the sandbox, in pieces
def test_autograde_without_a_sandbox_refuses_unless_told_and_then_warns(tiny_course, monkeypatch, capsys):
    (tiny_course / "gradebook.db").write_bytes(b"")  # released, as far as the refusal is concerned
    monkeypatch.setattr(sandbox, "unavailable", lambda: "bubblewrap (bwrap) is not installed")
    assert cli.main(["course", "autograde", "--course", str(tiny_course)]) == 2
    one_line_error(capsys, str(tiny_course), "bubblewrap (bwrap) is not installed", "--unsafe-no-sandbox")
    assert not (tiny_course / autograde.FAILURES).exists() and not (tiny_course / "autograded").exists()
    assert cli.main(["course", "autograde", "--unsafe-no-sandbox", "--course", str(tiny_course)]) == 0
    captured = capsys.readouterr()
    assert captured.err.startswith("WARNING: autograding WITHOUT a sandbox") and "gradebook.db" in captured.err
    assert "nothing to autograde: no submission collected" in captured.out


def test_the_sandbox_shows_neither_solutions_nor_the_course_folder(tmp_path):
    root = exercises.NOTEBOOK_DIR.parent
    readable = sandbox.readable_paths()
    assert root / "geodepth_lite" in readable and root / "data_manifests" in readable
    assert not any(p == root or p in (root / "notebooks").parents or p.name in ("notebooks", "tests", ".git")
                   for p in readable)
    assert root / "notebooks" / "study" in readable  # the committed tables notebook 05 reads
    # the Python environment is readable wherever it lives, inside the checkout too (the README's .venv): its
    # packages' own notebooks (nbgrader's test files) are not the checkout's; every other readable path is
    env = {Path(sys.prefix).resolve(), Path(sys.base_prefix).resolve(), Path(sys.executable).resolve().parent.parent}
    of_checkout = [p for p in readable if root in p.parents and p not in env]
    assert not [nb for p in of_checkout for nb in ([p] if p.is_file() else p.rglob("*")) if nb.suffix == ".ipynb"]
    inside = root / "data_manifests" / "course"  # a course folder under a folder the kernel reads: hidden
    cmd = sandbox.bwrap_command(["python"], tmp_path, [inside, tmp_path / "course"])
    where = cmd.index(str(inside))
    assert cmd[where - 1] == "--tmpfs" and cmd.index("--ro-bind", cmd.index(str(root / "data_manifests")) - 1) < where
    assert str(tmp_path / "course") not in cmd  # not under anything bound: not there at all
    assert "--unshare-all" in cmd and "--clearenv" in cmd
    # the kernel's command, after the program that sets the hard limits (4 GiB of data by default) and becomes it
    assert cmd[cmd.index("--") + 1:] == [sys.executable, "-c", sandbox.LIMITS, str(4 << 30), str(sandbox.FILE_BYTES),
                                         "0", str(sandbox.FILES_OPEN), shutil.which("python") or "python"]
    where = cmd.index("/tmp")  # its /tmp: a tmpfs of bounded size
    assert cmd[where - 3:where] == ["--size", str(sandbox.TMP_BYTES), "--tmpfs"]
    assert sandbox.readable_paths([root / "data_manifests"]).count(root / "data_manifests") == 0


BOUNDED = """import resource
from pathlib import Path
try:
    resource.setrlimit(resource.RLIMIT_DATA, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
    print("done: raise the memory limit")
except (ValueError, OSError):
    print("blocked: raise the memory limit")
try:
    block = bytearray(1536 << 20)
    print("done: hold 1.5 GiB")
except MemoryError:
    print("blocked: hold 1.5 GiB")
block = None
for what, folder, mib, files in (("fill /tmp", "/tmp", 24, 3), ("write a big file", ".", 48, 1),
                                 ("fill the working folder", ".", 24, 3)):  # no file too big, too many of them
    try:
        for k in range(files):
            with open(f"{folder}/fill{k}", "wb") as f:
                f.write(bytes(mib << 20))
        print(f"done: {what}")
    except OSError:
        print(f"blocked: {what}")
    for k in range(files):
        Path(f"{folder}/fill{k}").unlink(missing_ok=True)
import numpy
print("numpy", int(numpy.ones((1000, 1000)).sum()))
"""


def test_the_sandbox_bounds_memory_its_tmp_and_file_sizes(tmp_path, monkeypatch, needs_sandbox):
    """Each process of a kernel holds at most its memory limit, which it cannot raise; /tmp (a tmpfs, held
    in memory) and a file it writes are bounded too; a plain program still runs under those limits. The
    same attempts all succeed without the sandbox's limits."""
    monkeypatch.setattr(sandbox, "TMP_BYTES", 64 << 20)
    monkeypatch.setattr(sandbox, "FILE_BYTES", 32 << 20)
    outside = subprocess.run([sys.executable, "-c", BOUNDED], capture_output=True, text=True, cwd=tmp_path)
    assert [ln.split(":")[0] for ln in outside.stdout.splitlines()[:5]] == ["done"] * 5, outside.stdout
    for name in ("work", "kernel"):
        (tmp_path / "scratch" / name).mkdir(parents=True)
    cmd = sandbox.bwrap_command([sys.executable, "-c", BOUNDED], tmp_path / "scratch", [], sandbox.memory_bytes(1))
    inside = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert inside.returncode == 0, inside.stderr[-2000:]
    assert inside.stdout.splitlines() == ["blocked: raise the memory limit", "blocked: hold 1.5 GiB",
                                          "blocked: fill /tmp", "blocked: write a big file",
                                          "blocked: fill the working folder", "numpy 1000000"]
    assert sorted(p.name for p in (tmp_path / "scratch").rglob("*")) == ["kernel", "work"]  # nothing on disk


def test_the_kernel_reads_the_submissions_own_files_in_its_working_folder(tmp_path, needs_sandbox):
    """The working folder lies in the sandbox's /tmp, yet holds the submission's files at their names."""
    for name in ("work", "kernel"):
        (tmp_path / "scratch" / name).mkdir(parents=True)
    (tmp_path / "scratch" / "work" / "my data.csv").write_text("depth\n1.5\n")
    code = "import os; print(os.getcwd(), sorted(os.listdir('.')), open('my data.csv').read().split())"
    inside = subprocess.run(sandbox.bwrap_command([sys.executable, "-c", code], tmp_path / "scratch", []),
                            capture_output=True, text=True, timeout=120)
    assert inside.stdout.split(" ", 1) == [str(sandbox.WORK_INSIDE), "['my data.csv'] ['depth', '1.5']\n"], (
        inside.stdout, inside.stderr[-2000:])


SHADOW = """from pathlib import Path
from IPython.core.shellapp import InteractiveShellApp
InteractiveShellApp().init_path()  # as a kernel starts: IPython puts the working folder on sys.path
Path("tifffile.py").write_text("WRITTEN = True")  # installed, and imported by no lesson before
import tifffile
print("written" if hasattr(tifffile, "WRITTEN") else "installed")
"""


def test_a_kernel_never_imports_a_module_written_into_its_folder(tmp_path, needs_sandbox):
    """A notebook could write its own code under the name of an installed module and import it, out of the
    review's sight; in the sandbox the kernel's working folder stays off sys.path."""
    (tmp_path / "plain").mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONSAFEPATH"}
    outside = subprocess.run([sys.executable, "-c", SHADOW], capture_output=True, text=True, cwd=tmp_path / "plain",
                             env=env)
    assert outside.stdout.strip() == "written", outside.stderr[-2000:]
    for name in ("work", "kernel"):
        (tmp_path / "scratch" / name).mkdir(parents=True)
    inside = subprocess.run(sandbox.bwrap_command([sys.executable, "-c", SHADOW], tmp_path / "scratch", []),
                            capture_output=True, text=True, timeout=120)
    assert inside.stdout.strip() == "installed", inside.stderr[-2000:]


# what a kernel run by a grader with root's capabilities could do to the folders it reads: remount one as
# writable and write there, unmount the empty folder over the course (the gradebook and solutions beneath)
MOUNTS = """import ctypes, os, sys
readable, course = sys.argv[1], sys.argv[2]
libc = ctypes.CDLL(None, use_errno=True)
status = open("/proc/self/status").read().splitlines()
print("capabilities", int(next(ln.split()[1] for ln in status if ln.startswith("CapEff:")), 16))
remounted = libc.mount(None, readable.encode(), None, 32 | 4096, None) == 0  # MS_REMOUNT | MS_BIND: writable
try:
    with open(os.path.join(readable, "written.txt"), "w") as f:
        f.write("a student's file")
    print("remounted" if remounted else "", "wrote")
except OSError:
    print("remounted" if remounted else "", "read-only")
unmounted = libc.umount2(course.encode(), 2) == 0  # MNT_DETACH
print("unmounted" if unmounted else "", "course holds", sorted(os.listdir(course)))
"""


def test_the_kernel_holds_no_capability_even_where_the_grader_is_root(tmp_path, monkeypatch, needs_sandbox):
    """Run as root, bubblewrap keeps root's capabilities in the sandbox unless told otherwise; a kernel with
    CAP_SYS_ADMIN there remounted a folder it reads as writable and wrote into it, and unmounted the empty
    folder over the course, seeing the gradebook (checked as root before ``--cap-drop ALL``). It holds none."""
    readable = tmp_path / "readable"
    (readable / "course").mkdir(parents=True)
    (readable / "course" / "gradebook.db").write_text("the grades")
    plain = sandbox.readable_paths
    monkeypatch.setattr(sandbox, "readable_paths", lambda hidden=(): [*plain(hidden), readable])
    for name in ("work", "kernel"):
        (tmp_path / "scratch" / name).mkdir(parents=True)
    cmd = sandbox.bwrap_command([sys.executable, "-c", MOUNTS, str(readable), str(readable / "course")],
                                tmp_path / "scratch", [readable / "course"])
    inside = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert inside.stdout.split() == ["capabilities", "0", "read-only", "course", "holds", "[]"], (
        inside.stdout, inside.stderr[-2000:])
    assert sorted(p.name for p in readable.iterdir()) == ["course"]


SETTINGS = """import os
try:
    with open("/proc/sys/kernel/hostname", "w") as f:  # the sandbox's own name (its own UTS namespace)
        f.write("renamed")
    print("wrote")
except OSError as exc:
    print("refused", exc.errno)
print("writable", sum(os.access(os.path.join(d, f), os.W_OK) for d, _, fs in os.walk("/proc/sys") for f in fs))
"""


def test_the_kernel_cannot_write_the_machines_settings(tmp_path, needs_sandbox):
    """A process whose user is root may write /proc/sys with no capability (kernel.core_pattern names a
    program the machine runs as root when a process crashes); in the sandbox it is read-only, whoever grades.
    Run as root before the read-only bind, the kernel renamed itself and hundreds of settings were writable."""
    for name in ("work", "kernel"):
        (tmp_path / "scratch" / name).mkdir(parents=True)
    inside = subprocess.run(sandbox.bwrap_command([sys.executable, "-c", SETTINGS], tmp_path / "scratch", []),
                            capture_output=True, text=True, timeout=120)
    assert inside.stdout.split() == ["refused", str(errno.EROFS), "writable", "0"], (
        inside.stdout, inside.stderr[-2000:])


DEVICES = """import multiprocessing, os
try:
    for k in range(3):
        with open(f"/dev/shm/fill{k}", "wb") as f:
            f.write(bytes(100 << 20))
    print("wrote 300 MiB into /dev/shm")
except OSError as exc:
    print("stopped", exc.errno, "at", sum(os.path.getsize(f"/dev/shm/{n}") >> 20 for n in os.listdir("/dev/shm")))
for name in os.listdir("/dev/shm"):
    os.unlink(f"/dev/shm/{name}")
try:
    open("/dev/fill", "w").write("x")
    print("wrote into /dev")
except OSError as exc:
    print("refused", exc.errno)
with multiprocessing.Lock():  # a semaphore of its own in /dev/shm
    open("/dev/null", "w").write("still writable")
print("lock and /dev/null")
"""


def test_the_kernel_holds_no_more_than_a_little_in_dev_shm(tmp_path, needs_sandbox):
    """bubblewrap's /dev is a tmpfs of half the machine's memory, held by no process the watch counts: a kernel
    wrote 300 MiB into /dev/shm there (checked before the change). Now /dev/shm holds SHM_BYTES and the rest
    of /dev is read-only; a semaphore and /dev/null still work."""
    for name in ("work", "kernel"):
        (tmp_path / "scratch" / name).mkdir(parents=True)
    inside = subprocess.run(sandbox.bwrap_command([sys.executable, "-c", DEVICES], tmp_path / "scratch", []),
                            capture_output=True, text=True, timeout=120)
    assert inside.stdout.splitlines() == [f"stopped {errno.ENOSPC} at {sandbox.SHM_BYTES >> 20}",
                                          f"refused {errno.EROFS}", "lock and /dev/null"], (
        inside.stdout, inside.stderr[-2000:])


# a stand-in kernel: it starts `n` processes that each hold `mib` MiB (written, so in memory), or that share
# them (forked after the parent wrote them), prints their exit statuses and ends
HOLDERS = """import os, sys, time
n, mib, shared = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "shared"
block = b"x" * (mib << 20) if shared else None
kids = []
for _ in range(n):
    pid = os.fork()
    if pid == 0:
        mine = block if shared else b"y" * (mib << 20)
        time.sleep(6)
        os._exit(0)
    kids.append(pid)
print(sorted(os.waitstatus_to_exitcode(os.waitpid(k, 0)[1]) for k in kids))
"""


def _watched(n, mib, shared, memory, processes=sandbox.PROCESSES_MAX):
    proc = subprocess.Popen([sys.executable, "-c", HOLDERS, str(n), str(mib), shared], stdout=subprocess.PIPE,
                            text=True)
    watch = autograde.KernelWatch(proc.pid, memory, processes)
    watch.start()
    out = proc.communicate(timeout=60)[0]
    watch.stop()
    return out.strip(), watch.reason


def test_the_watch_stops_a_kernel_whose_processes_hold_too_much_together():
    """RLIMIT_DATA bounds each process; the watch bounds what they hold together. Three processes of 120 MiB
    each are killed under a limit of 256 MiB, not under 1 GiB; three that share one 120 MiB block (forked
    after it was written: 480 MiB resident in all, counted once) are left alone under 256 MiB; eight
    processes are killed where six are the most."""
    assert _watched(3, 120, "own", 1 << 30) == ("[0, 0, 0]", None)
    out, why = _watched(3, 120, "own", 256 << 20)
    assert out == "[-9, -9, -9]" and why.startswith("its processes held ") and "over the limit of 0.25 GiB" in why
    assert _watched(3, 120, "shared", 256 << 20) == ("[0, 0, 0]", None)
    out, why = _watched(8, 1, "own", 1 << 30, processes=6)
    assert out == "[-9, -9, -9, -9, -9, -9, -9, -9]" and why == "it started more than 6 processes at once"


def test_the_watch_stops_a_fork_bomb_in_the_sandbox(tmp_path, needs_sandbox):
    """Processes that fork until there are 2,048 of them, each then sleeping: in the sandbox, watched, they
    are killed (bubblewrap ends with SIGKILL's status) once they pass PROCESSES_MAX, and the reason says so."""
    for name in ("work", "kernel"):
        (tmp_path / "scratch" / name).mkdir(parents=True)
    bomb = "import os, time\nfor _ in range(11):\n    os.fork()\ntime.sleep(30)\n"
    proc = subprocess.Popen(sandbox.bwrap_command([sys.executable, "-c", bomb], tmp_path / "scratch", []))
    watch = autograde.KernelWatch(proc.pid, sandbox.KERNEL_MEMORY_BYTES)
    watch.start()
    proc.wait(timeout=120)
    watch.stop()
    assert (proc.returncode, watch.reason) == (128 + signal.SIGKILL, "it started more than 64 processes at once")


# a kernel that writes into the one folder on the grader's disk it may write (its sockets', named by its argument),
# and into the submission's file it was given, then says what it could do
DISK = """import ctypes, os, sys, time
folder, how = sys.argv[1], sys.argv[2]
many = how == "many"
try:
    with open("my data.csv", "a") as f:
        f.write("overwritten")
    print("wrote the submission's file", flush=True)
except OSError:
    print("the submission's file is read-only:", open("my data.csv").read().split(), flush=True)
libc = ctypes.CDLL(None, use_errno=True)
for k in range(2000 if many else 12):
    with open(os.path.join(folder, f"fill{k}"), "wb") as f:
        if how == "kept":  # 4 MiB of disk kept past the file's end (FALLOC_FL_KEEP_SIZE): its length stays 0
            assert libc.fallocate(f.fileno(), 1, ctypes.c_long(0), ctypes.c_long(4 << 20)) == 0
        f.write(b"" if many or how == "kept" else bytes(4 << 20))
    time.sleep(0.005 if many else 0.05)
print("done")
"""


@pytest.mark.parametrize("how", ["big", "kept", "many"])
def test_the_watch_stops_a_kernel_that_fills_its_sockets_folder(tmp_path, how, needs_sandbox):
    """The folder of the kernel's sockets lies on the grader's disk and the kernel writes there (it makes its
    sockets): 48 MiB written there, 48 MiB of disk kept past the ends of empty files, or 2,000 empty files,
    are stopped at 1 MiB or 64 files, the reason says so. Without the watch of that folder the kernel wrote
    on to the end. The submission's own files, copied to the grader's disk, are read-only to it."""
    many = how == "many"
    scratch = tmp_path / "scratch"
    for name in ("work", "kernel"):
        (scratch / name).mkdir(parents=True)
    (scratch / "work" / "my data.csv").write_text("depth\n1.5\n")
    cmd = sandbox.bwrap_command([sys.executable, "-c", DISK, str(scratch / "kernel"), how], scratch, [])
    results = {}
    for sockets in (None, scratch / "kernel"):
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        watch = autograde.KernelWatch(proc.pid, sandbox.KERNEL_MEMORY_BYTES, sockets=sockets)
        watch.start()
        out, err = proc.communicate(timeout=120)
        watch.stop()
        use = sandbox.folder_use(scratch / "kernel")
        results[sockets is None] = (out.splitlines(), proc.returncode, watch.reason, use)
        for f in (scratch / "kernel").iterdir():
            f.unlink()
    lines, code, reason, (entries, size) = results[False]
    assert lines == ["the submission's file is read-only: ['depth', '1.5']"], (lines, err[-2000:])
    assert code == 128 + signal.SIGKILL and entries <= sandbox.SOCKETS_ENTRIES + 20 and size < (24 << 20)
    assert reason.startswith("it wrote more than 64 files" if many else "it wrote ") and "sockets" in reason, reason
    assert (scratch / "work" / "my data.csv").read_text() == "depth\n1.5\n"
    unwatched, code, reason, _ = results[True]
    assert (unwatched[-1], code, reason) == ("done", 0, None)


# a kernel that holds memory in in-memory files (memfd_create) it writes but never maps: no resident size shows it
MEMFD = """import os, resource, time
print("open files at most", resource.getrlimit(resource.RLIMIT_NOFILE), flush=True)
held = []
for k in range(3):
    held.append(os.memfd_create(f"hold{k}"))
    os.write(held[-1], bytes(120 << 20))
print("held", flush=True)
time.sleep(8)
print("done", flush=True)
"""


def test_the_watch_counts_the_memory_of_in_memory_files(tmp_path, monkeypatch, needs_sandbox):
    """360 MiB written into three in-memory files (os.memfd_create) and never mapped show in no process's
    resident size: watched under 256 MiB, the kernel is stopped and the reason gives what it held; without
    the files counted, it runs to its end. A process may hold at most FILES_OPEN files open (the watch reads
    them all)."""
    for name in ("work", "kernel"):
        (tmp_path / "scratch" / name).mkdir(parents=True)
    cmd = sandbox.bwrap_command([sys.executable, "-c", MEMFD], tmp_path / "scratch", [])
    results = []
    for counted in (True, False):
        if not counted:
            monkeypatch.setattr(sandbox, "memory_files_bytes", lambda pids: 0)
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        watch = autograde.KernelWatch(proc.pid, 256 << 20)
        watch.start()
        out, err = proc.communicate(timeout=120)
        watch.stop()
        results.append((out.splitlines(), proc.returncode, watch.reason))
    limit = f"open files at most ({sandbox.FILES_OPEN}, {sandbox.FILES_OPEN})"
    (lines, code, reason), unwatched = results
    assert lines[0] == limit and "done" not in lines and code == 128 + signal.SIGKILL, (lines, code, err[-2000:])
    # the watch reads every 0.2 s, maybe while the third file is being written: what it saw lies between the
    # limit and the 360 MiB of files with the interpreter's own resident memory (under 0.40 GiB)
    held = re.fullmatch(r"its processes held (\d\.\d\d) GiB together, over the limit of 0\.25 GiB \(--kernel-memory\)",
                        reason)
    assert held and 0.25 <= float(held[1]) < 0.40, reason
    assert unwatched == ([limit, "held", "done"], 0, None)


def test_the_lecturers_page_states_the_kernels_limits_as_the_sandbox_sets_them():
    text = " ".join((Path(__file__).parent.parent / "docs" / "teaching.md").read_text().split())
    stated = [f"each of its processes at most {sandbox.KERNEL_MEMORY_GIB:g} GiB of data",
              f"holds the same {sandbox.KERNEL_MEMORY_GIB:g} GiB with all its processes together, and has at most "
              f"{sandbox.PROCESSES_MAX} processes at once", f"hold every {sandbox.WATCH_S:g} s (`sandbox.WATCH_S`;",
              f"outgrow the limit by what it writes in {sandbox.WATCH_S:g} s",
              f"more than {sandbox.SOCKETS_ENTRIES} files or {sandbox.SOCKETS_BYTES >> 20} MiB there",
              f"its `/dev/shm` at most {sandbox.SHM_BYTES >> 20} MiB",
              f"each process may hold at most {sandbox.FILES_OPEN} files open"]
    assert [s for s in stated if s not in text] == []
    # the check can fail: a page that still says 32 processes is caught
    assert stated[1] not in text.replace(f"at most {sandbox.PROCESSES_MAX} processes", "at most 32 processes")


HOG = ("import subprocess, sys\n\nhold = 'block = b\"x\" * (400 << 20); import time; time.sleep(30)'\n"
       "kids = [subprocess.Popen([sys.executable, '-c', hold]) for _ in range(3)]\n"
       "print([k.wait() for k in kids])\nmy_sum = 5")


@pytest.mark.slow
def test_a_kernel_whose_processes_hold_too_much_together_could_not_run(tiny_course, tmp_path, capsys,
                                                                       needs_sandbox):
    """bo's answer starts three processes of 400 MiB, each under the kernels' 1 GiB: together they are over
    it, so the grader stops bo's kernel and says why; ana, graded in the same class, keeps her points."""
    course.release(tiny_course)
    released = tiny_course / "release" / TINY / f"{TINY}.ipynb"
    right = {n: _solution(a) for n, (a, _) in ANSWERS.items()}
    subs = _submissions(tmp_path, {f"{who}/{TINY}.ipynb": _returned(released, answers)
                                   for who, answers in (("ana", right), ("bo", {**right, 1: HOG}))})
    course.collect(tiny_course, subs)
    capsys.readouterr()
    assert cli.main(["course", "autograde", "--kernel-memory", "1", "--course", str(tiny_course)]) == 0
    (line,) = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("could not run")]
    assert line.startswith(f"could not run: bo, {TINY}.ipynb: the grader stopped the kernel: its processes held ")
    assert line.endswith("GiB together, over the limit of 1 GiB (--kernel-memory)")
    assert cli.main(["course", "grades", "--out", str(tmp_path / "grades.csv"), "--course", str(tiny_course)]) == 0
    rows = {r["student"]: r for r in csv.DictReader((tmp_path / "grades.csv").open())}
    assert (float(rows["ana"]["points"]), rows["ana"]["could_not_run"]) == (5.0, "")
    assert rows["bo"]["could_not_run"].startswith("the grader stopped the kernel")


@pytest.mark.parametrize("gib", [0.25, float("nan"), float("inf"), 1e6])
def test_a_kernel_memory_limit_out_of_range_is_one_line(tiny_course, capsys, gib):
    assert cli.main(["course", "autograde", "--course", str(tiny_course), "--kernel-memory", str(gib)]) == 2
    assert "--kernel-memory" in one_line_error(capsys)


def test_feedback_page_names_exercises_and_shows_messages_not_tests():
    nb = json.loads(tiny_notebook_text())
    exercises.grade_by_hand(nb)  # as the course's source/ and autograded/ hold it: 99.3's answer graded by hand
    hidden = "assert isinstance(my_sum, int)"
    for cell in nb["cells"]:
        gid = cell["metadata"].get("nbgrader", {}).get("grade_id", "")
        if gid == "ex99-1-check":  # failed: nbgrader keeps the traceback, which quotes the hidden line
            cell["outputs"] = [{"output_type": "error", "ename": "AssertionError", "evalue": "my_sum",
                                "traceback": [f"----> 3 {hidden}", "AssertionError: my_sum"]}]
        if gid == "ex99-2-answer":  # past the cell timeout: the kernel's interrupt, then nbgrader's error
            cell["outputs"] = [{"output_type": "error", "ename": ename, "evalue": "", "traceback": []}
                               for ename in ("KeyboardInterrupt", "CellTimeoutError")]
    grades = {"ex99-1-check": (0.0, 2.0, False), "ex99-2-check": (3.0, 3.0, False),
              "ex99-3-check": (0.0, 0.0, False), "ex99-3-answer": (None, 4.0, True)}
    rows = autograde.exercise_rows(nb, grades)
    assert [(r["number"], r["title"], r["points"], r["max_points"], r["outcome"], r["message"]) for r in rows] == [
        ("99.1", "Add", 0.0, 2.0, "failed", "AssertionError: my_sum"),
        ("99.2", "Square", 3.0, 3.0, "passed", "your answer cell stopped: CellTimeoutError: the cell ran longer "
                                               "than the course's cell timeout and was stopped"),
        ("99.3", "Why", 0.0, 4.0, "passed", None)]
    text = autograde.page("ana", TINY, f"{TINY}.ipynb", rows, None)
    assert "99.1 Add" in text and "AssertionError: my_sum" in text and "3 of 9 points" in text
    assert "0 / 4 (graded by hand, pending)" in text
    assert hidden not in text and "http" not in text and "<script" not in text
    dead = autograde.page("bo", TINY, f"{TINY}.ipynb", None, "the kernel died: DeadKernelError: Kernel died")
    assert "could not run" in dead and "DeadKernelError" in dead
    # an exercise the static review flagged: what its check printed may carry what the student's code read
    held = autograde.exercise_rows(nb, grades, frozenset({"99.1"}))
    assert [(r["number"], r["outcome"], r["message"]) for r in held] == [
        ("99.1", "held", autograde.HELD_MESSAGE), *[(r["number"], r["outcome"], r["message"]) for r in rows[1:]]]
    assert "AssertionError: my_sum" not in autograde.page("ana", TINY, f"{TINY}.ipynb", held, None)


def tiny_notebook_text() -> str:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        return tiny_notebook(Path(tmp) / "t.ipynb").read_text()


def test_a_failed_run_is_one_line_with_its_reason():
    dead = ("Traceback ...\n    raise DeadKernelError(\"Kernel died\") from None\n"
            "nbclient.exceptions.DeadKernelError: Kernel died\n[ERROR] There was an error processing\n")
    assert autograde.failure_reason(dead, 1) == ("the kernel died (the notebook ended Python, crashed or ran out of "
                                                 "memory): nbclient.exceptions.DeadKernelError: Kernel died")
    assert autograde.failure_reason("[ERROR] no such notebook\n", 1) == (
        "nbgrader exited with status 1: [ERROR] no such notebook")
    rows = [{"student": "ana", "assignment": TINY, "points": 5.0, "needs_manual_grading": 1, "pending_max_points": 4.0},
            {"student": "bo", "assignment": TINY, "points": 0.0, "needs_manual_grading": 5, "pending_max_points": 13.0}]
    out = course.with_could_not_run(rows, {("bo", TINY): "the kernel died", ("cy", TINY): "nbgrader exited"},
                                    {TINY: 9.0})
    assert [(r["student"], r["points"], r["max_points"] if r["student"] == "cy" else None, r["needs_manual_grading"],
             r["could_not_run"]) for r in out] == [
        ("ana", 5.0, None, 1, ""), ("bo", 0.0, None, 0, "the kernel died"), ("cy", 0.0, 9.0, 0, "nbgrader exited")]


def test_a_damaged_list_of_failed_runs_is_one_line(tiny_course, capsys):
    (tiny_course / "gradebook.db").write_bytes(b"")
    (tiny_course / autograde.FAILURES).write_text("[{\"student\": 1}]")
    assert cli.main(["course", "autograde", "--unsafe-no-sandbox", "--course", str(tiny_course)]) == 2
    one_line_error(capsys, str(tiny_course / autograde.FAILURES), "damaged")


def test_flagged_answers_reach_the_grade_table_and_a_damaged_record_is_one_line(tiny_course, capsys):
    rows = [{"student": "ana", "assignment": TINY}, {"student": "cy", "assignment": TINY}]
    reason = "line 2: class Always defines __eq__: defines a special method"
    flags = {("cy", TINY): [{"notebook": TINY, "exercise": "99.2", "reasons": [reason, "line 5: .__hash__: x"]}]}
    assert [r["flagged_for_review"] for r in course.with_flags(rows, flags)] == [
        "", f"99.2: {reason}; line 5: .__hash__: x"]
    (tiny_course / "gradebook.db").write_bytes(b"")
    (tiny_course / autograde.FLAGGED).write_text("[{\"student\": \"cy\"}]")
    assert cli.main(["course", "autograde", "--unsafe-no-sandbox", "--course", str(tiny_course)]) == 2
    one_line_error(capsys, str(tiny_course / autograde.FLAGGED), "damaged")


def test_a_rerun_skips_what_is_graded_and_retry_runs_the_failed_again(tmp_path, monkeypatch):
    """The class loop alone, nbgrader replaced by a stand-in that records whom it grades."""
    root = tmp_path / "course"
    for student in ("ana", "bo", "cy"):
        (root / "submitted" / student / TINY).mkdir(parents=True)
        (root / "submitted" / student / TINY / f"{TINY}.ipynb").write_text('{"cells": []}')
    (root / "autograded" / "ana" / TINY).mkdir(parents=True)  # graded before
    (root / autograde.FAILURES).write_text(json.dumps([{"student": "bo", "assignment": TINY, "reason": "died"}]))
    calls = []

    def stand_in(course_dir, student, assignment, sandboxed, limit_s, memory):
        assert memory == sandbox.memory_bytes(sandbox.KERNEL_MEMORY_GIB)
        calls.append((student, limit_s))
        return "the kernel died again" if student == "bo" else None

    monkeypatch.setattr(autograde, "grade_one", stand_in)
    monkeypatch.setattr(sandbox, "unavailable", lambda: None)
    lines = []
    info = autograde.grade_class(root, [TINY], 8, echo=lines.append)
    assert calls == [("cy", 8 + autograde.KERNEL_START_S)] and info["graded"] == [("cy", TINY)]
    assert info["skipped"] == [("ana", TINY), ("bo", TINY)] and lines == []
    calls.clear()
    info = autograde.grade_class(root, [TINY], 8, retry=True, echo=lines.append)
    assert [c[0] for c in calls] == ["bo", "cy"]  # cy has no autograded/ folder here: the stand-in wrote none
    assert lines == [f"could not run: bo, {TINY}.ipynb: the kernel died again"]
    assert autograde.read_failures(root) == {("bo", TINY): "the kernel died again"}


def test_the_run_limit_counts_the_courses_cells_not_the_cells_a_student_adds(tmp_path, monkeypatch):
    """A student who adds 40 cells does not hold the class 40 cell timeouts longer."""
    root = tmp_path / "course"
    (root / "source" / TINY).mkdir(parents=True)
    tiny_notebook(root / "source" / TINY / f"{TINY}.ipynb")
    released = json.loads((root / "source" / TINY / f"{TINY}.ipynb").read_text())
    ours = sum(c["cell_type"] == "code" for c in released["cells"])
    released["cells"] += [{"cell_type": "code", "metadata": {}, "source": "import time\ntime.sleep(7)",
                           "outputs": [], "execution_count": None}] * 40
    (root / "submitted" / "ana" / TINY).mkdir(parents=True)
    (root / "submitted" / "ana" / TINY / f"{TINY}.ipynb").write_text(json.dumps(released))
    limits = []
    monkeypatch.setattr(autograde, "grade_one", lambda c, s, a, sb, limit_s, memory: limits.append((limit_s, memory))
                        or "stand-in")
    monkeypatch.setattr(sandbox, "unavailable", lambda: None)
    autograde.grade_class(root, [TINY], 8, memory=sandbox.memory_bytes(2))
    assert limits == [(8 * ours + autograde.KERNEL_START_S, 2 << 30)] and ours < 40


def test_what_a_notebook_prints_is_kept_to_its_tail_in_the_grader(tmp_path, monkeypatch):
    """nbgrader passes the kernel's standard error on; the grader keeps only the last OUTPUT_TAIL_BYTES of
    it, so a notebook writing hundreds of MB there cannot fill the lecturer's memory."""
    tail = bytearray()
    autograde.keep_tail(io.BytesIO(b"a" * 100_000 + b"END"), tail, 10)
    assert bytes(tail) == b"aaaaaaaEND"
    flood = ("import sys\nprint('DeadKernelError: said first', flush=True)\n"
             "for _ in range(20000):\n    sys.stdout.write('y' * 99 + '\\n')\n"
             "print('[ERROR] the last line')\nsys.exit(1)")
    real = subprocess.Popen

    def stand_in(cmd, **kwargs):  # nbgrader replaced by a process that floods its output and fails
        return real([sys.executable, "-c", flood], **kwargs)

    monkeypatch.setattr(autograde.subprocess, "Popen", stand_in)
    monkeypatch.setattr(autograde, "OUTPUT_TAIL_BYTES", 4096)
    (tmp_path / "autograded").mkdir()
    reason = autograde.grade_one(tmp_path, "ana", TINY, False, 60)
    assert reason == "nbgrader exited with status 1: [ERROR] the last line"  # the first 2 MB were let go


def test_a_graded_notebook_too_big_to_read_back_gets_its_page_and_the_class_goes_on(tmp_path, monkeypatch):
    """A 70 MB print once stopped `course feedback` for the whole class; now that student's page says why
    and the others are written."""
    root = tmp_path / "course"
    (root / "source" / TINY).mkdir(parents=True)
    tiny_notebook(root / "source" / TINY / f"{TINY}.ipynb")
    text = (root / "source" / TINY / f"{TINY}.ipynb").read_text()
    for who, extra in (("ana", 0), ("big", 4000), ("zoe", 0)):
        (root / "submitted" / who / TINY).mkdir(parents=True)
        (root / "autograded" / who / TINY).mkdir(parents=True)
        nb = json.loads(text)
        nb["cells"][0]["outputs"] = [{"output_type": "stream", "name": "stdout", "text": "x" * extra}]
        (root / "autograded" / who / TINY / f"{TINY}.ipynb").write_text(json.dumps(nb))
    monkeypatch.setattr(exercises, "NOTEBOOK_MAX_BYTES", len(text) + 2000)
    monkeypatch.setattr(autograde, "notebook_grades", lambda *a: {})
    lines = []
    pages = autograde.write_feedback(root, [TINY], lines.append)
    assert [p.parent.parent.name for p in pages] == ["ana", "big", "zoe"]
    big = pages[1].read_text()
    assert "could not be read back" in big and "MB, more than a notebook" in big and str(root) not in big
    assert "Add" in pages[2].read_text() and "could not be read back" not in pages[2].read_text()
    assert len(lines) == 1 and lines[0].startswith(f"feedback: big, {TINY}.ipynb: cannot read ")
