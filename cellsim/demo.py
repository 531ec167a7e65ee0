"""The whole cell, end to end: plant, pose server and servo as three processes.

- the plant (``python -m cellsim.plant``): the cell's physics at 500 Hz in
  real time, a part arriving on the conveyor, the arm's drives on a
  shared-memory fieldbus, the world state for the cameras;
- the pose server (``vespro serve --source world``): renders the cameras from
  the world state at 26 Hz, tracks the part from the images alone (automatic
  initialisation, no ground truth) and publishes every estimate on the link;
- the servo (``servo run --robot shm:...``): the 500 Hz visual-servoing loop
  driving the plant's arm from the poses it receives.

The link is TCP on localhost, or with ``link="serial"`` a pair of
pseudo-terminals bridged by this process at a simulated baud rate (a serial
cable). Afterwards the demo scores the run against the plant's ground-truth log
(an evaluator: only here is ground truth read) and writes ``summary.json``,
plots, the overlay video, the servo's time histories and the recording itself,
which ``vespro eval`` replays.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .steal import read_steal_ms, steal_since

__all__ = ["DemoConfig", "run_demo", "CAMERA_SETS"]

CAMERA_SETS = {"fixed": "fixed3", "eye-in-hand": "hand", "hybrid": "hybrid"}
STANDOFF = 0.15


def cell_workspace() -> tuple:
    """The demo cell's working volume as its user states it (``--workspace``): the stretch of
    conveyor the cameras watch, from 10 cm under its belt's top to 30 cm over it; world, m."""
    from vespro.sim.scene import WATCHED_VOLUME

    return WATCHED_VOLUME


@dataclass(frozen=True)
class DemoConfig:
    """What the demo runs.

    Attributes
    ----------
    out : Path
    object : str
    cameras : str
        ``fixed`` (three fixed cameras), ``eye-in-hand`` or ``hybrid``.
    duration : float
        Simulated (and, in real time, wall) seconds of plant time.
    speed : float
        Belt speed, m/s.
    y0 : float
        Where the part starts along the belt, m.
    stop_time : float
        When the belt starts stopping, s.
    noise_px : float
        Pixel noise of the rendered images.
    link : str
        ``tcp`` or ``serial``.
    baud : int
        Serial link's simulated baud rate.
    video : bool
    kill_server_at : float or None
        Kill the pose server this many seconds into the run (a failure test).
    view, view_connect, view_save, view_image_every
        The Rerun view (:mod:`vespro.viewer`): spawn a viewer, stream to one at
        a URL, save a ``.rrd``; every n-th image. In real time the pose server and
        the servo each log into one recording (the servo: its end effector, target,
        series and events); in lockstep the demo adds the true pose, the arm's end
        effector and its target, and the servo's status and error against the truth.
    symmetry : str
        How the tracker picks among a symmetric part's equivalent poses
        (``TrackerConfig.symmetry``).
    """

    out: Path = Path("out/demo")
    object: str = "bracket"
    cameras: str = "hybrid"
    duration: float = 40.0
    speed: float = 0.05
    y0: float = -0.30
    stop_time: float = 11.0
    noise_px: float = 0.5
    link: str = "tcp"
    baud: int = 115200
    video: bool = True
    kill_server_at: float | None = None
    lockstep: bool = False
    view: bool = False
    view_connect: str | None = None
    view_save: Path | None = None
    view_image_every: int = 1
    symmetry: str = "continuity"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class SerialBridge:
    """Two pty pairs joined by a thread: a serial cable at ``baud`` (8N1)."""

    def __init__(self, baud: int):
        import pty
        import tty

        self.m_a, s_a = pty.openpty()
        self.m_b, s_b = pty.openpty()
        for fd in (self.m_a, self.m_b, s_a, s_b):
            tty.setraw(fd)
        self.path_a, self.path_b = os.ttyname(s_a), os.ttyname(s_b)
        self._keep = (s_a, s_b)  # keep the slaves open so the masters do not see hang-ups
        self.bytes_per_s = baud / 10.0
        self.bytes = 0
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True, name="serial-bridge")
        self._t.start()

    def _run(self) -> None:
        import select

        t_free = time.monotonic()
        while not self._stop.is_set():
            r, _, _ = select.select([self.m_a], [], [], 0.1)
            if not r:
                continue
            try:
                data = os.read(self.m_a, 4096)
            except OSError:
                time.sleep(0.01)
                continue
            # The bytes leave the cable no faster than the line rate.
            t_free = max(t_free, time.monotonic()) + len(data) / self.bytes_per_s
            delay = t_free - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            try:
                os.write(self.m_b, data)
                self.bytes += len(data)
            except OSError:
                pass

    def close(self) -> None:
        self._stop.set()
        self._t.join(1)
        for fd in (self.m_a, self.m_b, *self._keep):
            try:
                os.close(fd)
            except OSError:
                pass


