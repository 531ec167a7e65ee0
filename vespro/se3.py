"""Rigid transforms, rotations and quaternions.

Conventions (shared/STYLE.md):

- ``T_a_b`` is a (4, 4) float64 array, the pose of frame b in frame a:
  ``p_a = T_a_b @ p_b``.
- Quaternions are scalar first ``(w, x, y, z)``, Hamilton product, unit norm.
  SciPy's ``Rotation`` is scalar last: conversions happen here and are named
  ``q_xyzw`` where they occur.
- A pose on disk or on the wire is 7 numbers ``x y z qw qx qy qz`` ("pq").
- Rotation vectors (axis * angle, rad) parametrise small rotations; ``exp_so3``
  and ``log_so3`` map between them and rotation matrices.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from .jit import njit

__all__ = [
    "check_transform",
    "transform_from_pq",
    "pq_from_transform",
    "transform_from_rt",
    "invert_transform",
    "matrix_from_quat",
    "quat_from_matrix",
    "quat_multiply",
    "quat_conjugate",
    "quat_normalize",
    "quat_canonical",
    "quat_from_rotvec",
    "rotvec_from_quat",
    "skew",
    "exp_so3",
    "log_so3",
    "rotation_angle",
    "transform_points",
    "pose_error",
]


def check_transform(T: np.ndarray, name: str = "T", atol: float = 1e-6) -> np.ndarray:
    """Validate a homogeneous transform at a module boundary.

    Parameters
    ----------
    T : array_like, shape (4, 4)
    name : str
        Used in the error message.
    atol : float
        Tolerance on orthonormality of the rotation block and on the last row.

    Returns
    -------
    T : ndarray, shape (4, 4), float64

    Raises
    ------
    ValueError
        Wrong shape, non-finite values, a rotation block that is not a proper
        rotation, or a last row that is not ``[0, 0, 0, 1]``.
    """
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"{name}: expected shape (4, 4), got {T.shape}")
    if not np.isfinite(T).all():
        raise ValueError(f"{name}: contains non-finite values")
    R = T[:3, :3]
    # np.allclose(a, b, atol) spelled out (|a - b| <= atol + 1e-5 |b|): it is on every frame's path
    E = R @ R.T
    E -= _EYE3
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    det = r00 * (r11 * r22 - r12 * r21) - r01 * (r10 * r22 - r12 * r20) + r02 * (r10 * r21 - r11 * r20)
    if not (np.abs(E) <= atol + _RTOL_EYE3).all() or det < 0:
        raise ValueError(f"{name}: rotation block is not a proper rotation matrix")
    if not (np.abs(T[3] - _LAST_ROW) <= atol + _RTOL_LAST_ROW).all():
        raise ValueError(f"{name}: last row must be [0, 0, 0, 1], got {T[3]}")
    return T


_EYE3 = np.eye(3)
_RTOL_EYE3 = 1e-5 * _EYE3
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_RTOL_LAST_ROW = 1e-5 * _LAST_ROW


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion(s), shape (..., 4); raises on a zero or non-finite input."""
    q = np.asarray(q, dtype=float)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(q)) or np.any(n < 1e-12):
        raise ValueError(f"quaternion cannot be normalised: {q}")
    return q / n


def quat_canonical(q: np.ndarray) -> np.ndarray:
    """Flip sign so that ``w >= 0`` (the same rotation), shape (..., 4)."""
    q = np.asarray(q, dtype=float)
    sign = np.where(q[..., :1] < 0.0, -1.0, 1.0)
    return q * sign


