"""The graded exercises of notebooks 01-07: enough of them, solutions pass, unanswered stubs fail,
and the student release (nbgrader's generate_assignment) holds no solution text."""

import json

import pytest
from test_course import notebook_strings, solution_leaks

from geodepth_lite.workbook import exercises as E

NOTEBOOKS = E.notebook_paths()
LEVELS = ("recall", "apply", "open")


def _load(path):
    return json.loads(path.read_text())


def _all_exercises():
    return [(p.name, ex) for p in NOTEBOOKS for ex in E.notebook_exercises(_load(p)).values()]


@pytest.fixture(scope="module")
def released(tmp_path_factory):
    out = tmp_path_factory.mktemp("release") / "student"
    E.write_release(out)
    return {p.name: _load(out / p.name) for p in NOTEBOOKS}


def test_every_lesson_notebook_has_three_graded_exercises_from_recall_to_open():
    assert [p.name[:2] for p in NOTEBOOKS] == list(E.EXERCISE_NOTEBOOKS)
    for p in NOTEBOOKS:
        exs = E.notebook_exercises(_load(p))
        assert len(exs) >= 3, f"{p.name}: {len(exs)} exercises"
        for ex in exs.values():
            assert set(ex.cells) == {"answer", "check"}, f"{p.name} {ex.ident}: needs an answer and a check cell"
            assert ex.points > 0 and ex.prompt.lstrip().startswith(f"### Exercise {ex.ident.replace('-', '.')}")
            assert E.SOLUTION_MARKERS[0] in ex.answer, f"{p.name} {ex.ident}: no solution region"
        levels = {lvl for ex in exs.values() for lvl in LEVELS if f"({lvl}," in ex.prompt}
        assert levels == set(LEVELS), f"{p.name}: levels {sorted(levels)}"


@pytest.mark.parametrize("name,ex", _all_exercises(), ids=lambda v: getattr(v, "ident", v))
def test_solution_passes_its_check(name, ex):
    E.run_exercise(ex.answer, ex.check)


@pytest.mark.parametrize("name,ex", _all_exercises(), ids=lambda v: getattr(v, "ident", v))
def test_check_fails_on_the_students_unanswered_stub(name, ex, released):
    stub = E.notebook_exercises(released[name])[ex.ident]
    assert E.SOLUTION_MARKERS[0] not in stub.answer and "NotImplementedError" in stub.answer
    fails, why = E.stub_fails(stub.answer, stub.check)
    assert fails, f"{name} exercise {ex.ident}: {why}"


def test_release_holds_no_solution_text_and_no_outputs(released):
    for p in NOTEBOOKS:
        source, student = _load(p), released[p.name]
        assert E.leaks(source, student) == []
        assert not any(c.get("outputs") for c in student["cells"] if c["cell_type"] == "code")
        assert len(E.notebook_exercises(student)) == len(E.notebook_exercises(source))


def test_the_release_speaks_as_the_student_version(released):
    """Each lesson's note that "this copy shows the solutions" becomes the student version's in the release,
    and only there: the lecturer's notebooks keep it."""
    for p in NOTEBOOKS:
        src = "\n".join("".join(c["source"]) for c in _load(p)["cells"])
        out = "\n".join("".join(c["source"]) for c in released[p.name]["cells"])
        assert E.LECTURER_NOTE in src and E.LECTURER_NOTE not in out and E.STUDENT_NOTE in out, p.name
    plain = {"cells": [{"cell_type": "code", "source": E.LECTURER_NOTE}]}
    assert E.student_wording(plain) == 0 and plain["cells"][0]["source"] == E.LECTURER_NOTE


def test_release_holds_no_solution_line_and_no_marker_anywhere(released):
    """Every string of every released notebook (sources, metadata, outputs) against every solution line
    of notebooks 01-07 and the markers (the scan itself is shown to fail in test_course.py)."""
    texts = {name: "\n".join(notebook_strings(nb)) for name, nb in released.items()}
    assert len(texts) == len(NOTEBOOKS) and solution_leaks(texts) == []


