"""The confirmatory ablation study of docs/study_plan.md: its runs, its scores and its verdicts.

Depth term {L1 (the paper's), silog (the teach recipe)} x geometric losses {off (Case 1), all
(Case 4)}, plus Cases 2 and 3 with silog, each at the same 8 paired seeds: 48 training runs
of the ``teach`` recipe. Every run is scored on the confirmation set (``scenario_study_confirm``,
scenes generated after the plan was committed) and, as secondary sets, on the held-out texture x
lighting groups and the close-ups.

``python -m geodepth_lite reproduce --study`` trains what is missing (seeds 0 and 1 of the silog
cells are the default ``reproduce``'s ablation runs), scores every run and writes three tables
into ``runs/<profile>/study/``:

- ``runs.csv``: one row per run and evaluation set, the seven metrics over the set's frames;
- ``frames.csv.gz``: one row per run and frame of the confirmation set (the primary endpoint's
  raw material: a run's row in ``runs.csv`` is the mean of its frames here);
- ``baselines.csv``: the trivial predictors on every set (no training involved).

The committed copies in ``notebooks/study/`` are what notebook 05 analyses, so its verdicts are
the same on every computer; ``tests/test_results.py`` retrains the default subset and checks it
against them. The analysis itself (:func:`family`) is the plan's: ten paired t-tests over the
seeds, Holm's rule for "differs from zero", Bonferroni intervals for the size.
"""

from __future__ import annotations

import functools
import gzip
import math
from pathlib import Path
from typing import Any

import numpy as np
from scipy import optimize, stats
from tqdm.auto import tqdm

from geodepth_lite import utils
from geodepth_lite.core import metrics
from geodepth_lite.data import synth
from geodepth_lite.evaluation import ablation, evaluate, run_scores
from geodepth_lite.evaluation import tables as tbl
from geodepth_lite.training import checkpoint, provenance, run_cache
from geodepth_lite.training.config import Profile, RunConfig

SEEDS = tuple(range(8))          # the plan's paired seeds
DEFAULT_SEEDS = (0, 1)           # the default reproduce's ablation seeds: a subset a test run retrains
CONFIRM = "scenario_study_confirm"
PRIMARY = "confirmation set"
CLOSEUPS = "close-ups"
DEPTH_TERMS = ("silog", "l1")
DEPTH_LABELS = {"silog": "silog", "l1": "L1"}
CELLS = (("silog", 1), ("silog", 2), ("silog", 3), ("silog", 4), ("l1", 1), ("l1", 4))
INTERACTION = "interaction"      # the "case" of the two interaction tests in family()
TESTS = (("silog", 2), ("silog", 3), ("silog", 4), ("l1", 4), ("l1 - silog", INTERACTION))  # family()'s, in order
METRIC_COLUMNS = tuple(metrics.METRIC_NAMES)


def committed_dir() -> Path:
    """``notebooks/study/``: the committed tables notebook 05 reads."""
    root = utils.project_root()
    if root is None:
        raise FileNotFoundError("notebooks/study/ not found: run from a checkout of geodepth-lite")
    return root / "notebooks" / "study"


def run_overrides(prof: Profile, depth_term: str) -> dict:
    """The settings of a study run beyond the profile's ablation settings: none for the profile's
    own depth term (so those runs are the default ablation's), else ``depth_term``."""
    return {} if prof.get("depth_term") == depth_term else {"depth_term": depth_term}


def study_runs(prof: Profile, seeds=SEEDS) -> list[tuple[str, int, int, RunConfig]]:
    """Every run of the study as (depth term, case, seed, its configuration for ``run_cache.ensure_runs``)."""
    return [(term, case, int(s), prof.run(case, int(s), **run_overrides(prof, term))) for term, case in CELLS
            for s in seeds]


