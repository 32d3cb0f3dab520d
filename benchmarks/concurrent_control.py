"""The second study's concurrent control: the first study's silog Case 1, seeds 0-3, retrained with the
code of this checkout, scored on the study's three sets, and compared with the committed rows
(``notebooks/study/runs.csv``) metric by metric; then the second study's six comparisons
(``study2.family``) with those seeds' Case 1 taken from the fresh runs instead of the committed ones.

    python benchmarks/concurrent_control.py --out notebooks/study2/concurrent_control.json

Finished runs in ``$GEODEPTH_LITE_HOME`` are reused (``run_cache``), so a second call only scores.
The record keeps each run's provenance (its log's sessions: UTC start and end, commit, clean tree,
versions, CPU, threads, config hash) and this script's own start, end and commit.
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

from geodepth_lite import utils
from geodepth_lite.evaluation import study, study2
from geodepth_lite.training import config, provenance, run_cache

METRICS = ("abs_rel", "rmse")


def compare(fresh: list[dict], committed: dict) -> list[dict]:
    """One row per (seed, set): the fresh and committed values of every metric, whether all are
    identical as written (6 significant digits), and the relative differences in percent."""
    ref = {(r["case"], r["seed"], r["set"]): r for r in committed["runs"]
           if r["depth_term"] == "silog" and r["case"] == 1}
    out = []
    for row in map(study.typed_row, fresh):
        c = ref[(row["case"], row["seed"], row["set"])]
        out.append({"seed": row["seed"], "set": row["set"],
                    "identical": all(row[m] == c[m] for m in study.METRIC_COLUMNS),
                    "fresh": {m: row[m] for m in study.METRIC_COLUMNS},
                    "committed": {m: c[m] for m in study.METRIC_COLUMNS},
                    "rel_diff_pct": {m: 100 * (row[m] / c[m] - 1) for m in study.METRIC_COLUMNS}})
    return out


def substituted(committed: dict, fresh: list[dict]) -> dict:
    """``committed`` (the first study's tables) with the fresh runs' rows in place of theirs."""
    keys = {(r["depth_term"], r["case"], r["seed"], r["set"]) for r in map(study.typed_row, fresh)}
    tables = copy.deepcopy(committed)
    tables["runs"] = [r for r in tables["runs"] if (r["depth_term"], r["case"], r["seed"], r["set"]) not in keys]
    tables["runs"] += [study.typed_row(r) for r in fresh]
    return tables


def comparisons(tables1: dict, tables2: dict) -> list[dict]:
    return [{k: t[k] for k in ("label", "mean", "low", "high", "verdict")} for t in study2.family(tables1, tables2)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="the JSON record to write")
    ap.add_argument("--seeds", default="0,1,2,3", help="the Case 1 seeds to retrain (default 0,1,2,3)")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    start, (commit, clean) = provenance.utc_now(), provenance.code_version()
    prof = config.profile("teach")
    paths = run_cache.ensure_runs([prof.run(1, s) for s in seeds], workers=1)
    fresh, _ = study.score({("silog", 1, s): p for s, p in zip(seeds, paths)}, study.evaluation_sets(prof))
    tables1, tables2 = study.read_tables(), study2.read_tables()
    rows = compare(fresh, tables1)
    record = {
        "what": "silog Case 1 of the first study retrained with this checkout's code and scored on its three sets",
        "start_utc": start, "end_utc": provenance.utc_now(), "git_commit": commit, "git_clean": clean,
        "seeds": seeds, "rows": rows, "identical_rows": sum(r["identical"] for r in rows), "rows_total": len(rows),
        "runs": {str(s): json.loads((p.parent / "log.json").read_text()).get("provenance")
                 for s, p in zip(seeds, paths)},
        "six_comparisons": {"committed": comparisons(tables1, tables2),
                            "fresh_case1": comparisons(substituted(tables1, fresh), tables2)},
    }
    utils.write_json_atomic(Path(args.out), record)
    print(f"{record['identical_rows']} of {record['rows_total']} rows identical to the committed runs; "
          f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
