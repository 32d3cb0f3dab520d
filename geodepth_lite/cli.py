"""``python -m geodepth_lite <subcommand>``: the command-line entry point.

Each subcommand lives in the module that does the work. That module defines
``add_arguments_<name>(parser)`` and ``run_<name>(args) -> int``; this file only
wires them together, so ``--help`` stays in one place and a module can be read
on its own.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "synth": ("geodepth_lite.synth", "generate a synthetic RGB-depth dataset from a manifest"),
    "verify": ("geodepth_lite.synth", "check a generated dataset against its checksums"),
    "train": ("geodepth_lite.train", "train the depth network (a profile, or your own settings)"),
    "evaluate": ("geodepth_lite.evaluate", "evaluate a checkpoint with the seven depth metrics"),
    "predict": ("geodepth_lite.predict", "zero-shot depth, colorized depth and PLY for your own images or video"),
    "reproduce": ("geodepth_lite.reproduce", "run the numbered notebooks with papermill and write a report"),
}


class UserError(Exception):
    """An error in what the user asked for; printed as one line, exit status 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m geodepth_lite",
        description="geodepth-lite: reproduce Yang et al. (2023), geometry-aware depth in monocular endoscopy.",
    )
    sub = parser.add_subparsers(dest="command", metavar="<command>")
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        module = importlib.import_module(module_name)
        getattr(module, f"add_arguments_{name}")(p)
        p.set_defaults(_run=getattr(module, f"run_{name}"))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except (UserError, ValueError, FileNotFoundError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: everything written so far is complete; run the same command again to continue", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
