"""Shared set-up for the servo tests (not a test module)."""

import select
import socket
import time

import numpy as np

from servo.kinematics import ArmKinematics, solve_ik
from servo.loop import Command, LoopConfig, LoopState
from servo.planner import FollowTask
from servo.target import TargetSample
from vespro import wire
from vespro.wire import HelloMsg, PoseMsg, PoseStatus

DT_NS = 2_000_000
FRAME_NS = int(round(1e9 / 26))
T_DOWN = np.diag([1.0, -1.0, -1.0, 1.0])  # TCP 0.15 m above the object, pointing down
T_DOWN[2, 3] = 0.15
LATENCY_NS = 40_000_000
WAIT_S = 10.0  # hang guard for "eventually" on the loopback link, not a speed requirement

_KIN = ArmKinematics()


def q_above(p_tcp=(0.9, 0.0, 0.8)) -> np.ndarray:
    """Joint configuration with the TCP at ``p_tcp`` pointing down."""
    T = np.diag([1.0, -1.0, -1.0, 1.0])
    T[:3, 3] = p_tcp
    q, ok = solve_ik(_KIN, T, np.array([0.0, 0.3, -0.3, 0.0, 1.57, 0.0]))
    assert ok
    return q


def obj_sample(t_capture_ns, p=(0.9, 0.0, 0.5), v=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0), **kw):
    return TargetSample(t_capture_ns, p, q, v, (0.0, 0.0, 0.0), np.eye(6) * 1e-6, **kw)


def make_loop(safety=None, **kw):
    cfg = LoopConfig(task=FollowTask(T_DOWN, standoff_m=0.1), safety=safety or {}, **kw)
    state = LoopState(cfg)
    state.start(q_above(), 0)
    return state, Command(state.n)


class ScriptedStream:
    """A fresh object sample every frame (26 Hz, 40 ms latency) unless told otherwise."""

    def __init__(self, p=(0.9, 0.0, 0.5), v=(0.0, 0.0, 0.0)):
        self.p = np.asarray(p, float)
        self.v = np.asarray(v, float)
        self.k = None
        self.s = None

    def at(self, t_ns):
        k = (t_ns - LATENCY_NS) // FRAME_NS
        if k < 0:
            return None
        if k != self.k:
            tc = k * FRAME_NS
            self.k = k
            self.s = obj_sample(tc, self.p + self.v * tc * 1e-9, self.v)
        return self.s


class MockRobot:
    """Records what the scheduler sends; a perfect plant (measured = commanded)."""

    def __init__(self, q0):
        self.n = 6
        self.q = np.array(q0, float)
        self.commands = 0
        self.stops = 0
        self.steps = 0
        self.enables = 0

    def read(self, q_out):
        q_out[:] = self.q

    def command(self, q, qd):
        self.q[:] = q
        self.commands += 1

    def stop(self):
        self.stops += 1

    def enable(self):
        self.enables += 1

    def plant_step(self):
        self.steps += 1


class FakePoseServer:
    """A pose server on 127.0.0.1 speaking the wire protocol, driven step by step by the test.

    Lockstep: every ``send`` waits until the receiver has decoded the frame,
    polling it at the simulated time the test gives, so what the loop sees
    does not depend on the machine's speed.
    """

    def __init__(self, names=("part",), rate_hz: float = 26.0):
        self.hello = HelloMsg(rate_hz, tuple(names))
        self.srv = socket.socket()
        self.srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.srv.bind(("127.0.0.1", 0))
        self.srv.listen(4)
        self.url = "socket://127.0.0.1:%d" % self.srv.getsockname()[1]
        self.conn = None

    def accept(self, rx, now_ns: int = 0, hello: bool = True) -> None:
        """Accept the receiver's (re)connection and send a HELLO first."""
        deadline = time.monotonic() + WAIT_S
        while self.conn is None:
            rx.poll(now_ns)
            r, _, _ = select.select([self.srv], [], [], 0.001)
            if r:
                self.conn, _ = self.srv.accept()
            assert time.monotonic() < deadline, "the receiver did not connect"
        while rx.stats().state.name != "CONNECTED":
            rx.poll(now_ns)
            assert time.monotonic() < deadline, "the receiver did not connect"
        if hello:
            self.send(rx, self.hello, now_ns, lead=b"\x00")

    def send(self, rx, msg, now_ns: int, lead: bytes = b"") -> None:
        """Send one message; return once the receiver has decoded (or rejected) it."""
        def seen():
            s = rx.stats()
            return s.frames_ok + s.rejected_total
        n0 = seen()
        self.conn.sendall(lead + wire.encode(msg))
        deadline = time.monotonic() + WAIT_S
        while seen() == n0:
            rx.poll(now_ns)
            assert time.monotonic() < deadline, "the frame did not arrive"

    def drop(self) -> None:
        """The server goes away (its connection closes)."""
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    def close(self) -> None:
        self.drop()
        self.srv.close()


def pose_msg(seq, t_capture_ns, t_send_ns, p, v=(0.0, 0.0, 0.0), object_id=0, status=PoseStatus.TRACKING,
             std_m=3e-4):
    """A POSE of an upright part (identity orientation)."""
    cov = np.diag([std_m**2] * 3 + [1e-6] * 3)
    return PoseMsg(seq, t_capture_ns, t_send_ns, object_id, status, p, [1.0, 0.0, 0.0, 0.0], v, [0.0, 0.0, 0.0], cov)


class BeltOverLink:
    """A part on a belt published by a :class:`FakePoseServer`: capture at 26 Hz,
    sent 40 ms later (the vision latency); call :meth:`tick` from the scheduler's
    ``on_tick`` to publish what is due by then."""

    def __init__(self, server: FakePoseServer, rx, p0, v, rate_hz: float = 26.0, latency_ns: int = LATENCY_NS):
        self.server, self.rx = server, rx
        self.p0, self.v = np.asarray(p0, float), np.asarray(v, float)
        self.period_ns = int(round(1e9 / rate_hz))
        self.latency_ns = latency_ns
        self.k = 0
        self.seq = 0
        self.paused_until_ns = -1

    def position(self, t_ns: int) -> np.ndarray:
        return self.p0 + self.v * (t_ns * 1e-9)

    def tick(self, t_ns: int) -> None:
        while self.k * self.period_ns + self.latency_ns <= t_ns:
            t_cap = self.k * self.period_ns
            self.k += 1
            if t_cap < self.paused_until_ns:
                continue  # the tracker published nothing for this frame
            self.server.send(self.rx, pose_msg(self.seq, t_cap, t_ns, self.position(t_cap), self.v), t_ns)
            self.seq += 1
