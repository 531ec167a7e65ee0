"""Pose accuracy metrics against ground truth: pure functions, arrays in and out.

Error convention (shared with the EKF and ``poses.csv``): position error
``p_true - p_est`` (world, m) and orientation error ``log(R_true @ R_est.T)``
(world-frame rotation vector, rad).

ADD / ADD-S follow Hinterstoisser et al. (2012); MSSD / MSPD follow the BOP
challenge (Hodan et al., 2020).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import chi2

from .camera import CameraIntrinsics, project_points
from .jit import njit
from .numerics import dot3, pairwise_sum
from .se3 import invert_transform, log_so3, rotation_angle, transform_points

__all__ = [
    "pose_error_vector", "position_errors", "rotation_errors", "add", "add_numpy", "add_s", "mssd", "mspd",
    "nees", "nees_band", "rmse", "recall", "axis_rotations", "discrete_symmetries", "mssd_thresholds",
    "mspd_thresholds", "reacquisition_times",
]


def pose_error_vector(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """6-vector ``[p_true - p_est, log(R_true R_est^T)]`` (m, rad)."""
    return np.concatenate([T_true[:3, 3] - T_est[:3, 3], log_so3(T_true[:3, :3] @ T_est[:3, :3].T)])


def position_errors(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """Euclidean position errors (m), shapes (N, 4, 4) -> (N,)."""
    return np.linalg.norm(T_est[:, :3, 3] - T_true[:, :3, 3], axis=1)


def rotation_errors(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """Geodesic orientation errors (rad), shapes (N, 4, 4) -> (N,)."""
    R = np.einsum("nji,njk->nik", T_est[:, :3, :3], T_true[:, :3, :3])
    return rotation_angle(R)


def add(T_est: np.ndarray, T_true: np.ndarray, P_object: np.ndarray) -> float:
    """Average distance of model points (m): mean ||T_est p - T_true p||.

    Compiled for two or more float64 points (:func:`_add_kernel`; the tracker asks twice a
    frame), else :func:`add_numpy`: the same value to the bit."""
    P = np.asarray(P_object)
    if P.dtype != np.float64 or P.ndim != 2 or P.shape[0] < 2 or P.shape[1] != 3:  # (one point: gemv)
        return add_numpy(T_est, T_true, P_object)
    return float(_add_kernel(np.ascontiguousarray(T_est, dtype=float), np.ascontiguousarray(T_true, dtype=float),
                             np.ascontiguousarray(P)))


def add_numpy(T_est: np.ndarray, T_true: np.ndarray, P_object: np.ndarray) -> float:
    """:func:`add` in NumPy."""
    return float(np.mean(np.linalg.norm(transform_points(T_est, P_object) - transform_points(T_true, P_object), axis=1)))


@njit
def _add_kernel(Ta, Tb, P):
    """:func:`add_numpy`'s arithmetic: the points moved as OpenBLAS multiplies them
    (:func:`vespro.numerics.dot3`), each distance the square root of its three squares summed
    in order (NumPy's ``norm`` along a row), their mean by NumPy's pairwise sum."""
    N = P.shape[0]
    d = np.empty(N)
    for i in range(N):
        s = 0.0
        for j in range(3):
            e = (dot3(P[i, 0], P[i, 1], P[i, 2], Ta[j, 0], Ta[j, 1], Ta[j, 2]) + Ta[j, 3]) - \
                (dot3(P[i, 0], P[i, 1], P[i, 2], Tb[j, 0], Tb[j, 1], Tb[j, 2]) + Tb[j, 3])
            s = e * e if j == 0 else s + e * e
        d[i] = np.sqrt(s)
    return pairwise_sum(d, N) / N


def add_sym(T_est: np.ndarray, T_true: np.ndarray, P_object: np.ndarray, symmetries) -> float:
    """ADD to the nearest of the true pose's symmetric equivalents ``T_true @ S`` (m).

    Not ADD-S (nearest point): a part that is nearly symmetric (an L-block turned
    over) lies close to itself point for point, so a distinct pose of it would
    pass for the same one.
    """
    A = P_object @ T_est[:3, :3].T + T_est[:3, 3]
    return float(min(np.mean(np.linalg.norm(A - (P_object @ (T_true @ S)[:3, :3].T + (T_true @ S)[:3, 3]), axis=1))
                     for S in symmetries))


def add_s(T_est: np.ndarray, T_true: np.ndarray, P_object: np.ndarray) -> float:
    """ADD for symmetric objects (m): mean distance to the closest true-pose point."""
    tree = cKDTree(transform_points(T_true, P_object))
    d, _ = tree.query(transform_points(T_est, P_object))
    return float(np.mean(d))


def mssd(T_est: np.ndarray, T_true: np.ndarray, P_object: np.ndarray, symmetries=None) -> float:
    """Maximum symmetry-aware surface distance (m).

    ``symmetries``: list of (4, 4) object-frame transforms S with the object
    looking the same under ``T_true @ S``; identity alone when None.
    """
    syms = [np.eye(4)] if symmetries is None else list(symmetries)
    Pe = transform_points(T_est, P_object)
    return float(min(np.max(np.linalg.norm(Pe - transform_points(T_true @ S, P_object), axis=1)) for S in syms))


def mspd(T_est_cam: np.ndarray, T_true_cam: np.ndarray, P_object: np.ndarray, intr: CameraIntrinsics,
         symmetries=None) -> float:
    """Maximum symmetry-aware projection distance (px), poses in the camera frame."""
    syms = [np.eye(4)] if symmetries is None else list(symmetries)
    ue, _ = project_points(intr, T_est_cam, P_object)
    return float(min(np.max(np.linalg.norm(ue - project_points(intr, T_true_cam @ S, P_object)[0], axis=1))
                     for S in syms))


def nees(T_est: np.ndarray, T_true: np.ndarray, P6: np.ndarray) -> float:
    """Normalised estimation error squared of one pose with its 6x6 covariance."""
    e = pose_error_vector(T_est, T_true)
    return float(e @ np.linalg.solve(P6, e))


def nees_band(dof: int = 6, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided chi-square band a consistent filter's NEES falls in with ``probability``."""
    a = (1.0 - probability) / 2
    return float(chi2.ppf(a, dof)), float(chi2.ppf(1 - a, dof))


def rmse(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def recall(errors: np.ndarray, thresholds) -> float:
    """BOP-style average recall: fraction of errors below each threshold, averaged."""
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        return 0.0
    return float(np.mean([np.mean(e < th) for th in thresholds]))


def camera_pose(T_world_camera: np.ndarray, T_world_object: np.ndarray) -> np.ndarray:
    """``T_camera_object``."""
    return invert_transform(T_world_camera) @ T_world_object


def axis_rotations() -> np.ndarray:
    """The 24 proper rotations that map the coordinate axes onto themselves (signed permutations, det +1).

    Returns
    -------
    ndarray, shape (24, 3, 3)
    """
    import itertools

    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    return np.array(out)


def discrete_symmetries(P_object: np.ndarray, atol: float = 1e-6) -> list[np.ndarray]:
    """Discrete symmetries of a point set among the 24 axis-aligned rotations about its bounding-box centre.

    A rotation ``R`` about the centre ``c`` is a symmetry when it maps every
    vertex onto some vertex (within ``atol``, m). For a polyhedral CAD model the
    vertex set is the shape's corner set, so this finds the symmetries BOP lists
    as ``symmetries_discrete`` for axis-aligned parts (a box with three distinct
    edge lengths: the identity and the three half turns). Symmetries about other
    axes are not searched.

    Parameters
    ----------
    P_object : ndarray, shape (N, 3)
        Model vertices, object frame, m.
    atol : float
        Matching tolerance, m.

    Returns
    -------
    list of ndarray (4, 4)
        Object-frame transforms ``S = [R, c - R c]`` with the identity first;
        the object looks the same at ``T @ S`` as at ``T``.
    """
    P = np.asarray(P_object, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"P_object must have shape (N, 3), got {P.shape}")
    c = 0.5 * (P.min(axis=0) + P.max(axis=0))
    tree = cKDTree(P)
    out = []
    for R in axis_rotations():
        S = np.eye(4)
        S[:3, :3] = R
        S[:3, 3] = c - R @ c
        d, _ = tree.query(transform_points(S, P))
        if np.all(d <= atol):
            out.append(S)
    out.sort(key=lambda S: 0 if np.allclose(S, np.eye(4)) else 1)
    return out


def mssd_thresholds(diameter: float) -> np.ndarray:
    """BOP MSSD correctness thresholds: 0.05 .. 0.5 of the object diameter, step 0.05 (m)."""
    return np.arange(1, 11) * 0.05 * diameter


def mspd_thresholds(image_width: int) -> np.ndarray:
    """BOP MSPD correctness thresholds: 5 .. 50 px step 5, times ``r = width / 640`` (px)."""
    return np.arange(1, 11) * 5.0 * image_width / 640.0


def reacquisition_times(tracking: np.ndarray, t: np.ndarray) -> list[float | None]:
    """Time from each loss of track to the next tracked frame (s).

    Parameters
    ----------
    tracking : ndarray, shape (N,), bool
        Tracked per frame.
    t : ndarray, shape (N,)
        Capture times, s.

    Returns
    -------
    list
        One entry per loss (a tracked frame followed by an untracked one): the
        time from the first untracked frame's capture to the next tracked
        frame's capture, or None when the track never came back.
    """
    tr = np.asarray(tracking, dtype=bool)
    out = []
    for i in range(1, len(tr)):
        if tr[i - 1] and not tr[i]:
            nxt = np.flatnonzero(tr[i:])
            out.append(float(t[i + nxt[0]] - t[i]) if nxt.size else None)
    return out
