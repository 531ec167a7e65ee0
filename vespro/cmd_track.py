"""``vespro track``: track a recording, write poses.csv."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .options import (add_model_unit_option, add_tracker_options, initializer_for, say_symmetry, tracker_config,
                      workspace_of)
from .recording_report import INPUT_HELP, open_recording, report_images


def add_parser(sub) -> None:
    p = sub.add_parser(
        "track", help="track a recording and write poses.csv",
        description="Track the object through a recording (any recording in the format of "
                    "shared/spec/recording.md; its ground truth is never read) and write the tracker "
                    "output (index,t,pose,status,time_ms,velocity,covariance).",
        epilog=INPUT_HELP,
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
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
    tracker = make_tracker(rec, tracker_config(args), unit=args.model_unit, workspace=workspace_of(args))
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
