"""Where a frame's time goes: the tracker's stages, and the demo's vision process.

Part 1, the tracker, per view set, one process run:

- ``fixed1/2/3``: the tracker bench's recordings (``bench/tracker.py``: the bracket on the
  conveyor, 1-3 fixed cameras), started from the first true pose;
- ``demo``: a recording of the demo's cell (two fixed cameras and the eye-in-hand camera
  seeing the part close up; ``vespro demo --lockstep`` writes one to
  ``out/demo/vision/recording``), started by the automatic initialiser as in the demo;
- ``cube``: ViSP's real cube sequence (``visp-images-data``, one camera), from its start pose.

Times are the tracker thread's CPU time by default (``--clock wall``: wall time; see
``bench/_cpuclock.py``). Stages: the tracker's own (``TrackerOutput.stage_ms``: visibility, selection, extraction,
update, edges) and, timed by wrapping the functions for this run, the edge fit's image
gradient and pose fit, the filter's predict and updates, and each initialiser call. Per
stage: median and p99 over the frames it ran in, and in how many.

With ViSP's cube: its edge fit calls are also timed through the NumPy formulation the
compiled fit replaced (the tests' reference), interleaved in this process: the ratio.

Part 2, the demo's vision process (``vespro demo``, real time or ``--lockstep``): the live
loop's stages per frame as its pose server recorded them (``vision/server.json``:
capture, i.e. rendering the cameras; track; backlog; publish; record; and the
initialisation jobs), with the run's capture instants processed and missed and its
capture-to-publish latency.

Usage: ``python bench/profile.py [--frames 78] [--demo-recording out/demo/vision/recording]
[--demo-frames 260] [--demo-run out/demo ...] [--skip fixed1,cube,...]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from _cpuclock import tracker_clock  # noqa: E402
from _table import print_table  # noqa: E402
from _visp_data import visp_cube  # noqa: E402
from tracker import bench_recording  # noqa: E402

import vespro.edgeaid  # noqa: E402
import vespro.ekf  # noqa: E402
from vespro.groundtruth import read_groundtruth  # noqa: E402
from vespro.model import load_model  # noqa: E402
from vespro.recording import Recording  # noqa: E402
from vespro.tracker import InitResult, Tracker  # noqa: E402

TRACKER_STAGES = ("visibility", "selection", "extraction", "update", "edges")
#: (owner, attribute, label): functions timed by wrapping, per frame.
WRAPPED = ((vespro.edgeaid, "_gradient", "edges: image gradient"),
           (vespro.edgeaid, "refine_subpixel", "edges: pose fit"),
           (vespro.ekf.PoseEKF, "predict", "filter predict"),
           (vespro.ekf.PoseEKF, "update", "filter update (corners)"),
           (vespro.ekf.PoseEKF, "update_pose", "filter update (edge pose)"))


class StageClock:
    """Per-frame time of wrapped functions (summed over their calls in the frame), by ``now``."""

    def __init__(self, now=time.perf_counter):
        self.acc: dict[str, float] = {}
        self.now = now
        self._undo = []

    def wrap(self, owner, attr: str, label: str) -> None:
        f = getattr(owner, attr)
        now = self.now

        def timed(*a, **k):
            t = now()
            try:
                return f(*a, **k)
            finally:
                self.acc[label] = self.acc.get(label, 0.0) + now() - t

        setattr(owner, attr, timed)
        self._undo.append((owner, attr, f))

    def take(self) -> dict:
        """This frame's times, ms; starts the next frame."""
        d, self.acc = {k: v * 1e3 for k, v in self.acc.items()}, {}
        return d

    def __enter__(self):
        for owner, attr, label in WRAPPED:
            self.wrap(owner, attr, label)
        return self

    def __exit__(self, *exc):
        for owner, attr, f in reversed(self._undo):
            setattr(owner, attr, f)


class TimedInitializer:
    """An initialiser whose calls are timed into a :class:`StageClock` (its other methods pass through)."""

    def __init__(self, inner, clock: StageClock):
        self._inner, self._clock = inner, clock

    def __call__(self, fs):
        c = self._clock
        t = c.now()
        try:
            return self._inner(fs)
        finally:
            c.acc["initialiser call"] = c.acc.get("initialiser call", 0.0) + c.now() - t

    def __getattr__(self, name):
        return getattr(self._inner, name)


