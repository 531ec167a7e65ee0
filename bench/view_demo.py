"""Per-frame cost of watching the demo: the lockstep demo with and without ``--view-save``.

The lockstep demo (``vespro demo --lockstep``: plant, pose server and servo on
one simulated clock, in one process) does the same work on every run of a
configuration, so its figures compare runs: it is run without a view (the
baseline) and with the Rerun view saving to a file (what ``--view-save`` does;
``--view`` streams the same messages), alternately, in this process. Per frame
set: the pose server's step (tracking, then its output handed to the
recording writer and, with the view, to the view's queue; wall time and this
thread's CPU time), and the tracker's own time in this thread's CPU time
(``TrackerOutput.time_ms`` under ``_cpuclock.tracker_clock``). Per run: the
process's CPU time per frame set (all its threads: the plant, the servo, the
rendering, the view's queue feeder). The view's own work (projection, JPEG
encoding, logging) runs in a process of its own and is not counted: on a
machine with a core to spare it costs the loop nothing; on a busy one it
competes with everything else.

Usage: ``python bench/view_demo.py [--duration 3] [--repeats 1] [--object bracket] [--image-every 1]``
"""

from __future__ import annotations

import argparse
import pickle
import sys
import tempfile
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent  # after the packages on the path: bench/servo.py is a script, not servo
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE] + [str(_HERE)]

import numpy as np  # noqa: E402
from _cpuclock import tracker_clock  # noqa: E402
from _table import print_table  # noqa: E402

from cellsim.demo import DemoConfig, run_demo  # noqa: E402
from vespro.server import PoseServer  # noqa: E402


def run(cfg: DemoConfig) -> dict:
    """One lockstep demo; per frame set: step wall and CPU time (ms), tracker CPU time (ms)."""
    wall, cpu = [], []
    step = PoseServer.step

    def timed_step(self, fs):
        t, c = time.perf_counter(), time.thread_time()
        r = step(self, fs)
        cpu.append(time.thread_time() - c)
        wall.append(time.perf_counter() - t)
        return r

    PoseServer.step = timed_step
    p0 = time.process_time()
    try:
        with tracker_clock("cpu"):
            run_demo(cfg, log=lambda m: None)
    finally:
        PoseServer.step = step
    proc = time.process_time() - p0
    with open(Path(cfg.out) / "vision" / "outputs.pkl", "rb") as f:
        tracker = [o.time_ms for o in pickle.load(f)]
    return {"wall": np.array(wall) * 1e3, "cpu": np.array(cpu) * 1e3, "tracker": np.array(tracker),
            "proc_per_frame": proc * 1e3 / max(len(wall), 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=3.0, help="cell time per run, s (26 frame sets a second)")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--object", default="bracket")
    ap.add_argument("--cameras", default="fixed", choices=["fixed", "eye-in-hand", "hybrid"])
    ap.add_argument("--image-every", type=int, default=1)
    args = ap.parse_args()
    runs = {"without view": [], "with --view-save": []}
    with tempfile.TemporaryDirectory() as tmp:
        base = DemoConfig(out=Path(tmp) / "demo", object=args.object, cameras=args.cameras, duration=args.duration,
                          lockstep=True, video=False, view_image_every=args.image_every)
        run(DemoConfig(**{**base.__dict__, "duration": min(args.duration, 1.0)}))  # warm-up: kernels, caches
        for k in range(args.repeats):
            runs["without view"].append(run(base))
            runs["with --view-save"].append(run(DemoConfig(**{**base.__dict__,
                                                                "view_save": Path(tmp) / f"run{k}.rrd"})))
    cols = [("wall", "step wall ms"), ("cpu", "step CPU ms"), ("tracker", "tracker CPU ms")]
    agg = {name: {c: np.concatenate([r[c] for r in rs]) for c, _ in cols} for name, rs in runs.items()}
    proc = {name: float(np.median([r["proc_per_frame"] for r in rs])) for name, rs in runs.items()}
    b = agg["without view"]
    rows = []
    for name, a in agg.items():
        row = [name, len(a["wall"])]
        for c, _ in cols:
            row += [float(np.median(a[c])), float(np.median(a[c]) / np.median(b[c]))]
        row += [float(np.percentile(a["wall"], 99)), proc[name], proc[name] / proc["without view"]]
        rows.append(row)
    heads = ["run", "frames"]
    for _, h in cols:
        heads += [f"{h} (median)", "ratio"]
    heads += ["step wall ms p99", "process CPU ms/frame", "ratio"]
    print_table(heads, rows, title=f"lockstep demo, {args.object}, {args.cameras} cameras, {args.duration:g} s x "
                                   f"{args.repeats} run(s) each; images every {args.image_every} frame(s)")


if __name__ == "__main__":
    main()
