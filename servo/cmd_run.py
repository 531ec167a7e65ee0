"""``servo run``: follow the object streamed by a pose server."""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path

import numpy as np

from .report import status_line, write_stats_json


def add_parser(sub) -> None:
    p = sub.add_parser(
        "run", help="connect to a pose server and servo the arm onto the object",
        description=(
            "Connect to a pose server through a pyserial URL (socket://HOST:PORT, /dev/ttyUSB0, ...), "
            "then run the 500 Hz visual-servoing loop on the wall clock: approach a stand-off above the "
            "object, then follow it. The arm is the simulated MuJoCo arm (models/arm.xml) stepped in real "
            "time; a real arm is another Robot class. Prints one status line a second (status, poses used, "
            "their age, the link, and every stop, fault, late tick and rejected pose so far by cause), and a "
            "line for each stop, fault and status change with its time on the monotonic clock (s) and what "
            "tripped it; SIGINT or SIGTERM makes a controlled stop and exits."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--connect", default="socket://127.0.0.1:5555",
                   help="pyserial URL of the pose server, or zenoh/KEY[?connect=tcp/HOST:PORT] to subscribe to "
                        "the poses on Zenoh (pip install 'vespro[interop]'; see servo.zenoh_source)")
    p.add_argument("--baud", type=int, default=115200, help="serial lines: baud rate")
    p.add_argument("--standoff", type=float, default=0.15, help="TCP height above the object origin while following, m")
    p.add_argument("--standoff-frame", choices=["world", "object"], default="world",
                   help="world: straight above the object (world z), turned with its heading only, so its estimated "
                        "tilt does not move the stand-off point (parts on a belt or table); object: along the "
                        "object's own z axis, following its full orientation")
    p.add_argument("--config", type=Path, help="YAML loop configuration (servo.loop.LoopConfig.from_dict keys)")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: until SIGINT)")
    p.add_argument("--record", type=Path, help="write the time histories (NPZ + CSV) into this folder at the end")
    p.add_argument("--record-seconds", type=float, default=120.0, help="recorder capacity, s")
    p.add_argument("--no-latency-compensation", action="store_true", help="do not predict the pose to the tick time")
    p.add_argument("--cpu", type=int, help="pin the loop to this core and ask for SCHED_FIFO")
    p.add_argument("--robot", default="mujoco",
                   help="mujoco: the MuJoCo arm in this process; shm:NAME: a plant process on a shared-memory fieldbus")
    p.add_argument("--stats-json", type=Path, help="write tick, status and link statistics here at the end")
    p.add_argument("--max-dt-ticks", type=int,
                   help="a tick longer than this many periods is a timing FAULT, drives off (loop config default: 50)")
    p.add_argument("--stop-dt-ticks", type=int,
                   help="a tick longer than this many periods makes a controlled stop (loop config default: 10)")
    p.add_argument("--max-late-ticks", type=int,
                   help="more late ticks (over 1.5 periods) than this within --late-window make a controlled stop "
                        "(loop config default: 10)")
    p.add_argument("--late-window", type=float, help="window of the late-tick count, s (loop config default: 1.0)")
    p.add_argument("--clock-tolerance", type=float,
                   help="a pose captured after it was sent, or stamped after the tick, by more than this is "
                        "rejected (future_stamp / future), s (loop config safety.max_future_s, default 0.005)")
    from .view import add_view_options

    add_view_options(p)
    p.set_defaults(func=run)








def run(args) -> int:
    import yaml

    from .link_source import LinkSource
    from .loop import LoopConfig
    from .planner import follow_task
    from .receiver import PoseReceiver

    try:
        cfg = LoopConfig.from_dict(yaml.safe_load(args.config.read_text()) or {}) if args.config else LoopConfig()
    except (OSError, ValueError, yaml.YAMLError) as e:
        print(f"servo run: {args.config}: {e}", file=sys.stderr)
        return 2
    if cfg.task is None:
        cfg = LoopConfig(**{**cfg.__dict__, "task": follow_task(args.standoff, upright=args.standoff_frame == "world")})
    for opt, key in (("max_dt_ticks", "max_dt_ticks"), ("stop_dt_ticks", "stop_dt_ticks"),
                     ("max_late_ticks", "max_late_ticks"), ("late_window", "late_window_s")):
        if getattr(args, opt) is not None:
            try:
                cfg = LoopConfig(**{**cfg.__dict__, key: getattr(args, opt)})
            except ValueError as e:
                print(f"servo run: --{opt.replace('_', '-')}: {e}", file=sys.stderr)
                return 2
    if args.no_latency_compensation:
        cfg = LoopConfig(**{**cfg.__dict__, "latency_compensation": False})
    if args.clock_tolerance is not None:
        if not args.clock_tolerance >= 0:
            print("servo run: --clock-tolerance: expected a time >= 0 in seconds", file=sys.stderr)
            return 2
        cfg = LoopConfig(**{**cfg.__dict__, "safety": {**cfg.safety, "max_future_s": args.clock_tolerance}})
    try:
        receiver = PoseReceiver(args.connect, baudrate=args.baud,
                                future_tolerance_s=cfg.safety.get("max_future_s", 0.005))
    except ValueError as e:
        print(f"servo run: --connect: {e}", file=sys.stderr)
        return 2
    source = LinkSource(receiver)
    from .view import ViewUnavailable, view_from_args

    try:  # before the loop goes real-time (its process and thread must not inherit the loop's core
        # and class), and while a plant starts (it takes a second or two)
        view = view_from_args(args, cfg.model_path, cfg.site)
    except ViewUnavailable as e:
        receiver.close()
        print(f"servo run: {e}", file=sys.stderr)
        return 2
    try:
        robot = _robot(args, cfg)
    except ValueError as e:
        receiver.close()
        if view is not None:
            view.close()
        print(f"servo run: {e}", file=sys.stderr)
        return 2
    return _run(args, cfg, receiver, source, robot, view)


