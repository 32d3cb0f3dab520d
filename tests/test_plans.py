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


@pytest.mark.parametrize("rel", sorted(PINNED))
def test_the_plan_above_its_amendments_is_the_committed_text(rel):
    assert body_sha256(_text(rel)) == PINNED[rel], f"{rel} was edited above '## Amendments'"


@pytest.mark.parametrize("rel", sorted(PINNED))
def test_amendments_are_dated_and_appended_at_the_end(rel):
    text = _text(rel)
    assert text.count(AMENDMENTS) == 1, "one Amendments section"
    tail = text.split(AMENDMENTS, 1)[1]
    assert "\n## " not in tail, "the Amendments section is the last one"
    items = [line for line in tail.splitlines() if line.startswith("- ")]
    assert all(re.match(r"- \*\*\d{4}-\d{2}-\d{2}\b", line) for line in items), "every amendment is dated"


def test_an_edit_above_the_amendments_is_caught_and_one_below_is_not():
    text = _text("docs/study_plan.md")
    assert "48 runs in about 40 min" in text
    edited = text.replace("48 runs in about 40 min", "48 runs in about 72 min", 1)
    assert body_sha256(edited) != PINNED["docs/study_plan.md"]
    amended = text.rstrip("\n") + "\n- **2099-01-01, a later fact.** Appended.\n"
    assert body_sha256(amended) == PINNED["docs/study_plan.md"]
