"""Every sentence about the two ablation studies says what its interval says.

The README, notebook 05's prose and docs/training_and_evaluation.md are read paragraph by paragraph
(a bullet is a paragraph) and held against the committed study tables (`notebooks/study/`,
`notebooks/study2/`):

- an effect "excluded beyond X" names a bound some comparison's interval gives (and a range
  "X-Y% ... with silog" the smallest and largest silog Abs Rel bound);
- an interval "A% to B%" is some comparison's interval;
- "not reproduced" / "excludes the paper's value" carries the scale (64 px synthetic frames);
- the second study's Case 4 set beside the first study's is labelled exploratory and not
  pre-registered, with its own figures;
- words stronger than an interval ("nothing moves", "loses its gain", "agree with every verdict")
  and "Holm-corrected" intervals (they are Bonferroni intervals) do not appear;
- a paragraph about the exploratory arms (E1, E2; docs/exploratory_plan.md) says they are
  exploratory, and its bounds and intervals are theirs (`notebooks/study2/exploratory/`).

`tests/data/study_sentences_before.md` holds the sentences these checks were written against, as
they stood before; each of its paragraphs must be caught.
"""

import json
import re
from pathlib import Path

import pytest

from geodepth_lite.evaluation import exploratory, study, study2

ROOT = Path(__file__).resolve().parent.parent
BEFORE = ROOT / "tests" / "data" / "study_sentences_before.md"

# words that say more than "no change detected" or than an interval that contains zero
OVERCLAIMS = {
    r"nothing moves": "says nothing moves where the data say no change was detected",
    r"does not move": "says a metric does not move where the data say no change was detected",
    r"moves in no comparison": "says a metric moves nowhere where the data say no change was detected",
    r"(?:loses|cost\w*) (?:Case 4 )?its RMSE gain": "says Case 4 loses its gain: that comparison's interval "
                                                    "contains zero",
    r"agree\w* with every t-test verdict": "robustness tests give decisions about zero, not verdicts",
    r"Holm[- ]corrected": "the intervals are Bonferroni intervals (Holm adjusts p values)",
    r"paper's implied": "the paper does not imply lambda3 = 0.01 or the silog depth term",
    r"not where the SDF samples lie": "where the samples lie was tried at a weight that also changed",
}
SCALE = re.compile(r"not reproduced|excludes? the paper's value")
BEYOND = re.compile(r"beyond ([^;:()]{0,40}?) (?:are )?excluded")
SILOG_RANGE = re.compile(r"beyond (\d+\.\d)-(\d+\.\d)% excluded with (?:the )?silog")
L1_BOUND = re.compile(r"beyond (\d+\.\d)% with L1")
INTERVAL = re.compile(r"(?:\(|interval )([+-]?\d+\.\d)% to ([+-]?\d+\.\d)%")
EXPLORATORY_MEAN = re.compile(r"([+-]\d+\.\d) points")
EXPLORATORY_CI = re.compile(r"(\d+)% interval \[?([+-]?\d+\.\d)(?: to |, )([+-]?\d+\.\d)\]? points")
NUMBER = re.compile(r"\d+\.\d")
ARMS = re.compile(r"\bE[12]\b|exploratory arms?")


def flat(text: str) -> str:
    return " ".join(text.split())


def paragraphs(text: str) -> list[str]:
    """Blank-line separated blocks, each bullet ("- " at any indent) its own paragraph, flattened."""
    out, cur = [], []
    for line in text.splitlines():
        if not line.strip() or re.match(r"^\s*- ", line):
            if cur:
                out.append(flat(" ".join(cur)))
            cur = [line] if line.strip() else []
        else:
            cur.append(line)
    if cur:
        out.append(flat(" ".join(cur)))
    return out


