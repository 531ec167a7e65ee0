"""The one base class of every error caused by a user's input.

A command that meets bad input (a malformed file, a model that is not a valid
solid, a rig with a negative focal length...) raises a subclass of
:class:`InputError` whose message names the file, the field and what to do.
The command line (``vespro.cli.main``) prints that message as one line and
exits with status 2; no traceback reaches the user.
"""

from __future__ import annotations

import sys

__all__ = ["InputError", "yaml_problem", "warn"]


class InputError(ValueError):
    """Bad user input; the message is one line naming the file, the field and the fix."""


def yaml_problem(e: Exception) -> str:
    """A YAML parser error as one line: what is wrong and where (line, column)."""
    mark = getattr(e, "problem_mark", None)
    problem = getattr(e, "problem", None) or str(e).splitlines()[0]
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"{problem}{where}"


def warn(command: str, text: str) -> None:
    """Print a line about input that does not stop the command (stderr, prefixed with the command)."""
    print(f"vespro {command}: {text}", file=sys.stderr, flush=True)
