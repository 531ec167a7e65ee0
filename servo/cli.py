"""The ``servo`` command: the control side's jobs, one subcommand each.

Same registration scheme as ``vespro.cli``: modules expose ``add_parser(subparsers)``.
"""

from __future__ import annotations

import argparse
import importlib
import sys

_COMMANDS: list[tuple[str, str]] = [
    ("servo.cmd_run", "run"),
]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="servo", description="VESPRO control side: 500 Hz visual servoing of the arm.")
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
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
