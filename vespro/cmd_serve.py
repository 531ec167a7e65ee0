"""``vespro serve``: the standalone pose server process."""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path


def add_parser(sub) -> None:
    from .cmd_record import add_scenario_options
    from .cmd_track import add_tracker_options

    p = sub.add_parser(
        "serve", help="run the pose server: track a source, stream poses over TCP or a serial line",
        description=(
            "Track the object in frames from a source (the simulated cell, a recording replayed at its "
            "own rate, or live cameras) and publish every estimate (pose, velocity, covariance, status, "
            "capture and send stamps) with the vespro wire protocol over TCP (clients connect with "
            "socket://HOST:PORT) or a serial line. Logs one status line a second; SIGINT/SIGTERM stop it "
            "cleanly."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--source", choices=["sim", "replay", "camera", "world"], default="sim",
                   help="where frames come from (world: render a plant process's shared world state, the demo)")
    p.add_argument("--world-shm", help="world: name of the plant's world-state shared memory")
    p.add_argument("--record", type=Path, metavar="DIR",
                   help="also write DIR/recording (frames as served), DIR/poses.csv, DIR/outputs.pkl, DIR/server.json")
    p.add_argument("--record-defer-png", action="store_true",
                   help="with --record: keep frames raw while running and PNG-encode them at the end "
                        "(saves 3-8 ms of CPU per image while the loop runs; needs the disk for raw frames)")
    p.add_argument("--recording", type=Path, help="replay: the recording folder")
    p.add_argument("--loop", action="store_true", help="replay: start over at the end")
    p.add_argument("--device", action="append", default=[], help="camera: a cv2.VideoCapture device per rig camera")
    p.add_argument("--model", type=Path, help="camera: the object's CAD file (metres)")
    p.add_argument("--lockstep", action="store_true",
                   help="sim/replay: run on simulated time as fast as possible instead of in real time")
    link = p.add_mutually_exclusive_group()
    link.add_argument("--tcp", type=int, default=5555, metavar="PORT", help="listen for TCP clients on this port")
    link.add_argument("--serial", metavar="URL", help="write to a serial device or pyserial URL instead")
    p.add_argument("--host", default="127.0.0.1", help="TCP: address to bind (localhost unless told otherwise)")
    p.add_argument("--baud", type=int, default=115200, help="serial: baud rate")
    p.add_argument("--frames", type=int, help="stop after this many frames")
    p.add_argument("--quiet", action="store_true", help="no once-a-second status line")
    p.add_argument("--cpu", type=int, metavar="N",
                   help="pin the live loop (capture, rendering, tracking) to core N; the initialisation worker "
                        "stays free to use every core")
    p.add_argument("--nice", type=int, default=0,
                   help="scheduling niceness of the live loop (negative = ahead of other work; needs root)")
    p.add_argument("--fifo", type=int, default=0, metavar="PRIO",
                   help="run the live loop SCHED_FIFO at this priority (1-99; 0 = normal scheduling), as on a "
                        "dedicated vision PC: other work on its core waits; the initialisation worker is not")
    add_scenario_options(p)
    add_tracker_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from .clock import SimClock, WallClock
    from .link import PosePublisher
    from .model import load_model
    from .recording import Recording, RecordingError
    from .server import PoseServer
    from .sources import CameraSource, ReplaySource, SimSource
    from .track import parse_pose
    from .tracker import InitResult, Tracker
    from .wire import HelloMsg

    from .cmd_track import say_symmetry, tracker_config

    clock = SimClock() if args.lockstep else WallClock()
    from .realtime import enter_realtime, leave_realtime

    for msg in enter_realtime(args.cpu, args.nice, args.fifo):  # before any renderer or worker starts a thread
        print(f"vespro serve: {msg}", file=sys.stderr)
    try:
        if args.source == "replay":
            if not args.recording:
                raise ValueError("--source replay needs --recording PATH")
            rec = Recording(args.recording)
            source = ReplaySource(rec, clock, loop=args.loop)
            model = load_model(rec.model_path, name=rec.object_name)
        elif args.source == "sim":
            from .cmd_record import build_config
            from .sim.cell import SimCell

            config, motion, name = build_config(args)
            cell = SimCell(config, motion)
            cell.settle_arm()
            source = SimSource(cell, clock)
            model = load_model(config.object_mesh, name=name)
        elif args.source == "world":
            from .cmd_record import build_config
            from .sources import WorldSource

            if not args.world_shm:
                raise ValueError("--source world needs --world-shm NAME")
            config, _, name = build_config(args)
            source = WorldSource(args.world_shm, config, clock)
            model = load_model(config.object_mesh, name=name)
        else:
            from .cmd_record import rig_path
            from .rig import load_rig

            if not args.model:
                raise ValueError("--source camera needs --model CAD_FILE")
            rig = load_rig(rig_path(args.rig))
            source = CameraSource(rig, args.device or ["0"], clock, rate_hz=args.rate)
            model = load_model(args.model)
    except (ValueError, RecordingError) as e:
        print(f"vespro serve: {e}", file=sys.stderr)
        return 2

    tracker = Tracker(source.rig, model, tracker_config(args))
    initializer = factory = None
    if args.init_pose:
        T0 = parse_pose(args.init_pose)
        fired = []

        def initializer(fs, T0=T0):  # the user's pose, once
            if fired:
                return None
            fired.append(True)
            return InitResult(T0, given=True)
    else:
        try:
            from functools import partial

            from .init import make_initializer

            from .cmd_track import init_options

            opts = init_options(args)
            initializer = make_initializer(source.rig, model, **opts)
            factory = partial(make_initializer, source.rig, model, **opts)
        except ImportError:
            print("vespro serve: automatic initialisation is not available; pass --init-pose", file=sys.stderr)
            return 2
    say_symmetry("vespro serve", tracker, bool(args.init_pose), not args.init_pose)

    hello = HelloMsg(rate_hz=float(source.rate_hz), object_names=(model.name,))
    clock_ns = clock.now_ns
    if args.serial:
        publisher = PosePublisher.serial(hello, args.serial, baudrate=args.baud, clock_ns=clock_ns)
        where = f"serial {args.serial} at {args.baud} baud"
    else:
        publisher = PosePublisher.tcp(hello, port=args.tcp, host=args.host, clock_ns=clock_ns)
        host, port = publisher.address
        where = f"tcp: connect to socket://{host}:{port}"
    log = None if args.quiet else (lambda line: print(line, flush=True))
    outputs, writer = [], None
    if args.record:
        from .recording import AsyncRecordingWriter

        args.record.mkdir(parents=True, exist_ok=True)
        mesh = getattr(getattr(source, "cell", None), "config", None)
        mesh = mesh.object_mesh if mesh is not None else (args.model or rec.model_path)
        writer = AsyncRecordingWriter(args.record / "recording", source.rig, mesh, source.rate_hz, model.name,
                                      overwrite=True, defer_png=args.record_defer_png)

    def on_output(fs, out):
        if writer is not None:
            writer.write(fs)
            outputs.append(out)

    mode = False if args.lockstep else ("process" if factory is not None else "thread")
    server = PoseServer(source, tracker, publisher, clock, initializer, background_init=mode, log=log,
                        on_output=on_output, initializer_factory=factory)

    def _stop(signum, frame):
        server.stop()

    if not server.wait_ready():
        print("vespro serve: the initialisation worker is not ready; starting anyway", file=sys.stderr, flush=True)
    old = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)}
    print(f"vespro serve: {args.source} source, cameras {', '.join(source.rig.names)}, object {model.name}; "
          f"{where}", flush=True)
    try:
        stats = server.run(max_frames=args.frames)
    finally:
        link_stats = publisher.stats()
        publisher.close()
        source.close()
        if writer is not None:
            if args.cpu is not None or args.fifo:  # the saving (PNG encoding) is not live work
                leave_realtime()
            _save_run(args.record, writer, outputs, server.stats, link_stats, source)
        for s, h in old.items():  # restored last: a late signal must not interrupt the saving
            signal.signal(s, h)
    print(f"vespro serve: stopped after {stats.frames} frames ({stats.tracking} tracking, "
          f"{stats.init_successes} initialisations)", flush=True)
    return 0


