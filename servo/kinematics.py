"""Arm kinematics from the MJCF: TCP forward kinematics, geometric Jacobian, CLIK.

Everything is read from ``models/arm.xml`` (joint order, offsets, limits, the
"tool" site that is the TCP), so the controller and the simulated plant can
never disagree about the arm. Two independent implementations:

- :class:`ArmKinematics` runs MuJoCo's ``mj_kinematics`` / ``mj_jacSite`` on a
  private ``MjData`` (fast, allocation-free, used at 500 Hz);
- :func:`chain_from_model`, :func:`fk_chain`, :func:`jacobian_chain` extract the
  chain once and compute in plain NumPy (the cross-check in the tests).

Conventions: ``T_world_tcp`` (4, 4) is the TCP pose in the world frame; the
geometric Jacobian ``J`` (6, n) maps joint rates (rad/s) to the TCP twist
``[v (m/s); w (rad/s)]``, both in world coordinates, ``v`` the velocity of the
TCP point.

Closed-loop inverse kinematics (:class:`Clik`) integrates
``qd = J^#(x) (xd_ref + K e)`` where ``e = [p_ref - p; log(q_ref q^-1)]``
(orientation error from quaternions, world frame) and ``J^#`` is a damped
least-squares inverse whose damping grows smoothly as the smallest singular
value falls below ``eps`` (Nakamura & Hanafusa 1986, Maciejewski & Klein 1988):
``lambda^2 = (1 - (s_min/eps)^2) lambda_max^2`` inside the singular region,
0 outside. Joint rates are scaled (direction kept) to the velocity limits,
then each joint is slowed so it can brake before its position limit. The
commanded TCP speed ``|v_ref + K e_p|`` is capped at ``tcp_speed_max`` (the
planner's limit) first, so a tracking error is closed at the planner's speed at
most, never by a faster catch-up. :attr:`Clik.limited` tells the caller when a
cap or limit changed the motion (the reference then has to wait for the arm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from scipy.linalg.lapack import dgesdd as _dgesdd

from .rotation import (
    matrix_from_quat,
    quat_conjugate_into,
    quat_from_matrix_into,
    quat_multiply_into,
    rotvec_from_quat_into,
)

__all__ = [
    "DEFAULT_ARM_XML",
    "ArmKinematics",
    "KinematicChain",
    "chain_from_model",
    "fk_chain",
    "jacobian_chain",
    "damping_squared",
    "dls_solve_into",
    "ClikConfig",
    "Clik",
    "solve_ik",
]

DEFAULT_ARM_XML = Path(__file__).resolve().parents[1] / "models" / "arm.xml"


class ArmKinematics:
    """FK and Jacobian of one site (the TCP) of an MJCF arm with hinge joints.

    Parameters
    ----------
    model : mujoco.MjModel or str or Path
        The arm model (or a path to its MJCF). Only read.
    site : str
        The TCP site.

    Attributes
    ----------
    n : int
        Number of joints (= nq = nv).
    q_min, q_max : ndarray, shape (n,)
        Joint position limits, rad.
    qd_max : ndarray, shape (n,)
        Joint velocity limits, rad/s (MJCF custom numeric "joint_velocity_limits").
    p, R, J : ndarray, shapes (3,), (3, 3), (6, n)
        Results of the last :meth:`update` (world frame, m, rad).
    """

    def __init__(self, model=DEFAULT_ARM_XML, site: str = "tool"):
        if not isinstance(model, mujoco.MjModel):
            model = mujoco.MjModel.from_xml_path(str(model))
        self.model = model
        self._data = mujoco.MjData(model)
        n = model.njnt
        if model.nq != n or model.nv != n or np.any(model.jnt_type != mujoco.mjtJoint.mjJNT_HINGE):
            raise ValueError("ArmKinematics expects an arm with hinge joints only (nq == nv == njnt)")
        self.n = n
        self.site_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
        if self.site_id < 0:
            raise ValueError(f"no site named {site!r} in the model")
        self.q_min = model.jnt_range[:, 0].copy()
        self.q_max = model.jnt_range[:, 1].copy()
        nid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, "joint_velocity_limits")
        if nid < 0:
            raise ValueError("model has no custom numeric 'joint_velocity_limits'")
        adr, size = model.numeric_adr[nid], model.numeric_size[nid]
        if size != n:
            raise ValueError(f"joint_velocity_limits: expected {n} values, got {size}")
        self.qd_max = model.numeric_data[adr : adr + size].copy()
        for a in (self.q_min, self.q_max, self.qd_max):
            a.setflags(write=False)
        self.p = np.zeros(3)
        self.R = np.eye(3)
        self.J = np.zeros((6, n))
        self._jp = self.J[:3]  # contiguous row blocks: mj_jacSite writes straight in
        self._jr = self.J[3:]

    def update(self, q: np.ndarray, jacobian: bool = True) -> None:
        """Compute ``p``, ``R`` (and ``J``) at joint positions ``q`` (n,), rad. No allocation."""
        d = self._data
        d.qpos[:] = q
        mujoco.mj_kinematics(self.model, d)
        self.p[:] = d.site_xpos[self.site_id]
        self.R.flat[:] = d.site_xmat[self.site_id]
        if jacobian:
            mujoco.mj_comPos(self.model, d)  # mj_jac needs cdof / subtree com
            mujoco.mj_jacSite(self.model, d, self._jp, self._jr, self.site_id)

    # -- allocating conveniences (set-up code and tests) --
    def forward(self, q: np.ndarray) -> np.ndarray:
        """``T_world_tcp`` (4, 4) at ``q`` (n,)."""
        self.update(np.asarray(q, float), jacobian=False)
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.p
        return T

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """Geometric Jacobian (6, n) at ``q``, world frame, [linear; angular]."""
        self.update(np.asarray(q, float))
        return self.J.copy()


# --- independent NumPy chain --------------------------------------------------


@dataclass(frozen=True)
class KinematicChain:
    """Serial chain extracted from an MjModel, one entry per body from the root.

    ``T_parent_body[i]`` (4, 4) is the fixed body offset; ``joint_axis[i]`` (3,)
    and ``joint_pos[i]`` (3,) are the hinge (in the body frame) or None;
    ``T_body_site`` (4, 4) places the TCP on the last body.
    """

    T_parent_body: tuple
    joint_axis: tuple
    joint_pos: tuple
    T_body_site: np.ndarray


def _T(pos, quat) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(quat)
    T[:3, 3] = pos
    return T


def chain_from_model(model: mujoco.MjModel, site: str = "tool") -> KinematicChain:
    """Walk from the site's body to the world; one hinge at most per body."""
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
    bodies = []
    b = int(model.site_bodyid[sid])
    while b != 0:
        bodies.append(b)
        b = int(model.body_parentid[b])
    bodies.reverse()
    Ts, axes, poss = [], [], []
    for b in bodies:
        Ts.append(_T(model.body_pos[b], model.body_quat[b]))
        jn = model.body_jntnum[b]
        if jn > 1:
            raise ValueError("chain_from_model: more than one joint in a body")
        if jn == 1:
            j = model.body_jntadr[b]
            axes.append(model.jnt_axis[j].copy())
            poss.append(model.jnt_pos[j].copy())
        else:
            axes.append(None)
            poss.append(None)
    return KinematicChain(tuple(Ts), tuple(axes), tuple(poss), _T(model.site_pos[sid], model.site_quat[sid]))


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def _walk(chain: KinematicChain, q: np.ndarray):
    T = np.eye(4)
    axes_w, anchors_w = [], []
    k = 0
    for T_pb, axis, jpos in zip(chain.T_parent_body, chain.joint_axis, chain.joint_pos):
        T = T @ T_pb
        if axis is not None:
            anchor = T[:3, :3] @ jpos + T[:3, 3]
            axes_w.append(T[:3, :3] @ axis)
            anchors_w.append(anchor)
            J = np.eye(4)
            J[:3, :3] = _rot(axis, q[k])
            J[:3, 3] = jpos - J[:3, :3] @ jpos  # rotate about the joint anchor
            T = T @ J
            k += 1
    return T @ chain.T_body_site, axes_w, anchors_w