def profile_tracker(name: str, rig, model, framesets, T_start=None, initializer=None, kind: str = "cpu") -> list[list]:
    """Rows (view set, stage, median, p99, frames) of one tracker run, timed by ``kind`` ("cpu" or "wall")."""
    per_frame = []
    with tracker_clock(kind) as now, StageClock(now) as clock:
        init = TimedInitializer(initializer, clock) if initializer is not None else None
        tr = Tracker(rig, model, initializer=init)
        clock.take()  # set-up calls (the warm-up) are not a frame's
        n_track = 0
        for i, fs in enumerate(framesets):
            if i == 0 and T_start is not None:
                tr.start(InitResult(T_start), fs.t_ns)
            o = tr.process(fs)
            d = clock.take()
            d.update(o.stage_ms)
            d["whole frame"] = o.time_ms
            per_frame.append(d)
            n_track += o.status == "tracking"
    labels = list(TRACKER_STAGES) + [lab for _, _, lab in WRAPPED] + ["initialiser call", "whole frame"]
    rows = []
    for lab in labels:
        v = np.array([d[lab] for d in per_frame if lab in d])
        if v.size:
            rows.append([name, lab, float(np.median(v)), float(np.percentile(v, 99)), f"{v.size}/{len(per_frame)}"])
    rows[-1][1] = f"whole frame ({n_track} tracking)"
    return rows


def edgefit_baseline(seq, n_calls: int = 120) -> list[list] | None:
    """The edge fit's calls of a tracker run on ``seq``, each timed (thread CPU) through the
    compiled :func:`vespro.edgefit.refine_subpixel` and through the NumPy formulation it
    replaced (kept as the reference of ``tests/vespro/test_init_kernels.py``), interleaved in
    this process: rows (stage, median, p99, ratio). None where the tests are not at hand."""
    tests = Path(__file__).resolve().parents[1] / "tests" / "vespro"
    if not (tests / "test_init_kernels.py").exists():
        return None
    sys.path.insert(0, str(tests))
    try:
        from test_init_kernels import refine_subpixel_ref
    except ImportError:
        return None
    calls = []
    real = vespro.edgeaid.refine_subpixel

    def keep(*a, **k):
        calls.append((a, k))
        return real(*a, **k)

    vespro.edgeaid.refine_subpixel = keep
    try:
        tr = Tracker(seq.rig, seq.model)
        for i in range(min(len(seq), n_calls)):
            fs = seq.frameset(i)
            if i == 0:
                tr.start(InitResult(seq.T_start), fs.t_ns)
            tr.process(fs)
    finally:
        vespro.edgeaid.refine_subpixel = real
    ta, tb = [], []
    for a, k in calls:
        t0 = time.thread_time()
        real(*a, **k)
        t1 = time.thread_time()
        refine_subpixel_ref(*a, **k)
        ta.append((t1 - t0) * 1e3)
        tb.append((time.thread_time() - t1) * 1e3)
    return [["edge fit (compiled)", float(np.median(ta)), float(np.percentile(ta, 99)),
             f"{np.median(ta) / np.median(tb):.2f}"],
            ["edge fit (NumPy formulation)", float(np.median(tb)), float(np.percentile(tb, 99)), "1.00"]]


def _frames(rec: Recording, n: int | None):
    for i in range(len(rec) if n is None else min(n, len(rec))):
        yield rec.frameset(i)


