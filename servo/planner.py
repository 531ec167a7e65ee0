"""TCP reference generation: tracking a moving object within jerk limits, plus
classic point-to-point and via-point motions.

:class:`TrackingPlanner` follows Ruckig's cycle every 2 ms tick: set the input
(current reference state, target state), call ``update``, feed the output
back. Ruckig (online, time-optimal, jerk-limited) re-plans from the current
state each tick, so the reference stays within the velocity, acceleration and
jerk limits however the target jumps.

Orientation representation. Ruckig plans in R^n, so the orientation is given
three coordinates: the rotation vector ``r`` of the orientation relative to an
anchor, ``q = exp(r) * q_anchor`` (world frame, left). The anchor is
re-anchored *every tick* to the current reference orientation, so the current
state is always ``r = 0`` where this chart is exact: at ``r = 0`` the left
Jacobian is the identity, ``dr/dt = w`` and ``d2r/dt2 = dw/dt`` (the quadratic
term ``w x w`` vanishes). After one tick ``|r| = |w| dt`` (2 mrad at 1 rad/s),
so mapping the new ``(dr, ddr)`` back to ``(w, dw)`` has a relative error of
O(|w| dt). Compared with Euler angles there is no gimbal lock; compared with a
fixed anchor there is no singularity at ``|r| = pi`` and no distortion of the
limits for large rotations; compared with planning the quaternion directly,
Ruckig's per-axis limits keep their meaning as world-frame angular rates.
The target enters the chart as ``log(q_target * q_ref^-1)`` (shorter way round).

Limits are per axis (Ruckig's box constraints): ``|v_x|, |v_y|, |v_z| <=
v_lin`` (so ``|v| <= sqrt(3) v_lin``), and likewise for acceleration, jerk and
the angular quantities (world frame).

Latency compensation: the object pose is predicted from its capture time to
the current tick with the sample's velocity (constant-velocity model, capped at
``max_prediction_s``). Switch it off to compare.

Workspace: the TCP target is clamped to a box and a reach sphere; a clamped
target gets zero velocity, so the reference waits at the boundary and comes
back when the target does.

Time-scaling: the reference is a plan for the tool, but the joints have their
own limits. When the CLIK could not follow a step (tool speed cap, joint
velocity scaling, a joint limit), the loop calls :meth:`TrackingPlanner.hold_back`
and the reference goes on from the arm's real pose and speed: the plan is
slowed to what the arm does instead of running ahead and being caught up later
above the limits.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np
from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig, RuckigError, Synchronization

from .rotation import (
    quat_conjugate,
    quat_conjugate_into,
    quat_from_matrix,
    quat_from_rotvec_into,
    quat_multiply,
    quat_multiply_into,
    rotvec_from_quat,
    rotvec_from_quat_into,
    matrix_from_quat_into,
)
from .target import TargetSample

__all__ = [
    "CartesianLimits",
    "Workspace",
    "FollowTask",
    "Phase",
    "Reference",
    "TrackingPlanner",
    "Trapezoid",
    "JointTrapezoid",
    "CartesianTrapezoid",
    "ViaPath",
    "follow_task",
]


def _vec(a, n, name) -> np.ndarray:
    a = np.array(a, dtype=float)
    if a.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {a.shape}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class CartesianLimits:
    """Per-axis TCP limits, world frame (m/s, m/s^2, m/s^3; rad/s, rad/s^2, rad/s^3).

    ``v_lin`` is also the limit of the tool's speed as a norm: the loop's CLIK
    caps the commanded tool speed there (reference velocity plus error
    feedback), so the arm never moves its tool faster than ``v_lin`` in any
    direction, however far behind it is.
    """

    v_lin: float = 0.5
    a_lin: float = 2.0
    j_lin: float = 20.0
    v_ang: float = 1.5
    a_ang: float = 6.0
    j_ang: float = 60.0

    def __post_init__(self):
        for k in ("v_lin", "a_lin", "j_lin", "v_ang", "a_ang", "j_ang"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"CartesianLimits.{k} must be positive and finite, got {v}")


@dataclass(frozen=True)
class Workspace:
    """Reachable TCP region: an axis-aligned box (world, m) intersected with a sphere.

    The sphere centre must lie inside the box, so pulling a point in the box
    towards the centre keeps it in the box.
    """

    box_min: np.ndarray = field(default_factory=lambda: np.array([0.35, -0.9, 0.25]))
    box_max: np.ndarray = field(default_factory=lambda: np.array([1.30, 0.9, 1.40]))
    reach_center: np.ndarray = field(default_factory=lambda: np.array([0.15, 0.0, 0.61]))
    reach_radius: float = 1.20

    def __post_init__(self):
        object.__setattr__(self, "box_min", _vec(self.box_min, 3, "box_min"))
        object.__setattr__(self, "box_max", _vec(self.box_max, 3, "box_max"))
        object.__setattr__(self, "reach_center", _vec(self.reach_center, 3, "reach_center"))
        if np.any(self.box_min >= self.box_max):
            raise ValueError("Workspace: box_min must be below box_max")

    def clamp_into(self, p: np.ndarray, out: np.ndarray) -> bool:
        """Clamp a point (3,) into the workspace; returns True if it moved."""
        lo, hi = self.box_min, self.box_max
        moved = False
        for i in range(3):  # out may alias p: decide before writing
            x = p[i]
            if x < lo[i]:
                x, moved = lo[i], True
            elif x > hi[i]:
                x, moved = hi[i], True
            out[i] = x
        c = self.reach_center
        dx, dy, dz = out[0] - c[0], out[1] - c[1], out[2] - c[2]
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d > self.reach_radius:
            k = self.reach_radius / d
            out[0] = c[0] + k * dx
            out[1] = c[1] + k * dy
            out[2] = c[2] + k * dz
            moved = True
        return moved

    def contains(self, p: np.ndarray, tol: float = 0.0) -> bool:
        return bool(
            np.all(p >= self.box_min - tol)
            and np.all(p <= self.box_max + tol)
            and np.linalg.norm(p - self.reach_center) <= self.reach_radius + tol
        )


@dataclass(frozen=True)
class FollowTask:
    """Where the TCP goes relative to the object.

    T_object_tcp : (4, 4)
        Desired TCP pose in the object frame during "follow".
    standoff_m : float
        "approach" aims this far above (world +z) the follow pose first.
    approach_tol_m, approach_tol_rad, approach_tol_mps : float
        The switch to "follow" happens when the reference is this close to the
        stand-off target (position, angle, velocity).
    upright : bool
        Apply ``T_object_tcp`` to the object's heading only (its rotation about
        world z, from the object's x axis), not to its full orientation: the
        stand-off is then straight above the object whatever its estimated roll
        and pitch, so a 1 degree tilt error no longer moves a 0.15 m stand-off
        point by 2.6 mm, and tilt noise does not shake the arm. For parts that
        lie on a belt or a table; off for parts that are really tilted.
    """

    T_object_tcp: np.ndarray
    standoff_m: float = 0.10
    approach_tol_m: float = 0.002
    approach_tol_rad: float = 0.01
    approach_tol_mps: float = 0.01
    upright: bool = False

    def __post_init__(self):
        T = np.array(self.T_object_tcp, dtype=float)
        if T.shape != (4, 4):
            raise ValueError(f"T_object_tcp: expected shape (4, 4), got {T.shape}")
        T.setflags(write=False)
        object.__setattr__(self, "T_object_tcp", T)


class Phase(enum.IntEnum):
    IDLE = 0  # at rest, no task
    APPROACH = 1
    FOLLOW = 2


class Reference:
    """TCP reference state (preallocated; world frame, SI).

    p (3,) m, quat (4,) (w, x, y, z), v (3,) m/s, w (3,) rad/s, a (3,) m/s^2,
    alpha (3,) rad/s^2.
    """

    __slots__ = ("p", "quat", "v", "w", "a", "alpha")

    def __init__(self):
        self.p = np.zeros(3)
        self.quat = np.array([1.0, 0.0, 0.0, 0.0])
        self.v = np.zeros(3)
        self.w = np.zeros(3)
        self.a = np.zeros(3)
        self.alpha = np.zeros(3)

    def set_rest(self, p, quat) -> None:
        self.p[:] = p
        self.quat[:] = quat
        for x in (self.v, self.w, self.a, self.alpha):
            x[:] = 0.0

    def copy_from(self, o: "Reference") -> None:
        self.p[:] = o.p
        self.quat[:] = o.quat
        self.v[:] = o.v
        self.w[:] = o.w
        self.a[:] = o.a
        self.alpha[:] = o.alpha


class TrackingPlanner:
    """Jerk-limited TCP reference that approaches, then follows, a moving object.

    Parameters
    ----------
    limits : CartesianLimits
    workspace : Workspace
    dt : float
        Nominal tick, s (each call passes its own dt, from timestamps).
    latency_compensation : bool
        Predict the object pose from capture time to the tick time.
    max_prediction_s : float
        Cap on the prediction horizon (a stale sample is not extrapolated far).
    """

    def __init__(
        self,
        limits: CartesianLimits = CartesianLimits(),
        workspace: Workspace = Workspace(),
        dt: float = 0.002,
        latency_compensation: bool = True,
        max_prediction_s: float = 0.3,
    ):
        self.limits = limits
        self.workspace = workspace
        self.latency_compensation = bool(latency_compensation)
        self.max_prediction_s = float(max_prediction_s)
        self.otg = Ruckig(6, dt)
        self.inp = InputParameter(6)
        self.out = OutputParameter(6)
        L = limits
        self.inp.max_velocity = [L.v_lin] * 3 + [L.v_ang] * 3
        self.inp.max_acceleration = [L.a_lin] * 3 + [L.a_ang] * 3
        self.inp.max_jerk = [L.j_lin] * 3 + [L.j_ang] * 3
        # Target velocities are kept strictly inside the limits (Ruckig rejects
        # a target state it cannot hold).
        self._vmax_abs = np.array([L.v_lin] * 3 + [L.v_ang] * 3)
        self._vmax_abs_l = self._vmax_abs.tolist()
        self._v_tgt_cap_l = (self._vmax_abs * 0.9).tolist()
        self._zero6_l = [0.0] * 6
        self.ref = Reference()
        self.phase = Phase.IDLE
        self.task: FollowTask | None = None
        self._p_object_tcp = np.zeros(3)
        self._p_object_tcp_l = [0.0, 0.0, 0.0]
        self._sp_l = [0.0, 0.0, 0.0]
        self._sv_l = [0.0, 0.0, 0.0]
        self._sw_l = [0.0, 0.0, 0.0]
        self._q_object_tcp = np.array([1.0, 0.0, 0.0, 0.0])
        # latest object sample
        self.have_sample = False
        self.t_capture_ns = 0
        self.s_p = np.zeros(3)
        self.s_q = np.array([1.0, 0.0, 0.0, 0.0])
        self.s_v = np.zeros(3)
        self.s_w = np.zeros(3)
        # target (TCP, world), after prediction and clamping
        self.tgt_p = np.zeros(3)
        self.tgt_q = np.array([1.0, 0.0, 0.0, 0.0])
        self.tgt_v = np.zeros(3)
        self.tgt_w = np.zeros(3)
        self.clamped = False
        self.clamp_distance = 0.0  # how far the last clamped target was moved, m
        self.last_result = 0
        self.n_fallbacks = 0  # Ruckig retries without time synchronisation (diagnostics)
        self.n_held_back = 0  # ticks the reference waited for the arm (diagnostics)
        # work buffers
        self._cur_p = np.zeros(6)
        self._cur_v = np.zeros(6)
        self._cur_a = np.zeros(6)
        self._tp = np.zeros(6)
        self._tv = np.zeros(6)
        self._zero6 = np.zeros(6)
        self._q4a = np.zeros(4)
        self._q4b = np.zeros(4)
        self._r3 = np.zeros(3)
        self._v3 = np.zeros(3)
        self._R = np.eye(3)
        self._p3 = np.zeros(3)

    # -- set-up ---------------------------------------------------------------
    def reset(self, p_world_tcp, quat_world_tcp) -> None:
        """Start at rest at the given TCP pose (e.g. FK of the measured joints)."""
        self.ref.set_rest(p_world_tcp, quat_world_tcp)
        self.phase = Phase.IDLE if self.task is None else Phase.APPROACH
        self.otg.reset()

    def set_task(self, task: FollowTask | None) -> None:
        """Set (or clear) the follow task; restarts at the approach phase."""
        self.task = task
        if task is None:
            self.phase = Phase.IDLE
            return
        self._p_object_tcp[:] = task.T_object_tcp[:3, 3]
        self._p_object_tcp_l = self._p_object_tcp.tolist()
        self._q_object_tcp[:] = quat_from_matrix(np.ascontiguousarray(task.T_object_tcp[:3, :3]))
        self.phase = Phase.APPROACH

    def set_sample(self, s: TargetSample) -> None:
        """Take a new (already validated) object sample."""
        self.t_capture_ns = s.t_capture_ns
        self.s_p[:] = s.p_world_object
        self.s_q[:] = s.q_world_object
        self.s_v[:] = s.v_world_object
        self.s_w[:] = s.w_world_object
        self._sp_l = self.s_p.tolist()
        self._sv_l = self.s_v.tolist()
        self._sw_l = self.s_w.tolist()
        self.have_sample = True

    # -- per tick ---------------------------------------------------------------
    def update_target(self, t_ns: int) -> None:
        """Predicted, clamped TCP target at ``t_ns`` into ``tgt_*``."""
        tau = 0.0
        stale = (t_ns - self.t_capture_ns) * 1e-9 > self.max_prediction_s
        if self.latency_compensation:
            tau = (t_ns - self.t_capture_ns) * 1e-9
            tau = min(max(tau, 0.0), self.max_prediction_s)
        # object pose at t: p + v tau, exp(w tau) * q
        sp, sv, sw = self._sp_l, self._sv_l, self._sw_l
        r = self._r3
        r[0], r[1], r[2] = sw[0] * tau, sw[1] * tau, sw[2] * tau
        quat_from_rotvec_into(r, self._q4a)
        quat_multiply_into(self._q4a, self.s_q, self._q4b)  # q_world_object(t)
        # TCP target: T_world_object @ T_object_tcp
        matrix_from_quat_into(self._q4b, self._R)
        if self.task is not None and self.task.upright:
            # Heading only: rotation about world z that takes x to the object's x axis.
            R0 = self._R
            half = 0.5 * math.atan2(R0[1, 0], R0[0, 0])
            q = self._q4b
            q[0], q[1], q[2], q[3] = math.cos(half), 0.0, 0.0, math.sin(half)
            matrix_from_quat_into(q, self._R)
            sw = [0.0, 0.0, sw[2]]
        R = self._R.tolist()
        o = self._p_object_tcp_l
        ax = R[0][0] * o[0] + R[0][1] * o[1] + R[0][2] * o[2]  # object origin -> TCP, world
        ay = R[1][0] * o[0] + R[1][1] * o[1] + R[1][2] * o[2]
        az = R[2][0] * o[0] + R[2][1] * o[1] + R[2][2] * o[2]
        self.tgt_p[:] = [sp[0] + sv[0] * tau + ax, sp[1] + sv[1] * tau + ay, sp[2] + sv[2] * tau + az]
        quat_multiply_into(self._q4b, self._q_object_tcp, self.tgt_q)
        # v_tcp = v + w x arm ; w_tcp = w
        tv = self.tgt_v
        tv[:] = [sv[0] + sw[1] * az - sw[2] * ay, sv[1] + sw[2] * ax - sw[0] * az, sv[2] + sw[0] * ay - sw[1] * ax]
        self.tgt_w[:] = sw
        if self.phase == Phase.APPROACH and self.task is not None:
            self.tgt_p[2] += self.task.standoff_m
        self._p3[:] = self.tgt_p
        self.clamped = self.workspace.clamp_into(self.tgt_p, self.tgt_p)
        if self.clamped:
            self.clamp_distance = math.dist(self._p3, self.tgt_p)
        if self.clamped or stale:
            # Wait at the boundary; a stale target is no longer predicted to move.
            tv[:] = 0.0
            self.tgt_w[:] = 0.0

    def _set_current(self) -> None:
        ref = self.ref
        inp = self.inp
        cp, cv, ca = self._cur_p, self._cur_v, self._cur_a
        cp[:3] = ref.p
        cp[3:] = 0.0  # the chart is anchored at the current orientation
        cv[:3] = ref.v
        cv[3:] = ref.w
        ca[:3] = ref.a
        ca[3:] = ref.alpha
        inp.current_position = cp
        inp.current_velocity = cv
        inp.current_acceleration = ca

    def _apply_output(self) -> None:
        """Absolute-coordinate output (stop / hold) back into the reference."""
        out = self.out
        ref = self.ref
        np_ = out.new_position
        nv = out.new_velocity
        na = out.new_acceleration
        r = self._r3
        for i in range(3):
            ref.p[i] = np_[i]
            r[i] = np_[i + 3]
            ref.v[i] = nv[i]
            ref.w[i] = nv[i + 3]
            ref.a[i] = na[i]
            ref.alpha[i] = na[i + 3]
        self._rotate_ref(r)

    def step(self, t_ns: int, dt: float) -> int:
        """Advance the tracking reference by ``dt`` (s) towards the target at ``t_ns``.

        Ruckig plans in the frame moving with the target (Galilean change of
        variables, target velocity constant over the plan): current state
        ``(x_ref - x_tgt, v_ref - v_tgt, a_ref)``, target state zero. Planning
        to the target's *current* position in fixed coordinates instead makes
        the reference trail a moving target by a gap that closes only slowly
        (each re-plan aims where the target was). Accelerations and jerks are
        the same in both frames; the velocity limit of each axis is reduced by
        ``|v_tgt|`` on that axis so that the absolute velocity stays within
        ``v_max``. A change of the target velocity changes only the relative
        current state, so the absolute reference stays continuous.

        Returns Ruckig's result as an int (0 working, 1 on the target,
        negative: error; the reference is then left unchanged). Without a
        sample or a task the reference decelerates to rest and holds
        (see :meth:`stop_step`).
        """
        if not self.have_sample or self.task is None or self.phase == Phase.IDLE:
            self.stop_step(dt)
            return 0
        self.update_target(t_ns)
        ref = self.ref
        # Plain floats below: NumPy calls on 3- and 6-vectors cost ~1 us each,
        # more than the arithmetic.
        cap = self._v_tgt_cap_l
        tv = self.tgt_v.tolist() + self.tgt_w.tolist()
        for i in range(6):
            if tv[i] > cap[i]:
                tv[i] = cap[i]
            elif tv[i] < -cap[i]:
                tv[i] = -cap[i]
        # target orientation in the chart anchored at q_ref
        quat_conjugate_into(ref.quat, self._q4a)
        quat_multiply_into(self.tgt_q, self._q4a, self._q4b)
        rotvec_from_quat_into(self._q4b, self._r3)
        rt = self._r3.tolist()
        tp = self.tgt_p.tolist()
        p, v, w = ref.p.tolist(), ref.v.tolist(), ref.w.tolist()
        # current state relative to the target
        cp = [p[0] - tp[0], p[1] - tp[1], p[2] - tp[2], -rt[0], -rt[1], -rt[2]]
        cv = [v[0] - tv[0], v[1] - tv[1], v[2] - tv[2], w[0] - tv[3], w[1] - tv[4], w[2] - tv[5]]
        vabs = self._vmax_abs_l
        vmax = [vabs[i] - abs(tv[i]) for i in range(6)]
        inp = self.inp
        inp.control_interface = ControlInterface.Position
        inp.max_velocity = vmax
        inp.current_position = cp
        inp.current_velocity = cv
        inp.current_acceleration = ref.a.tolist() + ref.alpha.tolist()
        inp.target_position = self._zero6_l
        inp.target_velocity = self._zero6_l
        inp.target_acceleration = self._zero6_l
        res = self._update(dt)
        if res < 0:
            return res
        # back to absolute: x = x_tgt + v_tgt dt + x_rel, v = v_tgt + v_rel, a = a_rel
        out = self.out
        np_ = out.new_position
        nv = out.new_velocity
        na = out.new_acceleration
        ref.p[:] = [tp[0] + tv[0] * dt + np_[0], tp[1] + tv[1] * dt + np_[1], tp[2] + tv[2] * dt + np_[2]]
        self._r3[:] = [rt[0] + tv[3] * dt + np_[3], rt[1] + tv[4] * dt + np_[4], rt[2] + tv[5] * dt + np_[5]]
        ref.v[:] = [tv[0] + nv[0], tv[1] + nv[1], tv[2] + nv[2]]
        ref.w[:] = [tv[3] + nv[3], tv[4] + nv[4], tv[5] + nv[5]]
        ref.a[:] = na[:3]
        ref.alpha[:] = na[3:]
        self._rotate_ref(self._r3)
        if self.phase == Phase.APPROACH:
            self._maybe_switch_to_follow()
        return res

    def _update(self, dt: float) -> int:
        """Ruckig update that never raises.

        The Python binding raises ``RuckigError`` where the C++ returns an error
        code; for a handful of near-degenerate inputs the time-synchronised
        solution fails numerically (seen with ~1e-4 m relative states), so
        retry once with independent DoFs (each still time-optimal and within
        its limits) before reporting an error.
        """
        self.otg.delta_time = dt
        inp = self.inp
        try:
            res = int(self.otg.update(inp, self.out))
        except RuckigError:
            res = int(Result.ErrorSynchronizationCalculation)
        if res < 0:
            inp.synchronization = Synchronization.No
            try:
                res = int(self.otg.update(inp, self.out))
            except RuckigError:
                res = int(Result.Error)
            inp.synchronization = Synchronization.Time
            self.n_fallbacks += 1
        self.last_result = res
        return res

    def _rotate_ref(self, r: np.ndarray) -> None:
        """q_ref <- exp(r) q_ref, renormalised (rounding drift over hours of ticks)."""
        ref = self.ref
        quat_from_rotvec_into(r, self._q4a)
        quat_multiply_into(self._q4a, ref.quat, self._q4b)
        n = math.sqrt(float(self._q4b @ self._q4b))
        np.multiply(self._q4b, 1.0 / n, out=ref.quat)

    def _maybe_switch_to_follow(self) -> None:
        t = self.task
        ref = self.ref
        dp = self._v3
        np.subtract(self.tgt_p, ref.p, out=dp)
        if math.sqrt(float(dp @ dp)) > t.approach_tol_m:
            return
        np.subtract(self.tgt_v, ref.v, out=dp)
        if math.sqrt(float(dp @ dp)) > t.approach_tol_mps:
            return
        quat_conjugate_into(ref.quat, self._q4a)
        quat_multiply_into(self.tgt_q, self._q4a, self._q4b)
        rotvec_from_quat_into(self._q4b, self._r3)
        if math.sqrt(float(self._r3 @ self._r3)) > t.approach_tol_rad:
            return
        self.phase = Phase.FOLLOW

    def hold_back(self, p, quat, v, w) -> None:
        """Time-scale the reference to the arm: take its pose and velocity as the reference's.

        Called when the arm could not follow the last step (the CLIK's speed
        cap, a joint velocity limit or a joint limit brake cut the motion). The
        reference then goes on from where the arm really is, at the speed it
        really has, so no tracking error builds up to be caught up later; the
        acceleration is kept (it is within the limits, and Ruckig re-plans from
        this state at the next tick).
        """
        ref = self.ref
        ref.p[:] = p
        ref.quat[:] = quat
        ref.v[:] = v
        ref.w[:] = w
        self.n_held_back += 1

    def stop_step(self, dt: float) -> bool:
        """Decelerate to rest within the limits (Ruckig velocity interface).

        Returns True once at rest (velocity and acceleration zero).
        """
        self._set_current()
        inp = self.inp
        inp.max_velocity = self._vmax_abs
        inp.control_interface = ControlInterface.Velocity
        inp.target_velocity = self._zero6
        inp.target_acceleration = self._zero6
        res = self._update(dt)
        if res < 0:
            return False
        self._apply_output()
        return res == int(Result.Finished)


# --- classic motions ------------------------------------------------------------


class Trapezoid:
    """Trapezoidal (or triangular) velocity profile of a path parameter s: 0 -> 1.

    Parameters
    ----------
    v_max, a_max : float
        Limits on ds/dt (1/s) and d2s/dt2 (1/s^2).
    """

    def __init__(self, v_max: float, a_max: float):
        if not (v_max > 0 and a_max > 0):
            raise ValueError("Trapezoid: limits must be positive")
        if v_max * v_max / a_max >= 1.0:  # cannot reach v_max: triangle
            self.t_acc = math.sqrt(1.0 / a_max)
            self.v_peak = a_max * self.t_acc
            self.duration = 2.0 * self.t_acc
        else:
            self.t_acc = v_max / a_max
            self.v_peak = v_max
            self.duration = self.t_acc + 1.0 / v_max
        self.a = a_max

    def sample(self, t: float):
        """(s, ds/dt, d2s/dt2) at time ``t`` (s), clamped to [0, duration]."""
        T, ta, a, v = self.duration, self.t_acc, self.a, self.v_peak
        if t <= 0.0:
            return 0.0, 0.0, 0.0
        if t >= T:
            return 1.0, 0.0, 0.0
        if t < ta:
            return 0.5 * a * t * t, a * t, a
        if t <= T - ta:
            return 0.5 * a * ta * ta + v * (t - ta), v, 0.0
        r = T - t
        return 1.0 - 0.5 * a * r * r, a * r, -a


class JointTrapezoid:
    """Synchronised straight-line joint motion with a trapezoidal velocity profile.

    All joints share s(t), so they start and stop together; each respects its
    own velocity and acceleration limit (the slowest joint sets the profile).

    Parameters
    ----------
    q0, q1 : (n,) start and goal, rad
    qd_max, qdd_max : (n,) limits, rad/s, rad/s^2
    """

    space = "joint"

    def __init__(self, q0, q1, qd_max, qdd_max):
        self.q0 = np.array(q0, float)
        self.dq = np.array(q1, float) - self.q0
        d = np.abs(self.dq)
        if d.max() < 1e-12:
            self.profile = None
            self.duration = 0.0
            return
        nz = d > 1e-12
        v = float(np.min(np.asarray(qd_max, float)[nz] / d[nz]))
        a = float(np.min(np.asarray(qdd_max, float)[nz] / d[nz]))
        self.profile = Trapezoid(v, a)
        self.duration = self.profile.duration

    def sample(self, t: float, q_out, qd_out, qdd_out) -> None:
        s, sd, sdd = (1.0, 0.0, 0.0) if self.profile is None else self.profile.sample(t)
        np.multiply(self.dq, s, out=q_out)
        q_out += self.q0
        np.multiply(self.dq, sd, out=qd_out)
        np.multiply(self.dq, sdd, out=qdd_out)


class CartesianTrapezoid:
    """Straight-line TCP motion with slerp orientation and a trapezoidal profile.

    ``p(s) = p0 + s (p1 - p0)``, ``q(s) = exp(s theta) q0`` with
    ``theta = log(q1 q0^-1)`` (world frame, the shorter way). Limits are on the
    norms of the linear and angular velocity and acceleration.
    """

    space = "task"

    def __init__(self, T0, T1, limits: CartesianLimits = CartesianLimits()):
        T0, T1 = np.asarray(T0, float), np.asarray(T1, float)
        self.p0 = T0[:3, 3].copy()
        self.dp = T1[:3, 3] - self.p0
        self.q0 = quat_from_matrix(np.ascontiguousarray(T0[:3, :3]))
        q1 = quat_from_matrix(np.ascontiguousarray(T1[:3, :3]))
        self.theta = rotvec_from_quat(quat_multiply(q1, quat_conjugate(self.q0)))
        L = np.linalg.norm(self.dp)
        A = np.linalg.norm(self.theta)
        cands_v = [limits.v_lin / L] if L > 1e-12 else []
        cands_a = [limits.a_lin / L] if L > 1e-12 else []
        if A > 1e-12:
            cands_v.append(limits.v_ang / A)
            cands_a.append(limits.a_ang / A)
        if not cands_v:
            self.profile = None
            self.duration = 0.0
        else:
            self.profile = Trapezoid(min(cands_v), min(cands_a))
            self.duration = self.profile.duration
        self._r = np.zeros(3)
        self._q = np.zeros(4)

    def sample(self, t: float, ref: Reference) -> None:
        s, sd, sdd = (1.0, 0.0, 0.0) if self.profile is None else self.profile.sample(t)
        np.multiply(self.dp, s, out=ref.p)
        ref.p += self.p0
        np.multiply(self.theta, s, out=self._r)
        quat_from_rotvec_into(self._r, self._q)
        quat_multiply_into(self._q, self.q0, ref.quat)
        np.multiply(self.dp, sd, out=ref.v)
        np.multiply(self.theta, sd, out=ref.w)
        np.multiply(self.dp, sdd, out=ref.a)
        np.multiply(self.theta, sdd, out=ref.alpha)


class ViaPath:
    """Linear segments with parabolic blends (LSPB) through via points.

    Each segment moves all coordinates at constant velocity (the slowest
    coordinate at its limit); at each via point a constant-acceleration blend
    of duration ``tb_j = max_i |v_j,i - v_j-1,i| / a_i`` joins the segments,
    so velocity and acceleration limits hold per coordinate. The path starts
    and ends at rest, at the first and last point exactly; interior via points
    are passed within ``|v_j - v_j-1| tb_j / 8`` (the blend cuts the corner).
    Segments too short for their blends are slowed until the blends fit.

    Parameters
    ----------
    points : (N, d)
        Via points: joint positions (``space="joint"``) or TCP positions
        (``space="position"``, orientation held by the caller).
    v_max, a_max : (d,) or float
        Per-coordinate limits.
    """

    def __init__(self, points, v_max, a_max, space: str = "joint"):
        P = np.asarray(points, float)
        if P.ndim != 2 or P.shape[0] < 2:
            raise ValueError(f"points: expected shape (N>=2, d), got {P.shape}")
        self.space = space
        N, d = P.shape
        vmax = np.broadcast_to(np.asarray(v_max, float), (d,))
        amax = np.broadcast_to(np.asarray(a_max, float), (d,))
        D = np.diff(P, axis=0)  # (N-1, d)
        T = np.maximum(np.max(np.abs(D) / vmax, axis=1), 1e-3)
        for _ in range(200):
            V = D / T[:, None]
            Vx = np.vstack([np.zeros(d), V, np.zeros(d)])  # v_-1 = v_N-1 = 0
            tb = np.max(np.abs(np.diff(Vx, axis=0)) / amax, axis=1)  # (N,)
            need = 0.5 * (tb[:-1] + tb[1:])
            bad = need > T * (1 + 1e-12)
            if not bad.any():
                break
            T[bad] *= 1.05
        self.P, self.V, self.Vx, self.tb = P, V, Vx, tb
        self.t_knot = tb[0] / 2 + np.concatenate([[0.0], np.cumsum(T)])
        self.duration = float(self.t_knot[-1] + tb[-1] / 2)

    def sample(self, t: float, x_out, xd_out, xdd_out) -> None:
        """Position, velocity, acceleration (d,) at time ``t``, s."""
        t = min(max(t, 0.0), self.duration)
        tk, tb, P, Vx = self.t_knot, self.tb, self.P, self.Vx
        j = int(np.searchsorted(tk, t))  # tk[j-1] < t <= tk[j]
        for k in (j - 1, j):
            if 0 <= k < len(tk) and tb[k] > 0 and abs(t - tk[k]) <= tb[k] / 2:
                v0, v1 = Vx[k], Vx[k + 1]
                u = t - tk[k] + tb[k] / 2
                acc = (v1 - v0) / tb[k]
                x_out[:] = P[k] + v0 * (t - tk[k]) + acc * (u * u / 2)
                xd_out[:] = v0 + acc * u
                xdd_out[:] = acc
                return
        k = min(max(j - 1, 0), len(self.V) - 1)
        x_out[:] = P[k] + self.V[k] * (t - tk[k])
        xd_out[:] = self.V[k]
        xdd_out[:] = 0.0

def follow_task(standoff: float, upright: bool = True):
    """TCP ``standoff`` above the object origin, pointing down (z against the object's z).

    ``upright``: above in the world (the object's heading only, see
    :class:`servo.planner.FollowTask`); otherwise along the object's own z axis.

    The approach ends (and following starts) once the reference is within 5 mm,
    3 degrees and 0.02 m/s of the stand-off target: tolerances above the noise of
    a vision estimate (about 1 mm and 1 degree), or the switch would wait for luck.
    """
    T = np.diag([1.0, -1.0, -1.0, 1.0])
    T[2, 3] = standoff
    return FollowTask(T_object_tcp=T, standoff_m=0.10, approach_tol_m=0.005, approach_tol_rad=np.deg2rad(3.0),
                      approach_tol_mps=0.02, upright=upright)
