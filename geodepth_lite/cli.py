"""``python -m geodepth_lite <subcommand>``: the command-line entry point.

Each subcommand lives in the module that does the work (``train``'s in ``train_cli.py``,
so that ``train.py`` is the training loop alone). That module defines
``add_arguments_<name>(parser)`` and ``run_<name>(args) -> int``; this file only
wires them together, so ``--help`` stays in one place and a module can be read
on its own.

A failure is one line on stderr (``--debug`` or GEODEPTH_DEBUG=1 add the traceback):

- the user's mistake (``UserError`` and its subclasses) or a file or device the system refused
  (an ``OSError``, ``utils.FileProblem`` among them): ``error: ...``, exit status 2;
- anything else is a bug in geodepth-lite: a line that says so, names the command and asks for
  a run with ``--debug``, exit status 1.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import traceback

from geodepth_lite.core.errors import UserError
from geodepth_lite.utils import FileProblem, os_reason

# name -> (module under geodepth_lite, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "synth": ("data.synth", "generate a synthetic RGB-depth dataset from a manifest"),
    "verify": ("data.integrity", "check a generated dataset against its checksums"),
    "train": ("training.train_cli", "train the depth network (a profile, or your own settings)"),
    "train-many": ("training.train_many", "train several cases or seeds at once on one device, one process each"),
    "evaluate": ("evaluation.evaluate_cli", "evaluate a checkpoint with the seven depth metrics"),
    "predict": ("apps.predict", "zero-shot depth, colorized depth and PLY for your own images or video"),
    "reproduce": ("workbook.reproduce", "run the numbered notebooks with papermill and write a report"),
    "convert-checkpoint": ("training.checkpoint", "rewrite checkpoints of the first format so they load safely"),
    "gpu-check": ("apps.gpu_check", "check the CUDA paths in minutes and predict the paper profile's time"),
    "bundle": ("apps.bundle", "pack a profile's trained models into one file to hand out (a class bundle)"),
    "unbundle": ("apps.bundle", "unpack a class bundle, so the notebooks load its models instead of training"),
    "exercises": ("workbook.exercises", "write the student release of the notebooks' graded exercises (nbgrader)"),
    "course": ("workbook.course", "run a course with nbgrader: release, collect, autograde, feedback, grades"),
    "book": ("workbook.book", "publish the executed notebooks as a static web book (Jupyter Book 2, MyST)"),
}


DEBUG_ENV = "GEODEPTH_DEBUG"  # set to 1 for full tracebacks, as --debug does



def build_parser(commands: tuple[str, ...] | None = None) -> argparse.ArgumentParser:
    """The parser of every subcommand, or of ``commands`` alone (only their modules are imported)."""
    parser = argparse.ArgumentParser(
        prog="python -m geodepth_lite",
        description="geodepth-lite: reproduce Yang et al. (2023), geometry-aware depth in monocular endoscopy.",
    )
    parser.add_argument("--debug", action="store_true",
                        help=f"show the full traceback of an error (also: {DEBUG_ENV}=1)")
    sub = parser.add_subparsers(dest="command", metavar="<command>")
    for name, (module_name, help_text) in COMMANDS.items():
        if commands is not None and name not in commands:
            continue
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                       help=f"show the full traceback of an error (also: {DEBUG_ENV}=1)")
        module = importlib.import_module(f"geodepth_lite.{module_name}")
        ident = name.replace("-", "_")
        getattr(module, f"add_arguments_{ident}")(p)
        p.set_defaults(_run=getattr(module, f"run_{ident}"))
    return parser


def error_line(exc: BaseException) -> str:
    """One line saying what went wrong, and with which file where one is known.

    ``utils.FileProblem`` already reads "cannot <action> <path>: <reason>"; another OSError
    becomes "<reason>: <path>"; an error re-raised from a DataLoader worker keeps only its
    original message (its last line).
    """
    if isinstance(exc, FileProblem):
        text = str(exc)
    elif isinstance(exc, OSError) and exc.filename is not None:
        target = f"{exc.filename} -> {exc.filename2}" if exc.filename2 else str(exc.filename)
        text = f"{os_reason(exc)}: {target}"
    else:
        text = str(exc) or type(exc).__name__
    lines = [ln for ln in text.strip().splitlines() if ln.strip()]
    if "Original Traceback" in text and lines:  # re-raised from a DataLoader worker: its last line
        kind, _, message = lines[-1].partition(": ")
        return message if message and kind.endswith(("Error", "Problem")) else lines[-1]
    return " ".join(lines)


def is_user_error(exc: BaseException) -> bool:
    """True for a failure the user can fix (exit 2), False for a bug in geodepth-lite (exit 1)."""
    return isinstance(exc, (UserError, OSError))  # OSError: FileNotFoundError, FileExistsError, FileProblem...


def bug_line(command: str, exc: BaseException) -> str:
    """The one line printed for a bug: what failed, in which command, and how to see more."""
    what = f"{type(exc).__name__}: {error_line(exc)}"
    return (f"error: this is a bug in geodepth-lite ({what}) in the command {command!r}; "
            f"please run it again with --debug to see the traceback, and report it")


def main(argv: list[str] | None = None, commands: tuple[str, ...] | None = None) -> int:
    """Runs one subcommand; ``commands``: the ones this call knows (all by default; ``train-many``
    starts each run as ``main(argv, commands=("train",))``, which imports ``train``'s modules alone)."""
    parser = build_parser(commands)
    args = parser.parse_args(argv)
    debug = args.debug or os.environ.get(DEBUG_ENV, "") not in ("", "0")
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted: everything written so far is complete; run the same command again to continue",
              file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - every failure ends as one line (see the module's docstring)
        if debug:
            traceback.print_exc()
        if is_user_error(exc):
            print(f"error: {error_line(exc)}", file=sys.stderr)
            return 2
        print(bug_line(args.command, exc), file=sys.stderr)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
