"""The ``vespro`` command: one subcommand per job.

Each subcommand lives in its own module and exposes ``add_parser(subparsers)``,
which registers the subparser and sets ``func(args) -> int``. Register new
subcommands in ``_COMMANDS``; imports are lazy so ``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# (module, one-line help) in the order shown by --help.
_COMMANDS = [
    ("vespro.cmd_record", "record"),
    ("vespro.cmd_track", "track"),
    ("vespro.cmd_eval", "eval"),
    ("vespro.cmd_serve", "serve"),
    ("vespro.cmd_demo", "demo"),
    ("vespro.cmd_calibrate", "calibrate"),
    ("vespro.cmd_bop", "bop"),
    ("vespro.cmd_import", "import"),
    ("vespro.cmd_export", "export"),
]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="vespro",
        description="VESPRO vision side: simulated cell, recordings, tracking, pose server.",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for module, _ in _COMMANDS:
        importlib.import_module(module).add_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from .errors import InputError

    try:
        return int(args.func(args) or 0)
    except InputError as e:
        # Bad input is the user's to fix: one line, no traceback.
        print(f"vespro {args.command}: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
