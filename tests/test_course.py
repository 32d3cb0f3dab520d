"""The lecturer's course (``course init / release / collect / autograde / feedback / grades``): the
cell timeout taken from the notebooks' own execution records, open-ended exercises graded by hand,
returned notebooks collected without replacing one, and a round trip through nbgrader in which
three students (all right, all wrong, the release untouched) get known scores.

The round trip grades a tiny notebook built here in the project's exercise conventions (executing
notebooks 01-07 would take many minutes): an answer cell with a solution region and a locked check
cell with hidden tests per exercise, the last one open-ended."""

import csv
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from conftest import one_line_error

from geodepth_lite import cli, course, exercises, utils

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
        before, after = exercises.collect(json.loads(p.read_text())), exercises.collect(src)
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
def test_three_students_through_nbgrader_get_known_scores(tiny_course, tmp_path, capsys):
    """release -> collect -> autograde -> feedback -> grades, with nbgrader itself (about 30 s)."""
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
    for who in ("right", "wrong", "untouched"):
        assert (tiny_course / "feedback" / who / TINY / f"{TINY}.html").is_file()
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
    assert all(r["assignment"] == TINY for r in rows.values())
    _grade_by_hand(tiny_course, "right", "ex99-3-answer", 4.0)  # what formgrader does
    rows = course.grade_rows(tiny_course)
    assert [(r["student"], r["points"], r["needs_manual_grading"]) for r in rows if r["student"] == "right"] == [
        ("right", 9.0, 0)]
    # the table is never replaced
    assert cli.main(["course", "grades", "--out", str(tmp_path / "grades.csv"), *run]) == 2
    one_line_error(capsys, str(tmp_path / "grades.csv"), "exists")


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
# lessons use implements what some exercises ask for (02-2 and 02-4 in model.py, 05-2's Holm rule in
# ablation.py, 06-1's bands in border.py; 01-3/01-4's pixel grid in a test). Pinned by the SHA-256 of
# the line (this file ships to students too, so it must not hold the lines themselves): any other
# solution line in what students get fails the tests below.
SHARED_WITH_THE_PROJECT = {
    "320c96563e2be11a": {"tests/test_render.py"},
    "603da3fc218796a7": {"geodepth_lite/model.py"},
    "03d402e8058d6f40": {"geodepth_lite/model.py"},
    "ac6de9fa23fc3050": {"geodepth_lite/ablation.py"},
    "b332d63d46722f4b": {"geodepth_lite/border.py"},
    "693a347d777327f5": {"geodepth_lite/border.py"},
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
        for ex in exercises.collect(nb).values():
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
    assert "geodepth_lite/course.py" in names and "geodepth_lite/exercises.py" in names
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
    assert (out / "data_manifests").is_dir() and (out / "geodepth_lite" / "course.py").is_file()
    assert not any(course.holds_solutions(p) for p in out.rglob("*.ipynb"))
    assert solution_leaks(_text_files(out)) == []
    assert not (out / ".lock").exists()
    assert cli.main(["course", "edition", "--course", str(tiny_course), "--out", str(out)]) == 2  # never again
    one_line_error(capsys, str(out), "not an empty folder")
    inside = exercises.NOTEBOOK_DIR.parent / "student-edition-test"
    assert cli.main(["course", "edition", "--course", str(tiny_course), "--out", str(inside)]) == 2
    one_line_error(capsys, str(inside), "inside the checkout")
    assert not inside.exists()
