"""``vespro serve``: the standalone pose server process."""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from .errors import InputError


def add_parser(sub) -> None:
    from .options import add_tracker_options
    from .sim.scenario import add_scenario_options

    p = sub.add_parser(
        "serve", help="run the pose server: track a source, stream poses over TCP or a serial line",
        description=(
            "Track the object in frames from a source (the simulated cell, a recording replayed at its "
            "own rate, or live cameras) and publish every estimate (pose, velocity, covariance, status, "
            "capture and send stamps) with the vespro wire protocol over TCP (clients connect with "
            "socket://HOST:PORT) or a serial line. Logs one status line a second; SIGINT/SIGTERM stop it "
            "cleanly. A malformed input file stops it at start with one line naming the file and field, exit "
            "status 2. Replayed images that cannot be used (missing, truncated, unreadable, not 8-bit, of another "
            "size than the rig's) are skipped and counted per camera and reason, in the status line and in the "
            "summary at the end, where a camera that gave no usable image is named in a warning (exit status 0)."
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
    p.add_argument("--device", action="append", default=[],
                   help="camera: a cv2.VideoCapture device per rig camera, in the rig's order: an index (0), "
                        "a video file or a stream URL (rtsp://, http://, ...); a file is paced at its frame rate (its "
                        "own, or --rate), a camera or a stream is taken as its frames come")
    p.add_argument("--on-camera-end", choices=["stop", "retry"], default="stop",
                   help="camera: when a stream ends or a camera fails: stop the server, or reopen the device "
                        "with backoff (0.5 s doubling to 8 s; a file starts over). Either way the end is logged "
                        "once and the track published lost")
    p.add_argument("--stall-s", type=float, metavar="S",
                   help="camera: no frame for this long after one was due is a stall, published lost "
                        "(default: 3 frame periods, at least 0.1 s)")
    p.add_argument("--max-clients", type=int, default=8,
                   help="TCP: clients served at once; one more is sent a line saying why, then closed")
    p.add_argument("--model", type=Path, help="camera: the object's CAD file (STL, OBJ, PLY, ViSP .cao; see --model-unit)")
    p.add_argument("--lockstep", action="store_true",
                   help="sim/replay: run on simulated time as fast as possible instead of in real time")
    link = p.add_mutually_exclusive_group()
    link.add_argument("--tcp", type=int, default=5555, metavar="PORT", help="listen for TCP clients on this port")
    link.add_argument("--serial", metavar="URL", help="write to a serial device or pyserial URL instead")
    p.add_argument("--host", default="127.0.0.1", help="TCP: address to bind (localhost unless told otherwise)")
    p.add_argument("--baud", type=int, default=115200, help="serial: baud rate")
    add_zenoh_options(p)
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
    p.add_argument("--init-nice", type=int, default=0,
                   help="niceness of the initialisation worker process (negative = ahead of other normal work "
                        "while it searches; needs root)")
    p.add_argument("--no-shed-load", action="store_true",
                   help="live sources: keep the full load when capture deadlines are missed (by default the "
                        "server says so and steps down: images recorded at a lower rate, then fewer cameras)")
    add_scenario_options(p, rate_default=None)
    add_tracker_options(p)
    from .viewer import add_view_options

    add_view_options(p)
    p.set_defaults(func=run)


def add_zenoh_options(p: argparse.ArgumentParser) -> None:
    from .wire import ZENOH_ENDPOINT

    z = p.add_argument_group("Zenoh (pip install 'vespro[interop]')")
    z.add_argument("--zenoh", metavar="KEY",
                   help="also publish every pose (wire frames) on this Zenoh key expression, for any number of "
                        "subscribers (servo run --connect zenoh/KEY)")
    z.add_argument("--zenoh-listen", action="append", metavar="ENDPOINT",
                   help=f"Zenoh endpoint to listen on (repeatable; default {ZENOH_ENDPOINT}: this machine only)")
    z.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to, e.g. a router tcp/HOST:7447 (repeatable)")
    z.add_argument("--zenoh-config", metavar="FILE", help="a Zenoh JSON5 configuration file instead of the above")
    z.add_argument("--zenoh-ros2", metavar="TOPIC",
                   help="also publish tracked poses as ROS 2 geometry_msgs/PoseWithCovarianceStamped on TOPIC, "
                        "keyed as rmw_zenoh does (domain 0)")


def zenoh_publisher(args, hello, clock_ns):
    """The Zenoh publisher the options ask for, or None."""
    if not args.zenoh:
        return None
    from .wire import ZENOH_ENDPOINT
    from .zenoh_link import ZenohPublisher, ros2_key

    return ZenohPublisher(args.zenoh, hello, listen=args.zenoh_listen or [ZENOH_ENDPOINT],
                          connect=args.zenoh_connect, config_file=args.zenoh_config,
                          ros2_key=ros2_key(args.zenoh_ros2) if args.zenoh_ros2 else None, clock_ns=clock_ns)


def run(args) -> int:
    from .clock import SimClock, WallClock
    from .link import PosePublisher
    from .model import load_model, model_file_in_metres
    from .recording import RecordingError
    from .server import PoseServer
    from .sources import CameraSource, ReplaySource, SimSource
    from .track import parse_pose
    from .tracker import InitResult, Tracker
    from .wire import HelloMsg

    from .frames import FrameSet
    from .options import say_symmetry, tracker_config, workspace_of
    from .server_record import save_run

    camera_rate = args.rate
    if args.rate is None:
        args.rate = 26.0
    if args.max_clients < 1:
        raise ServeOptionError(f"--max-clients must be at least 1, got {args.max_clients}")
    if args.stall_s is not None and not args.stall_s > 0:
        raise ServeOptionError(f"--stall-s must be positive, got {args.stall_s}")
    log = None if args.quiet else (lambda line: print(line, flush=True))
    clock = SimClock() if args.lockstep else WallClock()
    from .realtime import enter_realtime, freeze_set_up, leave_realtime

    for msg in enter_realtime(args.cpu, args.nice, args.fifo):  # before any renderer or worker starts a thread
        print(f"vespro serve: {msg}", file=sys.stderr)
    if not args.lockstep:  # a live server runs for hours: freed images go back to the system
        from .memory import return_freed_images

        if (why := return_freed_images()) is not None:
            print(f"vespro serve: {why}", file=sys.stderr)
    try:
        if args.source == "replay":
            if not args.recording:
                raise ValueError("--source replay needs --recording PATH")
            from .recording_report import open_recording

            rec = open_recording(args.recording, "serve")
            source = ReplaySource(rec, clock, loop=args.loop)
            model_file = model_file_in_metres(rec.model_path, args.model_unit)
            model = load_model(model_file, name=rec.object_name)
        elif args.source == "sim":
            from .sim.cell import SimCell
            from .sim.scenario import build_config

            config, motion, name = build_config(args)
            cell = SimCell(config, motion)
            cell.settle_arm()
            source = SimSource(cell, clock)
            model_file = config.object_mesh
            model = load_model(model_file, name=name)
        elif args.source == "world":
            from .sim.scenario import build_config
            from .sources import WorldSource

            if not args.world_shm:
                raise ValueError("--source world needs --world-shm NAME")
            config, _, name = build_config(args)
            source = WorldSource(args.world_shm, config, clock)
            model_file = config.object_mesh
            model = load_model(model_file, name=name)
        else:
            from .rig import load_rig
            from .sim.rigs import rig_path

            if not args.model:
                raise ValueError("--source camera needs --model CAD_FILE")
            rig = load_rig(rig_path(args.rig))
            model_file = model_file_in_metres(args.model, args.model_unit)
            source = CameraSource(rig, args.device or ["0"], clock, rate_hz=camera_rate, on_end=args.on_camera_end,
                                  stall_s=args.stall_s, threaded=not args.lockstep,
                                  log=lambda line: print(f"vespro serve: {line}", flush=True))
            model = load_model(model_file, name=args.model.stem)
    except (ValueError, RecordingError) as e:
        print(f"vespro serve: {e}", file=sys.stderr)
        return 2

    tracker = Tracker(source.rig, model, tracker_config(args), workspace=workspace_of(args))
    factory = None
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
            from .options import init_options

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
        publisher = PosePublisher.tcp(hello, port=args.tcp, host=args.host, clock_ns=clock_ns,
                                      max_clients=args.max_clients,
                                      log=lambda line: print(f"vespro serve: {line}", flush=True))
        host, port = publisher.address
        where = f"tcp: connect to socket://{host}:{port}"
    zpub = zenoh_publisher(args, hello, clock_ns)
    if zpub is not None:
        from .link import PublisherGroup

        publisher = PublisherGroup(publisher, zpub)
        where += f"; zenoh key {args.zenoh}"
    outputs, writer = [], None
    if args.record:
        from .recording import AsyncRecordingWriter

        args.record.mkdir(parents=True, exist_ok=True)
        from functools import partial

        from .realtime import background_thread

        # The writer's thread: off the live loop's core and class, niced (it would inherit both).
        writer = AsyncRecordingWriter(args.record / "recording", source.rig, model_file, source.rate_hz, model.name,
                                      overwrite=True, defer_png=args.record_defer_png,
                                      thread_setup=partial(background_thread, args.cpu, 10))
    shedder = None
    if not args.lockstep and not args.no_shed_load:
        from .loadshed import LoadShedder

        shedder = LoadShedder(source.rate_hz, [(c.name, c.is_fixed) for c in source.rig])

    from .viewer import view_from_args

    view = view_from_args(args, source.rig, model, block=args.lockstep, name="vespro serve")

    def on_output(fs, out):
        if writer is not None:
            if shedder is not None and not shedder.record_images(fs.index):
                fs = FrameSet(fs.index, fs.t_ns, {k: None for k in fs.images}, fs.T_world_camera)
            writer.write(fs)
            outputs.append(out)
        if view is not None:
            view.observe(fs, out, series={"latency_ms": server.stats.last_latency_ms})

    mode = False if args.lockstep else ("process" if factory is not None else "thread")
    server = PoseServer(source, tracker, publisher, clock, initializer, background_init=mode, log=log,
                        on_output=on_output, initializer_factory=factory, shedder=shedder,
                        worker_nice=args.init_nice)

    def _stop(signum, frame):
        server.stop()

    if not server.wait_ready():
        print("vespro serve: the initialisation worker is not ready; starting anyway", file=sys.stderr, flush=True)
    old = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)}
    print(f"vespro serve: {args.source} source, cameras {', '.join(source.rig.names)}, object {model.name}; "
          f"{where}", flush=True)
    if not args.lockstep:
        freeze_set_up()
    try:
        stats = server.run(max_frames=args.frames)
    finally:
        link_stats = publisher.stats()
        publisher.close()
        source.close()
        if view is not None and (line := view.close()):
            print(line, file=sys.stderr)
        if writer is not None:
            if args.cpu is not None or args.fifo:  # the saving (PNG encoding) is not live work
                leave_realtime()
            save_run(args.record, writer, outputs, server.stats, link_stats, source, shedder)
        for s, h in old.items():  # restored last: a late signal must not interrupt the saving
            signal.signal(s, h)
    summ = stats.summary()
    print(f"vespro serve: stopped after {stats.frames} frames ({stats.tracking} tracking, "
          f"{stats.init_successes} initialisations); statuses {summ['statuses']}; tracker "
          f"{summ['tracker_ms_median']:.1f} ms median, {summ['tracker_ms_p99']:.1f} ms p99; latency "
          f"{summ['latency_ms_median']:.1f} ms median, {summ['latency_ms_p99']:.1f} ms p99"
          + (f"; {stats.source_gaps} source gap reports" if stats.source_gaps else "")
          + (f"; {source.missed} frames dropped behind" if getattr(source, "missed", 0) else ""), flush=True)
    for line in (source.images.report() if getattr(source, "images", None) is not None else []):
        print(f"vespro serve: {line}", file=sys.stderr, flush=True)
    return 0


class ServeOptionError(InputError):
    """An option of ``vespro serve`` out of its range."""