def test_leak_check_and_stub_check_can_fail():
    nb = _load(NOTEBOOKS[0])
    ex = next(iter(E.notebook_exercises(nb).values()))
    leaked = json.loads(json.dumps(nb))
    leaked["cells"].append({"cell_type": "markdown", "metadata": {}, "source": E.solution_lines(ex.answer)[-1]})
    assert E.leaks(nb, leaked)
    # a check that passes on the stub (it tests nothing of the answer) is reported
    fails, why = E.stub_fails("x = None\nraise NotImplementedError()", "assert True")
    assert not fails and "passed" in why
    fails, why = E.stub_fails("raise NotImplementedError()", "assert x == 1")
    assert not fails and "NameError" in why


def test_an_exercise_that_writes_into_its_working_folder_is_refused():
    with pytest.raises(AssertionError, match="wrote"):
        E.run_exercise("open('left_behind.txt', 'w').write('x')", "assert True")
    elsewhere = "import tempfile, pathlib\npathlib.Path(tempfile.mkdtemp(), 'ok.txt').write_text('x')"
    E.run_exercise(elsewhere, "assert True")


def test_release_command_writes_the_student_notebooks(tmp_path, capsys):
    from geodepth_lite import cli

    assert cli.main(["exercises", "--out", str(tmp_path / "class")]) == 0
    assert sorted(p.name for p in (tmp_path / "class").iterdir()) == sorted(p.name for p in NOTEBOOKS)
    assert "exercises" in capsys.readouterr().out


def test_the_lecturers_page_states_the_notebooks_exercise_count_and_points():
    total = [ex for p in E.notebook_paths() for ex in E.notebook_exercises(E.read_notebook(p)).values()]
    stated = f"{len(total)} graded exercises, {sum(ex.points for ex in total):g} points in all"
    text = " ".join((E.NOTEBOOK_DIR.parent / "docs" / "teaching.md").read_text().split())
    assert stated in text
    # the check can fail: the page's former count (26) is not what the notebooks hold
    assert stated not in text.replace(stated, "26 graded exercises, 77 points in all")


def test_the_lecturers_page_states_the_open_exercises_and_their_points():
    """The open-ended exercises (graded by hand) and their points, as the notebooks hold them."""
    opened = sorted((ex.ident, ex.points) for p in E.notebook_paths()
                    for ex in E.notebook_exercises(E.read_notebook(p)).values() if E.OPEN_LEVEL.search(ex.prompt))
    total = sum(ex.points for p in E.notebook_paths() for ex in E.notebook_exercises(E.read_notebook(p)).values())
    idents = ", ".join(i.replace("-", ".") for i, _ in opened)
    stated = f"{idents}; {sum(pt for _, pt in opened):g} of the {total:g} points"
    text = " ".join((E.NOTEBOOK_DIR.parent / "docs" / "teaching.md").read_text().split())
    assert stated in text
    # the check can fail: the page's former sum (24, one short of the notebooks') is caught
    assert stated not in text.replace(stated, stated.replace(f"; {sum(pt for _, pt in opened):g} of", "; 24 of"))


def test_release_sends_open_ended_answers_to_hand_grading(released):
    """An open answer's points sit on its answer cell (graded by hand), its check is worth 0: a long
    enough explanation earns nothing automatically in the release either."""
    seen = 0
    for p in NOTEBOOKS:
        for ex in E.notebook_exercises(released[p.name]).values():
            answer, check = ex.cells["answer"]["metadata"]["nbgrader"], ex.cells["check"]["metadata"]["nbgrader"]
            if E.OPEN_LEVEL.search(ex.prompt):
                seen += 1
                assert answer.get("grade") and answer.get("points", 0) > 0 and check.get("points") == 0, ex.ident
            else:
                assert not answer.get("grade") and check.get("points", 0) > 0, ex.ident
    assert seen == len(NOTEBOOKS)  # one open exercise per notebook


