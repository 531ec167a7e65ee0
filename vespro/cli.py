"""The ``vespro`` command: one subcommand per job.

Each subcommand lives in its own module and exposes ``add_parser(subparsers)``,
which registers the subparser and sets ``func(args) -> int``. Register new
subcommands in ``_COMMANDS``; imports are lazy so ``--help`` stays fast.

``demo`` drives both sides (the simulated plant, the pose server, the servo): its
options are registered here like any other command's, and its run is imported from
the package above both sides, ``cellsim``, only when it runs (:func:`run_demo`).
This is the one place in ``vespro`` that reaches ``cellsim``: the command line is
the outermost shell.
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


def run_demo(args) -> int:
    """``vespro demo``: the whole cell, run by ``cellsim`` (above the vision and servo sides)."""
    from cellsim.cmd_demo import run

    return run(args)


#: Commands whose run lives outside ``vespro`` (their ``add_parser`` sets no ``func``).
_RUNS = {"demo": run_demo}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="vespro",
        description="VESPRO vision side: simulated cell, recordings, tracking, pose server.",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for module, name in _COMMANDS:
        importlib.import_module(module).add_parser(sub)
        if name in _RUNS:
            sub.choices[name].set_defaults(func=_RUNS[name])
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