@pytest.fixture(scope="module")
def facts() -> dict:
    t1, t2 = study.read_tables(), study2.read_tables()
    fam = study.family(t1) + study2.family(t1, t2)
    bounds = {round(max(abs(t["low"]), abs(t["high"])), 1) for t in fam if t["verdict"].startswith("no ")}
    silog_abs = [round(max(abs(t["low"]), abs(t["high"])), 1) for t in fam
                 if t["metric"] == "abs_rel" and t.get("term", "silog") == "silog" and t["verdict"].startswith("no ")]
    l1 = {round(max(abs(t["low"]), abs(t["high"])), 1) for t in fam
          if t.get("term") == "l1" and t["verdict"].startswith("no ")}
    intervals = {(round(t["low"], 1), round(t["high"], 1)) for t in fam}
    arms = exploratory.arm_comparisons(t1, exploratory.read_arms())
    return {"bounds": bounds, "silog_abs_range": (min(silog_abs), max(silog_abs)), "l1": l1,
            "intervals": intervals, "exploratory": study2.exploratory_vs_first(t1, t2),
            "arm_bounds": {round(max(abs(t["low"]), abs(t["high"])), 1) for t in arms
                           if t["verdict"].startswith("no ")},
            "arm_intervals": {(round(t["low"], 1), round(t["high"], 1)) for t in arms}}


def _with_arms(para: str, f: dict) -> tuple[dict, list[str]]:
    """The facts a paragraph is held to: a paragraph about the exploratory arms may quote their bounds
    and intervals, and must say that they are exploratory."""
    if not ARMS.search(para):
        return f, []
    own = {**f, "bounds": f["bounds"] | f["arm_bounds"], "intervals": f["intervals"] | f["arm_intervals"]}
    return own, [] if "exploratory" in para else ["speaks of the exploratory arms without saying they are exploratory"]


def _numbers_problems(para: str, f: dict) -> list[str]:
    out = []
    for m in BEYOND.finditer(para):
        for x in NUMBER.findall(m.group(1)):
            if float(x) not in f["bounds"]:
                out.append(f"'beyond {m.group(1)} excluded': {x} is no comparison's bound {sorted(f['bounds'])}")
    for m in SILOG_RANGE.finditer(para):
        got = (float(m.group(1)), float(m.group(2)))
        if got != f["silog_abs_range"]:
            out.append(f"silog Abs Rel bounds stated {got}, the tables give {f['silog_abs_range']}")
    for m in L1_BOUND.finditer(para):
        if float(m.group(1)) not in f["l1"]:
            out.append(f"L1 bound {m.group(1)} is none of {sorted(f['l1'])}")
    for m in INTERVAL.finditer(para):
        pair = (float(m.group(1)), float(m.group(2)))
        if pair not in f["intervals"]:
            out.append(f"interval {pair} is no comparison's interval")
    return out


def _exploratory_problems(para: str, f: dict) -> list[str]:
    if ARMS.search(para) or not ("first study" in para and "Case 4" in para
                                 and ("lambda2 = 1" in para or "full weight" in para)
                                 and ("gain" in para or "points" in para)):
        return []
    e, out = f["exploratory"], []
    if "exploratory" not in para or "not pre-registered" not in para:
        out.append("compares the second study's Case 4 with the first study's without saying it is exploratory "
                   "and not pre-registered")
    m = EXPLORATORY_MEAN.search(para)
    if m is None or float(m.group(1)) != round(e["mean"], 1):
        out.append(f"the exploratory difference is {e['mean']:+.1f} points (stated: {m and m.group(1)})")
    m = EXPLORATORY_CI.search(para)
    want = (round(e["low"], 1), round(e["high"], 1))
    if m is None or (float(m.group(2)), float(m.group(3))) != want or int(m.group(1)) != round(100 * e["level"]):
        out.append(f"the exploratory 95% interval is {want} points (stated: {m and m.groups()})")
    if f"p = {e['p']:.2f}" not in para:
        out.append(f"the exploratory p is {e['p']:.2f}")
    return out


