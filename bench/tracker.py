"""Per-frame tracker time by stage, for 1, 2 and 3 cameras.

For each rig (fixed1, fixed2, fixed3) a short recording of the bracket on the
conveyor (0.5 px pixel noise) is made once (cached under --cache), then tracked
from its first pose. Printed per rig: the median and p99 of each stage
(visibility, selection, extraction, update) and of the whole frame, beside the
per-frame baseline run in this process on the same detections (OpenCV
solvePnP per camera, no filter), and the ratio. Accuracy (position RMSE) is
printed too, so speed is never read without it.

With one camera the filter is also updated with the pose the part's edges fit
(``TrackerConfig.edge_aid``, stage "edges"); that rig is tracked a second time
on corners alone, and the rows "whole frame, corners only" give its time and
accuracy for comparison.

Each rig is also tracked with the hypothesis bank deciding (``TrackerConfig.decision``
``"bank"``): its weighing stage and whole frame beside the default's, from the same start.

With ``--mono`` the cameras are monochrome (8-bit grey, as in the demo's cell and most
industrial cameras): the tracker then has no colour conversion to do.

Usage: ``python bench/tracker.py [--frames 78] [--object bracket] [--cache DIR] [--mono] [--clock wall|cpu]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from _cpuclock import tracker_clock  # noqa: E402
from _table import print_table  # noqa: E402

from vespro.evaluate import pnp_baseline, score  # noqa: E402
from vespro.groundtruth import read_groundtruth  # noqa: E402
from vespro.recording import Recording  # noqa: E402
from vespro.rig import load_rig  # noqa: E402
from vespro.sim.cell import CellConfig  # noqa: E402
from vespro.sim.imaging import ImageEffects  # noqa: E402
from vespro.sim.motion import Conveyor  # noqa: E402
from vespro.sim.record import record  # noqa: E402
from vespro.sim.rigs import CAMERAS_DIR  # noqa: E402
from vespro.sim.scene import MODELS_DIR  # noqa: E402
from vespro.track import make_tracker, track_recording  # noqa: E402
from vespro.tracker import TrackerConfig  # noqa: E402


def bench_recording(cache: Path, obj: str, rig_name: str, frames: int, mono: bool = False) -> Path:
    """The bench's recording of ``obj`` on the conveyor seen by rig ``rig_name`` (made once, cached)."""
    path = cache / f"{obj}_{rig_name}_{frames}{'_mono' if mono else ''}"
    if not (path / "groundtruth.csv").exists():
        cfg = CellConfig(MODELS_DIR / "objects" / f"{obj}.stl", load_rig(CAMERAS_DIR / f"{rig_name}.yaml"),
                         effects=ImageEffects(noise_px=0.5), mono=mono)
        record(path, cfg, Conveyor(speed=0.1, y0=-0.2), frames, obj, overwrite=True)
    return path


def _tracked(rec, T, config, clock: str):
    """The recording tracked from its first true pose: (outputs, frame times ms, position RMSE mm,
    the tracker's model)."""
    tr = make_tracker(rec) if config is None else make_tracker(rec, config)
    with tracker_clock(clock):
        outs = track_recording(rec, tr, T[0])
    s = score([o.T_world_object for o in outs], [o.status for o in outs], T, rec.t, tr.model)
    return outs, np.array([o.time_ms for o in outs]), s["position_rmse_mm"], tr.model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=78)
    ap.add_argument("--object", default="bracket")
    ap.add_argument("--cache", type=Path, default=Path("out/bench_tracker"))
    ap.add_argument("--mono", action="store_true", help="monochrome cameras (grey images)")
    ap.add_argument("--clock", choices=["wall", "cpu"], default="wall",
                    help="the tracker's times as wall time or as its thread's CPU time (a busy machine's "
                         "preemptions left out; bench/_cpuclock.py)")
    args = ap.parse_args()
    rows = []
    for rig_name in ("fixed1", "fixed2", "fixed3"):
        path = bench_recording(args.cache, args.object, rig_name, args.frames, args.mono)
        rec = Recording(path)
        _, _, T = read_groundtruth(path)
        outs, tot, rmse, model = _tracked(rec, T, None, args.clock)
        # Baseline on the same detections, timed in this process.
        base = []
        now = time.thread_time if args.clock == "cpu" else time.perf_counter
        for o in outs:
            t = now()
            pnp_baseline(rec, [o], model)
            base.append((now() - t) * 1e3)
        b_med = float(np.median(base))
        for stage in ("visibility", "selection", "extraction", "update", "edges"):
            v = np.array([o.stage_ms.get(stage, np.nan) for o in outs])
            if np.all(np.isnan(v)):
                continue
            rows.append([rig_name, stage, float(np.nanmedian(v)), float(np.nanpercentile(v, 99)), "", ""])
        rows.append([rig_name, "whole frame", float(np.median(tot)), float(np.percentile(tot, 99)), f"{rmse:.2f}", ""])
        if any("edges" in o.stage_ms for o in outs):
            _, tot0, rmse0, _ = _tracked(rec, T, TrackerConfig(edge_aid="off"), args.clock)
            rows.append([rig_name, "whole frame, corners only", float(np.median(tot0)), float(np.percentile(tot0, 99)),
                         f"{rmse0:.2f}", f"{np.median(tot) / np.median(tot0):.1f}x (edges/off)"])
        outsb, totb, rmseb, _ = _tracked(rec, T, TrackerConfig(decision="bank"), args.clock)
        vb = np.array([o.stage_ms.get("bank", np.nan) for o in outsb])
        rows.append([rig_name, "bank (weighing, decision bank)", float(np.nanmedian(vb)),
                     float(np.nanpercentile(vb, 99)), "", ""])
        rows.append([rig_name, "whole frame, decision bank", float(np.median(totb)), float(np.percentile(totb, 99)),
                     f"{rmseb:.2f}", f"{np.median(totb) / np.median(tot):.1f}x (bank/rules)"])
        rows.append([rig_name, "baseline solvePnP", b_med, float(np.percentile(base, 99)), "",
                     f"{np.median(tot) / b_med:.1f}x"])
    print_table(["rig", "stage", "median ms", "p99 ms", "pos RMSE mm", "frame/baseline"], rows,
                title=f"Tracker {args.clock} time per frame set ({args.object}, {args.frames} frames, 640x480 "
                      f"{'grey' if args.mono else 'colour'}, 0.5 px noise)")


if __name__ == "__main__":
    main()
