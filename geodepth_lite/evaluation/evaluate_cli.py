"""``python -m geodepth_lite evaluate``: the command line of :func:`evaluate.evaluate_checkpoint`.

Checks ``--out`` (a writable folder with room for the tables) and the synthetic dataset's files
against their checksums (``--no-verify`` skips it) before any work, scores the checkpoint and,
unless ``--no-baselines``, the trivial baselines on the same frames, writes the set of result
files (``tables.write_results``) and prints the overall table. ``--check`` only counts the frames
of a public dataset's evaluation subsets under ``--root``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from geodepth_lite import utils
from geodepth_lite.core.errors import UserError
from geodepth_lite.data import datasets, integrity, synth
from geodepth_lite.evaluation import evaluate, tables
from geodepth_lite.training.inference import FLIPS


def add_arguments_evaluate(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--checkpoint", default=None, help="checkpoint.pt written by `train` (not needed with --check)")
    parser.add_argument("--dataset", default="scenario_teach",
                        help="synthetic manifest name or dataset folder, or one of " + ", ".join(datasets.REGISTRY))
    parser.add_argument("--root", default=None, help="folder of a public dataset (its own layout)")
    parser.add_argument("--check", nargs="?", const="", default=None, metavar="MANIFEST",
                        help="public datasets: only count the frames of the paper's evaluation subsets under --root "
                        "and print expected and found counts (exit 0 when all match, 1 otherwise); MANIFEST: a "
                        "subset JSON (default: the dataset's own, data_manifests/eval_subsets/<dataset>.json)")
    parser.add_argument("--split", default="test", help="split of a synthetic dataset (default test)")
    parser.add_argument("--group", default=None, help="public datasets: keep one group (e.g. T1-L1)")
    parser.add_argument("--organ", default=None, help="public datasets: keep one organ (e.g. colon)")
    parser.add_argument("--limit", type=int, default=None, help="public datasets: first N frames only")
    parser.add_argument("--out", default=None, help="output folder (default runs/eval/<dataset>-<split>)")
    parser.add_argument("--error-maps", type=int, default=4, help="number of error-map PNGs (default 4)")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--device", default=None, help="cpu | cuda (default: CUDA when available)")
    parser.add_argument("--flips", choices=tuple(FLIPS), default="none",
                        help="test-time flips averaged into each prediction: none (default, one pass as in the "
                        "paper), h (left-right) or hv (all four mirrorings; what the teach predict model uses)")
    parser.add_argument("--no-baselines", action="store_true",
                        help="skip the trivial baselines (constant, mean depth map, shading prior) in the tables")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--no-verify", action="store_true",
                        help="synthetic datasets: skip checking the files against checksums.sha256 first")


def verify_synthetic(dataset: str, split: str, *, own_train: bool = True, progress: bool = False) -> None:
    """Check a synthetic dataset's files against its checksums (``integrity.check_dataset``) before any work:
    the evaluated ``split``, and its train split (where the mean-depth-map baseline is fitted) when
    ``own_train`` and the dataset has one."""
    path = Path(dataset).expanduser()
    ds_root = (path if path.is_dir() and (path / "manifest.json").exists()
               else synth.ensure_dataset(dataset, progress=progress))
    with_train = own_train and (Path(ds_root) / "train" / "frames.jsonl").is_file()
    integrity.check_dataset(ds_root, {split, "train"} if with_train else {split})


def check_subsets(args: argparse.Namespace, public: bool, kw: dict) -> int:
    """``evaluate --check``: count the frames of a public dataset's evaluation subsets under --root and print
    expected and found counts; 0 when every subset matches, else 1. ``kw``: the --group/--organ/--limit given."""
    if not public:
        raise UserError(f"--check applies to the public datasets ({', '.join(datasets.REGISTRY)}), "
                         f"not {args.dataset!r}")
    if kw:
        raise UserError(f"--{', --'.join(kw)} do not apply to --check, which counts every frame under --root")
    if args.root is None:
        raise UserError(f"--check needs --root, the folder of your copy of {args.dataset}")
    rows = datasets.check_eval_subsets(args.dataset, args.root, args.check or None)
    print(datasets.format_check(rows))
    return 0 if all(r["status"] == "ok" for r in rows) else 1


def run_evaluate(args: argparse.Namespace) -> int:
    """``evaluate``: check --out, verify the dataset, score the checkpoint, write the set of result files.

    --out is checked (a folder that is new, empty or evaluate's own, writable, room for the tables) and
    locked (``utils.FolderLock``: a second evaluation into it is refused, naming this one's PID) before the
    model is loaded; a run that fails leaves no folder it created behind, and never part of a result set
    (``tables.write_results``)."""
    if args.device is not None:
        utils.parse_device(args.device)  # a bad --device: one line, before any work
    public = args.dataset in datasets.REGISTRY
    kw = {k: getattr(args, k) for k in ("group", "organ", "limit") if getattr(args, k) is not None}
    if kw and not public:
        raise UserError(f"--{', --'.join(kw)} apply to the public datasets only, not {args.dataset!r}")
    if args.check is not None:  # the subset report only: no checkpoint, no metrics
        return check_subsets(args, public, kw)
    if args.checkpoint is None:
        raise UserError("--checkpoint is required (except with --check)")
    if args.error_maps < 0:
        raise UserError(f"--error-maps must be >= 0, got {args.error_maps}")
    out = Path(args.out) if args.out else utils.runs_dir() / "eval" / f"{Path(args.dataset).name}-{args.split}"
    # before any work: a refusal costs nothing. A folder of files evaluate did not write is refused.
    if out.is_dir():  # a file of that name: prepare_output_dir says so
        utils.claim_folder(out, tables.MARKER, "evaluate", own_prefixes=(tables.STAGING_PREFIX, tables.PREVIOUS_PREFIX))
    created = utils.missing_dirs(out)
    tables.prepare_output_dir(out, tables.output_bytes_needed(args.error_maps))
    lock = utils.FolderLock(out, "output folder", remove_file=True)  # one evaluation per --out at a time
    try:
        lock.acquire()
        if not public and not args.no_verify:  # a synthetic dataset: its checksums first, before any work
            verify_synthetic(args.dataset, args.split, own_train=not args.no_baselines,
                             progress=not args.no_progress)
        result = evaluate.evaluate_checkpoint(args.checkpoint, args.dataset, split=args.split, root=args.root,
                                              out_dir=out, device=args.device, batch_size=args.batch_size,
                                              error_maps=args.error_maps, progress=not args.no_progress,
                                              baselines=not args.no_baselines, flips=args.flips, **kw)
        utils.mark_folder(out, tables.MARKER, "evaluate")  # its results are in: the folder is evaluate's
    except BaseException:
        lock.release()
        utils.remove_empty_dirs(created)  # a failed run leaves no empty output folder behind
        raise
    lock.release()
    t = tables.metrics_table(result)
    print(tables.markdown_table(t["columns"], t["rows"]))
    print(f"wrote {out / 'metrics.json'}, {out / 'frames.csv'}, {out / 'tables.md'}")
    return 0