def train(prof: Profile, seeds=SEEDS, *, workers: int | None = None,
          progress: bool = False) -> dict[tuple[str, int, int], Path]:
    """Train (or reuse, or continue) every run of the study; {(depth term, case, seed): checkpoint}.
    Each run trained here is scored by the process that trained it (:func:`score_run`)."""
    runs = study_runs(prof, seeds)
    evaluation_sets(prof, progress=progress)  # built before the workers, which score on them
    paths = run_cache.ensure_runs([run for *_, run in runs], workers=workers, progress=progress,
                                  after=functools.partial(score_run, prof))
    return {(t, c, s): p for (t, c, s, _), p in zip(runs, paths)}


def score_run(prof: Profile, path: str | Path) -> dict:
    """The scores of one trained run on the study's sets (:func:`evaluation_sets`), with the frame
    rows of the confirmation set: computed once and kept in its run folder (``run_scores.scores``)."""
    return run_scores.scores(path, evaluation_sets(prof), frames_of=PRIMARY)


def subset_folders(prof: Profile) -> set[Path]:
    """The run folders of the silog cells at any of the plan's seeds: the runs :func:`retrain_subset`
    reads (with the ``teach`` profile, its default seeds are the default ``reproduce``'s ablation runs)."""
    return {run_cache.checkpoint_dir(run) for t, _, _, run in study_runs(prof) if t == "silog"}


def is_subset_run(prof: Profile, run: RunConfig) -> bool:
    """Whether ``run`` is one that :func:`retrain_subset` reads."""
    return run_cache.checkpoint_dir(run) in subset_folders(prof)


def score_if_subset_run(prof: Profile, path: str | Path) -> None:
    """:func:`score_run` when ``path`` is the checkpoint of a run :func:`retrain_subset` reads;
    nothing otherwise (``reproduce`` trains other models beside the ablation's)."""
    if Path(path).parent in subset_folders(prof):
        score_run(prof, path)


def evaluation_sets(prof: Profile, progress: bool = False) -> dict[str, Any]:
    """{PRIMARY: the confirmation set, ablation.HELDOUT: the three held-out groups together,
    CLOSEUPS: the held-out close-ups}, at the profile's sizes."""
    sets = {PRIMARY: evaluate.open_eval_dataset(str(synth.ensure_dataset(CONFIRM, progress=progress)))}
    sets[ablation.HELDOUT] = ablation.ablation_sets(prof, progress=progress)[ablation.HELDOUT]
    sets[CLOSEUPS] = evaluate.open_eval_dataset(
        str(synth.ensure_dataset("heldout_closeup", overrides=prof["closeup_overrides"], progress=progress)))
    return sets


def _fmt(x: float) -> str:
    return f"{x:.6g}"


def score(checkpoints: dict[tuple[str, int, int], Path], sets: dict[str, Any], *,
          progress: bool = False) -> tuple[list[dict], list[dict]]:
    """Score every run on every set: (run rows, frame rows of the primary set). A run is scored once:
    its scores are kept in its run folder and read from there while its checkpoint, the sets and
    the scoring code stay the same (``run_scores.scores``)."""
    runs, frames = [], []
    for (term, case, seed), path in tqdm(sorted(checkpoints.items()), desc="score the study's runs",
                                         disable=not progress):
        kept = run_scores.scores(path, sets, frames_of=PRIMARY if PRIMARY in sets else None)
        for name in sets:
            r = kept["sets"][name]
            runs.append({"depth_term": term, "case": case, "seed": seed, "set": name, "frames": r["n"],
                         **{m: _fmt(r["overall"][m]) for m in METRIC_COLUMNS}})
            if name == PRIMARY:
                frames += [{"depth_term": term, "case": case, "seed": seed, "index": f["index"],
                            "organ": f["organ"], "group": f["group"],
                            **{m: _fmt(math.nan if f[m] is None else f[m]) for m in (*METRIC_COLUMNS, "ratio")}}
                           for f in kept["frames"]]
    return runs, frames


def score_baselines(prof: Profile, sets: dict[str, Any]) -> list[dict]:
    """The trivial predictors on every set, one row each (``ablation.baseline_scores``)."""
    return [{"set": name, "baseline": b, **{m: _fmt(v[m]) for m in METRIC_COLUMNS}}
            for name, per in ablation.baseline_scores(prof, sets).items() for b, v in per.items()]


