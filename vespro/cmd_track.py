"""``vespro track``: track a recording, write poses.csv."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


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


def add_tracker_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--init-pose", metavar="x,y,z,qw,qx,qy,qz|FILE",
                   help="object pose T_world_object at the first frame (overrides automatic initialisation), "
                        "or a file holding it (e.g. the init_pose.txt that `vespro import` writes)")
    p.add_argument("--features", type=int, default=8, help="features selected per camera and frame")
    p.add_argument("--selection", choices=["information", "quality"], default="quality",
                   help="feature selection: information-greedy (log-det) or the classic quality index")
    p.add_argument("--sigma-px", type=float, default=0.5, help="corner measurement noise std, px")
    p.add_argument("--textured", action="store_true",
                   help="the part's faces carry texture or markings: image edges inside its faces do not count "
                        "against a pose found by one camera (by default faces are taken as plain, as CAD parts "
                        "of one material are; see InitOptions.plain_faces)")
    p.add_argument("--decision", choices=["rules", "bank"], default="rules",
                   help="what decides the published status: the confirmation rules, or the hypothesis bank "
                        "weighing the initialiser's poses by the image likelihood (texture counts as clutter "
                        "there: the initialiser then takes every part as textured)")
    add_symmetry_option(p)


def add_symmetry_option(p: argparse.ArgumentParser) -> None:
    from .symmetry import HELP, RULES

    p.add_argument("--symmetry", choices=RULES, default=RULES[0], help=HELP)


def say_symmetry(prog: str, tracker, given: bool, reacquires: bool) -> None:
    """On stderr: the part is symmetric, and which rule picks its frame (nothing otherwise)."""
    from .symmetry import describe

    line = describe(tracker.model.name, len(tracker.symmetries), tracker.config.symmetry, given, reacquires)
    if line:
        print(f"{prog}: {line}", file=sys.stderr, flush=True)


def tracker_config(args):
    from .tracker import TrackerConfig

    return TrackerConfig(features_per_camera=args.features, selection=args.selection, sigma_px=args.sigma_px,
                         decision=getattr(args, "decision", "rules"), symmetry=args.symmetry)


def init_options(args) -> dict:
    """``InitOptions`` fields the command line sets (``--textured``; ``--decision bank``: the bank's
    likelihood takes texture inside the faces as clutter, so the plain-face checks stay off)."""
    return {"plain_faces": not (getattr(args, "textured", False) or getattr(args, "decision", "rules") == "bank")}


def initializer_for(args, rec, model):
    """The automatic initialiser, unless --init-pose was given; None when unavailable."""
    if args.init_pose:
        return None
    try:
        from .init import make_initializer
    except ImportError:
        return None
    return make_initializer(rec.rig, model, **init_options(args))


def add_parser(sub) -> None:
    p = sub.add_parser(
        "track", help="track a recording and write poses.csv",
        description="Track the object through a recording (any recording in the format of "
                    "shared/spec/recording.md; its ground truth is never read) and write the tracker "
                    "output (index,t,pose,status,time_ms,velocity,covariance).",
        epilog=INPUT_HELP,
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    from .cmd_record import add_model_unit_option

    p.add_argument("recording", type=Path)
    p.add_argument("-o", "--output", type=Path, default=Path("poses.csv"), help="output CSV")
    add_tracker_options(p)
    add_model_unit_option(p)
    p.add_argument("--no-progress", action="store_true")
    from .viewer import add_view_options

    add_view_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from .track import make_tracker, parse_pose, track_recording, write_track

    rec = open_recording(args.recording, "track")
    init_pose = None
    if args.init_pose:
        try:
            init_pose = parse_pose(args.init_pose)
        except ValueError as e:
            print(f"vespro track: {e}", file=sys.stderr)
            return 2
    tracker = make_tracker(rec, tracker_config(args), unit=args.model_unit)
    tracker.initializer = initializer_for(args, rec, tracker.model)
    if init_pose is None and tracker.initializer is None:
        print("vespro track: an initial pose is needed: pass --init-pose x,y,z,qw,qx,qy,qz "
              "(the object's pose in the world at the first frame)", file=sys.stderr)
        return 2
    say_symmetry("vespro track", tracker, init_pose is not None, tracker.initializer is not None)
    from .viewer import view_from_args

    view = view_from_args(args, rec.rig, tracker.model, block=True, name="vespro track")
    try:
        outs = track_recording(rec, tracker, init_pose, progress=not args.no_progress,
                               on_output=None if view is None else view.observe)
    finally:
        if view is not None and (line := view.close()):
            print(line, file=sys.stderr)
    write_track(args.output, rec, outs)
    n = sum(o.status == "tracking" for o in outs)
    tm = np.median([o.time_ms for o in outs])
    print(f"wrote {args.output}: {n}/{len(outs)} frames tracking, median {tm:.2f} ms per frame", flush=True)
    report_images(rec, "track")
    return 0