# the static review reads every code cell a student can change, not only the answer cells
HOOK = ("ip = get_ipython()\nip.set_custom_exc((BaseException,), lambda *a, **k: [])\n"
        "ip.events.register('post_run_cell', lambda result: setattr(result, 'error_in_exec', None))\n")


def _code(text: str) -> dict:
    return {"cell_type": "code", "metadata": {}, "source": text, "outputs": [], "execution_count": None}


def _reviewed(name: str, student: dict) -> dict[str, list[str]]:
    from geodepth_lite.workbook import review

    found = review.review_notebook(_load(next(p for p in NOTEBOOKS if p.name == name)), student)
    return {ident: [f"{f.rule}|{f.text()}" for f in fs] for ident, fs in found.items()}


def test_every_released_notebook_returned_as_given_or_with_a_check_run_again_has_no_finding(released):
    """No false alarm: the release as the student gets it, with a visible check and an answer stub pasted into
    cells of their own and a lesson cell's number changed (the review reads these cells too)."""
    for name, nb in released.items():
        assert _reviewed(name, nb) == {}, name
        student = json.loads(json.dumps(nb))
        exs = list(E.notebook_exercises(student).values())
        student["cells"] += [_code(exs[0].check), _code(exs[-1].answer), _code("x = 3\nprint(x * 2)")]
        assert _reviewed(name, student) == {}, name


def test_a_cell_the_student_adds_is_reviewed_and_flags_every_exercise_checked_after_it(released):
    """The forging hook of an added cell (every later check's error swallowed) sends each exercise whose check
    runs after it to a hand grade; one added after the last check flags nothing graded."""
    name = sorted(released)[0]
    student = json.loads(json.dumps(released[name]))
    idents = list(E.notebook_exercises(student))
    first_answer = next(i for i, c in enumerate(student["cells"]) if "nbgrader" in c.get("metadata", {}))
    student["cells"].insert(first_answer, _code(HOOK))
    found = _reviewed(name, student)
    assert list(found) == idents
    assert all(any(t.startswith(f"kernel-history|in code cell {first_answer + 1}, added or changed by the student, "
                                "line 1: get_ipython") for t in texts) for texts in found.values()), found
    late = json.loads(json.dumps(released[name]))
    late["cells"].append(_code(HOOK))
    assert _reviewed(name, late) == {}


def test_a_magic_or_a_stripped_answer_cell_no_longer_escapes_the_review(released):
    """A %magic first line made the answer unreadable as Python, so it was not reviewed; an answer cell without
    its grading metadata was not seen as an answer. Both are flagged now, and what they do to the kernel
    reaches the later exercises; a literal answer concerns its own exercise only."""
    name = sorted(released)[0]
    idents = list(E.notebook_exercises(released[name]))
    magic = json.loads(json.dumps(released[name]))
    E.notebook_exercises(magic)[idents[0]].cells["answer"]["source"] = "%xmode Plain\n" + HOOK
    found = _reviewed(name, magic)
    assert list(found) == idents and any(t.startswith("ipython|line 1: %xmode") for t in found[idents[0]])
    assert any(t.startswith(f"kernel-history|in the answer cell of exercise {idents[0].replace('-', '.')}, line 2")
               for t in found[idents[1]])
    stripped = json.loads(json.dumps(released[name]))
    E.notebook_exercises(stripped)[idents[1]].cells["answer"].update(metadata={}, source="import inspect\nx = 1")
    found = _reviewed(name, stripped)
    assert list(found) == idents[1:]
    assert f"missing-cell|line 1: exercise {idents[1].replace('-', '.')}: the exercise's answer cell" in " ".join(
        found[idents[1]])
    assert all(any(t.startswith("introspection|in code cell") for t in found[i]) for i in idents[1:])
