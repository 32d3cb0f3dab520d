"""The concurrent control's record (notebooks/study2/concurrent_control.json) and what
docs/training_and_evaluation.md states from it; its script's comparison on tables made here."""

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RECORD = ROOT / "notebooks" / "study2" / "concurrent_control.json"
SETS = ("confirmation set", "held-out T x L", "close-ups")


def _script():
    spec = importlib.util.spec_from_file_location("concurrent_control", ROOT / "benchmarks" / "concurrent_control.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _pct(x: float) -> str:
    return "0" if x == 0 else f"{x:+.2f} %"


def stated_rows(rec: dict) -> list[str]:
    """The docs' table rows, recomputed from the record."""
    by = {(r["seed"], r["set"]): r for r in rec["rows"]}
    lines = []
    for seed in rec["seeds"]:
        cells = [", ".join(_pct(round(by[(seed, s)]["rel_diff_pct"][m], 2)) for m in ("abs_rel", "rmse"))
                 for s in SETS]
        same = all(by[(seed, s)]["identical"] for s in SETS)
        lines.append(f"| {seed} | " + " | ".join(cells) + f" | {'yes, on all three sets' if same else 'no'} |")
    return lines


def shifts(rec: dict) -> tuple[str, str]:
    a, b = rec["six_comparisons"]["committed"], rec["six_comparisons"]["fresh_case1"]
    mean = max(abs(x["mean"] - y["mean"]) for x, y in zip(a, b))
    ends = max(max(abs(x["low"] - y["low"]), abs(x["high"] - y["high"])) for x, y in zip(a, b))
    return f"at most {mean:.2f} points", f"at most {ends:.2f} points"


def test_the_docs_state_the_record():
    rec = json.loads(RECORD.read_text())
    assert rec["rows_total"] == 12 and rec["identical_rows"] == sum(r["identical"] for r in rec["rows"])
    assert all(s["git_clean"] for runs in rec["runs"].values() for s in runs)  # trained from committed code
    text = (ROOT / "docs" / "training_and_evaluation.md").read_text()
    flat = " ".join(text.split())
    for line in stated_rows(rec):
        assert line in text, line
    for figure in shifts(rec):
        assert figure in flat
    # the check can fail: a record whose seed 1 moved differently is not what the page states
    rec["rows"][3]["rel_diff_pct"]["abs_rel"] = -0.25
    assert any(line not in text for line in stated_rows(rec))


def test_compare_and_substitute_on_tables_made_here():
    mod = _script()
    metrics = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")
    base = {m: 0.5 for m in metrics}
    committed = {"runs": [{"depth_term": "silog", "case": 1, "seed": 0, "set": "confirmation set", **base},
                          {"depth_term": "silog", "case": 2, "seed": 0, "set": "confirmation set", **base}]}
    fresh = [{"depth_term": "silog", "case": 1, "seed": 0, "set": "confirmation set", "frames": 480,
              **{m: "0.5" for m in metrics}, "rmse": "0.55"}]
    rows = mod.compare(fresh, committed)
    assert len(rows) == 1 and not rows[0]["identical"]
    assert abs(rows[0]["rel_diff_pct"]["rmse"] - 10.0) < 1e-9 and rows[0]["rel_diff_pct"]["abs_rel"] == 0
    sub = mod.substituted(committed, fresh)
    case1 = [r for r in sub["runs"] if r["case"] == 1]
    assert len(sub["runs"]) == 2 and len(case1) == 1 and case1[0]["rmse"] == 0.55  # replaced, not added
    assert committed["runs"][0]["rmse"] == 0.5  # the committed tables are left as they were


def test_the_record_is_read_as_data(tmp_path):
    from geodepth_lite.evaluation import study2

    rec = study2.read_control()
    lines = study2.control_lines(rec)
    assert lines[3] == "seed 3: confirmation set: identical; held-out T x L: identical; close-ups: identical"
    assert lines[4].startswith("A2: Case 2 at lambda2 = 1 vs Case 1, rmse: +0.78 [-1.33, +2.88]")
    assert len(lines) == len(rec["seeds"]) + 6
    (tmp_path / study2.CONTROL_JSON).write_text('{"rows": [], "seeds": [0]}')  # no comparisons
    with pytest.raises(ValueError, match="not a concurrent-control record"):
        study2.read_control(tmp_path)
    (tmp_path / study2.CONTROL_JSON).write_text("[" * 100_000)  # nested past the parser's depth
    with pytest.raises(ValueError, match=study2.CONTROL_JSON):
        study2.read_control(tmp_path)
    (tmp_path / study2.CONTROL_JSON).write_bytes(b" " * (study2.MAX_CONTROL_BYTES + 1))
    with pytest.raises(ValueError, match="larger than"):
        study2.read_control(tmp_path)