def _robot(args, cfg):
    """The arm the options name (ValueError: a line for the user)."""
    from .robot import MujocoArm

    if args.robot.startswith("shm:"):
        from .shm_robot import ShmArm

        robot = ShmArm(args.robot[4:])  # its plant is waited for once the loop is set up (Scheduler.run)
        return robot
    if args.robot == "mujoco":
        return MujocoArm(cfg.model_path)
    raise ValueError(f"unknown robot {args.robot!r} (mujoco or shm:NAME)")


def _run(args, cfg, receiver, source, robot, view) -> int:
    """The loop on the wall clock until SIGINT, the duration or the plant's end."""
    from .clock import WallClock
    from .loop import LoopState, Scheduler
    from .recorder import Recorder
    from .safety import Status

    clock = WallClock()
    state = LoopState(cfg)
    ticks_per_s = int(round(1e9 / cfg.period_ns))
    recorder = Recorder(int(args.record_seconds * ticks_per_s)) if args.record else None
    stopping = {"sigint": False, "t": None}
    sched = None
    last_line = [time.monotonic()]
    logged = {"events": 0, "status": None}

    def log_changes(t_ns, st):
        """One line per stop, fault or clamp (cause, value, limit) and per status change, on the loop clock."""
        rec = state.record
        if rec.stops.n != logged["events"]:
            for e in rec.stops_since(logged["events"]):
                line = f"t={e['t_s']:.6f} {e['kind']} {e['cause']} value {e['value']} limit {e['limit']}"
                print(f"servo run: {line}", flush=True)
                if view is not None:
                    view.event(t_ns, line, "ERROR" if e["kind"] == "fault" else "WARN")
            logged["events"] = rec.stops.n
        if st != logged["status"]:
            print(f"servo run: t={t_ns * 1e-9:.6f} status {st.name}", flush=True)
            if view is not None:
                view.event(t_ns, f"status {st.name}")
            logged["status"] = st

    t_end = [None]

    def on_tick(t_ns, out):
        st = Status(state.status)
        log_changes(t_ns, st)
        if view is not None:
            view.tick(t_ns, out, state, sched.q_meas, sched.last_compute_ns, sched.overruns, cfg.period_ns)
        if args.duration:  # wall time: late ticks are skipped, so the tick count alone would run longer
            if t_end[0] is None:
                t_end[0] = t_ns + int(args.duration * 1e9)
            elif t_ns >= t_end[0]:
                sched.request_stop()
        if not getattr(robot, "plant_alive", True):
            sched.request_stop()  # the plant (the arm's controller) has gone
        if stopping["sigint"]:
            if stopping["t"] is None:
                stopping["t"] = t_ns
            # End once at rest after the controlled stop (or after 3 s at the most).
            if st in (Status.HOLD, Status.STOPPED, Status.FAULT) or t_ns - stopping["t"] > 3_000_000_000:
                sched.request_stop()
        now = time.monotonic()
        if now - last_line[0] >= 1.0:
            last_line[0] = now
            print(status_line(state, receiver, t_ns), flush=True)

    sched = Scheduler(clock, robot, state, source, recorder=recorder, realtime=True, cpu=args.cpu, robot_wait_s=30.0,
                      rt_setup=args.cpu is not None, on_tick=on_tick)

    def _sigint(signum, frame):
        stopping["sigint"] = True
        state.request_stop()

    old = {s: signal.signal(s, _sigint) for s in (signal.SIGINT, signal.SIGTERM)}
    n = int(args.duration * ticks_per_s) if args.duration else 2**62  # statistics are kept in a ring
    print(f"servo run: connecting to {args.connect}; following {args.standoff:.3f} m above the object", flush=True)
    try:
        stats = sched.run(n)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        receiver.close()
        if view is not None and (line := view.close()):
            print(line, flush=True)
    if getattr(robot, "came_up", True) is False:
        print(f"servo run: the plant did not start within {sched.robot_wait_s:.0f} s", file=sys.stderr, flush=True)
        return 2
    if recorder is not None:
        args.record.mkdir(parents=True, exist_ok=True)
        npz, csv = recorder.save(args.record / "servo")
        print(f"servo run: wrote {npz} and {csv}")
    per = stats.period_ns[1:] - cfg.period_ns
    if args.stats_json:
        write_stats_json(args.stats_json, stats, receiver, source.samples, cfg.period_ns, bool(stopping["sigint"]),
                         state=state)
    print(f"servo run: {stats.n_ticks} ticks, {stats.overruns} overruns, compute median "
          f"{np.median(stats.compute_ns) * 1e-3:.0f} us, period error p99 {np.percentile(np.abs(per), 99) * 1e-3:.1f} us"
          if stats.n_ticks > 2 else "servo run: stopped", flush=True)
    return 0
