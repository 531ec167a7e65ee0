"""``vespro demo``: the whole cell running end to end (its options).

The demo drives both sides (the simulated plant, the pose server, the servo), so it
runs from the package above them, :mod:`cellsim`; :mod:`vespro.cli` hands it the
parsed options (:func:`cellsim.cmd_demo.run`).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub) -> None:
    from .options import add_model_unit_option, add_symmetry_option

    p = sub.add_parser(
        "demo", help="run the whole cell: simulated plant, pose server and servo as three processes",
        description=(
            "A part arrives on the conveyor; the pose server (its own process) renders the cameras, "
            "acquires and tracks the part from the images alone and streams poses over a real link; the "
            "servo (its own process) approaches the part and follows it at a stand-off above it; the belt "
            "stops and the arm settles. Afterwards: a summary against ground truth, summary.json, plots, "
            "an overlay video, the servo's time histories and the recording (replay it with vespro eval)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--object", default="bracket",
                   help="box, lblock, bracket, or a model file (STL, OBJ, PLY, ViSP .cao; see --model-unit)")
    add_model_unit_option(p)
    p.add_argument("--cameras", choices=["fixed", "eye-in-hand", "hybrid"], default="hybrid")
    p.add_argument("--duration", type=float, default=40.0, help="seconds of cell time")
    p.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    p.add_argument("--link", choices=["tcp", "serial"], default="tcp",
                   help="tcp: localhost socket; serial: a pseudo-terminal pair at --baud")
    p.add_argument("--baud", type=int, default=115200)
    p.add_argument("--speed", type=float, default=0.05, help="belt speed, m/s")
    p.add_argument("--stop-time", type=float, default=11.0, help="when the belt stops, s")
    p.add_argument("--noise", type=float, default=0.5, help="image pixel noise, px")
    p.add_argument("--no-video", action="store_true")
    p.add_argument("--kill-server-at", type=float, help="kill the pose server after this many seconds (failure test)")
    p.add_argument("--lockstep", action="store_true",
                   help="run everything on one simulated clock in one process (slow machines, exact reproducibility)")
    from .viewer import add_view_options

    add_view_options(p, join=False)  # the demo joins its pose server's and servo's views itself
    add_symmetry_option(p)
