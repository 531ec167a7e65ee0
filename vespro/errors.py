"""The one base class of every error caused by a user's input.

A command that meets bad input (a malformed file, a model that is not a valid
solid, a rig with a negative focal length...) raises a subclass of
:class:`InputError` whose message names the file, the field and what to do.
The command line (``vespro.cli.main``) prints that message as one line and
exits with status 2; no traceback reaches the user.
"""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """Bad user input; the message is one line naming the file, the field and the fix."""