def write_tables(out: str | Path, runs: list[dict], frames: list[dict], baselines: list[dict],
                 sessions: list[dict] | None = None) -> Path:
    """Write runs.csv, frames.csv.gz and baselines.csv into ``out`` (each file whole or not at all), and
    provenance.csv from ``sessions`` (:func:`provenance_rows`) when given."""
    out = utils.check_output_dir(out)
    utils.write_bytes_atomic(out / "runs.csv", tbl.csv_bytes(runs))
    utils.write_bytes_atomic(out / "frames.csv.gz", gzip.compress(tbl.csv_bytes(frames), mtime=0))
    utils.write_bytes_atomic(out / "baselines.csv", tbl.csv_bytes(baselines))
    if sessions is not None:
        utils.write_bytes_atomic(out / PROVENANCE_CSV, tbl.csv_bytes(sessions))
    return out


PROVENANCE_CSV = "provenance.csv"


def provenance_rows(checkpoints: dict[tuple[str, int, int], Path]) -> list[dict]:
    """One row per training session of each run, from its ``log.json``: (depth term, case, seed, the
    session's number) and the session's record (``provenance.FIELDS``: UTC start and end, commit and
    clean tree, versions, CPU, threads, device, config hash). A run whose log holds no record (trained
    before runs recorded one) gets one row with those fields empty: nothing is filled in."""
    rows = []
    for (term, case, seed), path in sorted(checkpoints.items()):
        records = provenance.earlier_sessions(checkpoint.read_log_file(Path(path).parent)) or [{}]
        for i, rec in enumerate(records):
            rows.append({"depth_term": term, "case": case, "seed": seed, "session": i,
                         **{k: "" if rec.get(k) is None else rec[k] for k in provenance.FIELDS}})
    return rows


def _read(path: Path) -> list[dict]:
    return tbl.read_csv(path, " (`python -m geodepth_lite reproduce --study` writes it)")


def read_tables(folder: str | Path | None = None, frames: bool = False) -> dict:
    """The study's tables from ``folder`` (default: the committed ``notebooks/study/``), numbers as
    floats: {"runs": [...], "baselines": [...], "frames": [...] (only with ``frames``)}."""
    folder = Path(folder) if folder else committed_dir()
    tables = {"runs": [typed_row(r) for r in _read(folder / "runs.csv")],
              "baselines": [typed_row(r) for r in _read(folder / "baselines.csv")]}
    if frames:
        tables["frames"] = [typed_row(r) for r in _read(folder / "frames.csv.gz")]
    return tables


def typed_row(row: dict) -> dict:
    """A table row with its numbers as int or float (as a CSV round trip gives them)."""
    out = {}
    for k, v in row.items():
        if k in ("case", "seed", "index", "frames"):
            out[k] = int(v)
        elif k in (*METRIC_COLUMNS, "ratio"):
            out[k] = float(v)
        else:
            out[k] = v
    return out


def check_tables(tables: dict, frames_per_run: int | None = None, want=None) -> list[str]:
    """What is wrong with study tables read with ``frames=True``, one line each (none: they hold
    the plan's study). Every run of :func:`study_runs` has one row per evaluation set; its row on
    the confirmation set is the mean of its frame rows (to the tables' 6 significant digits), and
    each run has ``frames_per_run`` frames (default: as many as its row says). A metric changed in
    ``runs.csv`` alone, or a run left out or added, is named. ``want``: the runs expected, as
    (depth term, case, seed) (default: this study's)."""
    problems = []
    want = set(want) if want is not None else {(t, c, int(s)) for t, c in CELLS for s in SEEDS}
    sets = {r["set"] for r in tables["runs"]}
    have: dict = {}
    for r in tables["runs"]:
        have.setdefault((r["depth_term"], r["case"], r["seed"]), {})[r["set"]] = r
    problems += [f"run {k} is not in the plan" for k in sorted(set(have) - want)]
    problems += [f"run {k} is missing" for k in sorted(want - set(have))]
    problems += [f"run {k} has no row for {sorted(sets - set(v))}" for k, v in sorted(have.items()) if set(v) != sets]
    frames: dict = {}
    for f in tables["frames"]:
        frames.setdefault((f["depth_term"], f["case"], f["seed"]), []).append(f)
    for key in sorted(want & set(have)):
        row, fs = have[key].get(PRIMARY), frames.get(key, [])
        if row is None:
            continue
        n = frames_per_run or row["frames"]
        if len(fs) != n or len({f["index"] for f in fs}) != n:
            problems.append(f"run {key}: {len(fs)} frame rows, {len({f['index'] for f in fs})} distinct, expected {n}")
            continue
        for m in METRIC_COLUMNS:
            mean = float(np.mean([f[m] for f in fs]))
            if not math.isclose(row[m], mean, rel_tol=2e-5, abs_tol=1e-9):
                problems.append(f"run {key}, {m} on the {PRIMARY}: runs.csv says {row[m]:.6g}, "
                                f"the mean of its frames is {mean:.6g}")
    return problems


