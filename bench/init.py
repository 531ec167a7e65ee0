"""Benchmark of automatic initialisation: objects x rigs x random start poses.

Each trial: a simulated cell (``vespro.sim.trials``) with the object at a
random pose in the common view (random orientation, position around
(0.9, 0, 0.6) m), drifting slowly; the rig is a random subset of the standard
fixed cameras with perturbed placements (1, 2 or 3 cameras) or the hybrid rig
(2 random fixed cameras + the eye-in-hand camera on the watching arm) or the
hand rig (the eye-in-hand camera alone, the arm watching the work area). The
initialiser is called on frames 0, stride, 2 stride, ... up to ``--frames``
(26 frames = 1 s at 26 Hz) until it returns a pose.

- success: a pose returned within the frame budget with symmetry-aware ADD
  below 10% of the object's diameter;
- wrong lock: a pose returned with ADD >= 10% of the diameter (the trial
  stops there: the tracker would have started from it);
- compute: wall and CPU time of each call (median, p99; on a machine shared
  with other work the CPU time of the calling thread is the steadier
  figure), and the wall time of the calls up to the first pose (the
  time-to-first-pose a background thread would need);
- position / rotation error of the successful poses (median, max).

With ``--hide`` a paddle stands between the rig's first fixed camera and the
part for the whole trial (``vespro.sim.cell.OccluderSweep`` held still): the
part is hidden there by a body the model does not know (the demo's arm in
front of its top camera), and the other cameras must find and track it.

With ``--track N`` the trial also runs the tracker the server runs (the
same initialiser as its starting-pose hook, called on the same frames) for N
frames, and scores what a user sees: the status. A trial is then
*initialised* when the tracker publishes ``tracking`` within ``--frames``
frames with ADD below 10%, and a *wrong lock* when any frame of the N is
published ``tracking`` with ADD at or above 10%. The tracker confirms a
started filter on consecutive well-supported frames before it publishes
(``TrackerConfig.confirm_*``), so the published time lags the initialiser's
pose, and a near miss of the initialiser can be put right by the filter.
With ``--stride 0`` the initialiser is called as a real-time worker calls it
(the server's background initialiser): on the first frame captured once the
previous call's CPU time has passed, so a slow call costs frames as it would
live (the worker's wall time on a quiet core is its CPU time).

The baseline runs in the same process on the same frames: the same corner-path
P3P hypotheses and chamfer ranking, but from the rig's first camera alone,
without sub-pixel refinement and with only the inlier-fraction check (no
multi-camera verification, edge count, size or ambiguity tests).

Usage: ``python3 bench/init.py [--trials 10] [--objects box,lblock,bracket]
[--rigs 1,2,3,hybrid,hand] [--frames 26] [--stride 5 | --stride 0 --track N] [--seed 0] [--no-baseline]``
"""

from __future__ import annotations

import argparse
import ast
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("MUJOCO_GL", "egl")

from dataclasses import dataclass, replace  # noqa: E402

import numpy as np  # noqa: E402

from bench._table import print_table, stats_ms  # noqa: E402
from vespro.init import decision_options, make_initializer  # noqa: E402
from vespro.sim.scene import WATCHED_VOLUME  # noqa: E402
from vespro.library import object_mesh_path  # noqa: E402
from vespro.likelihood import ImageLikelihood  # noqa: E402
from vespro.metrics import add, add_sym  # noqa: E402
from vespro.model import load_model  # noqa: E402
from vespro.sim.cell import OccluderSweep, SimCell  # noqa: E402
from vespro.sim.trials import model_symmetries, random_rig, trial_config  # noqa: E402
from vespro.tracker import Tracker, TrackerConfig  # noqa: E402

BASELINE = dict(min_supported_edges=0, min_supported_edges_single=0, min_size_px=0.0, ambiguity_margin=-1.0,
                require_fixed_view=False, subpixel=False, min_camera_inlier_frac=0.0)


def sym_add(T_est, T_true, model, syms):
    return add_sym(T_est, T_true, model.vertices, syms)