def _spawn(cmd: list[str], log: Path, **env_extra) -> subprocess.Popen:
    """Start a cell process in a process group of its own, output to ``log``."""
    f = open(log, "w")
    env = dict(os.environ, PYTHONUNBUFFERED="1", MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), **env_extra)
    return subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env, start_new_session=True)


def search_q0(cameras: str) -> np.ndarray | None:
    """Starting joints for a camera set whose only camera is on the arm (None: the home pose).

    The tool 0.3 m above the belt and 0.15 m past the cell's centre, looking back at the
    belt's entry 0.15 m before it: from the home pose the hand camera sees the floor, and
    straight above the belt it would see the part face-on, the view a single camera
    settles worst.
    """
    if cameras != "eye-in-hand":
        return None
    import mujoco

    from servo.kinematics import ArmKinematics, solve_ik

    from vespro.se3 import transform_from_rt
    from vespro.sim.scene import BELT_CENTER_X, BELT_TOP_Z, CELL_XML

    tcp = np.array([BELT_CENTER_X, 0.15, BELT_TOP_Z + 0.30])
    z = np.array([BELT_CENTER_X, -0.15, BELT_TOP_Z]) - tcp
    z /= np.linalg.norm(z)
    x = np.array([1.0, 0.0, 0.0]) - z * z[0]
    x /= np.linalg.norm(x)
    home = mujoco.MjModel.from_xml_path(str(CELL_XML)).key("home").qpos[:6]
    q, ok = solve_ik(ArmKinematics(), transform_from_rt(np.column_stack([x, np.cross(z, x), z]), tcp), home)
    if not ok:
        raise RuntimeError("demo: no arm configuration reaches the search pose")
    return q


def _wait_ready(proc: subprocess.Popen, log: Path, line: str, timeout_s: float, note=None,
                note_after_s: float = 15.0) -> bool:
    """Wait until ``log`` holds ``line`` (the process is ready), it exits, or ``timeout_s``;
    ``note()`` is called once if that takes longer than ``note_after_s``."""
    t0 = time.monotonic()
    while time.monotonic() < t0 + timeout_s and proc.poll() is None:
        if log.exists() and line in log.read_text(errors="replace"):
            return True
        if note is not None and time.monotonic() > t0 + note_after_s:
            note()
            note = None
        time.sleep(0.05)
    return False


#: Where a spawned Rerun viewer listens (the servo connects there when the pose server spawned it).
VIEWER_URL = "rerun+http://127.0.0.1:9876/proxy"
VIEW_APP_ID = "vespro demo"


def view_options(cfg: DemoConfig, recording_id: str, t0_ns: int) -> tuple[list[str], list[str]]:
    """The view options of the pose server and of the servo (the real-time demo): both log into
    one recording (same application and recording ids, same time zero on the shared monotonic
    clock); each saves its own file (``--view-save``), joined at the end (:func:`_merge_view`)."""
    if not (cfg.view or cfg.view_connect or cfg.view_save):
        return [], []
    common = ["--view-recording-id", recording_id, "--view-app-id", VIEW_APP_ID, "--view-t0-ns", str(t0_ns)]
    vision = (["--view"] if cfg.view else []) + (["--view-connect", cfg.view_connect] if cfg.view_connect else [])
    vision += ["--view-save", str(cfg.view_save)] if cfg.view_save else []
    servo = ["--view-connect", cfg.view_connect or VIEWER_URL] if (cfg.view or cfg.view_connect) else []
    servo += ["--view-save", str(_servo_rrd(cfg.view_save))] if cfg.view_save else []
    return vision + ["--view-image-every", str(cfg.view_image_every)] + common, servo + common


def _servo_rrd(path: Path) -> Path:
    return Path(path).with_suffix(".servo.rrd")


def _merge_view(cfg: DemoConfig, log) -> None:
    """Join the servo's saved view into the pose server's file (one recording, one file)."""
    from vespro.viewer import merge_rrd

    main, servo = Path(cfg.view_save), _servo_rrd(cfg.view_save)
    if not (main.exists() and servo.exists()):
        log(f"demo: view: {servo if main.exists() else main} missing; {main} not merged")
        return
    try:
        merge_rrd([main, servo], main)
    except RuntimeError as e:
        log(f"demo: view: {e}; the servo's series stay in {servo}")
        return
    servo.unlink()


