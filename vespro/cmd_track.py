"""``vespro track``: track a recording, write poses.csv."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_tracker_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--init-pose", metavar="x,y,z,qw,qx,qy,qz",
                   help="object pose T_world_object at the first frame (overrides automatic initialisation)")
    p.add_argument("--features", type=int, default=8, help="features selected per camera and frame")
    p.add_argument("--selection", choices=["information", "quality"], default="quality",
                   help="feature selection: information-greedy (log-det) or the classic quality index")
    p.add_argument("--sigma-px", type=float, default=0.5, help="corner measurement noise std, px")
    p.add_argument("--textured", action="store_true",
                   help="the part's faces carry texture or markings: image edges inside its faces do not count "
                        "against a pose found by one camera (by default faces are taken as plain, as CAD parts "
                        "of one material are; see InitOptions.plain_faces)")
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
                         symmetry=args.symmetry)


def init_options(args) -> dict:
    """``InitOptions`` fields the command line sets (``--textured``)."""
    return {"plain_faces": not getattr(args, "textured", False)}


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
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("recording", type=Path)
    p.add_argument("-o", "--output", type=Path, default=Path("poses.csv"), help="output CSV")
    add_tracker_options(p)
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from .recording import Recording, RecordingError
    from .track import make_tracker, parse_pose, track_recording, write_track

    try:
        rec = Recording(args.recording)
    except RecordingError as e:
        print(f"vespro track: {e}", file=sys.stderr)
        return 2
    init_pose = None
    if args.init_pose:
        try:
            init_pose = parse_pose(args.init_pose)
        except ValueError as e:
            print(f"vespro track: {e}", file=sys.stderr)
            return 2
    tracker = make_tracker(rec, tracker_config(args))
    tracker.initializer = initializer_for(args, rec, tracker.model)
    if init_pose is None and tracker.initializer is None:
        print("vespro track: an initial pose is needed: pass --init-pose x,y,z,qw,qx,qy,qz "
              "(the object's pose in the world at the first frame)", file=sys.stderr)
        return 2
    say_symmetry("vespro track", tracker, init_pose is not None, tracker.initializer is not None)
    outs = track_recording(rec, tracker, init_pose, progress=not args.no_progress)
    write_track(args.output, rec, outs)
    n = sum(o.status == "tracking" for o in outs)
    tm = np.median([o.time_ms for o in outs])
    print(f"wrote {args.output}: {n}/{len(outs)} frames tracking, median {tm:.2f} ms per frame")
    return 0
