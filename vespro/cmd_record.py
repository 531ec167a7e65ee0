"""``vespro record``: write a recording of a simulated scenario."""

from __future__ import annotations

import argparse
from pathlib import Path

from .sim.scenario import add_scenario_options, build_config


def add_parser(sub) -> None:
    p = sub.add_parser(
        "record",
        help="simulate the cell and write a recording (shared/spec/recording.md)",
        description=(
            "Simulate the robotic cell (MuJoCo physics at 500 Hz, cameras at --rate) and write a "
            "recording: frames of every rig camera, the rig, the object model, measured eye-in-hand "
            "camera poses, and ground truth in groundtruth.csv (for evaluators only)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("out", type=Path, help="recording folder to create")
    p.add_argument("--frames", type=int, default=78, help="number of capture instants")
    add_scenario_options(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing recording folder")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    import sys

    from .rig import RigError
    from .sim.record import record

    try:
        config, motion, name = build_config(args)
    except (ValueError, RigError) as e:
        print(f"vespro record: {e}", file=sys.stderr)
        return 2
    out = record(args.out, config, motion, args.frames, name, overwrite=args.overwrite,
                 progress=not args.no_progress)
    print(f"wrote {out} ({args.frames} frames, cameras {', '.join(config.rig.names)})")
    return 0