class _Gated:
    """The initialiser called only on every ``stride``-th frame (as the stand-alone trial calls it),
    or with ``stride`` 0 as a real-time worker calls it: on the first frame set captured once the
    previous call's CPU time has passed since the frame set it worked on."""

    def __init__(self, ini, stride):
        self.ini, self.stride, self.results = ini, stride, []
        self._next_t_ns = None

    def __call__(self, fs):
        if self.stride and fs.index % self.stride:
            return None
        if not self.stride and self._next_t_ns is not None and fs.t_ns < self._next_t_ns:
            return None
        res = self.ini(fs)
        self.results.append((fs.index, res, self.ini.last_report))
        self._next_t_ns = fs.t_ns + int(self.ini.last_report.cpu_s * 1e9)
        return res

    @property
    def last_report(self):
        return self.ini.last_report

    def reseed(self, *a, **kw):
        self.ini.reseed(*a, **kw)

    def await_confirmation(self, *a):
        self.ini.await_confirmation(*a)


@dataclass(frozen=True)
class Trial:
    """One trial: an object (and its model, symmetries), a rig kind and seed, the frame
    budget, the initialiser's stride, and whether a paddle hides the first fixed camera."""

    obj: str
    model: object
    syms: list
    rig_kind: str
    seed: int
    frames: int
    stride: int
    hide: bool = False

    def cell_setup(self):
        """(rig, cell config, motion) of the trial."""
        rig = _trial_rig(self.rig_kind, self.seed)
        config, motion, _ = trial_config(self.obj, rig, self.seed)
        return rig, (_hidden(config, rig) if self.hide else config), motion


def _hidden(config, rig):
    """``config`` with a paddle held between the rig's first fixed camera and the part."""
    cam = next((c.name for c in rig if c.is_fixed), None)
    if cam is None:
        raise SystemExit("--hide needs a rig with a fixed camera")
    return replace(config, occluders=(OccluderSweep(cam, 0.0, duration=1e3, half_travel=0.0),))


def parse_overrides(text: str) -> dict:
    """``"a=1,b=off"`` -> ``{"a": 1, "b": "off"}`` (Python literals where they parse, else strings)."""
    out = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        k, sep, v = item.partition("=")
        if not sep:
            raise SystemExit(f"expected key=value, got {item!r}")
        try:
            out[k.strip()] = ast.literal_eval(v.strip())
        except (ValueError, SyntaxError):
            out[k.strip()] = v.strip()
    return out


def run_tracked(trial: Trial, track_frames: int, config_set: dict | None = None, edge_set: dict | None = None,
                init_set: dict | None = None, likelihood_set: dict | None = None, on_frame=None,
                workspace: tuple | None = None):
    """One trial through the tracker: the initialiser as its hook; status and ADD per frame.

    ``config_set``: ``TrackerConfig`` fields to change; ``edge_set``: attributes
    of the tracker's ``EdgeAid`` to change; ``init_set``: ``InitOptions`` fields to
    change; ``likelihood_set``: ``LikelihoodOptions`` fields of the hypothesis bank's
    likelihood to change (all for A/B runs from the command line). ``on_frame(k, fs,
    tracker, T_true)``, if given, is called after each frame is processed. ``workspace``: the
    cell's working volume, given to the initialiser and the tracker as a user gives it.
    """
    model, syms, frames = trial.model, trial.syms, trial.frames
    rig, config, motion = trial.cell_setup()
    init_set = {**decision_options((config_set or {}).get("decision", "rules")), **(init_set or {})}
    if workspace is not None:
        init_set.setdefault("workspace", workspace)
    gate = _Gated(make_initializer(rig, model, **init_set), trial.stride)
    tracker = Tracker(rig, model, config=replace(TrackerConfig(), **(config_set or {})), initializer=gate,
                      workspace=workspace)
    for k, v in (edge_set or {}).items():
        if tracker.edge_aid is None or not hasattr(tracker.edge_aid, k):
            raise SystemExit(f"the tracker's edge aid has no attribute {k!r}")
        setattr(tracker.edge_aid, k, v)
    if likelihood_set:
        if tracker.bank is None:
            raise SystemExit("likelihood settings apply to the hypothesis bank: they need decision=bank")
        lk = tracker.bank.likelihood
        tracker.bank.likelihood = ImageLikelihood(lk.mf, lk.tree, replace(lk.options, **likelihood_set))
    o = dict(frame=None, add=None, calls=[], cpu=[], to_first=0.0, err_p=None, err_r=None,
             track_frame=None, track_add=None, wrong_frame=None, wrong_add=None, max_track_add=None)
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        for k in range(track_frames):
            fs = cell.next_frameset()
            n_before = len(gate.results)
            out = tracker.process(fs)
            T_true = cell.true_object_pose()
            if on_frame is not None:
                on_frame(k, fs, tracker, T_true)
            for idx, res, r in gate.results[n_before:]:
                o["calls"].append(r.wall_s)
                o["cpu"].append(r.cpu_s)
                if o["frame"] is None and k < frames:  # the initialiser's own score: within the budget
                    o["to_first"] += r.wall_s
                    if res is not None and not res.provisional:  # a provisional start: the tracker's to confirm
                        _score(o, k, res.T_world_object, T_true, model, syms)
            if out.status == "tracking":
                e = sym_add(out.T_world_object, T_true, model, syms) / model.diameter
                o["max_track_add"] = max(e, o["max_track_add"] or 0.0)
                if o["track_frame"] is None:
                    o["track_frame"], o["track_add"] = k, e
                if e >= 0.1 and o["wrong_frame"] is None:
                    o["wrong_frame"], o["wrong_add"] = k, e
    return o