def fk_chain(chain: KinematicChain, q: np.ndarray) -> np.ndarray:
    """``T_world_tcp`` (4, 4) at ``q`` (n,), rad, in plain NumPy."""
    return _walk(chain, np.asarray(q, float))[0]


def jacobian_chain(chain: KinematicChain, q: np.ndarray) -> np.ndarray:
    """Geometric Jacobian (6, n), world frame: column i = [z_i x (p - o_i); z_i]."""
    T, axes, anchors = _walk(chain, np.asarray(q, float))
    p = T[:3, 3]
    J = np.zeros((6, len(axes)))
    for i, (z, o) in enumerate(zip(axes, anchors)):
        J[:3, i] = np.cross(z, p - o)
        J[3:, i] = z
    return J


# --- damped least squares -----------------------------------------------------


def damping_squared(s_min: float, eps: float, lambda_max: float) -> float:
    """``lambda^2``: 0 for ``s_min >= eps``, rising smoothly to ``lambda_max^2`` at 0."""
    if s_min >= eps:
        return 0.0
    r = s_min / eps
    return (1.0 - r * r) * lambda_max * lambda_max


def dls_solve_into(J: np.ndarray, x: np.ndarray, eps: float, lambda_max: float, out: np.ndarray) -> float:
    """Damped least-squares ``out = J^# x`` with singular-value dependent damping.

    ``J^# = V diag(s / (s^2 + lambda^2)) U^T``. The gain of each singular
    direction is bounded by ``max(1/eps, 1/(2 lambda_max))`` (see the tests),
    so joint rates stay bounded through singularities.

    Parameters
    ----------
    J : ndarray, shape (6, n)
    x : ndarray, shape (6,)
        Desired twist [m/s; rad/s] (or a pose error, for Newton steps).
    eps, lambda_max : float
        Singular region threshold and maximum damping (units of singular values).
    out : ndarray, shape (n,)
        Joint rates, rad/s.

    Returns
    -------
    s_min : float
        Smallest singular value of J (a manipulability measure).
    """
    # LAPACK returns fresh small arrays here: the one allocation per tick we
    # accept. Calling dgesdd directly halves the cost of np.linalg.svd's wrapper.
    U, s, Vt, info = _dgesdd(J)
    if info != 0:
        out[:] = np.nan  # caught downstream as a non-finite command (FAULT)
        return 0.0
    s_min = float(s[-1])
    lam2 = damping_squared(s_min, eps, lambda_max)
    y = (U.T if len(s) == U.shape[0] else U[:, : len(s)].T) @ x  # J may have fewer columns than rows
    y *= s / (s * s + lam2)
    np.dot(Vt.T, y, out=out)
    return s_min