def retrain_subset(prof: Profile, seeds=DEFAULT_SEEDS, *, workers: int | None = None,
                   progress: bool = False, baselines: bool = True) -> dict:
    """The silog cells at ``seeds`` trained (or reused) on this computer and scored on the study's
    sets: tables like :func:`read_tables`'s, plus "checkpoints" {(term, case, seed): path}. With the
    default seeds these are the default ``reproduce``'s ablation runs. Each run is scored once, by
    the process that trains it or at first need, and read from its run folder after that (:func:`score`).
    ``baselines=False`` leaves the trivial predictors out ("baselines" is empty): they involve no
    training, and the committed tables hold them."""
    runs = [r for r in study_runs(prof, seeds) if r[0] == "silog"]
    sets = evaluation_sets(prof, progress=progress)  # built before the workers, which score on them
    paths = run_cache.ensure_runs([run for *_, run in runs], workers=workers, progress=progress,
                                  after=functools.partial(score_run, prof))
    checkpoints = {(t, c, s): p for (t, c, s, _), p in zip(runs, paths)}
    rows, _ = score(checkpoints, sets, progress=progress)
    return {"runs": [typed_row(r) for r in rows],
            "baselines": [typed_row(r) for r in score_baselines(prof, sets)] if baselines else [],
            "checkpoints": checkpoints}


def as_result(tables: dict, depth_term: str, seeds=None) -> dict:
    """The runs of one depth term in ``ablation``'s result form ({"cases", "seeds", "scores":
    {(case, seed): {set: metrics}}, "baselines": {set: {baseline: metrics}}}), for its tables
    and per-case statistics. ``seeds`` keeps only those seeds (default: all in the tables)."""
    rows = [r for r in tables["runs"] if r["depth_term"] == depth_term and (seeds is None or r["seed"] in seeds)]
    scores: dict = {}
    for r in rows:
        scores.setdefault((r["case"], r["seed"]), {})[r["set"]] = {m: r[m] for m in METRIC_COLUMNS}
    baselines: dict = {}
    for r in tables["baselines"]:
        baselines.setdefault(r["set"], {})[r["baseline"]] = {m: r[m] for m in METRIC_COLUMNS}
    return {"cases": sorted({c for c, _ in scores}), "seeds": sorted({s for _, s in scores}), "scores": scores,
            "baselines": baselines}


def relative_changes(tables: dict, depth_term: str, case: int, metric: str, set_name: str = PRIMARY,
                     seeds=None) -> np.ndarray:
    """r_s = 100 (m(case, s) / m(Case 1, s) - 1) for each seed s (sorted), one depth term."""
    res = as_result(tables, depth_term, seeds)
    a = np.array([res["scores"][(case, s)][set_name][metric] for s in res["seeds"]])
    b = np.array([res["scores"][(1, s)][set_name][metric] for s in res["seeds"]])
    return 100 * (a / b - 1)


