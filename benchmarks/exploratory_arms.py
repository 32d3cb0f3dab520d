"""The exploratory arms of docs/exploratory_plan.md.

    python benchmarks/exploratory_arms.py match --out notebooks/study2/exploratory
    python benchmarks/exploratory_arms.py run --out notebooks/study2/exploratory
    python benchmarks/exploratory_arms.py floor --out notebooks/study2/exploratory

``match`` measures the plan's ratio of the box-grid SDF term to the frustum term on the teach
profile's silog Case 1 seed 0 predictions over the validation split, and writes ``match.json`` (the
ratio, E1's lambda3 by the plan's rule, the UTC time and the commit). ``run`` reads that record,
trains (or reuses) the 16 runs two side by side, scores them on the studies' sets and writes
``runs.csv``, ``frames.csv.gz``, ``baselines.csv`` and ``provenance.csv`` beside it. ``floor``
looks at E2's predictions: on every 4th confirmation frame (120), the share of valid pixels each run
predicts at the depth head's floor (below 0.02) and below 0.1x the true depth after median scaling,
written to ``floor.json``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from geodepth_lite import utils
from geodepth_lite.evaluation import exploratory, study
from geodepth_lite.training import config, provenance


def match(out: Path) -> int:
    start, (commit, clean) = provenance.utc_now(), provenance.code_version()
    m = exploratory.measure_ratio(config.profile("teach"))
    rec = {"what": "box-grid SDF term / frustum SDF term (val_sdf, view sign, sdf_grid 8) on the teach "
                   "profile's silog Case 1 seed 0 predictions over the validation split",
           **m, "lambda3": exploratory.matched_lambda3(m["ratio"]), "start_utc": start,
           "end_utc": provenance.utc_now(), "git_commit": commit, "git_clean": clean}
    out.mkdir(parents=True, exist_ok=True)
    utils.write_json_atomic(out / exploratory.MATCH_JSON, rec)
    print(f"box grid {m['bbox']:.5f}, frustum {m['frustum']:.5f}, ratio {m['ratio']:.4f} -> "
          f"E1 lambda3 = {rec['lambda3']:g}; wrote {out / exploratory.MATCH_JSON}")
    return 0


def run(out: Path, workers: int) -> int:
    lambda3 = exploratory.read_match(out)["lambda3"]
    prof = config.profile("teach")
    paths = exploratory.train_arms(lambda3, prof, workers=workers, progress=True)
    sets = study.evaluation_sets(prof)
    runs, frames = exploratory.score_arms(paths, sets, progress=True)
    sessions = study.provenance_rows({(exploratory.ARM_CELLS[a][0], c, s): p for (a, c, s), p in paths.items()})
    study.write_tables(out, runs, frames, study.score_baselines(prof, sets), sessions)
    print(f"{len(paths)} runs scored; wrote {out}")
    return 0


def floor(out: Path) -> int:
    import torch

    from geodepth_lite import utils
    from geodepth_lite.training import checkpoint, inference, run_cache

    lam = exploratory.read_match(out)["lambda3"]
    prof = config.profile("teach")
    ds = study.evaluation_sets(prof)[study.PRIMARY]
    batch = inference.collate([ds[i] for i in range(0, len(ds), 4)])
    gt = batch["depth"]
    valid = (gt > 0) & torch.isfinite(gt)
    rows = []
    for arm, case, seed, run in exploratory.arm_runs(lam, prof):
        if arm != "E2":
            continue
        folder = run_cache.checkpoint_dir(run)
        model, _ = checkpoint.load_model(folder / checkpoint.CHECKPOINT_NAME)
        with torch.no_grad():
            pred = model(batch["image"]).float()
        scaled = pred[valid] * (gt[valid].median() / pred[valid].median())
        rows.append({"arm": arm, "seed": seed, "frames": int(gt.shape[0]),
                     "at_floor_pct": 100 * float((pred[valid] < 0.02).float().mean()),
                     "below_tenth_pct": 100 * float((scaled < 0.1 * gt[valid]).float().mean())})
        print(rows[-1])
    utils.write_json_atomic(out / "floor.json", {"what": "E2's valid pixels at the head's floor (< 0.02) and "
                                                         "below 0.1x the true depth (median-scaled), every 4th "
                                                         "confirmation frame", "rows": rows})
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("step", choices=("match", "run", "floor"))
    ap.add_argument("--out", required=True, type=Path, help="the folder of the arms' record and tables")
    ap.add_argument("--workers", type=int, default=2, help="runs side by side (default 2)")
    args = ap.parse_args(argv)
    return {"match": lambda: match(args.out), "run": lambda: run(args.out, args.workers),
            "floor": lambda: floor(args.out)}[args.step]()


if __name__ == "__main__":
    raise SystemExit(main())