# --- closed-loop inverse kinematics -------------------------------------------


@dataclass(frozen=True)
class ClikConfig:
    """CLIK gains and limits.

    gain_pos, gain_rot : 1/s
        Error feedback gains (the bandwidth of the pose error correction).
    eps, lambda_max : float
        DLS singular region threshold and maximum damping.
    joint_margin_rad : rad
        Commands stay this far inside the MJCF joint ranges.
    joint_brake_acc : rad/s^2
        Deceleration assumed available to stop before a joint limit.
    """

    gain_pos: float = 60.0
    gain_rot: float = 60.0
    eps: float = 0.06
    lambda_max: float = 0.05
    joint_margin_rad: float = 0.02
    joint_brake_acc: float = 15.0


class Clik:
    """One CLIK integration step per tick, on preallocated buffers.

    Parameters
    ----------
    kin : ArmKinematics
    config : ClikConfig

    tcp_speed_max : float, m/s
        Cap on the commanded TCP linear speed (reference velocity plus error
        feedback).

    Attributes after :meth:`step`: ``s_min`` (smallest singular value),
    ``qd_raw`` (n,) the DLS rates before the limits (diagnostics, tests),
    ``p``, ``quat`` the TCP pose at the input joints, ``limited`` (True when
    the speed cap, the joint velocity scaling or a joint limit brake cut the
    motion the reference asked for).
    """

    def __init__(self, kin: ArmKinematics, config: ClikConfig = ClikConfig(), tcp_speed_max: float = math.inf):
        self.kin = kin
        self.cfg = config
        self.tcp_speed_max = float(tcp_speed_max)
        self.limited = False  # the last step's motion was cut by a cap or a joint limit
        self.at_limit = False  # ... by a joint position limit (its brake or its clamp)
        self._blocked = [False] * kin.n  # joints braked at a limit in the last pass
        n = kin.n
        self.lo = kin.q_min + config.joint_margin_rad
        self.hi = kin.q_max - config.joint_margin_rad
        self.qd_max = kin.qd_max
        self._qd_max_l = kin.qd_max.tolist()
        self._lo_l = self.lo.tolist()
        self._hi_l = self.hi.tolist()
        self.x = np.zeros(6)
        self.quat = np.zeros(4)
        self.quat_inv = np.zeros(4)
        self.quat_err = np.zeros(4)
        self.qd_raw = np.zeros(n)
        self._v3 = np.zeros(3)
        self._t = np.zeros(n)
        self.s_min = 0.0

    def pose_error_into(self, p_ref, quat_ref, out: np.ndarray) -> np.ndarray:
        """[p_ref - p; log(q_ref q^-1)] (6,) at the pose of the last ``kin.update``."""
        kin = self.kin
        np.subtract(p_ref, kin.p, out=out[:3])
        quat_from_matrix_into(kin.R, self.quat)
        quat_conjugate_into(self.quat, self.quat_inv)
        quat_multiply_into(quat_ref, self.quat_inv, self.quat_err)
        rotvec_from_quat_into(self.quat_err, out[3:])
        return out

    def step(self, q, p_ref, quat_ref, v_ref, w_ref, dt: float, q_out, qd_out) -> float:
        """Joint command for the next tick.

        Parameters
        ----------
        q : ndarray (n,)
            Current joint command (the integrator state), rad.
        p_ref, quat_ref : ndarray (3,), (4,)
            Reference TCP position (m) and orientation (w, x, y, z), world frame.
        v_ref, w_ref : ndarray (3,)
            Reference TCP linear (m/s) and angular (rad/s) velocity, world frame.
        dt : float
            Integration step, s.
        q_out, qd_out : ndarray (n,)
            Next joint command (rad) and the joint rate that reaches it (rad/s).
            ``q_out`` may alias ``q``.

        Returns
        -------
        s_min : float
            Smallest singular value of the Jacobian at ``q``.
        """
        cfg = self.cfg
        kin = self.kin
        kin.update(q)
        x = self.x
        self.pose_error_into(p_ref, quat_ref, x)
        x[:3] *= cfg.gain_pos
        x[3:] *= cfg.gain_rot
        x[:3] += v_ref
        x[3:] += w_ref
        sp = math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2])
        capped = sp > self.tcp_speed_max
        if capped:
            x[:3] *= self.tcp_speed_max / sp
        self.s_min = dls_solve_into(kin.J, x, cfg.eps, cfg.lambda_max, self.qd_raw)
        s_min = self._limit_and_integrate(q, self.qd_raw, dt, q_out, qd_out)
        if self.at_limit:
            self._without_blocked_joints(q, x, dt, q_out, qd_out)
        # The damped inverse trades linear against angular error, so the linear
        # speed it realises may exceed what was asked: check J qd.
        v = self._v3
        np.dot(kin.J[:3], qd_out, out=v)
        sp = math.sqrt(float(v @ v))
        if sp > self.tcp_speed_max:
            k = self.tcp_speed_max / sp
            q_out -= qd_out * (dt * (1.0 - k))  # q_out may alias q: shrink the step in place
            qd_out *= k
            capped = True
        self.limited = self.limited or capped
        return s_min

    def _without_blocked_joints(self, q, x, dt, q_out, qd_out) -> None:
        """Solve again with the joints braked at a limit held still (their Jacobian columns removed).

        A braked joint does not do its share of the motion; merely clipping it
        would leave the others moving the tool in another direction than asked
        (a drift of the reference that waits for the arm). Without it, the free
        joints do the least-squares best for the whole twist. Repeated while
        another joint reaches its limit; allocates (only on this path).
        """
        cfg = self.cfg
        n = self.kin.n
        blocked = list(self._blocked)
        for _ in range(n):
            free = [i for i in range(n) if not blocked[i]]
            qd = np.zeros(n)
            if free:
                qf = np.zeros(len(free))
                dls_solve_into(np.ascontiguousarray(self.kin.J[:, free]), x, cfg.eps, cfg.lambda_max, qf)
                qd[free] = qf
            self._limit_and_integrate(q, qd, dt, q_out, qd_out)
            new = [i for i in free if self._blocked[i]]
            if not new:
                break
            for i in new:
                blocked[i] = True
        self.at_limit = True
        self.limited = True

    def _limit_and_integrate(self, q, qd, dt, q_out, qd_out) -> float:
        # Plain floats: six-element NumPy calls cost more than the arithmetic.
        qv = q.tolist()
        v = qd.tolist()
        vmax, lo, hi = self._qd_max_l, self._lo_l, self._hi_l
        n = len(qv)
        # Uniform scaling keeps the Cartesian direction of the motion.
        worst = 0.0
        for i in range(n):
            r = abs(v[i]) / vmax[i]
            if not r <= worst:  # also takes a NaN, which then propagates to a FAULT
                worst = r
        s = 1.0 / worst if worst > 1.0 else 1.0
        limited = s < 1.0
        at_limit = False
        a2 = 2.0 * self.cfg.joint_brake_acc
        inv_dt = 1.0 / dt
        qn_l = [0.0] * n
        qd_l = [0.0] * n
        blocked = self._blocked
        for i in range(n):
            x = v[i] * s
            # braking distance to each limit: |qd| <= sqrt(2 a d)
            up = hi[i] - qv[i]
            up = math.sqrt(a2 * up) if up > 0.0 else 0.0
            b = False
            if x > up:
                x, b = up, True
            dn = qv[i] - lo[i]
            dn = math.sqrt(a2 * dn) if dn > 0.0 else 0.0
            if x < -dn:
                x, b = -dn, True
            qn = qv[i] + x * dt
            if qn > hi[i]:
                qn, b = hi[i], True
            elif qn < lo[i]:
                qn, b = lo[i], True
            blocked[i] = b
            at_limit = at_limit or b
            qn_l[i] = qn
            qd_l[i] = (qn - qv[i]) * inv_dt
        q_out[:] = qn_l
        qd_out[:] = qd_l
        self.limited = limited or at_limit
        self.at_limit = at_limit
        return self.s_min


