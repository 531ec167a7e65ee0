"""The 500 Hz servo loop: a per-tick core and a scheduler that owns timing.

``step(state, sample, t_ns, out) -> Status`` is the whole control law of one
tick: take the latest object sample (or None), advance the planner, run the
CLIK, check the command, write it into ``out``. It reads no clock, does no I/O,
never raises, and works on buffers allocated when the :class:`LoopState` is
built (NumPy/LAPACK still create a few small temporaries, e.g. in the 6x6 SVD;
there is no Python-level allocation of state). dt comes from the timestamps,
so a missed tick arrives as a doubled dt and is integrated as such.

:class:`Scheduler` reads the clock, calls ``step`` every 2 ms, sends the
command to a :class:`~servo.robot.Robot`, counts overruns and times each tick.
It runs on a :class:`~servo.clock.SimClock` (lockstep, virtual mode) or a
:class:`~servo.clock.WallClock` (real time, optionally pinned to a core with
SCHED_FIFO).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import math
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from .kinematics import DEFAULT_ARM_XML, ArmKinematics, Clik, ClikConfig
from .planner import (
    CartesianLimits,
    FollowTask,
    Phase,
    Reference,
    TrackingPlanner,
    Workspace,
)
from .rotation import matrix_from_quat, quat_from_matrix_into
from .events import EventKind, SafetyRecord
from .safety import Check, Safety, SafetyConfig, Status, StopPolicy
from .timing import TimingPolicy
from .target import TargetSample

__all__ = [
    "LoopConfig",
    "Command",
    "LoopState",
    "step",
    "SampleSource",
    "Scheduler",
    "TickStats",
    "Status",
]


@dataclass(frozen=True)
class LoopConfig:
    """Everything needed to build the loop (``servo run`` builds one from its config file).

    model_path : MJCF of the arm; site : the TCP site
    period_ns : nominal tick, ns
    late_tick_ticks, max_late_ticks, late_window_s, stop_dt_ticks, max_dt_ticks :
        the timing policy (:mod:`servo.timing`). A tick whose dt exceeds
        ``late_tick_ticks`` periods is late: counted, and integrated with its
        real dt. More than ``max_late_ticks`` late ticks within
        ``late_window_s``, or one tick longer than ``stop_dt_ticks`` periods,
        make a controlled stop (cause TIMING; ``safety.policy_timing``
        IMMEDIATE makes it a stop with drives off instead); tracking resumes
        once ``late_window_s`` has passed without another such trip. A tick
        longer than ``max_dt_ticks`` periods, or a clock that does not
        advance, is a FAULT: drives off, latched.
    limits, workspace : planner limits and reachable target region
    clik : CLIK gains
    safety : overrides of :class:`SafetyConfig` fields (joint limits come from the model)
    task : the follow task, or None (hold until a task or motion is given)
    latency_compensation : predict the object pose to the tick time
    joint_approach_after_ticks : when the Cartesian approach has been held at a
        joint limit for this many ticks, approach in joint space
        (:mod:`servo.joint_approach`); 0 never does
    """

    model_path: Path | str = DEFAULT_ARM_XML
    site: str = "tool"
    period_ns: int = 2_000_000
    late_tick_ticks: float = 1.5
    max_late_ticks: int = 10
    late_window_s: float = 1.0
    stop_dt_ticks: int = 10
    max_dt_ticks: int = 50
    limits: CartesianLimits = CartesianLimits()
    workspace: Workspace = field(default_factory=Workspace)
    clik: ClikConfig = ClikConfig()
    safety: dict = field(default_factory=dict)
    task: FollowTask | None = None
    latency_compensation: bool = True
    max_prediction_s: float = 0.3
    joint_approach_after_ticks: int = 100

    @classmethod
    def from_dict(cls, d: dict) -> "LoopConfig":
        """Build from plain data (a parsed YAML/JSON file), SI units.

        Keys: model_path, site, period_ns, late_tick_ticks, max_late_ticks,
        late_window_s, stop_dt_ticks, max_dt_ticks, latency_compensation,
        max_prediction_s; ``limits`` / ``workspace`` / ``clik``: the fields of
        :class:`CartesianLimits` / :class:`Workspace` / :class:`ClikConfig`;
        ``safety``: fields of :class:`SafetyConfig` (policies as
        "IMMEDIATE" / "CONTROLLED"); ``task``: ``pq_object_tcp`` (7 numbers
        ``x y z qw qx qy qz``, as on the wire) plus the other
        :class:`FollowTask` fields. Unknown keys raise ``ValueError``.
        """
        from .rotation import matrix_from_quat

        d = dict(d)
        kw = {}
        for k in ("model_path", "site", "period_ns", "late_tick_ticks", "max_late_ticks", "late_window_s",
                  "stop_dt_ticks", "max_dt_ticks", "latency_compensation", "max_prediction_s",
                  "joint_approach_after_ticks"):
            if k in d:
                kw[k] = d.pop(k)
        if "limits" in d:
            kw["limits"] = CartesianLimits(**d.pop("limits"))
        if "workspace" in d:
            kw["workspace"] = Workspace(**d.pop("workspace"))
        if "clik" in d:
            kw["clik"] = ClikConfig(**d.pop("clik"))
        if "safety" in d:
            saf = dict(d.pop("safety"))
            for k, v in saf.items():
                if k.startswith("policy_") and isinstance(v, str):
                    saf[k] = StopPolicy[v.upper()]
            kw["safety"] = saf
        if "task" in d:
            t = dict(d.pop("task"))
            pq = np.asarray(t.pop("pq_object_tcp"), float)
            if pq.shape != (7,):
                raise ValueError(f"task.pq_object_tcp: expected 7 numbers, got shape {pq.shape}")
            T = np.eye(4)
            T[:3, :3] = matrix_from_quat(pq[3:])
            T[:3, 3] = pq[:3]
            kw["task"] = FollowTask(T, **t)
        if d:
            raise ValueError(f"LoopConfig: unknown keys {sorted(d)}")
        return cls(**kw)

    def __post_init__(self):
        if not (self.late_tick_ticks >= 1.0 and self.stop_dt_ticks >= self.late_tick_ticks
                and self.max_dt_ticks >= 1 and self.max_late_ticks >= 0 and self.late_window_s > 0):
            raise ValueError("LoopConfig timing policy: need 1 <= late_tick_ticks <= stop_dt_ticks, max_dt_ticks >= 1, "
                             "max_late_ticks >= 0, late_window_s > 0")


class Command:
    """Output of one tick (preallocated, overwritten each tick).

    q (n,) rad, qd (n,) rad/s: joint command and velocity feedforward;
    drives_on: False after an immediate stop or a fault (the scheduler then
    calls ``robot.stop()``); status; flags: ``Check`` bits fired this tick;
    ref: the TCP reference (world frame); s_min: smallest Jacobian singular value;
    reject: why a pose that arrived this tick was not used (``servo.safety.Reject``,
    0 when used or none arrived); trip_value, trip_limit: what tripped the first
    of ``flags`` and its limit (SI units, see ``servo.events``; NaN when nothing).
    """

    def __init__(self, n: int):
        self.q = np.zeros(n)
        self.qd = np.zeros(n)
        self.drives_on = False
        self.status = Status.HOLD
        self.flags = 0
        self.ref = Reference()
        self.s_min = 0.0
        self.reject = 0
        self.trip_value = math.nan
        self.trip_limit = math.nan


class LoopState:
    """State that lasts between ticks (planner, integrator, safety timers) and the set-up.

    Build from a :class:`LoopConfig`, then call :meth:`start` with the measured
    joints before the first ``step``.
    """

    def __init__(self, config: LoopConfig = LoopConfig()):
        self.cfg = config
        self.kin = ArmKinematics(config.model_path, config.site)
        self.n = self.kin.n
        # The tool speed cap of the CLIK is the planner's linear limit (as a norm).
        self.clik = Clik(self.kin, config.clik, tcp_speed_max=config.limits.v_lin)
        self.planner = TrackingPlanner(
            config.limits,
            config.workspace,
            config.period_ns * 1e-9,
            latency_compensation=config.latency_compensation,
            max_prediction_s=config.max_prediction_s,
        )
        self.safety = Safety(SafetyConfig.from_kinematics(self.kin, **config.safety))
        self.timing = TimingPolicy(config.period_ns, config.late_tick_ticks, config.max_late_ticks,
                                   config.late_window_s, config.stop_dt_ticks, config.max_dt_ticks)
        self.record = SafetyRecord()
        self.q_cmd = np.zeros(self.n)
        self.q_new = np.zeros(self.n)
        self.qd = np.zeros(self.n)
        self.qdd = np.zeros(self.n)
        self.p_prev = np.zeros(3)
        self._quat = np.zeros(4)
        # CLIK runs on the reference at the tick time t (the previous output)
        # with the mean of the velocities at t and t + dt as feedforward: the
        # new joints then sit on the reference at t + dt up to O(dt^3 jerk).
        # (Using the new reference in the error *and* its velocity as
        # feedforward would count one tick twice: the joints would lead by v dt.)
        self.ref_prev = Reference()
        self.v_ff = np.zeros(3)
        self.w_ff = np.zeros(3)
        self.t_prev_ns: int | None = None
        self.status = Status.HOLD
        self.latched = False  # a controlled stop by a limit check: no auto-resume
        self.last_capture_ns: int | None = None
        self.n_rejected = 0
        self.n_used = 0  # poses taken by the planner
        self.stop_requested = False
        self.was_clamped = False
        self.joint_approach = None  # a joint-space approach in progress (servo.joint_approach)
        self.joint_approach_t0_ns = 0
        self.stall_ticks = 0
        self.flags_seen = 0
        self.motion = None
        self.motion_t0_ns = 0
        self.planner.set_task(config.task)

    def start(self, q_measured: np.ndarray, t_ns: int) -> None:
        """Initialise from the measured joints at time ``t_ns`` (also the reset path)."""
        np.clip(q_measured, self.clik.lo, self.clik.hi, out=self.q_cmd)
        self.kin.update(self.q_cmd, jacobian=False)
        quat_from_matrix_into(self.kin.R, self._quat)
        self.p_prev[:] = self.kin.p
        self.planner.set_task(self.planner.task)
        self.planner.reset(self.kin.p, self._quat)
        self.ref_prev.copy_from(self.planner.ref)
        self.safety.reset()
        self.t_prev_ns = int(t_ns)
        self.status = Status.HOLD
        self.latched = False
        self.flags_seen = 0
        self.last_capture_ns = None
        self.motion = None
        self.timing.reset()
        self.stop_requested = False
        self.joint_approach = None
        self.stall_ticks = 0

    def request_stop(self) -> None:
        """Ask for a controlled stop at the next tick (cause OPERATOR, latched until reset).

        Safe to call from a signal handler or another thread (sets a flag).
        """
        self.stop_requested = True

    def reset(self, q_measured: np.ndarray, t_ns: int) -> None:
        """Clear a latched stop or fault (explicit operator action); restart from rest."""
        self.start(q_measured, t_ns)

    def set_task(self, task: FollowTask | None) -> None:
        """Change the follow task (starts with the approach phase); ends a finished motion."""
        self.planner.set_task(task)
        self.joint_approach = None
        if self.status == Status.FINISHED:
            self.motion = None
            self.status = Status.HOLD

    def start_motion(self, motion, t_ns: int) -> None:
        """Run a classic motion (``JointTrapezoid``, ``CartesianTrapezoid``,
        ``ViaPath``) from ``t_ns``; ``step`` returns FINISHED at its end."""
        self.motion = motion
        self.motion_t0_ns = int(t_ns)
        if self.status in (Status.HOLD, Status.FINISHED, Status.TRACKING):
            self.status = Status.TRACKING


def _hold(state: LoopState, out: Command, status: Status, flags: int, drives_on: bool) -> Status:
    out.q[:] = state.q_cmd
    out.qd[:] = 0.0
    out.drives_on = drives_on
    out.status = status
    out.flags = flags
    state.status = status
    return status


def _joint_motion_step(state: LoopState, m, t: float, ref: Reference) -> None:
    """Joints from a joint-space motion at time ``t`` (s into it), the TCP reference from them."""
    m.sample(t, state.q_new, state.qd, state.qdd)
    np.clip(state.q_new, state.clik.lo, state.clik.hi, out=state.q_new)
    # Keep the TCP reference on the joint motion (pose, J qd, J qdd without
    # the Jd qd term), so that a controlled stop decelerates from where the
    # arm really is and how fast it really moves.
    kin = state.kin
    kin.update(state.q_new)
    ref.p[:] = kin.p
    quat_from_matrix_into(kin.R, ref.quat)
    J = kin.J
    np.dot(J[:3], state.qd, out=ref.v)
    np.dot(J[3:], state.qd, out=ref.w)
    np.dot(J[:3], state.qdd, out=ref.a)
    np.dot(J[3:], state.qdd, out=ref.alpha)


def _maybe_plan_joint_approach(state: LoopState, t_ns: int) -> None:
    """After the Cartesian approach has been held at a joint limit for ``joint_approach_after_ticks``
    ticks, plan a joint-space approach (see :mod:`servo.joint_approach`); recorded either way.

    The joint motion starts from rest: the arm held at a joint limit is (nearly) at rest there.
    """
    planner = state.planner
    if planner.phase != Phase.APPROACH or not state.clik.at_limit:
        state.stall_ticks = 0
        return
    state.stall_ticks += 1
    if state.stall_ticks < state.cfg.joint_approach_after_ticks:
        return
    state.stall_ticks = 0
    from .joint_approach import plan_joint_approach

    kin, saf = state.kin, state.safety.cfg
    qdd = np.full(state.n, state.cfg.clik.joint_brake_acc / 3.0)
    args = (kin.qd_max, qdd, state.cfg.limits.v_lin, saf.box_min, saf.box_max)
    T = np.eye(4)
    m = None
    for _ in range(2):  # aim where the part will be when the motion ends
        T[:3, :3] = matrix_from_quat(planner.tgt_q)
        T[:3, 3] = planner.tgt_p
        m = plan_joint_approach(kin, state.q_cmd, T, *args)
        if m is None:
            break
        planner.update_target(t_ns + int(m.duration * 1e9))
    planner.update_target(t_ns)
    state.record.add(t_ns, EventKind.JOINT_APPROACH, 0, math.nan if m is None else m.duration, math.nan)
    if m is None:  # nothing safe from here: the arm waits; try again in 1 s (the part moves)
        state.stall_ticks = -4 * state.cfg.joint_approach_after_ticks
    else:
        state.joint_approach = m
        state.joint_approach_t0_ns = t_ns


def _run_motion(state: LoopState, t_ns: int, dt: float, ref: Reference) -> bool:
    """Sample the classic motion; returns True when it has ended."""
    m = state.motion
    t = (t_ns - state.motion_t0_ns) * 1e-9
    if m.space == "joint":
        _joint_motion_step(state, m, t, ref)
    elif m.space == "task":
        m.sample(t, ref)
        _clik(state, dt)
    else:  # "position": TCP positions along a via path, orientation held
        m.sample(t, ref.p, ref.v, ref.a)
        _clik(state, dt)
    return t >= m.duration


def _clik(state: LoopState, dt: float, hold_back: bool = False) -> None:
    """Joints for t + dt from the reference at t (``ref_prev``) and the mean velocity.

    ``hold_back``: when the CLIK had to cut the motion (speed cap, joint
    velocity or joint limit), the planner's reference is moved to the arm
    (:meth:`TrackingPlanner.hold_back`), i.e. the plan is time-scaled to what
    the joints can do instead of running ahead of them.
    """
    rp, r = state.ref_prev, state.planner.ref
    np.add(rp.v, r.v, out=state.v_ff)
    state.v_ff *= 0.5
    np.add(rp.w, r.w, out=state.w_ff)
    state.w_ff *= 0.5
    clik = state.clik
    clik.step(state.q_cmd, rp.p, rp.quat, state.v_ff, state.w_ff, dt, state.q_new, state.qd)
    if hold_back and clik.limited:
        kin = state.kin
        kin.update(state.q_new)
        quat_from_matrix_into(kin.R, state._quat)
        J = kin.J
        np.dot(J[:3], state.qd, out=state.v_ff)
        np.dot(J[3:], state.qd, out=state.w_ff)
        state.planner.hold_back(kin.p, state._quat, state.v_ff, state.w_ff)


def step(state: LoopState, sample: TargetSample | None, t_ns: int, out: Command) -> Status:
    """One control tick. Never raises; all outcomes are a :class:`Status`.

    Parameters
    ----------
    state : LoopState
        Started with :meth:`LoopState.start`.
    sample : TargetSample or None
        The latest object sample (the same one may be passed again on later
        ticks: only a new ``t_capture_ns`` counts as new).
    t_ns : int
        Time of this tick, ns (dt is taken from the previous tick's stamp).
    out : Command
        Written in place.

    Every stop, fault, late tick and rejected pose is counted by cause in
    ``state.record`` (:class:`~servo.events.SafetyRecord`).
    """
    out.reject = 0
    out.trip_value = math.nan
    out.trip_limit = math.nan
    try:
        return _step(state, sample, t_ns, out)
    except Exception:  # noqa: BLE001 -- the loop must not raise; a bug becomes a FAULT
        state.flags_seen |= Check.PLANNER
        state.record.add(t_ns, EventKind.FAULT, Check.PLANNER, math.nan, math.nan)
        return _hold(state, out, Status.FAULT, int(Check.PLANNER), False)


def _trip(state: LoopState, out: Command, t_ns: int, kind: EventKind, flags: int, value: float, limit: float) -> None:
    """Record an event for each fired check (the first one's value goes into ``out``)."""
    tv, tl = state.safety.trip_value, state.safety.trip_limit
    first = True
    for bit in range(len(tv)):
        c = 1 << bit
        if flags & c:
            v, lim = (value, limit) if c in (Check.WATCHDOG, Check.TIMING, Check.OPERATOR) else (tv[bit], tl[bit])
            state.record.add(t_ns, kind, Check(c), v, lim)
            if first:
                out.trip_value, out.trip_limit, first = v, lim, False


def _step(state: LoopState, sample, t_ns: int, out: Command) -> Status:
    if state.t_prev_ns is None:
        return _hold(state, out, Status.FAULT, int(Check.TIMING), False)
    st = state.status
    if st == Status.STOPPED or st == Status.FAULT:
        state.t_prev_ns = t_ns
        return _hold(state, out, st, 0, False)
    dt_ns = t_ns - state.t_prev_ns
    safety = state.safety
    timing = state.timing
    if timing.broken(dt_ns):
        state.flags_seen |= Check.TIMING
        _trip(state, out, t_ns, EventKind.FAULT, Check.TIMING, dt_ns * 1e-9, timing.max_dt_ns * 1e-9)
        return _hold(state, out, Status.FAULT, int(Check.TIMING), False)
    state.t_prev_ns = t_ns
    dt = dt_ns * 1e-9
    planner = state.planner
    ref = planner.ref
    state.ref_prev.copy_from(ref)  # the reference at t (last tick's output)
    flags = 0

    # 1. timing policy (servo.timing)
    late_trip = False
    if timing.late(dt_ns):
        late_trip, late_value, late_limit = timing.observe_late(t_ns, dt_ns)
        state.record.add(t_ns, EventKind.LATE_TICK, 0, dt_ns * 1e-9, timing.late_ns * 1e-9)
    if late_trip:
        flags |= Check.TIMING
        state.flags_seen |= Check.TIMING
        if safety.cfg.policy_timing == StopPolicy.IMMEDIATE:
            _trip(state, out, t_ns, EventKind.IMMEDIATE_STOP, Check.TIMING, late_value, late_limit)
            return _hold(state, out, Status.STOPPED, flags, False)
        if st == Status.TRACKING or st == Status.FINISHED:
            _trip(state, out, t_ns, EventKind.STOP, Check.TIMING, late_value, late_limit)
            st = Status.STOPPING
        state.motion = None

    if state.stop_requested:  # the operator's stop: controlled, latched until reset
        state.stop_requested = False
        state.latched = True
        state.motion = None
        flags |= Check.OPERATOR
        if st == Status.TRACKING or st == Status.FINISHED:
            _trip(state, out, t_ns, EventKind.STOP, Check.OPERATOR, math.nan, math.nan)
            st = Status.STOPPING

    # 2. pose stream
    if sample is not None and sample.t_capture_ns != state.last_capture_ns:
        state.last_capture_ns = sample.t_capture_ns
        why = safety.sample_reject(sample, t_ns)
        if why == 0:
            safety.feed(t_ns)
            planner.set_sample(sample)
            state.n_used += 1
        else:
            state.n_rejected += 1
            out.reject = int(why)
            state.record.add(t_ns, EventKind.REJECT, int(why), safety.reject_value, safety.reject_limit)
            safety.reject_value = safety.reject_limit = math.nan

    # 3. mode and reference
    if state.motion is not None and st in (Status.TRACKING, Status.FINISHED):
        done = _run_motion(state, t_ns, dt, ref)
        st = Status.FINISHED if done else Status.TRACKING
        if done:
            if state.motion.space == "joint":
                state.kin.update(state.q_new, jacobian=False)
                quat_from_matrix_into(state.kin.R, state._quat)
                ref.set_rest(state.kin.p, state._quat)
            else:
                ref.v[:] = 0.0
                ref.w[:] = 0.0
                ref.a[:] = 0.0
                ref.alpha[:] = 0.0
            planner.otg.reset()
    else:
        if state.motion is not None:  # a stop interrupted the motion
            state.motion = None
        if st == Status.TRACKING and planner.task is not None and not safety.stream_ok(t_ns):
            flags |= Check.WATCHDOG
            state.flags_seen |= Check.WATCHDOG
            since = (t_ns - safety.t_last_valid_ns) * 1e-9 if safety.have_valid else math.inf
            immediate = safety.cfg.policy_watchdog == StopPolicy.IMMEDIATE
            _trip(state, out, t_ns, EventKind.IMMEDIATE_STOP if immediate else EventKind.STOP, Check.WATCHDOG,
                  since, safety.cfg.watchdog_timeout_s)
            if immediate:
                return _hold(state, out, Status.STOPPED, flags, False)
            st = Status.STOPPING
        if st == Status.HOLD or st == Status.FINISHED:
            if (not state.latched and planner.task is not None and safety.resume_ok(t_ns)
                    and timing.resume_ok(t_ns)):
                st = Status.TRACKING
                if planner.phase == Phase.IDLE:
                    planner.phase = Phase.APPROACH
        if st == Status.TRACKING and state.joint_approach is not None:
            m = state.joint_approach
            t_m = (t_ns - state.joint_approach_t0_ns) * 1e-9
            _joint_motion_step(state, m, t_m, ref)
            if t_m >= m.duration:  # at rest where the Cartesian approach can reach: it takes over
                state.joint_approach = None
                state.kin.update(state.q_new, jacobian=False)
                quat_from_matrix_into(state.kin.R, state._quat)
                ref.set_rest(state.kin.p, state._quat)
                planner.otg.reset()
        elif st == Status.TRACKING:
            res = planner.step(t_ns, dt)
            if res < 0:
                state.flags_seen |= Check.PLANNER
                _trip(state, out, t_ns, EventKind.FAULT, Check.PLANNER, float(res), 0.0)
                return _hold(state, out, Status.FAULT, int(Check.PLANNER), False)
            if planner.clamped and not state.was_clamped:
                state.record.add(t_ns, EventKind.CLAMP, 0, planner.clamp_distance, 0.0)
            state.was_clamped = planner.clamped
            _clik(state, dt, hold_back=True)
            if state.cfg.joint_approach_after_ticks > 0:
                _maybe_plan_joint_approach(state, t_ns)
        else:
            state.joint_approach = None
            at_rest = planner.stop_step(dt)
            if st == Status.STOPPING and at_rest:
                st = Status.HOLD
            _clik(state, dt, hold_back=True)

    # 4. check the command
    kin = state.kin
    kin.update(state.q_new, jacobian=False)
    checks = safety.check_command(state.q_new, state.q_cmd, dt, kin.p, state.p_prev)
    if checks:
        flags |= checks
        state.flags_seen |= checks
        if checks & Check.NONFINITE:
            _trip(state, out, t_ns, EventKind.FAULT, Check.NONFINITE, math.nan, math.nan)
            return _hold(state, out, Status.FAULT, flags, False)
        if safety.policy(checks) == StopPolicy.IMMEDIATE:
            _trip(state, out, t_ns, EventKind.IMMEDIATE_STOP, checks, math.nan, math.nan)
            return _hold(state, out, Status.STOPPED, flags, False)
        # a controlled stop by a limit check: latched
        state.latched = True
        state.motion = None
        if st == Status.TRACKING or st == Status.FINISHED:
            _trip(state, out, t_ns, EventKind.STOP, checks, math.nan, math.nan)
            st = Status.STOPPING

    # 5. commit
    state.q_cmd[:] = state.q_new
    state.p_prev[:] = kin.p
    out.q[:] = state.q_cmd
    out.qd[:] = state.qd
    out.drives_on = True
    out.status = st
    out.flags = flags
    out.s_min = state.clik.s_min
    out.ref.copy_from(ref)
    state.status = st
    return st


# --- scheduler -------------------------------------------------------------------


class SampleSource(Protocol):
    """Where the loop gets object poses (the link adapter, or a virtual target)."""

    def latest(self, now_ns: int) -> tuple[TargetSample | None, int]:
        """The newest sample available at ``now_ns`` and its age (ns)."""
        ...


@dataclass
class TickStats:
    """Per-tick timing of a scheduler run (arrays of length n_ticks).

    compute_ns : time inside the tick callable (``step`` or the baseline), ns
    tick_ns : wake-up to end of the tick's work (read, step, command, plant), ns
    lateness_ns : actual wake time - deadline, ns
    period_ns : interval between consecutive wake-ups, ns (first entry 0)
    status : Status per tick
    overruns : ticks whose work ended after the next deadline
    """

    compute_ns: np.ndarray
    tick_ns: np.ndarray
    lateness_ns: np.ndarray
    period_ns: np.ndarray
    status: np.ndarray
    overruns: int
    n_ticks: int
    rt_warning: str | None = None

    def period_error_ns(self, nominal_ns: int) -> np.ndarray:
        """|period - nominal| for ticks 1.., ns."""
        return np.abs(self.period_ns[1 : self.n_ticks] - nominal_ns)


class Scheduler:
    """Runs ``step`` every period on a clock, commanding a robot.

    Parameters
    ----------
    clock : SimClock or WallClock
    robot : Robot
    state : LoopState
    source : SampleSource or None
        Polled each tick (``latest(now_ns)``).
    recorder : servo.recorder.Recorder or None
        Channels recorded when the recorder has them: t_ns, q_cmd, qd_cmd,
        q_meas, p_ref, quat_ref, v_ref, status, flags, compute_ns, reject,
        trip_value, trip_limit (see ``servo.recorder.LOOP_CHANNELS``).
    realtime : bool
        Real-time mode: the tick time is the actual wake-up time (so a late
        tick yields a longer dt) and overruns are counted. In lockstep
        (False) the tick time is the deadline itself.
    lock_memory : bool
        With ``rt_setup``, ``mlockall`` the process for the run (no page faults).
    rt_setup : bool or None
        Pin to ``cpu``, ask for SCHED_FIFO at ``fifo_priority`` (falling back
        with a warning), freeze and disable the GC during the run. Defaults
        to ``realtime``; True in virtual mode measures compute time without
        preemption by other processes.
    tick_fn : callable or None
        Replaces ``step`` (same signature); used for the empty-tick baseline.
    on_tick : callable (t_ns, out) or None
        Called after each tick (tests, truth recording); outside the timed part.
    robot_wait_s : float
        In real time, how long to wait, set up and locked in memory, for a robot that says
        when it runs (``wait_alive``: an arm's controller coming up) before the first tick, s.
    """

    def __init__(
        self,
        clock,
        robot,
        state: LoopState,
        source: SampleSource | None = None,
        recorder=None,
        realtime: bool = False,
        cpu: int | None = None,
        fifo_priority: int | None = 80,
        tick_fn=None,
        on_tick=None,
        rt_setup: bool | None = None,
        lock_memory: bool = True,
        robot_wait_s: float = 60.0,
    ):
        self.robot_wait_s = float(robot_wait_s)
        self.rt_setup = realtime if rt_setup is None else bool(rt_setup)
        self.lock_memory = lock_memory
        self._locked = False
        self.clock = clock
        self.robot = robot
        self.state = state
        self.source = source
        self.recorder = recorder
        self.realtime = realtime
        self.cpu = cpu
        self.fifo_priority = fifo_priority
        self.tick_fn = tick_fn if tick_fn is not None else step
        self.on_tick = on_tick
        self.period_ns = state.cfg.period_ns
        self.out = Command(state.n)
        self._stop_requested = False
        self.stats_capacity = 300_000  # ticks of statistics kept: 10 min at 500 Hz
        self.q_meas = np.zeros(state.n)
        self._drives_off = False
        self.last_compute_ns = 0  # the last tick's compute time, and the overruns so far (for on_tick)
        self.overruns = 0

    @classmethod
    def from_config(cls, config: LoopConfig, clock, robot, source=None, **kw) -> "Scheduler":
        return cls(clock, robot, LoopState(config), source, **kw)

    def _enter_realtime(self) -> str | None:
        msgs = []
        if self.cpu is not None:
            try:
                os.sched_setaffinity(0, {self.cpu})
            except (OSError, AttributeError) as e:
                msgs.append(f"could not pin to CPU {self.cpu}: {e}")
        if self.fifo_priority is not None:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.fifo_priority))
            except (OSError, AttributeError) as e:
                msgs.append(f"SCHED_FIFO refused ({e}); running with the normal scheduler")
        if self.lock_memory:
            # Page faults (first touch, reclaimed pages) cost milliseconds: lock
            # what is mapped now and what gets mapped later.
            try:
                libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
                if libc.mlockall(3) != 0:  # MCL_CURRENT | MCL_FUTURE
                    raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()))
                self._locked = True
            except (OSError, AttributeError, TypeError) as e:
                msgs.append(f"mlockall failed ({e}); memory may page")
        if msgs:
            msg = "; ".join(msgs)
            warnings.warn(msg, RuntimeWarning, stacklevel=3)
            return msg
        return None

    def _leave_realtime(self, saved_affinity, saved_policy) -> None:
        if self._locked:
            try:
                ctypes.CDLL(ctypes.util.find_library("c")).munlockall()
            except (OSError, AttributeError):
                pass
            self._locked = False
        try:
            if self.fifo_priority is not None:
                os.sched_setscheduler(0, saved_policy[0], os.sched_param(saved_policy[1]))
            if saved_affinity is not None:
                os.sched_setaffinity(0, saved_affinity)
        except (OSError, AttributeError):
            pass

    def request_stop(self) -> None:
        """End :meth:`run` after the current tick (thread- and signal-safe)."""
        self._stop_requested = True

    def run(self, n_ticks: int) -> TickStats:
        """Run ``n_ticks`` ticks (or until :meth:`request_stop`); returns their timing."""
        clock, robot, state, out = self.clock, self.robot, self.state, self.out
        period = self.period_ns
        # Statistics of the last `cap` ticks (a ring: a run may last for days).
        cap = max(1, min(int(n_ticks), self.stats_capacity))
        compute = np.zeros(cap, dtype=np.int64)
        tick = np.zeros(cap, dtype=np.int64)
        late = np.zeros(cap, dtype=np.int64)
        per = np.zeros(cap, dtype=np.int64)
        stat = np.zeros(cap, dtype=np.int8)
        for a in (compute, tick, late, per, stat):
            a.fill(0)  # touch every page now: the resident memory stays flat while the ring fills
        overruns = self.overruns = 0
        rt_msg = None
        saved_aff = saved_pol = None
        drives_off = self._drives_off
        gc_was = gc.isenabled()
        if self.rt_setup:
            try:
                saved_aff = os.sched_getaffinity(0)
                saved_pol = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
            except (OSError, AttributeError):
                pass
            rt_msg = self._enter_realtime()
            gc.collect()
            gc.freeze()
            gc.disable()
        rec = self.recorder
        rec_ch = set(rec.channels) if rec is not None else set()
        perf = time.perf_counter_ns
        source = self.source
        q_meas = self.q_meas
        try:
            wait_alive = getattr(robot, "wait_alive", None)
            if self.realtime and wait_alive is not None:
                wait_alive(self.robot_wait_s)  # (not up in time: the caller sees it, `servo run` stops)
            robot.read(q_meas)
            t_next = clock.now_ns()
            state.start(q_meas, t_next)
            t_wake_prev = None
            drives_off = self._drives_off
            if drives_off:  # a new run is an explicit restart (state.start above)
                robot.enable()
                drives_off = False
            self._stop_requested = False
            for k in range(n_ticks):
                if self._stop_requested:
                    n_ticks = k
                    break
                j = k % cap
                t_next += period
                t_wake = clock.sleep_until(t_next)
                late[j] = t_wake - t_next
                per[j] = 0 if t_wake_prev is None else t_wake - t_wake_prev
                t_wake_prev = t_wake
                t_tick = t_wake if self.realtime else t_next
                robot.read(q_meas)
                sample = source.latest(t_tick)[0] if source is not None else None
                c0 = perf()
                st = self.tick_fn(state, sample, t_tick, out)
                c1 = perf()
                if out.drives_on:
                    if drives_off:  # the loop was reset (operator action): drives back on
                        robot.enable()
                        drives_off = False
                    robot.command(out.q, out.qd)
                else:
                    if not drives_off:
                        robot.stop()
                        drives_off = True
                robot.plant_step()
                t_end = clock.now_ns()
                compute[j] = self.last_compute_ns = c1 - c0
                tick[j] = t_end - t_wake if self.realtime else c1 - c0
                stat[j] = int(st)
                if self.realtime and t_end > t_next + period:
                    overruns += 1
                    self.overruns = overruns
                    # skip the missed deadlines: the next step sees a longer dt
                    while t_next + period < t_end:
                        t_next += period
                if rec is not None:
                    self._record(rec, rec_ch, t_tick, out, q_meas, c1 - c0)
                if self.on_tick is not None:
                    self.on_tick(t_tick, out)
        finally:
            self._drives_off = drives_off
            if self.rt_setup:
                gc.unfreeze()
                if gc_was:
                    gc.enable()
                self._leave_realtime(saved_aff, saved_pol)
        m = min(n_ticks, cap)
        shift = -(n_ticks % cap) if n_ticks > cap else 0  # oldest first
        arrs = [np.roll(a, shift)[:m] for a in (compute, tick, late, per, stat)]
        return TickStats(*arrs, overruns, n_ticks, rt_msg)

    @staticmethod
    def _record(rec, ch, t_ns, out, q_meas, compute_ns):
        row = rec.next_row()
        if row < 0:
            return
        if "t_ns" in ch:
            rec.data["t_ns"][row] = t_ns
        if "q_cmd" in ch:
            rec.data["q_cmd"][row] = out.q
        if "qd_cmd" in ch:
            rec.data["qd_cmd"][row] = out.qd
        if "q_meas" in ch:
            rec.data["q_meas"][row] = q_meas
        if "p_ref" in ch:
            rec.data["p_ref"][row] = out.ref.p
        if "quat_ref" in ch:
            rec.data["quat_ref"][row] = out.ref.quat
        if "v_ref" in ch:
            rec.data["v_ref"][row] = out.ref.v
        if "status" in ch:
            rec.data["status"][row] = int(out.status)
        if "flags" in ch:
            rec.data["flags"][row] = out.flags
        if "compute_ns" in ch:
            rec.data["compute_ns"][row] = compute_ns
        if "reject" in ch:
            rec.data["reject"][row] = out.reject
        if "trip_value" in ch:
            rec.data["trip_value"][row] = out.trip_value
        if "trip_limit" in ch:
            rec.data["trip_limit"][row] = out.trip_limit
