"""A committed study plan is never edited: its text above "## Amendments" is pinned by its SHA-256.

The pinned text of docs/study_plan_2.md is the plan as first committed, before its first run; that of
docs/study_plan.md is the plan as committed before the study's first run, with its
outcome appended after the last run. Later facts go below the "## Amendments" heading, dated.
"""

import hashlib
import re

import pytest

from geodepth_lite import utils

AMENDMENTS = "\n## Amendments\n"
PINNED = {
    "docs/study_plan.md": "fcf664c5fc8b6387ef56dd4ea5e9d70aa85c5c6b3e0203653ecf9851a5c830c9",
    "docs/study_plan_2.md": "3eea30b4182cceb2d31028339e72de811bd3c1a92fc54186b698470a4fa0adb5",
    "docs/exploratory_plan.md": "0c94ab662cc20c361de8662389714e1315213f1b9892409995e3e6d80c44bfde",  # fbb7ca4
    "docs/gpu_check_plan.md": "818243fed58903cb9ba17074d755633dc7a61441883c8cab641c6dfe324d0fac",
    "docs/real_finetune_plan.md": "18b4249319cf0240303aab9f50707d96b505b08b0818faa37098d4edbd1191d7",
}


def plan_body(text: str) -> str:
    """The plan's text above its amendments, without trailing newlines."""
    return text.split(AMENDMENTS, 1)[0].rstrip("\n")


def body_sha256(text: str) -> str:
    return hashlib.sha256(plan_body(text).encode("utf-8")).hexdigest()


def _text(rel: str) -> str:
    root = utils.project_root()
    if root is None or not (root / rel).is_file():
        pytest.skip(f"{rel} is not in this install (not a checkout)")
    return (root / rel).read_text(encoding="utf-8")


def plan_problems(text: str, pinned: str) -> list[str]:
    """What breaks the rule of a committed plan: its text above "## Amendments" differs from the
    pinned SHA-256, or its Amendments section is not one, last, with every item dated."""
    problems = [] if body_sha256(text) == pinned else ["edited above '## Amendments'"]
    if text.count(AMENDMENTS) != 1:
        return problems + [f"{text.count(AMENDMENTS)} Amendments sections, not one"]
    tail = text.split(AMENDMENTS, 1)[1]
    if "\n## " in tail:
        problems.append("the Amendments section is not the last one")
    items = [line for line in tail.splitlines() if line.startswith("- ")]
    dated = re.compile(r"- \*\*\d{4}-\d{2}-\d{2}\b")
    problems += [f"undated amendment {line[:40]!r}" for line in items if not dated.match(line)]
    return problems


@pytest.mark.parametrize("rel", sorted(PINNED))
def test_the_plan_keeps_its_committed_text_and_dated_amendments(rel):
    assert plan_problems(_text(rel), PINNED[rel]) == []


def test_each_way_of_breaking_a_plan_is_caught_and_a_dated_amendment_is_not():
    """Each defect planted in the committed plan is found; an amendment appended right is accepted."""
    text, pinned = _text("docs/study_plan.md"), PINNED["docs/study_plan.md"]
    assert "48 runs in about 40 min" in text and plan_problems(text, pinned) == []
    body, tail = text.split(AMENDMENTS, 1)
    fact = "- **2099-01-01, a later fact.** Appended.\n"
    assert plan_problems(text.rstrip("\n") + "\n" + fact, pinned) == []
    assert plan_problems(text.replace("48 runs in about 40 min", "48 runs in about 72 min", 1), pinned) == [
        "edited above '## Amendments'"]
    assert plan_problems(body.rstrip("\n") + "\n" + fact + AMENDMENTS + tail, pinned) == [  # dated, but above
        "edited above '## Amendments'"]
    assert plan_problems(text.rstrip("\n") + "\n- 2099-01-01 a later fact\n", pinned) == [
        "undated amendment '- 2099-01-01 a later fact'"]
    assert plan_problems(text.rstrip("\n") + "\n\n## Outcome\nbelow the amendments\n", pinned) == [
        "the Amendments section is not the last one"]
    assert plan_problems(text + AMENDMENTS, pinned) == ["2 Amendments sections, not one"]
