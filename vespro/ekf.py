"""Error-state EKF for the 6-DoF pose and velocity of a rigid object.

State
-----
Nominal state ``x``, shape (13,), float64 (index slices below)::

    x[P_]  p  (3,)  object origin in the world, m          (T_world_object translation)
    x[Q_]  q  (4,)  (w, x, y, z) unit quaternion            (T_world_object rotation)
    x[V_]  v  (3,)  linear velocity of the origin, world, m/s
    x[W_]  w  (3,)  angular velocity, world frame, rad/s    (dR/dt = [w]x R)

Error state ``dx``, shape (12,): ``[dp, dtheta, dv, dw]`` with the convention of
:mod:`vespro.projection`: ``R_true = Exp(dtheta) R``, ``p_true = p + dp``,
``v_true = v + dv``, ``w_true = w + dw``; ``dtheta`` is a world-frame rotation
vector applied on the left. ``P`` (12, 12) is the covariance of ``dx``. The
published 6x6 pose covariance is ``P[:6, :6]`` ordered ``[position, orientation]``.

Motion model
------------
Constant velocity driven by white linear / angular acceleration with spectral
densities ``q_acc`` (m^2/s^3) and ``q_alpha`` (rad^2/s^3)::

    p' = p + v dt,   R' = Exp(w dt) R,   v' = v,   w' = w

Error propagation (exact to first order in dx, derived in :func:`transition_jacobian`)::

    dp'     = dp + dt dv
    dtheta' = Exp(w dt) dtheta + dt Jl(w dt) dw

Structure follows filterpy: pure ``predict`` / ``update`` functions on
``(x, P)`` and a thin :class:`PoseEKF` that only keeps state. The quaternion's
"minus" is :func:`boxminus`, its "plus" is :func:`inject`.
"""

from __future__ import annotations

import enum
import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from .jit import njit
from .numerics import dot3, dot4
from .se3 import log_so3, matrix_from_quat, rotation_rows, skew

__all__ = [
    "Status",
    "UpdateResult",
    "PoseEKF",
    "state_from_pose",
    "pose_from_state",
    "motion_model",
    "transition_jacobian",
    "process_noise",
    "inject",
    "boxminus",
    "reset_jacobian",
    "left_jacobian_so3",
    "predict",
    "update",
    "nees",
    "stack_jacobian",
    "inject_and_reset",
    "mahalanobis_2d",
    "mahalanobis_2d_numpy",
]

# Nominal-state slices (13,)
P_ = slice(0, 3)
Q_ = slice(3, 7)
V_ = slice(7, 10)
W_ = slice(10, 13)
# Error-state slices (12,)
DP = slice(0, 3)
DTH = slice(3, 6)
DV = slice(6, 9)
DW = slice(9, 12)


class Status(enum.Enum):
    OK = "ok"
    #: No measurement survived the non-finite check and the gate; the state is unchanged.
    NO_MEASUREMENTS = "no_measurements"
    #: dt was negative or non-finite; the state is unchanged.
    BAD_DT = "bad_dt"


@dataclass(frozen=True)
class UpdateResult:
    """Outcome of one measurement update.

    Attributes
    ----------
    status : Status
    accepted : ndarray, shape (M,), bool
        Points used in the update.
    nonfinite : ndarray, shape (M,), bool
        Points rejected because z, h or H was not finite.
    nis : ndarray, shape (M,)
        Squared normalised innovation per point (chi-square, 2 dof) after the
        final update: for accepted points the leave-one-out statistic, for
        gated ones their innovation against the final estimate; NaN for
        non-finite points.
    n_gated : int
        Number of finite points rejected by the gate.
    P_pub : ndarray, shape (12, 12), or None
        The published (residual-consistent) covariance after this update, when
        :func:`update` was given one (``P_pub``); see its Notes.
    """

    status: Status
    accepted: np.ndarray
    nonfinite: np.ndarray
    nis: np.ndarray
    n_gated: int
    P_pub: np.ndarray | None = None

    @property
    def n_nonfinite(self) -> int:
        return int(self.nonfinite.sum())

    @property
    def n_accepted(self) -> int:
        return int(self.accepted.sum())


# --------------------------------------------------------------------------- small fast SO(3) helpers
# (scipy's Rotation costs ~10-15 us per call on a single vector; these are per-tick)


