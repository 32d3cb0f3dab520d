"""What nbgrader's process keeps of a sandboxed kernel's output (``sandbox.OutputBudget``): a cell's
outputs up to a budget, then a note and only what decides the grade, so that nbgrader grades the
cell as the whole output would have it graded. The kernel's messages are built here as jupyter's
protocol has them; the grades come from nbgrader's own ``determine_grade``."""

import itertools

import pytest
from nbformat.v4 import new_code_cell, output_from_msg
from nbgrader.utils import determine_grade

from geodepth_lite.workbook import sandbox

CELL = "execute-1"


def _msg(kind: str, content: dict, cell: str = CELL) -> dict:
    return {"msg_type": kind, "header": {"msg_type": kind, "msg_id": "m"}, "parent_header": {"msg_id": cell},
            "metadata": {}, "content": content, "buffers": []}


def stdout(n: int) -> dict:
    return _msg("stream", {"name": "stdout", "text": "x" * n})


def stderr(n: int) -> dict:
    return _msg("stream", {"name": "stderr", "text": "w" * n})


def error(n: int) -> dict:
    return _msg("error", {"ename": "AssertionError", "evalue": "e" * n, "traceback": ["t" * n] * 3})


def result(value: str) -> dict:
    return _msg("execute_result", {"data": {"text/plain": value}, "metadata": {}, "execution_count": 1})


def figure(n: int) -> dict:
    return _msg("display_data", {"data": {"image/png": "i" * n}, "metadata": {}})


def grade(messages: list[dict]) -> float:
    """nbgrader's grade of a 2-point check cell whose kernel sent ``messages``."""
    cell = new_code_cell("check()", metadata={"nbgrader": {"grade": True, "solution": False, "points": 2,
                                                           "grade_id": "c", "locked": True}})
    cell.outputs = [output_from_msg(m) for m in messages]
    return determine_grade(cell)[0]


def kept(messages: list[dict], budget: sandbox.OutputBudget) -> list[dict]:
    return [m for m in (budget.admit(m) for m in messages) if m is not None]


def test_output_within_the_budget_passes_unchanged():
    budget = sandbox.OutputBudget(cell_bytes=1000, notebook_bytes=3000)
    messages = [stdout(300), figure(300), stderr(10), result("1.0")]
    assert kept(messages, budget) == messages
    status = _msg("status", {"execution_state": "idle"})
    assert budget.admit(status) is status  # not an output: never counted, never dropped


def test_past_the_budget_a_cell_gets_one_note_and_only_what_decides_its_grade():
    budget = sandbox.OutputBudget(cell_bytes=1000, notebook_bytes=10_000)
    out = kept([stdout(600), stdout(600), stdout(600), figure(600), error(10_000), error(10)], budget)
    assert out[0]["content"]["text"] == "x" * 600
    assert out[1]["content"] == {"name": "stdout", "text": sandbox.OUTPUT_CUT.format(limit=0)}
    assert [m["msg_type"] for m in out] == ["stream", "stream", "error", "error"]
    assert len(out[2]["content"]["evalue"]) == sandbox.DECIDING_BYTES and len(out[2]["content"]["traceback"]) == 3
    many = kept([stdout(2000)] + [stderr(5)] * (sandbox.DECIDING_KEPT + 5), sandbox.OutputBudget(1000, 10_000))
    assert len(many) == 1 + sandbox.DECIDING_KEPT  # the note, then the first DECIDING_KEPT deciding outputs


def test_the_notebook_budget_holds_across_cells():
    budget = sandbox.OutputBudget(cell_bytes=1000, notebook_bytes=1500)
    first = kept([_msg("stream", {"name": "stdout", "text": "a" * 900}, cell="c1")], budget)
    second = kept([_msg("stream", {"name": "stdout", "text": "b" * 900}, cell="c2"),
                   _msg("stream", {"name": "stdout", "text": "b" * 10}, cell="c2")], budget)
    assert len(first) == 1 and [m["content"]["text"][:8] for m in second] == ["[output "]
    assert budget.total <= 1500


SEQUENCES = {  # what a check cell may send: a flood before, between or after what decides its grade
    "flood then error": [stdout(700)] * 5 + [error(50)],
    "flood then stderr then result": [stdout(700)] * 5 + [stderr(20), result("2")],
    "flood then partial credit": [stdout(700)] * 5 + [result("0.5")],
    "flood then a huge error": [figure(900)] * 3 + [error(50_000)],
    "result then flood then error": [result("0.5")] + [stdout(700)] * 5 + [error(10)],
    "flood only": [stdout(700)] * 6,
    "error first": [error(10)] + [stdout(700)] * 5,
}


@pytest.mark.parametrize("name", SEQUENCES)
def test_the_grade_of_what_is_kept_is_the_grade_of_the_whole_output(name):
    messages = SEQUENCES[name]
    whole = grade(messages)
    assert grade(kept(messages, sandbox.OutputBudget(cell_bytes=1000, notebook_bytes=100_000))) == whole
    assert whole in (0, 0.5, 2)  # every kind of outcome is among the cases: see the next test


def test_the_cases_cover_every_grade_and_a_budget_that_dropped_them_would_fail():
    """The equivalence above can fail: keeping the first outputs only (a plain cut, no deciding outputs
    past it) grades the flooded failing check as passed."""
    assert {grade(m) for m in SEQUENCES.values()} == {0, 0.5, 2}

    def plain_cut(messages):
        return list(itertools.islice(messages, 2))

    assert grade(plain_cut(SEQUENCES["flood then error"])) == 2 != grade(SEQUENCES["flood then error"])


def test_the_size_of_a_deeply_nested_message_costs_no_stack():
    deep = []
    for _ in range(200_000):
        deep = [deep]
    assert sandbox.message_bytes({"data": deep}) > 200_000
    assert sandbox.message_bytes({"text": "abc", "n": 1}) == 2 + len("text") + 3 + len("n") + 8
