"""A recording as a command reads it: its warnings when it opens, its unusable images at the end.

:data:`INPUT_HELP` says the same in the ``--help`` of the commands that read recordings.
"""

from __future__ import annotations

__all__ = ["INPUT_HELP", "open_recording", "report_images"]

#: The --help text on bad input, shared by the commands that read recordings.
INPUT_HELP = (
    "Bad input: a malformed recording file (meta.yaml, cameras.yaml, frames.csv, groundtruth.csv, the model) "
    "stops the command before any work with one line naming the file, the field and what to do, exit status 2. "
    "An image that cannot be used (missing, truncated, unreadable, not 8-bit, or of another size than "
    "cameras.yaml gives) is skipped for that frame (the tracker does without that camera) and counted: one "
    "line per camera on stderr at the end gives the counts per reason and the first file of each. A camera "
    "that gave no usable image in the whole run is named in a warning line; the exit status stays 0 since "
    "the poses come from the other cameras, but when no camera gave a usable image it is 2. Images past the "
    "last row of frames.csv (a frames.csv cut short) are not used and a warning gives their number.")


def open_recording(path, command: str):
    """Open a recording for a command, printing its warnings (stderr); raises RecordingError."""
    from .errors import warn
    from .recording import Recording

    rec = Recording(path)
    for w in rec.warnings:
        warn(command, f"warning: {w}")
    return rec


def report_images(rec, command: str) -> None:
    """End of a run: the image report on stderr; RecordingError when no camera gave a usable image."""
    from .errors import warn
    from .recording import RecordingError

    tally = rec.images
    for line in tally.report():
        warn(command, line)
    dead = tally.dead()
    if dead and len(dead) == len(tally.cameras):
        raise RecordingError(f"{rec.path / 'frames'}: no camera gave a usable image in the whole run "
                             "(see the lines above)")