def interaction_verdict(low: float, high: float, mean: float, rejected: bool,
                        max_width: float | None = None) -> str:
    """The plan's words for the interaction d_s = r_s(L1, Case 4) - r_s(silog, Case 4) (negative: the
    geometric losses reduce the error more under L1). Zero kept with an interval wider than
    ``max_width`` points (None: no bound) reads "undecided" (the plan's amendment of the "too wide"
    bound, :data:`ablation.WIDTH_BOUND`)."""
    if rejected and mean < 0:
        return f"the geometric losses help more against the L1 baseline (by {-high:.1f} to {-low:.1f} points)"
    if rejected:
        return "opposite (the geometric losses help more against the silog baseline)"
    if ablation.too_wide(low, high, max_width):
        return "undecided"
    return f"no depth-term dependence detected; differences beyond {max(abs(low), abs(high)):.1f} points excluded"


def paired_t_p(values) -> float:
    """The two-sided p of the paired t-test of mean 0 over ``values`` (one per seed): 1 for a single
    value (nothing is known about the spread); for values all equal, 0 unless they are 0."""
    v = np.asarray(values, dtype=np.float64)
    if v.size < 2:
        return 1.0
    if v.std() > 1e-9 * (1 + abs(v.mean())):
        return float(stats.ttest_1samp(v, 0.0).pvalue)
    return 1.0 if abs(v.mean()) <= 1e-9 else 0.0


def family(tables: dict, set_name: str = PRIMARY, seeds=None, alpha: float = ablation.ALPHA,
           max_width: float | None = ablation.WIDTH_BOUND) -> list[dict]:
    """The plan's ten tests on ``set_name``, in order: silog Cases 2, 3, 4 against Case 1, L1 Case 4
    against Case 1, and the interaction, each for RMSE and Abs Rel.

    Each is a paired t-test over the seeds of r_s (percent of Case 1) or, for the interaction, of
    d_s = r_s(L1) - r_s(silog) (points). Returns one dict per test: "term", "case" (or INTERACTION),
    "metric", "values", "mean", "sd", "p", "low"/"high" (the Bonferroni interval at 1 - alpha / 10),
    "rejected" (Holm), "paper" (None for the interaction), "too_wide" (high - low > ``max_width``,
    the plan's amended bound; None: no bound), "verdict".
    """
    out = []
    for term, case, metric, v in _test_values(tables, TESTS, set_name, seeds):
        p = paired_t_p(v)
        out.append({"term": term, "case": case, "metric": metric, "values": v.tolist(), "mean": float(v.mean()),
                    "sd": float(v.std(ddof=1)) if v.size > 1 else math.nan, "p": p})
    level = 1 - alpha / len(out)
    for t, rejected in zip(out, ablation.holm([t["p"] for t in out], alpha)):
        _, t["low"], t["high"] = ablation.t_interval(t["values"], level)
        t["rejected"], t["level"] = rejected, level
        t["too_wide"] = ablation.too_wide(t["low"], t["high"], max_width)
        if t["case"] == INTERACTION:
            t["paper"] = None
            t["verdict"] = interaction_verdict(t["low"], t["high"], t["mean"], rejected, max_width)
        else:
            t["paper"] = ablation.PAPER_REDUCTION[t["case"]][t["metric"]]
            t["verdict"] = ablation.size_verdict(t["low"], t["high"], t["mean"], t["paper"], rejected, max_width)
    return out


def comparison_key(t: dict, set_name: str = PRIMARY) -> str:
    """The record key stem of a test of :func:`family`: "paired | <set> | <metric> | <term> case<k>"."""
    who = f"{t['term']} case{t['case']}" if t["case"] != INTERACTION else t["term"]
    return f"paired | {set_name} | {t['metric']} | {who}"


