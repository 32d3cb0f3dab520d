"""``python -m geodepth_lite train``: the command line of :func:`train.fit` (the loop stays in train.py).

Checks the dataset against its checksums first (``--no-verify`` skips it), trains into
``--run-dir`` (``--resume`` continues an interrupted run) and prints the last epoch's losses.
Under ``torchrun --nproc_per_node N`` every process runs this; rank 0 writes and prints.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from geodepth_lite import utils
from geodepth_lite.data import integrity
from geodepth_lite.data.augment import AUGMENTS
from geodepth_lite.data.datasets import resolve_dataset
from geodepth_lite.training import checkpoint, config, distributed, train


def add_arguments_train(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", default="teach", help="smoke | teach | paper (default teach)")
    parser.add_argument("--case", type=int, default=4, help="ablation case 1-4 (Section 4.2.1; default 4 = all losses)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--run-dir", default=None,
                        help="where checkpoint.pt and log.csv/log.json go "
                             "(default runs/<profile>/train/case<c>_seed<s>)")
    parser.add_argument("--resume", action="store_true", help="continue the checkpoint in --run-dir")
    add_setting_arguments(parser)


# the training settings both train and train-many take: (flag, make_config key)
SETTING_FLAGS = (("--epochs", "epochs"), ("--batch-size", "batch_size"), ("--lr", "lr"),
                 ("--lr-schedule", "lr_schedule"), ("--image-size", "image_size"),
                 ("--border-weight", "border_weight"), ("--input-pad", "input_pad"), ("--augment", "augment"),
                 ("--dataset", "dataset"), ("--encoder-weights", "encoder_weights"),
                 ("--train-frames", "train_frames"), ("--val-frames", "val_frames"))


def add_setting_arguments(parser: argparse.ArgumentParser) -> None:
    """The training settings and run options ``train`` and ``train-many`` share."""
    parser.add_argument("--epochs", type=int, default=None, help="override the profile's epochs")
    parser.add_argument("--batch-size", type=int, default=None, help="override the profile's batch size")
    parser.add_argument("--lr", type=float, default=None, help="override the profile's learning rate")
    parser.add_argument("--lr-schedule", default=None, choices=config.LR_SCHEDULES,
                        help="override the profile's schedule")
    parser.add_argument("--image-size", type=int, default=None, help="override the network input size (multiple of 32)")
    parser.add_argument("--border-weight", type=float, default=None,
                        help="beta: the depth term weighs the image edge 1 + beta times the middle")
    parser.add_argument("--input-pad", type=int, default=None,
                        help="mirrored pixels added around the network's input and cropped off its depth "
                             "(a multiple of 16; 0 = off)")
    parser.add_argument("--augment", default=None, choices=AUGMENTS,
                        help="override the profile's training augmentation (crop: the model for real frames)")
    parser.add_argument("--dataset", default=None, help="manifest name or dataset directory (default: the profile's)")
    parser.add_argument("--encoder-weights", default=None,
                        help="torchvision-style resnet18 ImageNet state dict (.pth) for the encoder")
    parser.add_argument("--train-frames", type=int, default=None,
                        help="train on N evenly spaced training frames (default: the profile's)")
    parser.add_argument("--val-frames", type=int, default=None,
                        help="validate on N evenly spaced validation frames (default: the profile's)")
    parser.add_argument("--device", default=None, help="cpu | cuda | cuda:N (default: CUDA when available)")
    parser.add_argument("--num-workers", type=int, default=None, help="DataLoader workers (default: 0 when cached)")
    parser.add_argument("--no-cache", action="store_true",
                        help="stream from disk instead of caching the dataset in memory")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--keep-best", action="store_true",
                        help="also keep best.pt: the checkpoint of the epoch with the least validation Abs Rel")
    parser.add_argument("--channels-last", action="store_true",
                        help="the network in channels_last memory format (on CUDA: faster tensor-core convolutions)")
    parser.add_argument("--no-verify", action="store_true",
                        help="skip checking the dataset against its checksums.sha256 before training")


def setting_overrides(args: argparse.Namespace) -> dict:
    """The settings given on the command line, as ``config.make_config`` overrides (a frame limit
    left out keeps the profile's, where None would mean every frame)."""
    out = {key: getattr(args, key) for _, key in SETTING_FLAGS}
    for key in ("train_frames", "val_frames"):
        if out[key] is None:
            del out[key]
    return out


def run_train(args: argparse.Namespace) -> int:
    if args.device is not None:
        utils.parse_device(args.device)  # a bad --device: one line, before any work
    cfg = config.make_config(args.profile, args.case, args.seed, **setting_overrides(args))
    run_dir = (Path(args.run_dir) if args.run_dir
               else utils.runs_dir() / args.profile / "train" / f"case{args.case}_seed{args.seed}")
    if args.resume and not (run_dir / checkpoint.CHECKPOINT_NAME).is_file():
        raise FileNotFoundError(f"--resume: no checkpoint to continue in {run_dir} "
                                f"(no {checkpoint.CHECKPOINT_NAME}); leave out --resume to start a new run")
    if distributed.is_main_process():
        # before any work: an unwritable run folder, then a changed or missing frame, is named now, not
        # after an epoch (rank 0 builds a missing dataset here; the other ranks find it complete in fit)
        utils.check_can_create_dir(run_dir)  # creates nothing: fit makes the folder under its lock
        if not args.no_verify:
            integrity.check_dataset(resolve_dataset(cfg, progress=not args.no_progress), ("train", "val"))
    path = train.fit(cfg, run_dir, resume=args.resume, progress=not args.no_progress, device=args.device,
                     num_workers=args.num_workers, cache=False if args.no_cache else "auto",
                     keep_best=args.keep_best, channels_last=args.channels_last)
    if distributed.is_main_process():
        rows = checkpoint.read_log(run_dir)
        last = rows[-1] if rows else {}
        summary = ", ".join(f"{k} {last[k]:.4f}" for k in ("train_total", "val_total", "val_abs_rel", "val_rmse")
                            if k in last)
        print(f"checkpoint: {path} (epoch {last.get('epoch', '?')}/{cfg['epochs']}; {summary})")
        if last:
            print(f"data wait: {100 * last['data_wait_share']:.1f}% of step time")
    distributed.shutdown()
    return 0
