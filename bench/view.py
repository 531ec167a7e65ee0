"""Per-frame cost of watching: tracking a recording with and without the Rerun view.

A recording of the bracket on the conveyor seen by three fixed cameras (made
once, cached under --cache) is tracked from its first pose, alternately without
a view (the baseline, in this process) and with :class:`vespro.viewer.RerunView`
saving to a file (what ``--view-save`` does; ``--view`` streams the same
messages to a viewer). Frames are fed at the capture rate (``--rate``, 26 Hz as
the pose server gets them; 0: as fast as the loop goes). Per frame: the time of
the loop's own work (images decoded beforehand; ``tracker.process`` plus handing
the frame to the view), median and p99 over all frames of all repeats, and the
ratio to the baseline. The view's work (projection, JPEG encoding, logging)
runs in a process of its own, on the other core when there is one.

Usage: ``python bench/view.py [--frames 78] [--repeats 3] [--image-every 1] [--rate 26]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from _table import print_table  # noqa: E402

from vespro.groundtruth import read_groundtruth  # noqa: E402
from vespro.recording import Recording  # noqa: E402
from vespro.rig import load_rig  # noqa: E402
from vespro.sim.cell import CellConfig  # noqa: E402
from vespro.sim.imaging import ImageEffects  # noqa: E402
from vespro.sim.motion import Conveyor  # noqa: E402
from vespro.sim.record import record  # noqa: E402
from vespro.sim.rigs import CAMERAS_DIR  # noqa: E402
from vespro.sim.scene import MODELS_DIR  # noqa: E402
from vespro.track import make_tracker  # noqa: E402
from vespro.tracker import InitResult  # noqa: E402


def run(rec: Recording, framesets, T0, view, rate_hz: float) -> np.ndarray:
    tracker = make_tracker(rec)
    tracker.start(InitResult(T0), framesets[0].t_ns)
    dt = np.zeros(len(framesets))
    t0 = time.perf_counter()
    for i, fs in enumerate(framesets):
        if rate_hz > 0:  # frames arrive at the capture rate, as in the pose server
            time.sleep(max(0.0, t0 + i / rate_hz - time.perf_counter()))
        t = time.perf_counter()
        out = tracker.process(fs)
        if view is not None:
            view.observe(fs, out)
        dt[i] = time.perf_counter() - t
    if view is not None:
        view.close()
    return dt


def main() -> None:
    from vespro.viewer import RerunView

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=78)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--image-every", type=int, default=1)
    ap.add_argument("--rate", type=float, default=26.0, help="frames per second fed to the loop (0: as fast as it goes)")
    ap.add_argument("--cache", type=Path, default=Path("out/bench_view"))
    args = ap.parse_args()
    path = args.cache / f"bracket_fixed3_{args.frames}"
    if not (path / "groundtruth.csv").exists():
        cfg = CellConfig(MODELS_DIR / "objects" / "bracket.stl", load_rig(CAMERAS_DIR / "fixed3.yaml"),
                         effects=ImageEffects(noise_px=0.5), mono=True)
        record(path, cfg, Conveyor(speed=0.05, y0=-0.1), args.frames, "bracket")
    rec = Recording(path)
    _, _, T = read_groundtruth(path)
    framesets = [rec.frameset(i) for i in range(len(rec))]
    run(rec, framesets, T[0], None, 0.0)  # warm-up: compiled kernels, caches
    base, viewed = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeats):
            base.append(run(rec, framesets, T[0], None, args.rate))
            view = RerunView(rec.rig, make_tracker(rec).model, save=Path(tmp) / f"run{k}.rrd", block=False,
                             image_every=args.image_every)
            viewed.append(run(rec, framesets, T[0], view, args.rate))
            if view.dropped:
                print(f"repeat {k}: the view dropped {view.dropped} frames (its process fell behind)")
    b, v = np.concatenate(base) * 1e3, np.concatenate(viewed) * 1e3
    rows = [["without view", float(np.median(b)), float(np.percentile(b, 99)), 1.0, 1.0],
            ["with --view-save", float(np.median(v)), float(np.percentile(v, 99)),
             float(np.median(v) / np.median(b)), float(np.percentile(v, 99) / np.percentile(b, 99))]]
    print_table(["run", "median ms", "p99 ms", "median ratio", "p99 ratio"], rows,
                title=f"per-frame loop time, {len(framesets)} frames x {args.repeats} repeats at "
                      f"{args.rate:g} Hz, three cameras (images every {args.image_every} frame(s))")


if __name__ == "__main__":
    main()