def tracker_rows(args) -> list[list]:
    rows = []
    for rig_name in ("fixed1", "fixed2", "fixed3"):
        if rig_name in args.skip:
            continue
        path = bench_recording(args.cache, args.object, rig_name, args.frames, mono=True)
        rec = Recording(path)
        _, _, T = read_groundtruth(path)
        model = load_model(rec.model_path, name=rec.object_name)
        rows += profile_tracker(rig_name, rec.rig, model, [rec.frameset(i) for i in range(len(rec))], T[0],
                                kind=args.clock)
    if "demo" not in args.skip:
        if not (args.demo_recording / "meta.yaml").exists():
            print(f"profile: no demo recording at {args.demo_recording} (make one with "
                  f"`vespro demo --lockstep --out out/demo`); demo views skipped")
        else:
            from vespro.init import make_initializer

            rec = Recording(args.demo_recording)
            model = load_model(rec.model_path, name=rec.object_name)
            rows += profile_tracker(f"demo ({len(rec.rig)} cams)", rec.rig, model, _frames(rec, args.demo_frames),
                                    initializer=make_initializer(rec.rig, model), kind=args.clock)
    if "cube" not in args.skip:
        seq = visp_cube()
        if seq is None:
            print("profile: visp-images-data is not installed; ViSP's cube skipped")
        else:
            rows += profile_tracker("cube (1 cam)", seq.rig, seq.model, (seq.frameset(i) for i in range(len(seq))),
                                    seq.T_start, kind=args.clock)
    return rows


def vision_rows(run: Path) -> tuple[list[list], str] | None:
    """Rows of a demo run's vision stages, and a line of its figures (None: no such run)."""
    info_path = run / "vision" / "server.json"
    if not info_path.exists():
        return None
    info = json.loads(info_path.read_text())
    rows = []
    for lab, v in (info.get("stage_ms") or {}).items():  # histograms kept by the server (ServerStats.stage_ms)
        if v.get("n"):
            rows.append([run.name, lab, float(v["median"]), float(v["p99"]), str(v["n"])])
    line = (f"{run}: {info['frames']} capture instants processed, {info.get('missed_captures', 0)} missed; "
            f"latency median {info['latency_ms_median']:.1f} ms, p99 {info['latency_ms_p99']:.1f} ms")
    summary = run / "summary.json"
    if summary.exists():
        est = json.loads(summary.read_text()).get("estimation", {})
        if est.get("time_to_first_track_s") is not None:
            line += f"; first track at {est['time_to_first_track_s']:.2f} s"
    return rows, line


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=78, help="frames of the bench recordings")
    ap.add_argument("--object", default="bracket")
    ap.add_argument("--cache", type=Path, default=Path("out/bench_tracker"))
    ap.add_argument("--demo-recording", type=Path, default=Path("out/demo/vision/recording"))
    ap.add_argument("--demo-frames", type=int, default=260, help="frames of the demo recording (from its start)")
    ap.add_argument("--demo-run", type=Path, action="append", default=None,
                    help="a demo output folder whose vision stages to print (default out/demo); repeatable")
    ap.add_argument("--clock", choices=["cpu", "wall"], default="cpu",
                    help="time the tracker by its thread's CPU time (a busy machine's preemptions left out) "
                         "or by wall time")
    ap.add_argument("--skip", default="", help="comma-separated: fixed1, fixed2, fixed3, demo, cube, vision")
    args = ap.parse_args()
    args.skip = set(filter(None, args.skip.split(",")))
    rows = tracker_rows(args)
    print_table(["views", "stage", "median ms", "p99 ms", "frames"], rows,
                title=f"Tracker time per frame set by stage (640x480 grey; {args.clock} time)")
    seq = visp_cube() if "cube" not in args.skip else None
    base = edgefit_baseline(seq) if seq is not None else None
    if base:
        print()
        print_table(["stage", "median ms", "p99 ms", "ratio"], base,
                    title="The cube's edge fit calls, compiled against the NumPy formulation (same calls, "
                          "interleaved, thread CPU time)")
    if "vision" in args.skip:
        return
    for run in args.demo_run or [Path("out/demo")]:
        got = vision_rows(run)
        if got is not None and not got[0]:
            print(f"profile: {run}'s vision process recorded no stage times (an older run); {got[1]}")
            continue
        if got is None:
            print(f"profile: no demo run at {run} (run `vespro demo --out {run}`); vision stages skipped")
            continue
        print()
        print_table(["run", "stage", "median ms", "p99 ms", "frames"], got[0],
                    title="The demo's vision process: its live loop's stages per frame (wall time)")
        print(got[1])


if __name__ == "__main__":
    main()
