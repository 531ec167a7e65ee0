"""``vespro demo``'s run: the whole cell end to end, then its summary on the terminal.

The options are parsed by the ``vespro`` command (:mod:`vespro.cmd_demo`).
"""

from __future__ import annotations

from pathlib import Path


def _f(v, fmt="{:.2f}"):
    return "-" if v is None else fmt.format(v)


def run(args) -> int:
    """Run the demo with the options of ``vespro demo`` (:mod:`vespro.cmd_demo`); print its summary."""
    from vespro.library import object_mesh_path

    from .demo import DemoConfig, run_demo

    if Path(args.object).is_file():  # checked (and put in metres) once, before any process starts
        args.object = str(object_mesh_path(args.object, args.model_unit))

    cfg = DemoConfig(out=args.out, object=args.object, cameras=args.cameras, duration=args.duration,
                     speed=args.speed, stop_time=args.stop_time, noise_px=args.noise, link=args.link,
                     baud=args.baud, video=not args.no_video, kill_server_at=args.kill_server_at,
                     lockstep=args.lockstep, view=args.view, view_connect=args.view_connect,
                     view_save=args.view_save, view_image_every=args.view_image_every, symmetry=args.symmetry)
    s = run_demo(cfg, log=lambda m: print(m, flush=True))
    e, te, sv = s["estimation"], s["tracking_error"], s.get("servo", {})
    vis = s.get("vision", {})
    print()
    print(f"part acquired: {'yes' if e['acquired'] else 'NO'} (first track at {_f(e['time_to_first_track_s'])} s)")
    print(f"pose estimation: position RMSE {_f(e['position_rmse_mm'])} mm (max {_f(e['position_max_mm'])}), "
          f"orientation RMSE {_f(e['orientation_rmse_deg'])} deg (max {_f(e['orientation_max_deg'])}) "
          f"over {e['tracking_frames']}/{e['frames']} frames")
    print(f"end effector vs true part: stand-off reached {'yes' if te['reached_standoff'] else 'NO'} at "
          f"{_f(te['time_reached_s'])} s; following RMSE {_f(te['moving_rmse_mm'])} mm (max {_f(te['moving_max_mm'])}), "
          f"settled RMSE {_f(te['settled_rmse_mm'])} mm")
    if sv:
        pe = sv.get("period_error_us", {})
        print(f"servo: {sv['ticks']} ticks, {sv['overruns']} overruns, compute median {_f(sv['compute_us_median'], '{:.0f}')} us, "
              f"period error p99 {_f(pe.get('p99'), '{:.1f}')} us, controlled stops {sv['controlled_stops']}")
        lk = sv.get("link", {})
        print(f"link: {lk.get('poses')} poses received, {sum(lk.get('rejected', {}).values())} rejected, "
              f"{lk.get('seq_gaps')} sequence gaps; vision latency median {_f(vis.get('latency_ms_median'))} ms")
    if vis:
        print(f"vision: {vis['frames']} frames, {vis.get('missed_captures', 0)} capture deadlines missed, tracker "
              f"median {_f(vis['tracker_ms_median'])} ms")
    rt = s.get("realtime", {})
    if rt:
        steps = "; ".join(f"{st['what']} at {st['t_s']:.1f} s" for st in rt.get("load_steps", [])) or "none"
        print(f"real time: {rt['processed']}/{rt['capture_instants']} capture instants processed ({rt['missed']} "
              f"missed), capture-to-publish latency median {_f(rt['latency_ms_median'])} ms, p99 "
              f"{_f(rt['latency_ms_p99'])} ms; part tracked {_f(rt['first_track_after_view_s'])} s after it came "
              f"into view; load shed: {steps}")
    steal = s.get("machine", {}).get("steal_ms")
    if steal:
        # A virtual machine's host may stop a CPU whatever runs on it (cellsim.steal).
        print("machine: CPU time taken by the host (steal) during the run: "
              + ", ".join(f"{cpu} {ms:.0f} ms" for cpu, ms in steal.items())
              + (" (late servo ticks and missed capture instants can be the host's)" if sum(steal.values()) else ""))
    for ev in s.get("events", []):
        print(f"event: {ev}")
    if "recording_error" in s:
        print(f"note: {s['recording_error']}")
    print(f"wrote {args.out}/summary.json, estimation_error.png, tracking_error.png, loop_timing.png"
          f"{', overlay.mp4' if 'video' in s else ''}, servo/, vision/recording")
    return 0 if e["acquired"] else 1

