"""Safety checks on every joint command, and the watchdog on the pose stream.

The loop calls :meth:`Safety.check_command` on each new command and
:meth:`Safety.feed` / :meth:`Safety.stream_ok` for the pose stream. Each check
has a stop policy:

- ``IMMEDIATE``: hold the last safe position, drives off, latched until an
  explicit ``reset()`` of the loop;
- ``CONTROLLED``: decelerate to rest within the planner limits, then hold.
  For the watchdog the hold ends by itself once the stream has been valid for
  ``resume_hold_s``; for timing (see :class:`servo.loop.LoopConfig`) once the
  loop has kept time for its late-tick window; for the limit checks (joints,
  workspace, TCP speed) it is latched until ``reset()``: the plan keeps within
  them by construction, so a trip means something is wrong.

A non-finite command is always a ``FAULT`` (drives off, latched), and so is a
tick later than ``LoopConfig.max_dt_ticks`` periods or a clock going backwards.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field, replace

import numpy as np

from .target import SampleStatus, TargetSample

__all__ = ["Status", "StopPolicy", "Check", "Reject", "SafetyConfig", "Safety"]


class Status(enum.IntEnum):
    """What the loop is doing after a tick."""

    TRACKING = 0  # following the target (approach or follow phase)
    HOLD = 1  # at rest, drives on (waiting for a target, or after a controlled stop)
    STOPPING = 2  # controlled deceleration in progress
    STOPPED = 3  # immediate stop: holding, drives off, latched until reset()
    FINISHED = 4  # a point-to-point / via-point motion reached its end
    FAULT = 5  # non-finite command, broken timing or planner error: drives off, latched


class StopPolicy(enum.IntEnum):
    CONTROLLED = 1
    IMMEDIATE = 2


class Check(enum.IntFlag):
    """Which check fired (bit flags, reported in the command)."""

    NONE = 0
    JOINT_POSITION = 1
    JOINT_VELOCITY = 2
    WORKSPACE = 4
    TCP_SPEED = 8
    WATCHDOG = 16
    NONFINITE = 32
    TIMING = 64
    PLANNER = 128
    OPERATOR = 256  # a stop asked for by the operator (SIGINT in ``servo run``)


class Reject(enum.IntEnum):
    """Why the loop did not use a pose (0: it did)."""

    NONE = 0
    LOST = 1  # the tracker said lost
    STALE = 2  # older than max_sample_age_s at the tick
    FUTURE = 3  # stamped after the tick by more than the clock tolerance (max_future_s)
    NONFINITE = 4
    QUATERNION = 5  # not a unit quaternion
    UNCERTAIN = 6  # position std above max_position_std_m


def _ro(a, n=None, name="array"):
    a = np.array(a, dtype=float)
    if n is not None and a.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {a.shape}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class SafetyConfig:
    """Limits and stop policies.

    q_min, q_max : (n,) rad        hard joint ranges (the CLIK keeps a margin inside)
    qd_max : (n,) rad/s            joint velocity limits
    box_min, box_max : (3,) m      TCP workspace box, world frame
    tcp_speed_max : m/s            commanded TCP speed limit
    watchdog_timeout_s : s         no valid pose for this long -> stop (3 frames at 26 Hz)
    resume_hold_s : s              stream valid this long before tracking resumes
    max_sample_age_s : s           a sample older than this on arrival is invalid
    max_future_s : s               clock tolerance: a sample stamped further than this
                                   after the tick time is invalid (a clock error)
    max_position_std_m : m         a sample whose position std is larger is invalid
    velocity_tolerance : relative  rounding allowance on the joint velocity check
    policy_* : StopPolicy          one per check
    """

    q_min: np.ndarray
    q_max: np.ndarray
    qd_max: np.ndarray
    box_min: np.ndarray = field(default_factory=lambda: np.array([0.30, -0.95, 0.20]))
    box_max: np.ndarray = field(default_factory=lambda: np.array([1.35, 0.95, 1.45]))
    tcp_speed_max: float = 1.0
    watchdog_timeout_s: float = 3.0 / 26.0
    resume_hold_s: float = 0.2
    max_sample_age_s: float = 0.5
    max_future_s: float = 0.005
    max_position_std_m: float = 0.05
    velocity_tolerance: float = 1e-6
    policy_joint_position: StopPolicy = StopPolicy.IMMEDIATE
    policy_joint_velocity: StopPolicy = StopPolicy.IMMEDIATE
    policy_workspace: StopPolicy = StopPolicy.CONTROLLED
    policy_tcp_speed: StopPolicy = StopPolicy.CONTROLLED
    policy_watchdog: StopPolicy = StopPolicy.CONTROLLED
    policy_timing: StopPolicy = StopPolicy.CONTROLLED

    def __post_init__(self):
        n = len(np.atleast_1d(self.q_min))
        for k in ("q_min", "q_max", "qd_max"):
            object.__setattr__(self, k, _ro(getattr(self, k), n, k))
        for k in ("box_min", "box_max"):
            object.__setattr__(self, k, _ro(getattr(self, k), 3, k))
        if not self.watchdog_timeout_s > 0:
            raise ValueError("watchdog_timeout_s must be positive")

    @classmethod
    def from_kinematics(cls, kin, **overrides) -> "SafetyConfig":
        """Joint limits from the arm model (``ArmKinematics``), the rest default or given."""
        return cls(q_min=kin.q_min, q_max=kin.q_max, qd_max=kin.qd_max, **overrides)

    def with_(self, **kw) -> "SafetyConfig":
        return replace(self, **kw)


class Safety:
    """Stateful checks (the watchdog timers); limits come from :class:`SafetyConfig`."""

    def __init__(self, config: SafetyConfig):
        self.cfg = config
        self._timeout_ns = int(round(config.watchdog_timeout_s * 1e9))
        self._hold_ns = int(round(config.resume_hold_s * 1e9))
        self._max_age_ns = int(round(config.max_sample_age_s * 1e9))
        self._max_future_ns = int(round(config.max_future_s * 1e9))
        # What tripped each check last (index: the Check bit), SI units (see servo.events).
        self.trip_value = np.zeros(len(Check.__members__))
        self.trip_limit = np.zeros(len(Check.__members__))
        self._var_max = config.max_position_std_m**2
        self._policy = {
            Check.JOINT_POSITION: config.policy_joint_position,
            Check.JOINT_VELOCITY: config.policy_joint_velocity,
            Check.WORKSPACE: config.policy_workspace,
            Check.TCP_SPEED: config.policy_tcp_speed,
            Check.WATCHDOG: config.policy_watchdog,
            Check.TIMING: config.policy_timing,
        }
        self._q_min = config.q_min.tolist()
        self._q_max = config.q_max.tolist()
        self._qd_max = config.qd_max.tolist()
        self._box_min = config.box_min.tolist()
        self._box_max = config.box_max.tolist()
        self.reset()

    def reset(self) -> None:
        """Forget the stream history (no valid sample yet)."""
        self.reject_value = math.nan
        self.reject_limit = math.nan
        self.have_valid = False
        self.t_last_valid_ns = 0
        self.t_stream_back_ns = 0

    # -- pose stream --------------------------------------------------------------
    def sample_valid(self, s: TargetSample, t_ns: int) -> bool:
        """A sample is usable: tracker not lost, finite, not too old, not too uncertain."""
        return self.sample_reject(s, t_ns) == 0

    def sample_reject(self, s: TargetSample, t_ns: int) -> int:
        """Why a sample is not usable (a :class:`Reject` code), 0 if it is.

        The age (or, for a stamp in the future, the lead) of the rejected
        sample and its limit are left in ``reject_value``/``reject_limit``, s.
        """
        if s.status == SampleStatus.LOST:
            return Reject.LOST
        age = t_ns - s.t_capture_ns
        if age > self._max_age_ns:
            self.reject_value, self.reject_limit = age * 1e-9, self.cfg.max_sample_age_s
            return Reject.STALE
        if age < -self._max_future_ns:
            self.reject_value, self.reject_limit = -age * 1e-9, self.cfg.max_future_s
            return Reject.FUTURE
        for a in (s.p_world_object, s.q_world_object, s.v_world_object, s.w_world_object):
            if not (math.isfinite(a[0]) and math.isfinite(a[1]) and math.isfinite(a[2])):
                return Reject.NONFINITE
        q = s.q_world_object
        nq = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]
        if not (abs(nq - 1.0) < 1e-3):  # also false for NaN
            return Reject.NONFINITE if not math.isfinite(nq) else Reject.QUATERNION
        c = s.cov
        if not (c[0, 0] <= self._var_max and c[1, 1] <= self._var_max and c[2, 2] <= self._var_max):
            self.reject_value = math.sqrt(max(c[0, 0], c[1, 1], c[2, 2])) if math.isfinite(c[0, 0] + c[1, 1] + c[2, 2]) else math.nan
            self.reject_limit = self.cfg.max_position_std_m
            return Reject.UNCERTAIN
        return 0

    def feed(self, t_ns: int) -> None:
        """Record a new valid sample received at tick time ``t_ns``."""
        if not self.stream_ok(t_ns):
            self.t_stream_back_ns = t_ns  # the stream (re)starts here
        self.have_valid = True
        self.t_last_valid_ns = t_ns

    def watchdog_deadline_ns(self) -> int:
        """The stream counts as lost from this time on (ns)."""
        return self.t_last_valid_ns + self._timeout_ns

    def stream_ok(self, t_ns: int) -> bool:
        """A valid sample arrived less than ``watchdog_timeout_s`` ago."""
        return self.have_valid and t_ns < self.t_last_valid_ns + self._timeout_ns

    def resume_ok(self, t_ns: int) -> bool:
        """The stream has been continuously valid for ``resume_hold_s``."""
        return self.stream_ok(t_ns) and t_ns - self.t_stream_back_ns >= self._hold_ns

    # -- command ----------------------------------------------------------------
    def check_command(self, q_cmd, q_prev, dt: float, p_tcp, p_tcp_prev) -> int:
        """Check a new joint command; returns the ``Check`` flags that fired.

        Parameters
        ----------
        q_cmd, q_prev : (n,) rad
            New and previous joint commands.
        dt : float, s
        p_tcp, p_tcp_prev : (3,) m
            TCP position (world) at the new and previous command.
        """
        cfg = self.cfg
        flags = 0
        # Plain floats: six-element NumPy reductions cost more than the comparisons.
        q = q_cmd.tolist()
        qp = q_prev.tolist()
        lo, hi, vmax = self._q_min, self._q_max, self._qd_max
        k = dt * (1.0 + cfg.velocity_tolerance)
        tv, tl = self.trip_value, self.trip_limit
        for i in range(len(q)):
            x = q[i]
            if not math.isfinite(x):
                tv[5], tl[5] = math.nan, 0.0
                return int(Check.NONFINITE)
            if x < lo[i] or x > hi[i]:
                flags |= Check.JOINT_POSITION
                tv[0], tl[0] = x, (lo[i] if x < lo[i] else hi[i])
            if abs(x - qp[i]) > vmax[i] * k:
                flags |= Check.JOINT_VELOCITY
                tv[1], tl[1] = abs(x - qp[i]) / dt, vmax[i]
        bl, bh = self._box_min, self._box_max
        for i in range(3):
            if p_tcp[i] < bl[i] or p_tcp[i] > bh[i]:
                flags |= Check.WORKSPACE
                tv[2], tl[2] = max(bl[i] - p_tcp[i], p_tcp[i] - bh[i]), 0.0
        dx = p_tcp[0] - p_tcp_prev[0]
        dy = p_tcp[1] - p_tcp_prev[1]
        dz = p_tcp[2] - p_tcp_prev[2]
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d > cfg.tcp_speed_max * k:
            flags |= Check.TCP_SPEED
            tv[3], tl[3] = d / dt, cfg.tcp_speed_max
        return int(flags)

    def policy(self, flags: int) -> StopPolicy | None:
        """The strongest stop policy among the fired checks (None if none fired)."""
        worst = None
        for chk, pol in self._policy.items():
            if flags & chk and (worst is None or pol > worst):
                worst = pol
        return worst