def _quat_exp(v: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of the rotation vector ``v`` (3,).

    (In plain floats: the same IEEE arithmetic as on NumPy's scalars, at a tenth of the cost.)"""
    v0, v1, v2 = v.tolist()
    a = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if a < 1e-8:
        q = np.array([1.0, 0.5 * v0, 0.5 * v1, 0.5 * v2])
        return q / math.sqrt(q @ q)
    s = math.sin(0.5 * a) / a
    return np.array([math.cos(0.5 * a), s * v0, s * v1, s * v2])


def _quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of two single quaternions (4,)."""
    pw, px, py, pz = p.tolist()
    qw, qx, qy, qz = q.tolist()
    return np.array([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ])


def _exp_so3(v: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``v`` (3,) (Rodrigues)."""
    a = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    S = skew(v)
    if a < 1e-8:
        return np.eye(3) + S + 0.5 * (S @ S)
    return np.eye(3) + (math.sin(a) / a) * S + ((1.0 - math.cos(a)) / (a * a)) * (S @ S)


# --------------------------------------------------------------------------- state helpers


def state_from_pose(T_world_object: np.ndarray, v=None, w=None) -> np.ndarray:
    """Nominal state (13,) from a pose (4, 4) and optional velocities (3,) (world)."""
    from .se3 import quat_from_matrix

    T_world_object = np.asarray(T_world_object, dtype=float)
    if T_world_object.shape != (4, 4):
        raise ValueError(f"T_world_object: expected shape (4, 4), got {T_world_object.shape}")
    x = np.zeros(13)
    x[P_] = T_world_object[:3, 3]
    x[Q_] = quat_from_matrix(T_world_object[:3, :3])
    if v is not None:
        x[V_] = v
    if w is not None:
        x[W_] = w
    return x


def pose_from_state(x: np.ndarray) -> np.ndarray:
    """``T_world_object`` (4, 4) of a nominal state (13,).

    Built from :func:`vespro.se3.rotation_rows` in plain floats (the state's
    quaternion is finite and unit: :func:`vespro.se3.matrix_from_quat`'s input
    checks cost more than the arithmetic).
    """
    px, py, pz, w, qx, qy, qz = x[:7].tolist()
    r0, r1, r2 = rotation_rows(w, qx, qy, qz)
    return np.array([[*r0, px], [*r1, py], [*r2, pz], [0.0, 0.0, 0.0, 1.0]])


def _unit_rotation(q: np.ndarray) -> np.ndarray:
    """:func:`vespro.se3.matrix_from_quat` of one finite quaternion (4,): its normalisation
    (``np.linalg.norm`` of four sums them in order) in plain floats, without its checks."""
    w, x, y, z = q.tolist()
    n = math.sqrt(((w * w + x * x) + y * y) + z * z)
    return np.array(rotation_rows(w / n, x / n, y / n, z / n))


def left_jacobian_so3(phi: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3): ``Exp(phi + d) ~= Exp(Jl(phi) d) Exp(phi)``, (3,) -> (3, 3).

    (``np.linalg.norm`` of a vector is ``sqrt(phi @ phi)``, and NumPy's scalar ``cos``
    and ``sin`` of a float are libm's: written so, without their per-call overhead.)
    """
    phi = np.asarray(phi, dtype=float)
    a = math.sqrt(phi @ phi)
    S = skew(phi)
    if a < 1e-6:
        return _EYE3 + 0.5 * S + S @ S / 6.0
    return _EYE3 + (1.0 - math.cos(a)) / a**2 * S + (a - math.sin(a)) / a**3 * (S @ S)


def inject(x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """Nominal state plus error: ``x [+] dx`` (quaternion: ``q(dtheta) * q``, renormalised).

    Parameters
    ----------
    x : ndarray, shape (13,)
    dx : ndarray, shape (12,)

    Returns
    -------
    ndarray, shape (13,)
    """
    out = np.empty(13)
    out[P_] = x[P_] + dx[DP]
    q = _quat_mul(_quat_exp(dx[DTH]), x[Q_])
    out[Q_] = q / math.sqrt(q @ q)
    out[V_] = x[V_] + dx[DV]
    out[W_] = x[W_] + dx[DW]
    return out


def boxminus(x_a: np.ndarray, x_b: np.ndarray) -> np.ndarray:
    """Error ``dx`` (12,) with ``inject(x_b, dx) == x_a`` (rotation part: ``Log(R_a R_b^T)``)."""
    dx = np.empty(12)
    dx[DP] = x_a[P_] - x_b[P_]
    dx[DTH] = log_so3(matrix_from_quat(x_a[Q_]) @ matrix_from_quat(x_b[Q_]).T)
    dx[DV] = x_a[V_] - x_b[V_]
    dx[DW] = x_a[W_] - x_b[W_]
    return dx


def reset_jacobian(dx: np.ndarray) -> np.ndarray:
    """Covariance reset Jacobian ``G`` (12, 12) after injecting ``dx`` (12,).

    With a left, world-frame error the new rotation error is
    ``Exp(e_new) = Exp(dtheta_hat + e) Exp(-dtheta_hat)``, so to first order
    ``e_new = Jl(dtheta_hat) e`` (``~ I + [dtheta_hat]x / 2``). The other
    blocks are identities (additive errors).
    """
    G = _EYE12.copy()
    G[DTH, DTH] = left_jacobian_so3(dx[DTH])
    return G


def inject_and_reset(x: np.ndarray, dx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(inject(x, dx), reset_jacobian(dx))``, the same bits, compiled
    (:func:`_inject_reset_kernel`; the two scalars of the Jacobian's series taken here, as
    :func:`left_jacobian_so3` does: libm's ``pow``)."""
    phi = dx[DTH]
    a = math.sqrt(phi @ phi)
    if a < 1e-6:
        return _inject_reset_kernel(x, dx, True, 0.5, 0.0)
    return _inject_reset_kernel(x, dx, False, (1.0 - math.cos(a)) / a**2, (a - math.sin(a)) / a**3)


@njit
def _inject_reset_kernel(x, dx, series, c1, c2):
    """:func:`inject` and :func:`reset_jacobian` in one pass: their operations in their order
    (the quaternions' dot products and ``S @ S`` as OpenBLAS forms them, FMA chains,
    :func:`vespro.numerics.dot3`), so the same bits. ``series``: the Jacobian's small-angle
    form (``c1`` 0.5, ``S @ S / 6``), else ``I + c1 S + c2 S @ S``."""
    out = np.empty(13)
    for i in range(3):
        out[i] = x[i] + dx[i]
        out[7 + i] = x[7 + i] + dx[6 + i]
        out[10 + i] = x[10 + i] + dx[9 + i]
    v0, v1, v2 = dx[3], dx[4], dx[5]
    a = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if a < 1e-8:  # _quat_exp
        pw, px, py, pz = 1.0, 0.5 * v0, 0.5 * v1, 0.5 * v2
        n = math.sqrt(dot4(pw, px, py, pz, pw, px, py, pz))
        pw, px, py, pz = pw / n, px / n, py / n, pz / n
    else:
        sa = math.sin(0.5 * a) / a
        pw, px, py, pz = math.cos(0.5 * a), sa * v0, sa * v1, sa * v2
    qw, qx, qy, qz = x[3], x[4], x[5], x[6]  # _quat_mul
    rw = pw * qw - px * qx - py * qy - pz * qz
    rx = pw * qx + px * qw + py * qz - pz * qy
    ry = pw * qy - px * qz + py * qw + pz * qx
    rz = pw * qz + px * qy - py * qx + pz * qw
    n = math.sqrt(dot4(rw, rx, ry, rz, rw, rx, ry, rz))
    out[3], out[4], out[5], out[6] = rw / n, rx / n, ry / n, rz / n
    S = np.array([[0.0, -v2, v1], [v2, 0.0, -v0], [-v1, v0, 0.0]])  # skew
    G = np.eye(12)
    for i in range(3):
        for j in range(3):
            SS = dot3(S[i, 0], S[i, 1], S[i, 2], S[0, j], S[1, j], S[2, j])
            eye = 1.0 if i == j else 0.0
            if series:
                G[3 + i, 3 + j] = (eye + 0.5 * S[i, j]) + SS / 6.0
            else:
                G[3 + i, 3 + j] = (eye + c1 * S[i, j]) + c2 * SS
    return out, G


# --------------------------------------------------------------------------- motion model


def motion_model(x: np.ndarray, dt: float) -> np.ndarray:
    """Propagate the nominal state (13,) by ``dt`` seconds (constant velocity)."""
    out = x.copy()
    out[P_] = x[P_] + dt * x[V_]
    q = _quat_mul(_quat_exp(dt * x[W_]), x[Q_])
    out[Q_] = q / math.sqrt(q @ q)
    return out


def transition_jacobian(x: np.ndarray, dt: float) -> np.ndarray:
    """Error-state transition ``F`` (12, 12) of :func:`motion_model` at ``x``.

    ``R'_true = Exp((w + dw) dt) Exp(dtheta) R`` and
    ``Exp((w + dw) dt) ~= Exp(Jl(w dt) dw dt) Exp(w dt)`` give
    ``Exp(dtheta') = Exp(Jl dw dt) Exp(Exp(w dt) dtheta)``.

    ``Exp(phi)`` and ``Jl(phi)`` share ``[phi]x`` and its square: written out
    here (every frame) rather than through :func:`_exp_so3` and
    :func:`left_jacobian_so3`, the same values at a third of the cost.
    """
    F = _EYE12.copy()
    F[0, 6] = F[1, 7] = F[2, 8] = dt
    px, py, pz = (dt * x[W_]).tolist()
    a2 = px * px + py * py + pz * pz
    S = np.array([[0.0, -pz, py], [pz, 0.0, -px], [-py, px, 0.0]])
    S2 = S @ S
    if a2 < 1e-12:  # series (Exp below 1e-8 rad, Jl below 1e-6 rad in the closed forms)
        A, B, C = 1.0, 0.5, 1.0 / 6.0
    else:
        a = math.sqrt(a2)
        sa, ca = math.sin(a), math.cos(a)
        A, B, C = sa / a, (1.0 - ca) / a2, (a - sa) / (a2 * a)
    F[3:6, 3:6] = _EYE3 + A * S + B * S2
    F[3:6, 9:12] = dt * (_EYE3 + B * S + C * S2)
    return F


_EYE2 = np.eye(2)
_EYE2.setflags(write=False)
_EYE3 = np.eye(3)
_EYE3.setflags(write=False)
_EYE12 = np.eye(12)
_EYE12.setflags(write=False)


def process_noise(dt: float, q_acc: float, q_alpha: float) -> np.ndarray:
    """Discretised process noise ``Q`` (12, 12); see :func:`_process_noise_cached`.

    Cached per ``(dt, q_acc, q_alpha)``: dt from capture stamps repeats.
    """
    return _process_noise_cached(float(dt), float(q_acc), float(q_alpha)).copy()


@functools.lru_cache(maxsize=256)
def _process_noise_cached(dt: float, q_acc: float, q_alpha: float) -> np.ndarray:
    """Discretised process noise ``Q`` (12, 12) of the constant-velocity model.

    Per axis ``q * [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` (continuous white
    acceleration, filterpy's ``Q_continuous_white_noise``; its
    ``Q_discrete_white_noise`` is the piecewise-constant acceleration model,
    ``var * [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]``, parametrised by a per-step
    variance rather than a spectral density, so its tuning would change with
    the frame rate). For the rotation
    block the ``Exp(w dt)`` / ``Jl(w dt)`` factors are taken as identity: they
    rotate an isotropic density (no effect) up to O(|w| dt) terms in the
    cross block, below 4 % at 1 rad/s and 26 Hz.

    Parameters
    ----------
    dt : float
        s.
    q_acc : float
        Linear acceleration spectral density, m^2/s^3.
    q_alpha : float
        Angular acceleration spectral density, rad^2/s^3.
    """
    Q = np.zeros((12, 12))
    # filterpy's Q_continuous_white_noise(dim=2, dt, q, block_size=3, order_by_dim=False) of each
    # part, entry by entry (its arithmetic: the 2x2 block's entries, times the density), in
    # place: the adaptive motion model changes the densities from frame to frame.
    d3, d2 = np.float64((dt**3) / 3.0), np.float64((dt**2) / 2.0)
    for q, base in ((q_acc, 0), (q_alpha, 3)):
        a, b, c = d3 * q, d2 * q, np.float64(dt) * q
        for k in range(base, base + 3):
            Q[k, k], Q[k, k + 6], Q[k + 6, k], Q[k + 6, k + 6] = a, b, b, c
    Q.setflags(write=False)
    return Q


def predict(x: np.ndarray, P: np.ndarray, dt: float, q_acc: float, q_alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Propagate nominal state (13,) and error covariance (12, 12) by ``dt`` (s).

    The covariance step is filterpy's ``predict`` on the error state (which is
    zero before the step: the nominal state carries the mean).
    """
    F = transition_jacobian(x, dt)
    return motion_model(x, dt), _propagate(P, F, _process_noise_cached(float(dt), float(q_acc), float(q_alpha)))


def _propagate(P: np.ndarray, F: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``F P F^T + Q`` (filterpy's ``predict``, its products in its order), symmetrised."""
    P_new = np.dot(np.dot(F, P), F.T) + Q
    return 0.5 * (P_new + P_new.T)


def _kalman_step(P: np.ndarray, y: np.ndarray, R: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """filterpy's ``update`` (Joseph form) of the error state, prior mean zero, measurement
    ``y``: its products in its order, so the same ``(dx, P+)`` to the bit, without its
    argument handling (a filter step makes up to three)."""
    PHT = np.dot(P, H.T)
    S = np.dot(np.dot(H, P), H.T) + R
    K = np.dot(PHT, np.linalg.inv(S))
    dx = _ZERO12 + np.dot(K, y)
    I_KH = _EYE12 - np.dot(K, H)
    return dx, np.dot(np.dot(I_KH, P), I_KH.T) + np.dot(np.dot(K, R), K.T)


_ZERO12 = np.zeros(12)
_ZERO12.setflags(write=False)


# --------------------------------------------------------------------------- measurement update


def stack_jacobian(J_pose: np.ndarray) -> np.ndarray:
    """Pose Jacobians (M, 2, 6) -> error-state Jacobian (2M, 12) with zero velocity columns."""
    J_pose = np.asarray(J_pose, dtype=float)
    H = np.zeros((J_pose.shape[0], 2, 12))
    H[:, :, :6] = J_pose
    return H.reshape(-1, 12)


def mahalanobis_2d_numpy(r: np.ndarray, C: np.ndarray) -> np.ndarray:
    """``r_m^T C_m^-1 r_m`` for residuals ``r`` (M, 2) and covariances ``C`` (M, 2, 2): the
    NumPy formulation :func:`mahalanobis_2d` computes (the closed-form inverse, then
    ``einsum``)."""
    a, b, c, d = C[:, 0, 0], C[:, 0, 1], C[:, 1, 0], C[:, 1, 1]
    det = a * d - b * c
    inv = np.empty_like(C)
    inv[:, 0, 0] = d
    inv[:, 0, 1] = -b
    inv[:, 1, 0] = -c
    inv[:, 1, 1] = a
    return np.einsum("mi,mij,mj->m", r, inv / det[:, None, None], r)


@njit
def mahalanobis_2d(r, C, floor):
    """:func:`mahalanobis_2d_numpy`, compiled, with ``C``'s diagonal first raised to at least
    ``floor`` (M,) (``np.maximum``: NaN stays NaN; ``floor`` None: as it is). The same
    operations in the same order (``einsum`` sums ``r_i C^-1_ij r_j`` over ``i`` then ``j``,
    each term ``(r_i c_ij) r_j``), so the same bits; ``C`` is not changed."""
    M = r.shape[0]
    out = np.empty(M)
    for m in range(M):
        a, b, c, d = C[m, 0, 0], C[m, 0, 1], C[m, 1, 0], C[m, 1, 1]
        if floor is not None:
            f = floor[m]
            a = a if a >= f or np.isnan(a) else f  # np.maximum(a, f)
            d = d if d >= f or np.isnan(d) else f
        det = a * d - b * c
        i00, i01, i10, i11 = d / det, -b / det, -c / det, a / det
        r0, r1 = r[m, 0], r[m, 1]
        out[m] = ((r0 * i00 * r0 + r0 * i01 * r1) + r1 * i10 * r0) + r1 * i11 * r1
    return out


@functools.lru_cache(maxsize=64)
def _gate_2dof(gate_prob: float) -> float:
    """chi-square (2 dof) quantile; cached: scipy's ppf costs ~60 us, every frame."""
    return float(chi2.ppf(gate_prob, 2))


def update(
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    h: np.ndarray,
    J_pose: np.ndarray,
    sigma_px: float = 0.5,
    gate_prob: float = 0.999,
    min_points: int = 3,
    robust_nis: float = 0.0,
    P_pub: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, UpdateResult]:
    """Stacked multi-camera pixel update with one-by-one outlier gating.

    Parameters
    ----------
    x : ndarray, shape (13,)
        Nominal state (the linearisation point of ``h`` and ``J_pose``).
    P : ndarray, shape (12, 12)
    z : ndarray, shape (M, 2)
        Measured (distorted) pixels of all cameras, stacked.
    h : ndarray, shape (M, 2)
        Predicted pixels at ``x`` (:func:`vespro.projection.project_with_jacobian`).
    J_pose : ndarray, shape (M, 2, 6)
        ``d h / d [dp, dtheta]`` at ``x``.
    sigma_px : float or ndarray (M,)
        Pixel noise standard deviation (isotropic, independent), px; per point
        if an array (e.g. from the extractor's confidence).
    gate_prob : float
        Gate probability: a point is an outlier if its normalised innovation
        exceeds the ``gate_prob`` quantile of chi-square with 2 dof.
    min_points : int
        Below this many accepted points the update is skipped
        (``Status.NO_MEASUREMENTS``): gating cannot tell inliers apart.
    robust_nis : float
        Residual-consistent covariance threshold (0: no raise). With ``P_pub``:
        an accepted point whose leave-one-out statistic ``d2`` exceeds it counts
        in ``result.P_pub`` as if its variance were ``sigma^2 d2 / robust_nis``.
    P_pub : ndarray (12, 12), optional
        The published covariance before the update (the error covariance of
        this filter's estimate under the noise the residuals show; equal to
        ``P`` until some point raised it). Updated with the model's gain into
        ``result.P_pub``; the returned state and ``P`` are the model's
        whatever it holds. See Notes.

    Returns
    -------
    x, P : updated state (13,) and covariance (12, 12)
    result : UpdateResult

    Notes
    -----
    Gating: update with the accepted set, compute each accepted point's
    leave-one-out statistic ``r_i^T C_i^-1 r_i`` with the posterior residual
    ``r_i = y_i - H_i dx`` and ``C_i = R - H_i P+ H_i^T`` (identical to the
    innovation of point i against the update from all the others, so a single
    outlier cannot hide by dragging the estimate), drop the largest if it
    exceeds the gate, repeat.

    The Kalman step itself is filterpy's ``update`` (Joseph form) applied to
    the error state with prior mean zero and measurement ``y = z - h``;
    filterpy cannot do the rest of an error-state update (the non-additive
    injection of ``dtheta`` into the quaternion and the covariance reset),
    which follows here.

    Published covariance (``P_pub``, ``robust_nis`` > 0): real corner errors
    are heavier-tailed than the Gaussian ``sigma`` says (a corner 3-5 sigma
    off, e.g. found at a neighbouring junction, stays under a 0.999 gate), and
    the few frames that hold one account for most of the frames whose pose
    error lies outside the filter's own 95% band. Rejecting such points harder
    makes it worse (a tighter gate drops good points that disagree with the
    prediction). So the filter keeps its model (gain ``K`` from ``P`` and
    ``R``: estimates and velocities are the plain filter's), and beside ``P``
    it carries the covariance of that filter's error for the noise the data
    show: ``P_pub+ = A P_pub A^T + K R' K^T``, ``A = I - K H``, with ``R'`` each
    point's variance raised to ``sigma^2 d2 / robust_nis`` where that is larger
    (the analysis of a filter whose gain was designed for another ``R``; per
    frame a heteroskedasticity-consistent, "sandwich" covariance in the manner
    of White's estimator, floored at the model's ``R``). It is propagated like
    ``P`` (same transition and process noise), so an error a bad corner leaves
    in the estimate is still counted in the next frames. For Gaussian points
    and ``robust_nis = 3`` the measurement term grows by ~15% on average. The
    model gain is ``K = P+ H^T R^-1`` (R diagonal): no extra solve.
    """
    z = np.asarray(z, dtype=float)
    h = np.asarray(h, dtype=float)
    J_pose = np.asarray(J_pose, dtype=float)
    M = z.shape[0] if z.ndim == 2 else -1
    if z.shape != (M, 2) or h.shape != (M, 2) or J_pose.shape != (M, 2, 6):
        raise ValueError(f"update: expected z (M,2), h (M,2), J_pose (M,2,6); got {z.shape}, {h.shape}, {J_pose.shape}")

    try:
        sig2 = np.asarray(sigma_px, dtype=float) ** 2
        if sig2.shape != (M,):  # (broadcast_to costs more than the checks around it)
            sig2 = np.broadcast_to(sig2, (M,))
    except ValueError:
        raise ValueError(f"update: sigma_px must be a scalar or shape ({M},), got {np.shape(sigma_px)}") from None

    y_all = z - h
    finite = np.isfinite(y_all).all(axis=1) & np.isfinite(J_pose.reshape(M, 12)).all(axis=1)
    finite &= np.isfinite(sig2) & (sig2 > 0)
    nonfinite = ~finite
    accepted = finite.copy()
    nis = np.full(M, np.nan)
    H_all = np.zeros((M, 2, 12))
    if finite.all():
        H_all[:, :, :6] = J_pose
    else:
        H_all[:, :, :6] = np.where(finite[:, None, None], J_pose, 0.0)
        y_all = np.where(finite[:, None], y_all, 0.0)
    gate = _gate_2dof(float(gate_prob))

    dx = None
    P_post = None
    while accepted.sum() >= max(min_points, 1):
        idx = np.flatnonzero(accepted)
        H = H_all[idx].reshape(-1, 12)
        s2 = sig2[idx]
        dx, P_post = _kalman_step(P, y_all[idx].reshape(-1), np.diag(np.repeat(s2, 2)), H)
        Hi = H_all[idx]
        r = y_all[idx] - Hi @ dx
        C = s2[:, None, None] * _EYE2 - Hi @ P_post @ Hi.transpose(0, 2, 1)
        # C is the residual covariance; its diagonal is kept positive if a single point
        # carries (almost) all the information of a direction (leverage -> 1).
        d2 = mahalanobis_2d(r, C, 1e-6 * s2)
        nis[idx] = d2
        worst = int(np.argmax(d2))
        if d2[worst] <= gate:
            break
        accepted[idx[worst]] = False
        dx = None

    if dx is None:  # fewer than min_points survived
        accepted[:] = False
        return x.copy(), P.copy(), UpdateResult(Status.NO_MEASUREMENTS, accepted, nonfinite, nis, int(finite.sum()),
                                                None if P_pub is None else np.array(P_pub, dtype=float))

    Pp_post = None
    if P_pub is not None:
        idx = np.flatnonzero(accepted)
        r2 = sig2[idx] * (np.maximum(nis[idx] / robust_nis, 1.0) if robust_nis > 0 else 1.0)
        H = H_all[idx].reshape(-1, 12)
        K = (P_post @ H.T) / np.repeat(sig2[idx], 2)  # the model's gain, P+ H^T R^-1
        A = _EYE12 - K @ H
        Pp_post = A @ np.asarray(P_pub, dtype=float) @ A.T + (K * np.repeat(r2, 2)) @ K.T

    gated = finite & ~accepted
    if gated.any():
        Hg = H_all[gated]
        rg = y_all[gated] - Hg @ dx
        Sg = sig2[gated][:, None, None] * _EYE2 + Hg @ P_post @ Hg.transpose(0, 2, 1)
        nis[gated] = mahalanobis_2d(rg, Sg, None)

    x_new, G = inject_and_reset(x, dx)
    P_new = G @ P_post @ G.T
    P_new = 0.5 * (P_new + P_new.T)
    if Pp_post is not None:
        Pp_post = G @ Pp_post @ G.T
        Pp_post = 0.5 * (Pp_post + Pp_post.T)
    return x_new, P_new, UpdateResult(Status.OK, accepted, nonfinite, nis, int(gated.sum()), Pp_post)


def update_pose(x: np.ndarray, P: np.ndarray, T_meas: np.ndarray, R6: np.ndarray,
                P_pub: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, float]:
    """Update with a direct measurement of the pose (e.g. an edge fit).

    Parameters
    ----------
    x : ndarray (13,), P : ndarray (12, 12)
    T_meas : ndarray (4, 4)
        Measured ``T_world_object``.
    R6 : ndarray (6, 6)
        Its covariance, of ``[dp, dtheta]`` (world, rotation on the left: the
        error-state convention of ``P``).
    P_pub : ndarray (12, 12), optional
        The published covariance, updated with the same gain.

    Returns
    -------
    x, P, P_pub (or None), nis : the updated state and covariances, and the
    measurement's normalised innovation (6 dof).
    """
    T_meas = np.asarray(T_meas, dtype=float)
    R6 = np.asarray(R6, dtype=float)
    if T_meas.shape != (4, 4) or R6.shape != (6, 6):
        raise ValueError(f"update_pose: expected T_meas (4, 4) and R6 (6, 6), got {T_meas.shape}, {R6.shape}")
    R_est = _unit_rotation(x[Q_])
    y = np.concatenate([T_meas[:3, 3] - x[P_], log_so3(T_meas[:3, :3] @ R_est.T)])
    H = np.zeros((6, 12))
    H[:, :6] = np.eye(6)
    S_inv = np.linalg.inv(P[:6, :6] + R6)
    nis = float(y @ S_inv @ y)
    dx, P_post = _kalman_step(P, y, R6, H)
    Pp = None
    if P_pub is not None:
        K = P[:, :6] @ S_inv
        A = np.eye(12) - K @ H
        Pp = A @ np.asarray(P_pub, dtype=float) @ A.T + K @ R6 @ K.T
    x_new, G = inject_and_reset(x, dx)
    P_new = G @ P_post @ G.T
    if Pp is not None:
        Pp = G @ Pp @ G.T
        Pp = 0.5 * (Pp + Pp.T)
    return x_new, 0.5 * (P_new + P_new.T), Pp, nis


# --------------------------------------------------------------------------- consistency


def nees(T_est: np.ndarray, T_true: np.ndarray, P6: np.ndarray) -> float:
    """Normalised estimation error squared of a pose (chi-square, 6 dof if consistent).

    Parameters
    ----------
    T_est, T_true : ndarray, shape (4, 4)
        ``T_world_object`` estimated and true.
    P6 : ndarray, shape (6, 6)
        Covariance of ``[dp, dtheta]`` (world frame, rotation on the left), as
        published by :class:`PoseEKF`.

    Returns
    -------
    float
        ``e^T P6^-1 e`` with ``e = [p_true - p_est, Log(R_true R_est^T)]``.
    """
    P6 = np.asarray(P6, dtype=float)
    if P6.shape != (6, 6):
        raise ValueError(f"P6: expected shape (6, 6), got {P6.shape}")
    e = np.concatenate([T_true[:3, 3] - T_est[:3, 3], log_so3(T_true[:3, :3] @ T_est[:3, :3].T)])
    return float(e @ np.linalg.solve(P6, e))


# --------------------------------------------------------------------------- thin class


class PoseEKF:
    """Holds ``x`` (13,) and ``P`` (12, 12); the math is in the pure functions.

    Parameters
    ----------
    T_world_object : ndarray, shape (4, 4)
        Initial pose.
    P0 : ndarray, shape (12, 12)
        Initial error covariance (``[dp, dtheta, dv, dw]``).
    q_acc, q_alpha : float
        Process noise spectral densities, m^2/s^3 and rad^2/s^3.
    sigma_px : float
        Pixel noise, px.
    gate_prob : float
        Chi-square (2 dof) gate probability per point.
    robust_nis : float
        See :func:`update`. When > 0 the filter carries ``P_pub`` beside ``P``
        and publishes its pose block (:attr:`pose_covariance`); 0: ``P``.
    v, w : ndarray (3,), optional
        Initial velocities (world), m/s and rad/s.
    """

    def __init__(self, T_world_object, P0, q_acc=0.05, q_alpha=0.5, sigma_px=0.5, gate_prob=0.999, v=None, w=None,
                 robust_nis=0.0):
        self._pose_of = None  # (state array, its pose): the tracker asks for the pose several times a step
        self.x = state_from_pose(T_world_object, v, w)
        P0 = np.array(P0, dtype=float)
        if P0.shape != (12, 12):
            raise ValueError(f"P0: expected shape (12, 12), got {P0.shape}")
        self.P = P0
        self.q_acc = float(q_acc)
        self.q_alpha = float(q_alpha)
        self.sigma_px = float(sigma_px)
        self.gate_prob = float(gate_prob)
        self.robust_nis = float(robust_nis)
        self.P_pub = P0.copy() if self.robust_nis > 0 else None
        self.n_nonfinite = 0  # running count of non-finite measurements rejected

    def predict(self, dt: float) -> Status:
        """Propagate by ``dt`` s (from capture stamps). Bad dt: state unchanged."""
        if not np.isfinite(dt) or dt < 0.0:
            return Status.BAD_DT
        x = self.x
        dt = float(dt)
        # One transition and process noise for the filter's covariance and the published one.
        F = transition_jacobian(x, dt)
        Q = _process_noise_cached(dt, float(self.q_acc), float(self.q_alpha))
        self.x, self.P = motion_model(x, dt), _propagate(self.P, F, Q)
        if self.P_pub is not None:
            self.P_pub = _propagate(self.P_pub, F, Q)
        return Status.OK

    def update(self, z, h, J_pose) -> UpdateResult:
        """Stacked pixel update; see :func:`update`."""
        self.x, self.P, res = update(self.x, self.P, z, h, J_pose, self.sigma_px, self.gate_prob,
                                     robust_nis=self.robust_nis, P_pub=self.P_pub)
        if res.P_pub is not None:
            self.P_pub = res.P_pub
        self.n_nonfinite += res.n_nonfinite
        return res

    def update_pose(self, T_meas, R6) -> float:
        """Direct pose measurement; see :func:`update_pose`. Returns its NIS (6 dof)."""
        self.x, self.P, Pp, nis = update_pose(self.x, self.P, T_meas, R6, self.P_pub)
        if Pp is not None:
            self.P_pub = Pp
        return nis

    @property
    def x(self) -> np.ndarray:
        """Nominal state (13,); replaced (never edited in place) by predict and update."""
        return self._x

    @x.setter
    def x(self, value) -> None:
        self._x = np.asarray(value, dtype=float)
        self._pose_of = None

    @property
    def pose(self) -> np.ndarray:
        """``T_world_object`` (4, 4) (a copy)."""
        if self._pose_of is None or self._pose_of[0] is not self._x:
            self._pose_of = (self._x, pose_from_state(self._x))
        return self._pose_of[1].copy()

    @property
    def velocity(self) -> np.ndarray:
        """Linear velocity of the object origin, world, m/s (3,)."""
        return self.x[V_].copy()

    @property
    def angular_velocity(self) -> np.ndarray:
        """Angular velocity, world, rad/s (3,)."""
        return self.x[W_].copy()

    @property
    def pose_covariance(self) -> np.ndarray:
        """Covariance (6, 6) of ``[dp, dtheta]`` (world, left rotation error).

        The published one: ``P_pub``'s pose block with ``robust_nis``, else ``P``'s.
        """
        return (self.P if self.P_pub is None else self.P_pub)[:6, :6].copy()

    def snapshot(self) -> tuple:
        """State and covariances, for :meth:`restore`."""
        return (self.x.copy(), self.P.copy(), None if self.P_pub is None else self.P_pub.copy())

    def restore(self, snap: tuple) -> None:
        """Back to a :meth:`snapshot`."""
        self.x, self.P, self.P_pub = snap[0], snap[1], snap[2]

    def widen_velocity(self, sigma_vel: float, sigma_angvel: float) -> None:
        """Add independent linear (m/s) and angular (rad/s) velocity variance to ``P`` (and ``P_pub``)."""
        for M in (self.P, self.P_pub):
            if M is not None:
                M[6:9, 6:9] += np.eye(3) * sigma_vel**2
                M[9:12, 9:12] += np.eye(3) * sigma_angvel**2

    def widen_pose(self, sigma_pos: float, sigma_rot: float) -> None:
        """Add independent position (m) and orientation (rad) variance to ``P`` (and ``P_pub``)."""
        for M in (self.P, self.P_pub):
            if M is not None:
                M[:3, :3] += np.eye(3) * sigma_pos**2
                M[3:6, 3:6] += np.eye(3) * sigma_rot**2