def problems(text: str, f: dict) -> list[str]:
    """Every sentence-level problem of ``text``: one line each, with the paragraph's start."""
    out = []
    for para in paragraphs(text):
        own, found = _with_arms(para, f)
        found += [why for pat, why in OVERCLAIMS.items() if re.search(pat, para, re.I)]
        if SCALE.search(para) and "64 px" not in para:
            found.append("a verdict about the paper without the scale (synthetic frames, 64 px, 8 epochs)")
        found += _numbers_problems(para, own) + _exploratory_problems(para, own)
        out += [f"{para[:60]}...: {why}" for why in found]
    return out


def notebook_prose(path: Path) -> str:
    cells = json.loads(path.read_text(encoding="utf-8"))["cells"]
    return "\n\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "markdown")


@pytest.mark.parametrize("page", ["README.md", "notebooks/05_ablation.ipynb", "docs/training_and_evaluation.md"])
def test_study_sentences_match_the_tables(page, facts):
    path = ROOT / page
    text = notebook_prose(path) if path.suffix == ".ipynb" else path.read_text(encoding="utf-8")
    assert problems(text, facts) == []


def test_every_sentence_before_is_caught(facts):
    """Each paragraph of the earlier wording is caught, each for the reason it was wrong."""
    paras = [p for p in BEFORE.read_text(encoding="utf-8").split("\n\n") if p.strip()]
    assert len(paras) == 7
    caught = [problems(p, facts) for p in paras]
    assert all(caught), [p[:60] for p, c in zip(paras, caught) if not c]
    joined = "\n".join(sum(caught, []))
    for reason in ("Bonferroni", "no change was detected", "contains zero", "not verdicts", "the scale",
                   "lambda3 = 0.01", "a weight that also changed"):
        assert reason in joined, reason


def test_wrong_figures_are_caught(facts):
    """A bound, an interval and the exploratory figures altered to values near the right ones fail."""
    e = facts["exploratory"]
    good = (f"Case 4 at lambda2 = 1: paired by seed, it is {e['mean']:+.1f} points above the first study's Case 4, "
            f"an exploratory comparison that was not pre-registered (p = {e['p']:.2f}, 95% interval "
            f"{e['low']:+.1f} to {e['high']:+.1f} points).")
    assert problems(good, facts) == []
    assert problems(good.replace("exploratory ", ""), facts)
    assert problems(good.replace(f"{e['mean']:+.1f} points", f"{e['mean'] + 0.3:+.1f} points"), facts)
    assert problems("no effect detected, effects beyond 2.3% excluded (paper -10%)", facts)
    assert problems("no effect detected, effects beyond 2.2% excluded (paper -10%)", facts) == []
    assert problems("lowers RMSE by 3.2% (interval -5.0% to -1.2%; paper -13%)", facts)
    assert problems("lowers RMSE by 3.2% (interval -5.0% to -1.3%; paper -13%)", facts) == []
    lo, hi = facts["silog_abs_range"]
    assert problems(f"changes beyond {lo:.1f}-{hi + 0.1:.1f}% excluded with silog", facts)


def test_sentences_about_the_exploratory_arms_are_held_to_their_tables(facts):
    """An arm's interval passes in a paragraph about the arms that says they are exploratory; the same
    paragraph without the word, or with an interval end moved by 0.1, fails; the arm's interval is
    not accepted in a paragraph about the studies."""
    lo, hi = sorted(facts["arm_intervals"] - facts["intervals"])[0]
    good = f"The exploratory arm E1 changes RMSE by x% (interval {lo:+.1f}% to {hi:+.1f}%)."
    assert problems(good, facts) == []
    assert problems(good.replace("exploratory ", ""), facts)
    assert problems(good.replace(f"{hi:+.1f}%", f"{hi + 0.1:+.1f}%"), facts)
    assert problems(f"Case 3 changes RMSE by x% (interval {lo:+.1f}% to {hi:+.1f}%).", facts)