def _save_run(folder: Path, writer, outputs, stats, link_stats, source) -> None:
    """What a recorded server run leaves for evaluation (the demo's summary)."""
    import json
    import pickle

    import numpy as np

    from .poses import PoseRow, write_poses

    writer.close()
    t0 = writer.t0_ns or 0
    write_poses(folder / "poses.csv", [
        PoseRow(o.index, (o.t_ns - t0) * 1e-9, o.status, o.T_world_object, o.time_ms, o.velocity, o.cov6)
        for o in outputs])
    with open(folder / "outputs.pkl", "wb") as f:
        pickle.dump(outputs, f)
    lat = np.array(stats.latency_ms) if stats.latency_ms else np.zeros(1)
    tm = np.array(stats.tracker_ms) if stats.tracker_ms else np.zeros(1)
    info = {
        "frames": stats.frames, "tracking": stats.tracking, "init_attempts": stats.init_attempts,
        "init_successes": stats.init_successes, "recording_dropped": writer.dropped,
        "missed_captures": getattr(source, "missed", 0),
        "tracker_ms_median": float(np.median(tm)), "tracker_ms_p99": float(np.percentile(tm, 99)),
        "latency_ms_median": float(np.median(lat)), "latency_ms_p99": float(np.percentile(lat, 99)),
        "link": {"frames_published": link_stats.frames_published, "frames_sent": link_stats.frames_sent,
                 "drops": link_stats.drops, "clients_accepted": link_stats.clients_accepted,
                 "errors": link_stats.errors},
    }
    (folder / "server.json").write_text(json.dumps(info, indent=2))
