"""The times and counts the workbook states about itself, each from one record.

The README's notebook table, the notebooks' "Time" lines and docs/timings.md state run times,
reading times and counts; each comes from one of these records, and ``tests/test_stated_numbers.py``
holds every stated figure to it:

- a notebook's run time: ``metadata.papermill.duration`` of the committed executed notebook
  (``run_seconds``), its slowest cell the cells' ``metadata.papermill.duration`` (``slowest_cell``);
- training the ``predict`` model from scratch: the profile's epochs times the mean epoch time that
  notebook 04 prints from the run's log (``predict_training``);
- a training run of the recipe's tuning: its ``minutes`` in ``benchmarks/tuning_log.jsonl``
  (``tuning_minutes``);
- the models the notebooks load (what ``reproduce`` trains and ``bundle`` packs):
  ``reproduce.training_runs`` over every notebook (``model_count``);
- a reading time: the lesson's words (``lesson_words``) at a rate measured on reads of this
  workbook (``reading_rate``, from ``benchmarks/reading_times.json``).
"""

from __future__ import annotations

import json
import math
import re
import statistics
from pathlib import Path

from geodepth_lite import utils
from geodepth_lite.training import config
from geodepth_lite.workbook import reproduce

EXERCISES_HEADING = "## Exercises"  # a lesson's text ends where its graded exercises begin
WORD = re.compile(r"\S*[A-Za-z0-9]\S*")  # a whitespace-separated token with at least one letter or digit
EPOCH_LINE = re.compile(r"training: (\d+(?:\.\d+)?) s per epoch")  # notebook 04's line from the run's log
TRAINING_NOTEBOOK = "04_training"


def _notebook(name: str | Path) -> dict:
    path = Path(name) if Path(name).suffix == ".ipynb" else reproduce.notebooks_dir() / f"{name}.ipynb"
    return json.loads(path.read_text(encoding="utf-8"))


def run_seconds(name: str | Path) -> float:
    """How long the committed notebook's last execution took, from its own metadata (papermill)."""
    return float(_notebook(name)["metadata"]["papermill"]["duration"])


def slowest_cell(name: str | Path) -> tuple[int, float]:
    """(index, seconds) of the committed notebook's slowest cell, from the cells' papermill metadata."""
    cells = _notebook(name)["cells"]
    times = [(i, float(c["metadata"].get("papermill", {}).get("duration") or 0.0)) for i, c in enumerate(cells)]
    return max(times, key=lambda t: t[1])


def printed_text(name: str | Path) -> str:
    """Everything the committed notebook's cells print (stream and text outputs, in order)."""
    texts = []
    for cell in _notebook(name)["cells"]:
        for out in cell.get("outputs", []):
            texts.append("".join(out.get("text", "")))
            texts += ["".join(v) for k, v in out.get("data", {}).items() if k.startswith("text/")]
    return "\n".join(texts)


def predict_training(profile: str = "teach") -> dict:
    """Training the ``predict`` model from scratch: {"epochs", "epoch_s", "seconds"}, the epoch time
    as notebook 04 prints it (the mean ``epoch_s`` of the run's log) and the profile's epochs."""
    found = EPOCH_LINE.findall(printed_text(TRAINING_NOTEBOOK))
    if len(found) != 1:
        raise ValueError(f"{TRAINING_NOTEBOOK}: expected one line 'training: X s per epoch', found {len(found)}")
    epochs = int(config.make_config(profile, 4, 0)["epochs"])
    return {"epochs": epochs, "epoch_s": float(found[0]), "seconds": epochs * float(found[0])}


def tuning_minutes(run: str) -> float:
    """The training minutes of run ``run`` in ``benchmarks/tuning_log.jsonl`` (its first row that has them)."""
    for line in (_root() / "benchmarks" / "tuning_log.jsonl").read_text(encoding="utf-8").splitlines():
        row = json.loads(line) if line.strip() else {}
        if row.get("name") == run and "minutes" in row:
            return float(row["minutes"])
    raise KeyError(f"benchmarks/tuning_log.jsonl: no run {run!r} with minutes")


def model_count(profile: str = "teach") -> int:
    """The number of trained models the notebooks load (``reproduce`` trains them, ``bundle`` packs them)."""
    plan = [(nb, {"profile": profile}) for nb in reproduce.list_notebooks()]
    return len(reproduce.training_runs(config.profile(profile), plan)[0])


def ablation_run_count(profile: str = "teach") -> int:
    """The number of ablation runs (at the profile's own settings) the notebooks load: notebook 05's
    default subset, every case at the profile's seeds."""
    plan = [(nb, {"profile": profile}) for nb in reproduce.list_notebooks()]
    runs = reproduce.training_runs(config.profile(profile), plan)[0]
    return sum(1 for run in runs if not run.overrides)


def lesson_words(name: str | Path) -> int:
    """The words a reader reads in a notebook's lesson: every markdown and code cell's source (not its
    outputs) before the "## Exercises" heading, counted as whitespace-separated tokens that hold at
    least one letter or digit (so a lone ``=``, ``|`` or ``$$`` is not a word, ``x_p`` and ``0.094`` are)."""
    words = 0
    for cell in _notebook(name)["cells"]:
        source = "".join(cell["source"])
        if cell["cell_type"] == "markdown" and source.lstrip().startswith(EXERCISES_HEADING):
            break
        if cell["cell_type"] in ("markdown", "code"):
            words += len(WORD.findall(source))
    return words


def reading_reads() -> dict:
    """``benchmarks/reading_times.json``: timed reads of notebooks, each with its words and minutes."""
    return json.loads((_root() / "benchmarks" / "reading_times.json").read_text(encoding="utf-8"))


def reading_rate(reads: list[dict] | None = None) -> float:
    """Words per minute: the median over timed reads of (the lesson's words at the read) / (minutes)."""
    reads = reading_reads()["reads"] if reads is None else reads
    return statistics.median(r["words"] / r["minutes"] for r in reads)


def reading_minutes(name: str | Path, rate: float | None = None) -> int:
    """A notebook's reading time in whole minutes: its lesson's words at ``rate``, rounded up."""
    return math.ceil(lesson_words(name) / (rate or reading_rate()))


def about(seconds: float) -> str:
    """The rounded form every stated time takes: whole seconds under 100 s, else whole minutes."""
    return f"{round(seconds)} s" if seconds < 100 else f"{round(seconds / 60)} min"


def seconds_of(text: str) -> float:
    """``"385 s"``, ``"6 min"`` or ``"2.9 min"`` in seconds."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*(s|min)\s*", text)
    if not m:
        raise ValueError(f"not a time: {text!r}")
    return float(m.group(1)) * (60 if m.group(2) == "min" else 1)


def _root() -> Path:
    root = utils.project_root()
    if root is None:
        raise FileNotFoundError("benchmarks/ not found: run from a checkout of geodepth-lite")
    return root