def _trial_rig(rig_kind, seed):
    rng = np.random.default_rng(10_000 + seed)
    if rig_kind == "hybrid":
        return random_rig(rng, 2, hand=True)
    if rig_kind == "hand":
        return random_rig(rng, 0, hand=True)
    return random_rig(rng, int(rig_kind))


def _score(o, k, T_est, T_true, model, syms):
    e = sym_add(T_est, T_true, model, syms)
    o["frame"], o["add"] = k, e / model.diameter
    Ts = min((T_true @ S for S in syms), key=lambda Ts: add(T_est, Ts, model.vertices))
    o["err_p"] = float(np.linalg.norm(T_est[:3, 3] - Ts[:3, 3]))
    Rd = T_est[:3, :3].T @ Ts[:3, :3]
    o["err_r"] = float(np.arccos(np.clip((np.trace(Rd) - 1) / 2, -1, 1)))


def run_trial(trial: Trial, baseline: bool):
    """One trial of the initialiser alone (and the baseline): its first pose and compute."""
    model, syms, frames, stride = trial.model, trial.syms, trial.frames, trial.stride
    rig, config, motion = trial.cell_setup()
    methods = {"ours": make_initializer(rig, model)}
    if baseline:
        methods["base"] = make_initializer(rig.subset([rig.names[0]]), model, **BASELINE)
    out = {m: dict(frame=None, add=None, calls=[], cpu=[], to_first=0.0, err_p=None, err_r=None) for m in methods}
    done = set()
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        for k in range(frames):
            fs = cell.next_frameset()
            if k % stride or len(done) == len(methods):
                continue
            T_true = cell.true_object_pose()
            for m, ini in methods.items():
                if m in done:
                    continue
                if m == "base":
                    fs_m = type(fs)(fs.index, fs.t_ns, {rig.names[0]: fs.images[rig.names[0]]}, fs.T_world_camera)
                else:
                    fs_m = fs
                res = ini(fs_m)
                r = ini.last_report
                o = out[m]
                o["calls"].append(r.wall_s)
                o["cpu"].append(r.cpu_s)
                o["to_first"] += r.wall_s
                if res is not None and not res.provisional:
                    _score(o, k, res.T_world_object, T_true, model, syms)
                    done.add(m)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--objects", default="box,lblock,bracket")
    ap.add_argument("--rigs", default="1,2,3,hybrid")
    ap.add_argument("--frames", type=int, default=26)
    ap.add_argument("--stride", type=int, default=5,
                    help="call the initialiser every N frames; 0 (with --track): as a real-time worker, the next "
                         "call on the first frame after the previous call's CPU time")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--track", type=int, default=0, metavar="N",
                    help="also run the tracker for N frames and score its published status (no baseline)")
    ap.add_argument("--hide", action="store_true",
                    help="a paddle hides the part from the rig's first fixed camera throughout")
    ap.add_argument("--set", default="", metavar="K=V,...",
                    help="with --track: TrackerConfig fields to change, e.g. q_acc=0.02,recover_frames=2")
    ap.add_argument("--edge-aid", default="", metavar="K=V,...",
                    help="with --track: attributes of the tracker's EdgeAid to change, e.g. spacing_px=0,edge_outlier_px=0")
    ap.add_argument("--init-set", default="", metavar="K=V,...",
                    help="with --track: InitOptions fields to change, e.g. min_supported_edges_confirm=5")
    ap.add_argument("--likelihood-set", default="", metavar="K=V,...",
                    help="with --track and decision=bank: LikelihoodOptions fields of the bank's likelihood, "
                         "e.g. region=True")
    ap.add_argument("--workspace", action="store_true",
                    help="with --track: the simulated cell's working volume (the watched stretch of conveyor, "
                         "vespro.sim.scene.WATCHED_VOLUME) given to the initialiser and the tracker")
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args(argv)
    config_set, edge_set = parse_overrides(a.set), parse_overrides(a.edge_aid)
    init_set, lk_set = parse_overrides(a.init_set), parse_overrides(a.likelihood_set)
    if (config_set or edge_set or init_set or lk_set) and not a.track:
        raise SystemExit("--set, --edge-aid, --init-set and --likelihood-set apply to the tracked runs: "
                         "they need --track")
    if a.workspace and not a.track:
        raise SystemExit("--workspace applies to the tracked runs: it needs --track")
    workspace = WATCHED_VOLUME if a.workspace else None
    if a.track:
        a.no_baseline = True
        a.track = max(a.track, a.frames)
    elif a.stride < 1:
        raise SystemExit("--stride 0 (real-time cadence) needs --track")
    rows = []
    totals = {"ours": [0, 0, 0], "base": [0, 0, 0]}
    by_rig = {}  # rig kind -> [published within the budget, wrong locks, trials] (tracker)
    worst = []  # per tracked trial, the largest ADD / diameter of a frame published tracking
    t_start = time.perf_counter()
    for obj in a.objects.split(","):
        model = load_model(object_mesh_path(obj))
        syms = model_symmetries(model.vertices)
        for rk in a.rigs.split(","):
            trials = [Trial(obj, model, syms, rk, a.seed + i, a.frames, a.stride, a.hide) for i in range(a.trials)]
            if a.track:
                res = [{"ours": run_tracked(t, a.track, config_set, edge_set, init_set, lk_set, workspace=workspace)}
                       for t in trials]
            else:
                res = [run_trial(t, not a.no_baseline) for t in trials]
            row = [obj, rk, a.trials]
            for m in (["ours"] if a.no_baseline else ["ours", "base"]):
                ok = [r[m] for r in res if r[m]["add"] is not None and r[m]["add"] < 0.1]
                wrong = [r[m] for r in res if r[m]["add"] is not None and r[m]["add"] >= 0.1]
                calls = [c for r in res for c in r[m]["calls"]]
                first = [r[m]["to_first"] for r in res if r[m]["add"] is not None]
                med, p99 = stats_ms(calls) if calls else (float("nan"), float("nan"))
                row += [len(ok) / a.trials, len(wrong), med, p99]
                if m == "ours":
                    cpu = [c for r in res for c in r[m]["cpu"]]
                    row += list(stats_ms(cpu)) if cpu else [float("nan"), float("nan")]
                if m == "ours":
                    ep = [r["err_p"] * 1e3 for r in ok]
                    er = [np.rad2deg(r["err_r"]) for r in ok]
                    row += [float(np.median(ep)) if ep else float("nan"), float(np.max(ep)) if ep else float("nan"),
                            float(np.median(er)) if er else float("nan"), float(np.max(er)) if er else float("nan"),
                            float(np.median(first)) * 1e3 if first else float("nan")]
                if m == "ours" and a.track:
                    t_ok = [r[m] for r in res if r[m]["track_frame"] is not None and r[m]["track_frame"] < a.frames
                            and r[m]["track_add"] < 0.1]
                    t_wrong = [r[m] for r in res if r[m]["wrong_frame"] is not None]
                    t_at = [r[m]["track_frame"] for r in res if r[m]["track_frame"] is not None]
                    row += [len(t_ok) / a.trials, len(t_wrong),
                            float(np.median(t_at)) if t_at else float("nan"),
                            float(np.max(t_at)) if t_at else float("nan")]
                    worst += [r[m]["max_track_add"] for r in res if r[m]["max_track_add"] is not None]
                    tot = by_rig.setdefault(rk, [0, 0, 0])
                    tot[0] += len(t_ok)
                    tot[1] += len(t_wrong)
                    tot[2] += a.trials
                totals[m][0] += len(ok)
                totals[m][1] += len(wrong)
                totals[m][2] += a.trials
                if a.verbose:
                    for i, r in enumerate(res):
                        tr = (f" tracking from frame {r[m]['track_frame']} ADD/d {r[m]['track_add']} "
                              f"max {r[m]['max_track_add']} wrong at {r[m]['wrong_frame']}" if a.track else "")
                        print(f"  {obj} {rk} trial {i} {m}: frame {r[m]['frame']} ADD/d {r[m]['add']} calls "
                              f"{[round(c, 2) for c in r[m]['calls']]}{tr}", flush=True)
            rows.append(row)
            print(f"done {obj} {rk} ({time.perf_counter() - t_start:.0f} s)", flush=True)
    headers = ["object", "rig", "n", "success", "wrong", "call ms med", "call ms p99", "cpu ms med", "cpu ms p99",
               "dp mm med", "dp mm max",
               "dR deg med", "dR deg max", "to-pose ms med"]
    if a.track:
        headers += ["tracking", "trk wrong", "trk frame med", "trk frame max"]
    if not a.no_baseline:
        headers += ["base succ", "base wrong", "base ms med", "base ms p99"]
    cadence = f"attempts every {a.stride}" if a.stride else "attempts at the real-time cadence"
    print_table(headers, rows, title=f"Initialisation within {a.frames} frames ({cadence}), "
                                       f"success = ADD < 10% diameter"
                                       + (f"; tracker run {a.track} frames" if a.track else ""))
    for m, (ok, wrong, n) in totals.items():
        if n:
            print(f"{m}: success {ok}/{n} = {ok / n:.3f}, wrong locks {wrong}")
    if a.track:
        ok, wrong, n = np.sum(list(by_rig.values()), axis=0)
        print(f"tracker: published tracking within {a.frames} frames (ADD < 10%) {ok}/{n} = {ok / n:.3f}, "
              f"wrong locks (a tracking frame with ADD >= 10% in {a.track} frames) {wrong}")
        for rk, (ok, wrong, n) in by_rig.items():
            print(f"  rig {rk}: {ok}/{n} = {ok / n:.3f}, wrong locks {wrong}")
        if worst:
            print(f"  worst published ADD per tracked trial, % of the diameter: median {100 * np.median(worst):.2f}, "
                  f"p90 {100 * np.percentile(worst, 90):.2f}, max {100 * np.max(worst):.2f} ({len(worst)} trials)")
        cams = [by_rig[k] for k in ("1", "2", "3") if k in by_rig]
        if len(cams) == 3:  # the criterion: random rigs of 1, 2 and 3 cameras, drawn alike
            print(f"  1, 2 and 3 cameras weighted alike: {np.mean([ok / n for ok, _, n in cams]):.3f}")
    if not a.no_baseline and totals["base"][2]:
        so, sb = totals["ours"][0] / totals["ours"][2], totals["base"][0] / totals["base"][2]
        print(f"success ratio ours/base = {so / sb if sb else float('inf'):.2f}; wrong locks ours {totals['ours'][1]} "
              f"vs base {totals['base'][1]}")


if __name__ == "__main__":
    main()