def paired_record(tables: dict, seeds=None, set_name: str = PRIMARY) -> dict[str, float]:
    """What the family's intervals are made of, rounded to 0.01: per test of :func:`family` on
    ``set_name`` that ``seeds`` allow, the mean and sd of its per-seed values ("... | mean %",
    "... | sd %"), and the number of seeds ("paired | seeds"). Tests that need depth terms
    missing from the tables (the default subset trains silog only) are left out."""
    terms = {r["depth_term"] for r in tables["runs"]}
    out = {}
    for t in _available_tests(tables, terms, set_name, seeds):
        out[f"{comparison_key(t, set_name)} | mean %"] = round(t["mean"], 2)
        out[f"{comparison_key(t, set_name)} | sd %"] = round(t["sd"], 2)
    out["paired | seeds"] = float(len(as_result(tables, "silog", seeds)["seeds"]))
    return out


def _available_tests(tables: dict, terms: set, set_name: str, seeds) -> list[dict]:
    if terms >= set(DEPTH_TERMS):
        return family(tables, set_name, seeds)
    specs = [(term, case) for term, case in TESTS if term == "silog"]
    return [{"term": term, "case": case, "metric": metric, "mean": float(v.mean()),
             "sd": float(v.std(ddof=1)) if v.size > 1 else math.nan}
            for term, case, metric, v in _test_values(tables, specs, set_name, seeds)]


def _test_values(tables: dict, specs, set_name: str, seeds):
    """(term, case, metric, per-seed values) for each (term, case) of ``specs`` and each paired
    metric, RMSE first as the plan lists them: r_s, or d_s for the interaction."""
    for term, case in specs:
        for metric in ablation.PAIRED_METRICS[::-1]:
            if case == INTERACTION:
                v = (relative_changes(tables, "l1", 4, metric, set_name, seeds)
                     - relative_changes(tables, "silog", 4, metric, set_name, seeds))
            else:
                v = relative_changes(tables, term, case, metric, set_name, seeds)
            yield term, case, metric, v


def run_record(tables: dict, seeds=None, sets=None, digits: int = 4) -> dict[str, float]:
    """Every run's metrics, flat: {"<term> case<k> seed<s> | <set> | <metric>": value}, for the
    runs of ``seeds`` on ``sets`` (default: all)."""
    return {f"{r['depth_term']} case{r['case']} seed{r['seed']} | {r['set']} | {m}": round(r[m], digits)
            for r in tables["runs"] if (seeds is None or r["seed"] in seeds) and (sets is None or r["set"] in sets)
            for m in METRIC_COLUMNS}


def label(t: dict) -> str:
    """A test of :func:`family` in words: "Case 3 vs Case 1 (silog)", "interaction (L1 - silog), Case 4"."""
    if t["case"] == INTERACTION:
        return "interaction: Case 4 vs Case 1 under L1 minus under silog"
    return f"Case {t['case']} vs Case 1 ({DEPTH_LABELS[t['term']]})"


def cell_stats(tables: dict, set_name: str, metric: str) -> dict[tuple[str, int], tuple[float, float]]:
    """{(depth term, case): (mean, sample sd) over the seeds} of ``metric`` on ``set_name``."""
    out = {}
    for term, case in CELLS:
        v = np.array([r[metric] for r in tables["runs"]
                      if (r["depth_term"], r["case"], r["set"]) == (term, case, set_name)])
        if v.size:
            out[(term, case)] = (float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else math.nan)
    return out


def claims(tables: dict, margin: float = 0.2) -> list[str]:
    """The study's conclusions as sentences, computed from the tables: one verdict per test of
    :func:`family` on the confirmation set, then how every run stands against the baselines."""
    lines = [f"{PRIMARY}, {tbl.METRIC_LABELS[t['metric']]}: {label(t)} -> {t['verdict']}" for t in family(tables)]
    best = min(r["abs_rel"] for r in tables["baselines"] if r["set"] == PRIMARY)
    runs = [r for r in tables["runs"] if r["set"] == PRIMARY]
    for term in DEPTH_TERMS:
        mine = [r for r in runs if r["depth_term"] == term]
        lines.append(f"{PRIMARY}, {DEPTH_LABELS[term]} runs below every baseline in Abs Rel: "
                     f"{sum(r['abs_rel'] < best for r in mine)} of {len(mine)}; at least {100 * margin:.0f}% below "
                     f"the best baseline: {sum(r['abs_rel'] <= (1 - margin) * best for r in mine)} of {len(mine)}")
    return lines