def rotation_rows(w: float, x: float, y: float, z: float) -> list:
    """Rows of the rotation matrix of the quaternion ``(w, x, y, z)`` (normalised here), as
    Python floats: the formula of :func:`matrix_from_quat` for callers that add to it
    (the filter's pose, every frame) without NumPy's per-call overhead."""
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return [
        [x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
        [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
        [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2],
    ]


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix from a unit quaternion.

    Parameters
    ----------
    q : array_like, shape (4,) or (N, 4)
        ``(w, x, y, z)``; normalised here.

    Returns
    -------
    R : ndarray, shape (3, 3) or (N, 3, 3)
    """
    q = quat_normalize(q)
    if q.shape == (4,):
        # One quaternion (every filter step): SciPy's arithmetic, written out (it
        # normalises again, then the usual products), equal to it bit for bit and
        # without its ~40 us of per-call overhead.
        return np.array(rotation_rows(*q.tolist()))
    q_xyzw = np.roll(q, -1, axis=-1)
    return Rotation.from_quat(q_xyzw).as_matrix()


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` from rotation matrix/matrices."""
    q_xyzw = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    return quat_canonical(np.roll(q_xyzw, 1, axis=-1))


def quat_multiply(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Hamilton product ``q1 * q2`` (rotation q2 first, then q1), shape (..., 4)."""
    w1, x1, y1, z1 = np.moveaxis(np.asarray(q1, dtype=float), -1, 0)
    w2, x2, y2, z2 = np.moveaxis(np.asarray(q2, dtype=float), -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse for a unit quaternion), shape (..., 4)."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_from_rotvec(v: np.ndarray) -> np.ndarray:
    """Unit quaternion from rotation vector(s) (rad), shape (..., 3) -> (..., 4)."""
    q_xyzw = Rotation.from_rotvec(np.asarray(v, dtype=float)).as_quat()
    return np.roll(q_xyzw, 1, axis=-1)


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation vector (rad, angle in [0, pi]) from unit quaternion(s)."""
    q = quat_normalize(q)
    return Rotation.from_quat(np.roll(q, -1, axis=-1)).as_rotvec()


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix: ``skew(a) @ b == np.cross(a, b)``; shape (3,) -> (3, 3)."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def exp_so3(v: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``v`` (rad), shape (3,) -> (3, 3)."""
    return Rotation.from_rotvec(np.asarray(v, dtype=float)).as_matrix()


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad, angle in [0, pi]) of a rotation matrix, shape (3, 3) -> (3,).

    SciPy's ``Rotation.from_matrix(R).as_rotvec()`` to rounding for a rotation matrix
    (orthonormal to rounding: Markley's quaternion from the largest of the trace and the
    diagonal, then the vector), compiled: the tracker takes a few a frame, and SciPy's
    per-call overhead was 0.15 ms each.
    """
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        raise ValueError(f"log_so3 needs one 3x3 matrix, got shape {R.shape}")
    return _log_so3(np.ascontiguousarray(R))


@njit
def _log_so3(R):
    # Markley's method: the quaternion from the largest of the trace and the diagonal.
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    q = np.empty(4)  # x, y, z, w
    choice, best = 3, tr
    for i in range(3):
        if R[i, i] > best:
            choice, best = i, R[i, i]
    if choice == 3:
        q[0] = R[2, 1] - R[1, 2]
        q[1] = R[0, 2] - R[2, 0]
        q[2] = R[1, 0] - R[0, 1]
        q[3] = 1.0 + tr
    else:
        i = choice
        j = (i + 1) % 3
        k = (j + 1) % 3
        q[i] = 1.0 - tr + 2.0 * R[i, i]
        q[j] = R[j, i] + R[i, j]
        q[k] = R[k, i] + R[i, k]
        q[3] = R[k, j] - R[j, k]
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[3] < 0.0:
        n = -n  # w >= 0: the angle in [0, pi]
    x, y, z, w = q[0] / n, q[1] / n, q[2] / n, q[3] / n
    angle = 2.0 * np.arctan2(np.sqrt(x * x + y * y + z * z), w)
    if angle <= 1e-3:
        scale = 2.0 + angle * angle / 12.0 + 7.0 * angle ** 4 / 2880.0
    else:
        scale = angle / np.sin(angle / 2.0)
    out = np.empty(3)
    out[0], out[1], out[2] = scale * x, scale * y, scale * z
    return out


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Geodesic angle (rad, in [0, pi]) of rotation matrix/matrices."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R, axis1=-2, axis2=-1)
    # arccos is ill-conditioned near 0: use the antisymmetric part as well.
    s = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    return np.arctan2(0.5 * np.linalg.norm(s, axis=-1), 0.5 * (tr - 1.0))


def transform_from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 transform from rotation (3, 3) and translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def transform_from_pq(pq: np.ndarray) -> np.ndarray:
    """4x4 transform from ``[x, y, z, qw, qx, qy, qz]``.

    Raises
    ------
    ValueError
        Not 7 finite numbers, or a zero quaternion.
    """
    pq = np.asarray(pq, dtype=float)
    if pq.shape != (7,):
        raise ValueError(f"pose must be 7 numbers x y z qw qx qy qz, got shape {pq.shape}")
    if not np.all(np.isfinite(pq)):
        raise ValueError(f"pose contains non-finite values: {pq}")
    return transform_from_rt(matrix_from_quat(pq[3:]), pq[:3])


def pq_from_transform(T: np.ndarray) -> np.ndarray:
    """``[x, y, z, qw, qx, qy, qz]`` (``qw >= 0``) from a 4x4 transform."""
    T = np.asarray(T, dtype=float)
    return np.concatenate([T[:3, 3], quat_from_matrix(T[:3, :3])])


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform: ``invert_transform(T_a_b) == T_b_a``."""
    R = T[:3, :3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def transform_points(T_a_b: np.ndarray, P_b: np.ndarray) -> np.ndarray:
    """Map points from frame b to frame a: (N, 3) -> (N, 3)."""
    P_b = np.asarray(P_b, dtype=float)
    return P_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Position error (m) and geodesic orientation error (rad) between two poses."""
    dp = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    da = float(rotation_angle(T_est[:3, :3].T @ T_true[:3, :3]))
    return dp, da
