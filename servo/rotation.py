"""Small quaternion and rotation helpers for the servo (no ``vespro`` import).

Conventions (shared/STYLE.md): quaternions are scalar first ``(w, x, y, z)``,
Hamilton product, unit norm; rotation vectors are axis * angle (rad).

The in-place helpers (``*_into``) write into caller buffers and call MuJoCo's
``mju_*`` C routines, so the 500 Hz path allocates no arrays for them. The
allocating helpers are for set-up code and tests.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

__all__ = [
    "quat_multiply_into",
    "quat_conjugate_into",
    "quat_from_matrix_into",
    "matrix_from_quat_into",
    "rotvec_from_quat_into",
    "quat_from_rotvec_into",
    "quat_canonical_into",
    "quat_multiply",
    "quat_conjugate",
    "quat_from_matrix",
    "matrix_from_quat",
    "rotvec_from_quat",
    "quat_from_rotvec",
    "rotvec_error",
]


def quat_multiply_into(q_a: np.ndarray, q_b: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Hamilton product ``q_a * q_b`` into ``out`` (4,). ``out`` may alias an input."""
    mujoco.mju_mulQuat(out, q_a, q_b)
    return out


def quat_conjugate_into(q: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Conjugate (inverse of a unit quaternion) into ``out`` (4,)."""
    mujoco.mju_negQuat(out, q)
    return out


def quat_from_matrix_into(R: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix (3, 3) into ``out`` (4,), w >= 0."""
    mujoco.mju_mat2Quat(out, R.reshape(9))
    if out[0] < 0.0:
        np.negative(out, out=out)
    return out


def matrix_from_quat_into(q: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion into ``out`` (3, 3), C-contiguous."""
    mujoco.mju_quat2Mat(out.reshape(9), q)
    return out


def rotvec_from_quat_into(q: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Rotation vector (3,), rad, of a unit quaternion, angle wrapped to [0, pi].

    The shorter way round: ``q`` and ``-q`` give the same vector.
    """
    w, x, y, z = q[0], q[1], q[2], q[3]
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-12:
        # Small angle: log(q) ~ 2 * vec(q) (second-order exact).
        out[0] = 2.0 * x
        out[1] = 2.0 * y
        out[2] = 2.0 * z
        return out
    k = 2.0 * math.atan2(s, w) / s
    out[0] = k * x
    out[1] = k * y
    out[2] = k * z
    return out


def quat_from_rotvec_into(r: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Unit quaternion of a rotation vector (3,), rad, into ``out`` (4,)."""
    x, y, z = r[0], r[1], r[2]
    angle = math.sqrt(x * x + y * y + z * z)
    half = 0.5 * angle
    if angle < 1e-9:
        # sin(a/2)/a ~ 1/2 - a^2/48
        k = 0.5 - angle * angle / 48.0
    else:
        k = math.sin(half) / angle
    out[0] = math.cos(half)
    out[1] = k * x
    out[2] = k * y
    out[3] = k * z
    return out


def quat_canonical_into(q: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Normalise and flip to w >= 0 (the form to compare or send)."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    s = (1.0 / n) if q[0] >= 0.0 else (-1.0 / n)
    np.multiply(q, s, out=out)
    return out


# --- allocating conveniences (set-up code and tests) -------------------------


def quat_multiply(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Hamilton product, (4,) x (4,) -> (4,)."""
    return quat_multiply_into(np.asarray(q_a, float), np.asarray(q_b, float), np.empty(4))


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate, (4,) -> (4,)."""
    q = np.asarray(q, float)
    return np.array([q[0], -q[1], -q[2], -q[3]])


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) unit quaternion, w >= 0."""
    return quat_from_matrix_into(np.ascontiguousarray(R, dtype=float), np.empty(4))


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion -> (3, 3) rotation matrix."""
    q = np.asarray(q, float)
    return matrix_from_quat_into(q / np.linalg.norm(q), np.empty((3, 3)))


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion -> (3,) rotation vector, rad."""
    return rotvec_from_quat_into(np.asarray(q, float), np.empty(3))


def quat_from_rotvec(r: np.ndarray) -> np.ndarray:
    """(3,) rotation vector, rad -> (4,) unit quaternion."""
    return quat_from_rotvec_into(np.asarray(r, float), np.empty(4))


def rotvec_error(q_desired: np.ndarray, q_actual: np.ndarray) -> np.ndarray:
    """World-frame orientation error ``log(q_desired * q_actual^-1)``, (3,), rad."""
    return rotvec_from_quat(quat_multiply(q_desired, quat_conjugate(q_actual)))
