"""``vespro eval``: track a recording and score it against its ground truth."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_parser(sub) -> None:
    from .options import add_model_unit_option, add_tracker_options
    from .recording_report import INPUT_HELP

    p = sub.add_parser(
        "eval", help="track a recording and score it against ground truth",
        description="Track a recording (as `vespro track` does) and score it against groundtruth.csv: "
                    "position/orientation RMSE and max, ADD, tracked fraction, time to first track, "
                    "per-frame time, NEES; the same for a per-frame solvePnP baseline on the same "
                    "detections. Writes poses.csv, summary.json, errors.png and overlay.mp4.",
        epilog=INPUT_HELP + " Frames whose ground-truth pose is not finite (nan in groundtruth.csv) are left "
                            "out of the scores and a warning names them.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("recording", type=Path, nargs="?", help="recording folder (not with --suite)")
    p.add_argument("-o", "--out", type=Path,
                   help="output folder (default: <recording>/eval; with --suite: out/suite/<suite name>)")
    p.add_argument("--suite", type=Path, metavar="SUITE.yaml",
                   help="run a scenario suite (bench/suites/*.yaml): simulate the recordings it needs (cached), "
                        "track and score them, write results.md, results.json and plots")
    p.add_argument("--cache", type=Path, default=Path("out/suite_cache"), help="with --suite: recording cache folder")
    p.add_argument("--only", metavar="TEXT", help="with --suite: run only scenarios whose name contains TEXT")
    p.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    p.add_argument("--no-video", action="store_true", help="skip the overlay video")
    p.add_argument("--gt-init", action="store_true",
                   help="start from the ground-truth pose of frame 0 (evaluates tracking alone)")
    add_tracker_options(p)
    add_model_unit_option(p)
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=run)


def _fmt(v, unit=""):
    return "-" if v is None else f"{v:.3f}{unit}"


def run_suite(args) -> int:
    from .suite import run_suite as run

    try:
        summary = run(args.suite, args.out, args.cache, only=args.only)
    except (OSError, ValueError) as e:
        print(f"vespro eval: {e}", file=sys.stderr)
        return 2
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2, default=str))
    out = args.out or Path("out") / "suite" / summary["suite"]
    print(f"wrote {out}/results.md, results.json, summary.png ({len(summary['results'])} scenarios, "
          f"{summary['failed']} failed, {summary['wall_s']:.0f} s)")
    return 1 if summary["failed"] else 0


def run(args) -> int:
    if args.suite is not None:
        return run_suite(args)
    if args.recording is None:
        print("vespro eval: give a recording folder or --suite SUITE.yaml", file=sys.stderr)
        return 2
    from .errors import warn
    from .evaluate import overlay_video, plot_errors, pnp_baseline, score
    from .groundtruth import truth_per_frame
    from .options import initializer_for, say_symmetry, tracker_config, workspace_of
    from .recording_report import open_recording, report_images
    from .track import make_tracker, parse_pose, track_recording, write_track

    rec = open_recording(args.recording, "eval")
    try:
        T_true = truth_per_frame(rec.path, len(rec), lambda w: warn("eval", f"warning: {w}"),
                                 need_first="--gt-init" if args.gt_init and not args.init_pose else None)
    except FileNotFoundError as e:
        print(f"vespro eval: {e}", file=sys.stderr)
        return 2
    out = args.out or (args.recording / "eval")
    try:
        init_pose = parse_pose(args.init_pose) if args.init_pose else (T_true[0] if args.gt_init else None)
    except ValueError as e:
        print(f"vespro eval: {e}", file=sys.stderr)
        return 2
    tracker = make_tracker(rec, tracker_config(args), unit=args.model_unit, workspace=workspace_of(args))
    if init_pose is None:
        tracker.initializer = initializer_for(args, rec, tracker.model)
        if tracker.initializer is None:
            print("vespro eval: an initial pose is needed (--init-pose, or --gt-init)", file=sys.stderr)
            return 2
    say_symmetry("vespro eval", tracker, init_pose is not None, tracker.initializer is not None)
    out.mkdir(parents=True, exist_ok=True)  # after the inputs are checked: bad input leaves nothing behind
    outs = track_recording(rec, tracker, init_pose, progress=not args.no_progress)
    write_track(out / "poses.csv", rec, outs)
    report_images(rec, "eval")  # before the overlay video reads the images again
    model = tracker.model
    T_f = [o.T_world_object for o in outs]
    st = [o.status for o in outs]
    filt = score(T_f, st, T_true, rec.t, model, [o.time_ms for o in outs], [o.cov6 for o in outs])
    T_b = pnp_baseline(rec, outs, model)
    base = score(T_b, ["tracking" if T is not None else "lost" for T in T_b], T_true, rec.t, model)
    summary = {"recording": str(args.recording), "frames": len(rec), "cameras": rec.rig.names,
               "filter": filt, "baseline_pnp": base}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2))
    plot_errors(out / "errors.png", rec.t, {"EKF": T_f, "solvePnP per frame": T_b}, T_true, [o.cov6 for o in outs])
    if not args.no_video:
        overlay_video(out / "overlay.mp4", rec, outs, model)
    print(f"{'':24}{'EKF':>12}{'solvePnP':>12}")
    for key, unit in [("position_rmse_mm", " mm"), ("position_max_mm", " mm"), ("orientation_rmse_deg", " deg"),
                      ("orientation_max_deg", " deg"), ("add_mm", " mm"), ("tracked_fraction", "")]:
        print(f"{key:24}{_fmt(filt.get(key)):>12}{_fmt(base.get(key)):>12}")
    print(f"time to first track {_fmt(filt['time_to_first_track_s'], ' s')}, per-frame time median "
          f"{_fmt(filt.get('time_ms_median'), ' ms')} p99 {_fmt(filt.get('time_ms_p99'), ' ms')}, "
          f"NEES in 95% band {_fmt(filt.get('nees_in_band'))}")
    print(f"wrote {out}/summary.json, errors.png{'' if args.no_video else ', overlay.mp4'}, poses.csv")
    return 0