def solve_ik(
    kin: ArmKinematics,
    T_world_tcp: np.ndarray,
    q0: np.ndarray,
    tol_pos_m: float = 1e-6,
    tol_rot_rad: float = 1e-6,
    max_iter: int = 200,
    config: ClikConfig = ClikConfig(),
):
    """Pose IK by damped Newton iterations (CLIK with unit gain and step).

    Parameters
    ----------
    T_world_tcp : ndarray (4, 4)
        Desired TCP pose.
    q0 : ndarray (n,)
        Start (selects the branch), rad.

    Returns
    -------
    q : ndarray (n,), rad
    ok : bool
        Converged within the tolerances and inside the joint ranges.
    """
    T = np.asarray(T_world_tcp, float)
    if T.shape != (4, 4):
        raise ValueError(f"T_world_tcp: expected shape (4, 4), got {T.shape}")
    clik = Clik(kin, config)
    q = np.clip(np.array(q0, float), clik.lo, clik.hi)
    quat_ref = np.zeros(4)
    quat_from_matrix_into(np.ascontiguousarray(T[:3, :3]), quat_ref)
    p_ref = T[:3, 3].copy()
    e = np.zeros(6)
    dq = np.zeros(kin.n)
    for _ in range(max_iter):
        kin.update(q)
        clik.pose_error_into(p_ref, quat_ref, e)
        if np.linalg.norm(e[:3]) < tol_pos_m and np.linalg.norm(e[3:]) < tol_rot_rad:
            return q, True
        dls_solve_into(kin.J, e, config.eps, config.lambda_max, dq)
        # Limit the Newton step (the model is linear only locally).
        m = np.abs(dq).max()
        if m > 0.5:
            dq *= 0.5 / m
        q += dq
        np.clip(q, clik.lo, clik.hi, out=q)
    kin.update(q)
    clik.pose_error_into(p_ref, quat_ref, e)
    return q, bool(np.linalg.norm(e[:3]) < tol_pos_m and np.linalg.norm(e[3:]) < tol_rot_rad)