def run_demo(cfg: DemoConfig, log=print) -> dict:
    """Run the cell; returns the summary (also written to ``out/summary.json``)."""
    if cfg.lockstep:
        return run_demo_lockstep(cfg, log)
    from servo.shm_robot import RobotShm

    from vespro.sim.world import WorldShm

    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    rig = CAMERA_SETS[cfg.cameras]
    q0 = search_q0(cfg.cameras)
    robot = RobotShm(None)
    world = WorldShm(None)
    bridge = SerialBridge(cfg.baud) if cfg.link == "serial" else None
    port = _free_port()
    py = sys.executable
    procs = {}
    t_start = time.monotonic()
    events = []
    view_vision, view_servo = view_options(cfg, str(uuid.uuid4()), time.monotonic_ns())
    try:
        link_args = ["--serial", bridge.path_a, "--baud", str(cfg.baud)] if bridge else ["--tcp", str(port)]
        procs["vision"] = _spawn([py, "-m", "vespro", "serve", "--source", "world", "--world-shm", world.name,
                                  "--object", cfg.object, "--rig", rig, "--noise", str(cfg.noise_px),
                                  # Real time on 2 cores: no multisampling (46 -> 21 ms for three cameras),
                                  # a 0.6 px blur for the pixel integration it provided (0.84 -> 0.96 mm).
                                  "--render-samples", "0", "--blur", "0.6", "--mono",
                                  "--record", str(out / "vision"), "--record-defer-png", *link_args, *view_vision,
                                  # The vision PC's live loop owns a core (other work on it waits) and
                                  # renders in its own thread: the software renderer's own thread, handed
                                  # each frame and waited for, cost capture instants (six runs each:
                                  # 1-16 of ~1030 missed with it, 0-4 without; spread over both cores
                                  # it stalled on the servo's, 30 ms wall for 15 ms of work).
                                  "--cpu", "0", "--fifo", "10", "--symmetry", cfg.symmetry,
                                  # The initialiser's worker ahead of the machine's other normal work
                                  # (behind the real-time loops): the first track waits for it.
                                  "--init-nice", "-10",
                                  # Where the part can be: the start's search looks nowhere else (85% of its
                                  # hypotheses on these views lie elsewhere; a call costs a quarter less).
                                  "--workspace", ",".join(f"{v:.3f}" for v in cell_workspace())],
                                 out / "vision.log", LP_NUM_THREADS="0")
        # The plant (the world's clock) starts once the pose server is ready to capture: it
        # builds its tracker, initialiser and worker first (a second or two), and the cell's
        # first seconds would go by unseen.
        # Its kernels are compiled at set-up (python3 -m vespro.warmup); without that the first
        # run compiles them here, which can take a minute.
        _wait_ready(procs["vision"], out / "vision.log", "vespro serve: world source", timeout_s=120.0,
                    note=lambda: log("demo: waiting for the pose server (a first run without set-up's "
                                     "python3 -m vespro.warmup compiles its kernels: up to a minute)"))
        url = bridge.path_b if bridge else f"socket://127.0.0.1:{port}"
        procs["servo"] = _spawn([py, "-m", "servo", "run", "--connect", url, "--baud", str(cfg.baud),
                                 "--robot", f"shm:{robot.name}", "--standoff", str(STANDOFF),
                                 "--record", str(out / "servo"), "--record-seconds", str(cfg.duration + 30),
                                 # The servo's own timing policy applies: a late tick is counted, a burst
                                 # of them or one over 20 ms stops the arm, one over 100 ms cuts the drives.
                                 "--cpu", "1",
                                 "--stats-json", str(out / "servo" / "stats.json"), *view_servo],
                                out / "servo.log")
        # The servo sets itself up (imports, the arm's model, memory locked) and waits for the
        # arm's controller before the plant starts the world's clock: set up beside the start's
        # search, on the core the search shares, it delayed the first track.
        _wait_ready(procs["servo"], out / "servo.log", "servo run: connecting to", timeout_s=60.0)
        procs["plant"] = _spawn([py, "-m", "cellsim.plant", "--robot-shm", robot.name, "--world-shm", world.name,
                                 "--object", cfg.object, "--duration", str(cfg.duration), "--speed", str(cfg.speed),
                                 "--y0", str(cfg.y0), "--stop-time", str(cfg.stop_time),
                                 "--log", str(out / "plant.npz"),
                                 *(["--q0", ",".join(f"{v:.9f}" for v in q0)] if q0 is not None else []),
                                 # The world keeps real time whatever else the machine runs: on the
                                 # servo's core (the servo sleeps most of each tick; it has priority 80).
                                 "--cpu", "1", "--fifo", "20"], out / "plant.log")
        log(f"demo: plant, pose server and servo started ({cfg.link} link); {cfg.duration:.0f} s of cell time")
        killed = False
        last = -1
        steal_at_start = read_steal_ms()  # the host's share of the CPUs over the cell's run (cellsim.steal)
        while procs["plant"].poll() is None:
            el = time.monotonic() - t_start
            if cfg.kill_server_at is not None and not killed and world.running and \
                    (time.monotonic_ns() - world.t0_ns) * 1e-9 > cfg.kill_server_at:
                os.killpg(procs["vision"].pid, signal.SIGKILL)
                killed = True
                events.append({"event": "pose server killed", "t_s": (time.monotonic_ns() - world.t0_ns) * 1e-9})
                log(f"demo: killed the pose server at t = {events[-1]['t_s']:.1f} s")
            for name in ("vision", "servo"):
                if procs[name].poll() is not None and not any(e.get("process") == name for e in events):
                    events.append({"process": name, "exited": procs[name].returncode,
                                   "t_s": (time.monotonic_ns() - world.t0_ns) * 1e-9 if world.t0_ns else el})
            if int(el) // 10 != last:
                last = int(el) // 10
                tail = (out / "vision.log").read_text().strip().splitlines()[-1:] if (out / "vision.log").exists() else []
                log(f"demo: {el:5.1f} s  vision: {tail[0] if tail else '...'}")
            if el > cfg.duration * 6 + 120:
                events.append({"event": "timeout"})
                break
            time.sleep(0.2)
        steal_at_end = read_steal_ms()
        # The plant has stopped: the servo sees its arm's controller gone and stops; the
        # vision source ends by itself and saves its run. Signal only what lingers.
        for name, grace in (("servo", 10.0), ("vision", 60.0)):
            p = procs[name]
            try:
                p.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(p.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
        for name, p in procs.items():
            try:
                p.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
                events.append({"process": name, "event": "killed after timeout"})
    finally:
        for p in procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
        if bridge:
            bridge.close()
        robot.close()
        world.close()
    if cfg.view_save:
        _merge_view(cfg, log)
    log("demo: scoring against the plant's ground truth")
    summary = summarize(out, cfg, events)
    summary["machine"] = {"steal_ms": steal_since(steal_at_start, steal_at_end)}
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


#: Vision latency in lockstep mode (capture to send), simulated: fixed so runs repeat exactly.
LOCKSTEP_LATENCY_NS = 40_000_000


class _DelayedPublisher:
    """Holds each pose until the simulated clock reaches its capture time plus the
    vision latency, then sends it on the real link (lockstep mode)."""

    def __init__(self, publisher, latency_ns: int):
        from collections import deque

        self.publisher = publisher
        self.latency_ns = latency_ns
        self.pending = deque()

    def publish(self, msg) -> None:
        self.pending.append(msg)

    def pump(self, now_ns: int) -> list:
        from dataclasses import replace

        sent = []
        while self.pending and self.pending[0].t_capture_ns + self.latency_ns <= now_ns:
            msg = replace(self.pending.popleft(), t_send_ns=now_ns)
            self.publisher.publish(msg)
            sent.append(msg)
        return sent

    def stats(self):
        return self.publisher.stats()


def run_demo_lockstep(cfg: DemoConfig, log=print) -> dict:
    """The same plant, pose server and servo code on one simulated clock, in one process.

    Each 2 ms tick the servo's scheduler ticks, then steps the plant (through the
    same shared-memory fieldbus); at each capture instant the pose server renders
    and tracks (initialisation inline: it takes no simulated time); poses go over
    the real TCP link, each released ``LOCKSTEP_LATENCY_NS`` after its capture,
    and the tick waits until the servo's receiver has it. Reproducible to the bit
    for a given configuration, whatever the machine's speed.
    """
    from servo.link_source import LinkSource
    from servo.loop import LoopConfig, LoopState, Scheduler
    from servo.planner import follow_task
    from servo.receiver import PoseReceiver
    from servo.recorder import Recorder
    from servo.report import write_stats_json
    from servo.shm_robot import RobotShm, ShmArm

    from vespro.clock import SimClock
    from vespro.library import object_mesh_path
    from vespro.link import PosePublisher
    from vespro.model import load_model
    from vespro.recording import AsyncRecordingWriter
    from vespro.rig import load_rig
    from vespro.server import PoseServer
    from vespro.sim.cell import CellConfig
    from vespro.sim.imaging import ImageEffects
    from vespro.sim.motion import Conveyor
    from vespro.sim.rigs import CAMERAS_DIR
    from vespro.sim.world import WorldShm
    from vespro.sources import WorldSource
    from vespro.se3 import transform_from_pq
    from vespro.server_record import save_run
    from vespro.symmetry import describe as describe_symmetry
    from vespro.tracker import Tracker, TrackerConfig
    from vespro.wire import HelloMsg

    from .plant import Plant

    out = Path(cfg.out)
    (out / "servo").mkdir(parents=True, exist_ok=True)
    mesh = object_mesh_path(cfg.object)
    robot_shm, world_shm = RobotShm(None), WorldShm(None)
    clock = SimClock(t0_ns=1_000_000_000)  # t0 = 0 would read as "not started"
    plant = Plant(robot_shm.name, world_shm.name, mesh, Conveyor(speed=cfg.speed, y0=cfg.y0, stop_time=cfg.stop_time),
                  cfg.duration, q0=search_q0(cfg.cameras))
    plant.start(clock.now_ns())
    rig = load_rig(CAMERAS_DIR / f"{CAMERA_SETS[cfg.cameras]}.yaml")
    cell_cfg = CellConfig(mesh, rig, effects=ImageEffects(noise_px=cfg.noise_px), mono=True)  # the cell's cameras are monochrome
    source = WorldSource(world_shm.name, cell_cfg, clock)
    model = load_model(mesh, name=cfg.object)
    tracker = Tracker(rig, model, TrackerConfig(symmetry=cfg.symmetry), workspace=cell_workspace())
    note = describe_symmetry(model.name, len(tracker.symmetries), cfg.symmetry, False, True)
    if note:
        log(f"demo: {note}")
    try:
        from vespro.init import make_initializer

        initializer = make_initializer(rig, model, workspace=cell_workspace())
    except ImportError:
        initializer = None
    pub = PosePublisher.tcp(HelloMsg(cell_cfg.rate_hz, (model.name,)), port=0, clock_ns=clock.now_ns,
                            heartbeat_period_s=0)
    delayed = _DelayedPublisher(pub, LOCKSTEP_LATENCY_NS)
    writer = AsyncRecordingWriter(out / "vision" / "recording", rig, mesh, cell_cfg.rate_hz, model.name, overwrite=True)
    outputs = []
    view = None
    if cfg.view or cfg.view_connect or cfg.view_save:
        from vespro.viewer import COLORS, RerunView

        view = RerunView(rig, model, spawn=cfg.view, connect=cfg.view_connect, save=cfg.view_save, block=True,
                         image_every=cfg.view_image_every, name=VIEW_APP_ID)

    def on_output(fs, o):
        writer.write(fs)
        outputs.append(o)
        if view is not None:  # the truth beside the estimate: the demo (an evaluator) reads the plant
            n = min(plant.k, len(plant.log["t_ns"]))
            i = int(np.clip(np.searchsorted(plant.log["t_ns"][:n], fs.t_ns), 0, max(n - 1, 0)))
            view.observe(fs, o, T_true=transform_from_pq(plant.log["object"][i]),
                         series={"latency_ms": LOCKSTEP_LATENCY_NS * 1e-6})

    server = PoseServer(source, tracker, delayed, clock, initializer, background_init=False, log=None,
                        on_output=on_output)
    host, port = pub.address
    rx = PoseReceiver(f"socket://{host}:{port}", clock_ns=clock.now_ns)
    t_wait = time.monotonic() + 10
    while rx.stats().state.name != "CONNECTED" and time.monotonic() < t_wait:
        rx.poll()
        time.sleep(0.01)
    link = LinkSource(rx)
    loop_cfg = LoopConfig(task=follow_task(STANDOFF), max_dt_ticks=50)
    state = LoopState(loop_cfg)
    arm = ShmArm(robot_shm.name)
    arm.plant_step = plant.step  # lockstep: the servo's tick steps the plant
    recorder = Recorder(int((cfg.duration + 1) * 500))
    period = 1e9 / cell_cfg.rate_hz
    t0 = clock.now_ns()
    nxt = {"k": 0}
    events = []
    kill_ns = None if cfg.kill_server_at is None else t0 + int(cfg.kill_server_at * 1e9)

    def on_tick(t_ns, out_cmd):
        if view is not None and plant.k % 10 == 0 and plant.k > 0:  # the arm at 50 Hz
            k = min(plant.k, len(plant.log["t_ns"])) - 1
            tcp = plant.log["tcp"][k, :3]
            goal = plant.log["object"][k, :3] + [0.0, 0.0, STANDOFF]
            view.log_series(t_ns, {"servo_status": int(out_cmd.status),
                                   "servo_error_mm": 1e3 * np.linalg.norm(tcp - goal)},
                            {"arm/tcp": (tcp, COLORS["orange"]),
                             "arm/target": (np.array(out_cmd.ref.p), COLORS["blue"])})
        if kill_ns is not None and t_ns >= kill_ns:
            if not events:  # the pose server dies: no more poses, its link closes
                pub.close()
                events.append({"event": "pose server killed", "t_s": (t_ns - t0) * 1e-9})
            return
        while t_ns >= t0 + nxt["k"] * period:
            fs = source.render_now()
            if fs is not None:
                server.step(fs)
            nxt["k"] += 1
        for msg in delayed.pump(t_ns):
            until = time.monotonic() + 5
            while time.monotonic() < until:
                m, _ = rx.latest(t_ns)
                if m is not None and m.seq == msg.seq:
                    break
                rx.poll(t_ns)

    sched = Scheduler(clock, arm, state, link, recorder=recorder, realtime=False, on_tick=on_tick)
    log(f"demo (lockstep): {cfg.duration:.0f} s of cell time on a simulated clock, one process")
    try:
        stats = sched.run(int(round(cfg.duration * 500)))
    finally:
        rx.close()
        link_stats = pub.stats()
        pub.close()
        plant.finish(out / "plant.npz")
        if view is not None and (line := view.close()):
            log(line)
        save_run(out / "vision", writer, outputs, server.stats, link_stats, source)
        source.close()
        arm.close()
        robot_shm.close()
        world_shm.close()
    recorder.save(out / "servo" / "servo")
    write_stats_json(out / "servo" / "stats.json", stats, rx, link.samples, loop_cfg.period_ns, False,
                     state=state)
    log("demo: scoring against the plant's ground truth")
    summary = summarize(out, cfg, events)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def _pose_arrays(pq: np.ndarray) -> np.ndarray:
    from vespro.se3 import transform_from_pq

    return np.array([transform_from_pq(r) for r in pq])


def summarize(out: Path, cfg: DemoConfig, events: list) -> dict:
    """Figures of a demo run from the files its processes left (ground truth: the plant log)."""
    import pickle

    from vespro.groundtruth import GroundTruthWriter
    from vespro.metrics import pose_error_vector, rmse
    from vespro.recording import Recording, RecordingError

    plant = np.load(out / "plant.npz")
    t_log = plant["t_ns"]
    t0 = int(t_log[0]) - int(round((t_log[1] - t_log[0]))) if len(t_log) > 1 else 0
    T_obj_log = _pose_arrays(plant["object"])
    tcp = plant["tcp"]
    summary = {"config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()}, "events": events}

    # Pose estimation against the truth at each capture instant.
    vision = out / "vision"
    outputs = []
    if (vision / "outputs.pkl").exists():
        with open(vision / "outputs.pkl", "rb") as f:
            outputs = pickle.load(f)
    est_t, pe, re = [], [], []
    first_track = None
    for o in outputs:
        i = int(np.clip(np.searchsorted(t_log, o.t_ns), 0, len(t_log) - 1))
        if o.status == "tracking" and o.T_world_object is not None:
            e = pose_error_vector(o.T_world_object, T_obj_log[i])
            est_t.append((o.t_ns - t0) * 1e-9)
            pe.append(np.linalg.norm(e[:3]))
            re.append(np.linalg.norm(e[3:]))
            if first_track is None:
                first_track = (o.t_ns - t0) * 1e-9
    pe, re = np.array(pe), np.array(re)
    summary["estimation"] = {
        "frames": len(outputs), "tracking_frames": int(len(pe)),
        "acquired": first_track is not None, "time_to_first_track_s": first_track,
        "position_rmse_mm": rmse(pe) * 1e3 if pe.size else None,
        "position_max_mm": float(pe.max() * 1e3) if pe.size else None,
        "orientation_rmse_deg": float(np.rad2deg(rmse(re))) if re.size else None,
        "orientation_max_deg": float(np.rad2deg(re.max())) if re.size else None,
    }
    if (vision / "server.json").exists():
        summary["vision"] = json.loads((vision / "server.json").read_text())

    # End-effector against the true object: the TCP should be STANDOFF above it, pointing down.
    goal = T_obj_log[:, :3, 3] + [0.0, 0.0, STANDOFF]
    err = np.linalg.norm(tcp[:, :3] - goal, axis=1)
    t_s = (t_log - t0) * 1e-9
    follow = np.zeros(len(err), bool)
    if first_track is not None:
        below = np.flatnonzero((t_s > first_track) & (err < 0.005))
        if below.size:
            follow[below[0]:] = True
    stopped = t_s > cfg.stop_time + cfg.speed / 0.2 + 3.0  # belt at rest for 3 s
    summary["tracking_error"] = {
        "reached_standoff": bool(follow.any()),
        "time_reached_s": float(t_s[follow][0]) if follow.any() else None,
        "moving_rmse_mm": rmse(err[follow & ~stopped]) * 1e3 if (follow & ~stopped).any() else None,
        "moving_max_mm": float(err[follow & ~stopped].max() * 1e3) if (follow & ~stopped).any() else None,
        "settled_rmse_mm": rmse(err[follow & stopped]) * 1e3 if (follow & stopped).any() else None,
        "settled_max_mm": float(err[follow & stopped].max() * 1e3) if (follow & stopped).any() else None,
    }
    if (out / "servo" / "stats.json").exists():
        summary["servo"] = json.loads((out / "servo" / "stats.json").read_text())
    if (out / "servo" / "servo.npz").exists():
        from servo.safety import Status

        rec = np.load(out / "servo" / "servo.npz")
        st, ts = rec["status"], (rec["t_ns"] - t0) * 1e-9
        stop = np.flatnonzero((st == int(Status.STOPPING)) | (st == int(Status.STOPPED)))
        summary.setdefault("servo", {})["first_stop_s"] = float(ts[stop[0]]) if stop.size else None
        change = np.concatenate([[0], np.flatnonzero(np.diff(st)) + 1]) if st.size else np.zeros(0, int)
        summary["servo"]["status_changes"] = [[float(ts[i]), Status(int(st[i])).name] for i in change]

    # Ground truth for the recording, so `vespro eval` can replay it.
    rec_path = vision / "recording"
    rec_ok = False
    if (rec_path / "frames.csv").exists():
        try:
            rec = Recording(rec_path)
        except RecordingError as e:
            # A pose server that was killed never finished its recording: say so, keep the rest.
            summary["recording_error"] = f"recording incomplete: {e}"
        else:
            rec_ok = True
            first_ns = outputs[0].t_ns if outputs else t0  # frames.csv times are relative to the first frame set
            with GroundTruthWriter(rec_path) as gt:
                for k in range(len(rec)):
                    i = int(np.clip(np.searchsorted(t_log, first_ns + int(round(rec.t[k] * 1e9))), 0, len(t_log) - 1))
                    gt.write(k, float(rec.t[k]), T_obj_log[i])
            summary["recording"] = str(rec_path)
    summary["realtime"] = _realtime_figures(summary.get("vision", {}), rec if rec_ok else None, outputs, t_log,
                                            T_obj_log, t0, first_track)
    _plots(out, est_t, pe, re, t_s, err, follow)
    if cfg.video and outputs and rec_ok:
        try:
            _video(out, rec_path, outputs, plant, t0)
            summary["video"] = str(out / "overlay.mp4")
        except Exception as e:  # a video problem must not lose the figures
            summary["video_error"] = repr(e)
    return summary


def _realtime_figures(vision: dict, rec, outputs, t_log, T_obj_log, t0: int, first_track: float | None) -> dict:
    """Whether the vision loop kept its rate: capture instants processed and missed, latency,
    the load it shed, and how soon after the part came into a camera's view it was tracked
    (in view: its origin projects inside the image of a camera, in front of it; from the
    recording's rig and eye-in-hand poses and the plant's true object poses)."""
    from vespro.se3 import invert_transform

    processed = int(vision.get("frames", 0))
    missed = int(vision.get("missed_captures", 0))
    fig = {"capture_instants": processed + missed, "processed": processed, "missed": missed,
           "processed_frac": processed / max(processed + missed, 1),
           "latency_ms_median": vision.get("latency_ms_median"), "latency_ms_p99": vision.get("latency_ms_p99"),
           "tracker_ms_median": vision.get("tracker_ms_median"), "tracker_ms_p99": vision.get("tracker_ms_p99"),
           "load_steps": vision.get("load_steps", []), "time_to_first_track_s": first_track,
           "first_in_view_s": None, "first_track_after_view_s": None}
    if rec is None or not outputs:
        return fig
    first_ns = outputs[0].t_ns
    for k in range(len(rec)):
        t_ns = first_ns + int(round(rec.t[k] * 1e9))
        T_wo = T_obj_log[int(np.clip(np.searchsorted(t_log, t_ns), 0, len(t_log) - 1))]
        for cam in rec.rig:
            T_wc = cam.T_world_camera if cam.is_fixed else rec.T_world_camera(cam.name, k)
            p = invert_transform(T_wc) @ T_wo[:, 3]
            if p[2] <= 0:
                continue
            u, v = (cam.intrinsics.K @ (p[:3] / p[2]))[:2]
            if 0 <= u < cam.intrinsics.width and 0 <= v < cam.intrinsics.height:
                fig["first_in_view_s"] = (t_ns - t0) * 1e-9
                break
        if fig["first_in_view_s"] is not None:
            break
    if fig["first_in_view_s"] is not None and first_track is not None:
        fig["first_track_after_view_s"] = first_track - fig["first_in_view_s"]
    return fig


def _plots(out: Path, est_t, pe, re, t_s, err, follow) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    ax[0].plot(est_t, np.asarray(pe) * 1e3, ".", ms=3)
    ax[0].set_ylabel("position error (mm)")
    ax[1].plot(est_t, np.rad2deg(re), ".", ms=3, color="C1")
    ax[1].set_ylabel("orientation error (deg)")
    ax[1].set_xlabel("time (s)")
    ax[0].set_title("Pose estimation error against ground truth (tracking frames)")
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "estimation_error.png", dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 3.5))
    ax.semilogy(t_s[::10], np.maximum(err[::10], 1e-5) * 1e3, lw=1)
    if follow.any():
        ax.axvline(t_s[follow][0], color="g", ls="--", label="stand-off reached")
        ax.legend()
    ax.set_ylabel("TCP error (mm)")
    ax.set_xlabel("time (s)")
    ax.set_title("End-effector error against the true object pose (stand-off target)")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(out / "tracking_error.png", dpi=100)
    plt.close(fig)

    hist_path = out / "servo" / "stats.period_hist_us.npy"
    if hist_path.exists():
        h = np.load(hist_path)
        fig, ax = plt.subplots(figsize=(9, 3.5))
        x = np.arange(len(h))
        ax.bar(x, np.maximum(h, 0.1), width=1.0, log=True)
        ax.set_xlim(-1, max(50, int(np.flatnonzero(h)[-1]) + 2) if h.any() else 50)
        ax.set_xlabel("|period error| (us, 1 us bins; last bin: >= 2 ms)")
        ax.set_ylabel("ticks")
        ax.set_title("Servo loop timing (500 Hz)")
        fig.tight_layout()
        fig.savefig(out / "loop_timing.png", dpi=100)
        plt.close(fig)