FRESH_LEVEL = 0.99  # the chance that a correct retraining passes all of check_subset's checks together


def prediction_ranges(committed: dict, stem: str, n_fresh: int, n_checks: int,
                      level: float = FRESH_LEVEL) -> tuple[tuple[float, float], tuple[float, float]]:
    """Where a fresh draw of ``n_fresh`` seeds of test ``stem`` should fall, given the committed
    record's mean and sd over its n seeds (:func:`paired_record`): ((low, high) of the mean,
    (low, high) of the sd), each at level 1 - (1 - ``level``) / ``n_checks`` (Bonferroni over the
    ``n_checks`` checks made together). The mean's range is the prediction interval
    mean +/- t(n - 1) sd sqrt(1/n + 1/n_fresh); the sd's comes from the F distribution of the ratio
    of two sample variances (n_fresh - 1 and n - 1 degrees of freedom). The committed sd stands in
    for the true one."""
    n = int(committed["paired | seeds"])
    mean, sd = committed[f"{stem} | mean %"], committed[f"{stem} | sd %"]
    a = (1 - level) / n_checks
    tol = float(stats.t.ppf(1 - a / 2, n - 1)) * sd * math.sqrt(1 / n + 1 / n_fresh)
    f_lo, f_hi = stats.f.ppf([a / 2, 1 - a / 2], n_fresh - 1, n - 1)
    return (mean - tol, mean + tol), (sd * math.sqrt(f_lo), sd * math.sqrt(f_hi))


def check_subset(fresh: dict, committed: dict, level: float = FRESH_LEVEL) -> list[dict]:
    """Each test of the ``fresh`` record (a retrained subset, :func:`paired_record`) against the
    ``committed`` one: its mean and sd within :func:`prediction_ranges` (all checks together at
    ``level``). One dict per test: "test", "study", "here" (mean (sd) as text), "range" (the fresh
    mean's), "ok", and "problems" (one line per number outside its range)."""
    stems = [k[: -len(" | mean %")] for k in fresh if k.endswith(" | mean %")]
    missing = [s for s in stems if f"{s} | mean %" not in committed]
    if missing:
        raise KeyError(f"the committed record has no test {missing[0]!r}")
    n_fresh, out = int(fresh["paired | seeds"]), []
    for stem in stems:
        (m_lo, m_hi), (s_lo, s_hi) = prediction_ranges(committed, stem, n_fresh, 2 * len(stems), level)
        m, s = fresh[f"{stem} | mean %"], fresh[f"{stem} | sd %"]
        problems = []
        if not m_lo <= m <= m_hi:
            problems.append(f"{stem} | mean %: study {committed[f'{stem} | mean %']}, here {m} "
                            f"(range {m_lo:.2f} to {m_hi:.2f})")
        if not s_lo <= s <= s_hi:
            problems.append(f"{stem} | sd %: study {committed[f'{stem} | sd %']}, here {s} "
                            f"(range {s_lo:.2f} to {s_hi:.2f})")
        out.append({"test": stem.removeprefix("paired | "),
                    "study": f"{committed[f'{stem} | mean %']:+.2f} ({committed[f'{stem} | sd %']:.2f})",
                    "here": f"{m:+.2f} ({s:.2f})", "range": f"{m_lo:+.2f} to {m_hi:+.2f}", "ok": not problems,
                    "problems": problems})
    return out


def checked_stems(committed: dict) -> list[str]:
    """The tests the cross-machine check holds a retrained default subset to: the silog ones of the
    ``committed`` record (:func:`paired_record`), in its order."""
    return [k[: -len(" | mean %")] for k in committed if k.endswith(" | mean %") and "| silog case" in k]


