"""Shared set-up for the servo tests (not a test module)."""

import numpy as np

from servo.kinematics import ArmKinematics, solve_ik
from servo.loop import Command, LoopConfig, LoopState
from servo.planner import FollowTask
from servo.target import TargetSample

DT_NS = 2_000_000
FRAME_NS = int(round(1e9 / 26))
T_DOWN = np.diag([1.0, -1.0, -1.0, 1.0])  # TCP 0.15 m above the object, pointing down
T_DOWN[2, 3] = 0.15
LATENCY_NS = 40_000_000

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