def _video(out: Path, rec_path: Path, outputs, plant, t0: int) -> None:
    """Camera views with the projected model and features, plus an inset of the arm."""
    import cv2

    from vespro.camera import CameraIntrinsics
    from vespro.evaluate import overlay_video
    from vespro.model import load_model
    from vespro.recording import Recording
    from vespro.rig import Rig, RigCamera
    from vespro.se3 import transform_from_pq, transform_from_rt
    from vespro.sim.cell import CellConfig, SimCell
    from vespro.sim.motion import Static

    rec = Recording(rec_path)
    model = load_model(rec.model_path)
    # An overview camera for the inset, looking at the arm and the belt from the side.
    eye, target = np.array([1.9, -1.7, 1.6]), np.array([0.55, 0.0, 0.6])
    f = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(f, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    over = RigCamera("overview", CameraIntrinsics.from_fovy(320, 240, 50), "fixed",
                     T_world_camera=transform_from_rt(np.column_stack([x, y, f]), eye))
    cell = SimCell(CellConfig(rec.model_path, Rig((over,))), Static(np.eye(4)))
    t_log = plant["t_ns"]
    by_index = {o.index: o for o in outputs}

    def inset(index: int) -> np.ndarray:
        o = by_index.get(index)
        t_ns = o.t_ns if o is not None else outputs[0].t_ns + int(rec.t[index] * 1e9)
        i = int(np.clip(np.searchsorted(t_log, t_ns), 0, len(t_log) - 1))
        cell.set_world(plant["q"][i], transform_from_pq(plant["object"][i]))
        img = cell.render_frameset(index, t_ns, 0.0).images["overview"]
        return cv2.rectangle(img, (0, 0), (img.shape[1] - 1, img.shape[0] - 1), (255, 255, 255), 1)

    # Re-index the live outputs by recording index (the recording fills capture gaps).
    outs = []
    from vespro.tracker import TrackerOutput

    for k in range(len(rec)):
        outs.append(by_index.get(k, TrackerOutput(k, 0, "initializing")))
    overlay_video(out / "overlay.mp4", rec, outs, model, inset=inset)
    cell.close()