def check_flag_rate(committed: dict, stem: str, shift: float, n_fresh: int = len(DEFAULT_SEEDS),
                    n_checks: int | None = None, level: float = FRESH_LEVEL) -> float:
    """The chance that :func:`check_subset` flags test ``stem`` of a retraining of ``n_fresh`` seeds
    whose true mean change is the committed mean + ``shift`` (points), analytically: the per-seed
    changes normal with the committed sd as their true sd, so the fresh mean is normal with sd
    sd / sqrt(n_fresh) and, independent of it, (n_fresh - 1) s^2 / sd^2 is chi-square with n_fresh - 1
    degrees of freedom. Flagged when the mean or the sd falls outside :func:`prediction_ranges`
    (``n_checks`` checks together; default: two per test of :func:`checked_stems`)."""
    n_checks = n_checks or 2 * len(checked_stems(committed))
    (lo, hi), (s_lo, s_hi) = prediction_ranges(committed, stem, n_fresh, n_checks, level)
    mean, sd = committed[f"{stem} | mean %"], committed[f"{stem} | sd %"]
    se = sd / math.sqrt(n_fresh)
    p_mean = float(stats.norm.cdf((lo - mean - shift) / se) + stats.norm.sf((hi - mean - shift) / se))
    k = n_fresh - 1
    p_sd = float(stats.chi2.cdf(k * (s_lo / sd) ** 2, k) + stats.chi2.sf(k * (s_hi / sd) ** 2, k))
    return 1 - (1 - p_mean) * (1 - p_sd)


def detectable_shifts(committed: dict, power: float = 0.8, n_fresh: int = len(DEFAULT_SEEDS),
                      level: float = FRESH_LEVEL, stems=None) -> list[dict]:
    """What the cross-machine check can see: for each test it checks (default :func:`checked_stems`),
    the smallest shift of the true mean change that :func:`check_subset` flags with probability
    ``power`` (:func:`check_flag_rate`, analytic; the range is symmetric, so a shift of the same
    size either way). One dict per test: "test", "mean", "sd" (the committed record's), "range"
    (where a fresh mean is accepted), "shift" (points), "caught" (the true means caught with
    ``power``: at most mean - shift or at least mean + shift), "flag_if_correct" (the chance that
    a correct retraining is flagged on this test) and "flag_if_zero" (the chance when the true
    change is 0: the effect absent)."""
    stems = list(stems) if stems is not None else checked_stems(committed)
    n_checks = 2 * len(stems)
    out = []
    for stem in stems:
        mean, sd = committed[f"{stem} | mean %"], committed[f"{stem} | sd %"]
        (lo, hi), _ = prediction_ranges(committed, stem, n_fresh, n_checks, level)
        rate = lambda d: check_flag_rate(committed, stem, d, n_fresh, n_checks, level)  # noqa: E731
        top = hi - lo + 10 * sd + 1.0
        shift = float(optimize.brentq(lambda d: rate(d) - power, 0.0, top, xtol=1e-6))
        out.append({"test": stem.removeprefix("paired | "), "mean": mean, "sd": sd, "range": (lo, hi),
                    "shift": shift, "caught": (mean - shift, mean + shift), "flag_if_correct": rate(0.0),
                    "flag_if_zero": rate(-mean)})
    return out


def detectable_markdown(committed: dict, power: float = 0.8, n_fresh: int = len(DEFAULT_SEEDS)) -> str:
    """:func:`detectable_shifts` of the ``committed`` record for a retraining of ``n_fresh`` seeds as
    the Markdown table of docs/training_and_evaluation.md ("What the cross-machine check can see")."""
    rows = [[s["test"].split(" | ", 1)[1].replace(" | ", ", "), f"{s['mean']:+.2f} ({s['sd']:.2f})",
             f"{s['range'][0]:+.1f} to {s['range'][1]:+.1f}", f"{s['shift']:.1f}",
             f"<= {s['caught'][0]:+.1f} or >= {s['caught'][1]:+.1f}", f"{100 * s['flag_if_zero']:.1f}%"]
            for s in detectable_shifts(committed, power, n_fresh)]
    return tbl.markdown_table(["test", "study: mean (sd)", f"fresh {n_fresh}-seed mean accepted",
                               f"shift caught with {100 * power:.0f}% power (points)", "true mean caught",
                               "flagged if the true change is 0"], rows)
