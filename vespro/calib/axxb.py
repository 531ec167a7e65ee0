"""Closed-form solvers of the hand-eye equation ``A X = X B``.

OpenCV 5.0.0's Python package lacks ``cv2.calibrateHandEye`` and
``cv2.calibrateRobotWorldHandEye`` (opencv/opencv#29565; the C++ functions
exist, the bindings were added after the release by opencv/opencv#29584).
:func:`hand_eye` calls OpenCV when the binding is there and otherwise these
NumPy versions of three of its methods:

- ``tsai``: Tsai & Lenz 1989 (modified Rodrigues parameters, then translation);
- ``park``: Park & Martin 1994 (rotation from the log maps by orthogonal
  Procrustes, then translation);
- ``daniilidis``: Daniilidis 1999 (rotation and translation at once from dual
  quaternions, SVD);
- and for the robot-world form ``A_i X = Y B_i`` (camera on the link and board
  in the base frame at once, no motion pairs): Shah 2013
  (:func:`solve_robot_world_shah`).

Conventions are OpenCV's: ``gripper2base`` = ``T_base_link``, ``target2cam`` =
``T_camera_board``, result ``cam2gripper`` = ``X = T_link_camera``. With
``G_i = T_base_link_i`` and ``C_i = T_camera_board_i`` a pair of views gives
``A = inv(G_j) G_i`` and ``B = C_j inv(C_i)`` with ``A X = X B``.
"""

from __future__ import annotations

import itertools

import cv2
import numpy as np

from ..se3 import invert_transform, log_so3, quat_from_matrix, quat_multiply, skew, transform_from_rt

__all__ = ["motion_pairs", "solve_tsai", "solve_park", "solve_daniilidis", "solve_robot_world_shah", "hand_eye",
           "robot_world_hand_eye", "NUMPY_METHODS"]


def motion_pairs(T_base_link: list, T_camera_board: list) -> tuple[list, list]:
    """Relative motions ``(A, B)`` over all pairs of views, each (4, 4)."""
    As, Bs = [], []
    for i, j in itertools.combinations(range(len(T_base_link)), 2):
        As.append(invert_transform(T_base_link[j]) @ T_base_link[i])
        Bs.append(T_camera_board[j] @ invert_transform(T_camera_board[i]))
    return As, Bs


def _translation(As, Bs, R_X) -> np.ndarray:
    # (R_A - I) t_X = R_X t_B - t_A, stacked, least squares.
    M = np.concatenate([A[:3, :3] - np.eye(3) for A in As])
    v = np.concatenate([R_X @ B[:3, 3] - A[:3, 3] for A, B in zip(As, Bs)])
    return np.linalg.lstsq(M, v, rcond=None)[0]


def solve_park(As, Bs) -> np.ndarray:
    """Park & Martin: ``R_X`` maximising the alignment of rotation axes."""
    M = sum(np.outer(log_so3(B[:3, :3]), log_so3(A[:3, :3])) for A, B in zip(As, Bs))
    U, _, Vt = np.linalg.svd(M)
    # R_X = V diag(1, 1, det) U^T: the proper rotation maximising trace(R_X M).
    D = np.diag([1.0, 1.0, np.linalg.det(Vt.T @ U.T)])
    R = Vt.T @ D @ U.T
    return transform_from_rt(R, _translation(As, Bs, R))


def _mrp(R):
    """Tsai's modified Rodrigues vector ``2 sin(theta/2) axis``."""
    w = log_so3(R)
    th = np.linalg.norm(w)
    return np.zeros(3) if th < 1e-12 else 2.0 * np.sin(th / 2) * w / th


def solve_tsai(As, Bs) -> np.ndarray:
    """Tsai & Lenz."""
    M = np.concatenate([skew(_mrp(A[:3, :3]) + _mrp(B[:3, :3])) for A, B in zip(As, Bs)])
    v = np.concatenate([_mrp(B[:3, :3]) - _mrp(A[:3, :3]) for A, B in zip(As, Bs)])
    p1 = np.linalg.lstsq(M, v, rcond=None)[0]
    p = 2.0 * p1 / np.sqrt(1.0 + p1 @ p1)
    n2 = p @ p
    R = (1 - n2 / 2) * np.eye(3) + 0.5 * (np.outer(p, p) + np.sqrt(4 - n2) * skew(p))
    return transform_from_rt(R, _translation(As, Bs, R))


def _dual_quat(T):
    q = quat_from_matrix(T[:3, :3])
    qd = 0.5 * quat_multiply(np.r_[0.0, T[:3, 3]], q)
    return q, qd


def solve_daniilidis(As, Bs) -> np.ndarray:
    """Daniilidis: dual-quaternion SVD."""
    rows = []
    for A, B in zip(As, Bs):
        a, ad = _dual_quat(A)
        b, bd = _dual_quat(B)
        S = np.zeros((6, 8))
        S[:3, 0] = a[1:] - b[1:]
        S[:3, 1:4] = skew(a[1:] + b[1:])
        S[3:, 0] = ad[1:] - bd[1:]
        S[3:, 1:4] = skew(ad[1:] + bd[1:])
        S[3:, 4] = a[1:] - b[1:]
        S[3:, 5:8] = skew(a[1:] + b[1:])
        rows.append(S)
    _, _, Vt = np.linalg.svd(np.concatenate(rows))
    v7, v8 = Vt[-2], Vt[-1]
    u1, w1, u2, w2 = v7[:4], v7[4:], v8[:4], v8[4:]
    a_, b_, c_ = u1 @ w1, u1 @ w2 + u2 @ w1, u2 @ w2
    roots = np.roots([a_, b_, c_]) if abs(a_) > 1e-15 else np.array([-c_ / b_])
    best = None
    for s in np.real(roots):
        val = s * s * (u1 @ u1) + 2 * s * (u1 @ u2) + u2 @ u2
        if best is None or val > best[0]:
            best = (val, s)
    val, s = best
    l2 = 1.0 / np.sqrt(val)
    q = s * l2 * v7 + l2 * v8
    qr, qd = q[:4], q[4:]
    t = 2.0 * quat_multiply(qd, qr * [1, -1, -1, -1])[1:]
    from ..se3 import matrix_from_quat

    return transform_from_rt(matrix_from_quat(qr), t)


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def solve_robot_world_shah(T_base_link: list, T_camera_board: list) -> tuple[np.ndarray, np.ndarray]:
    """Shah 2013, robot-world/hand-eye ``A_i X = Y B_i`` at once.

    With ``A_i = T_base_link_i``, ``B_i = inv(T_camera_board_i)``,
    ``X = T_link_camera`` and ``Y = T_base_board``. Rotations: the null vector of
    the stacked Kronecker system ``(I (x) R_A) vec(R_X) - (R_B^T (x) I) vec(R_Y) = 0``,
    each block projected onto SO(3); translations: linear least squares on
    ``R_A t_X - t_Y = R_Y t_B - t_A``.

    Returns
    -------
    X, Y : ndarray (4, 4)
        ``T_link_camera`` and ``T_base_board``.
    """
    K = []
    for G, C in zip(T_base_link, T_camera_board):
        B = invert_transform(C)
        K.append(np.hstack([np.kron(np.eye(3), G[:3, :3]), -np.kron(B[:3, :3].T, np.eye(3))]))
    _, _, Vt = np.linalg.svd(np.concatenate(K))
    v = Vt[-1]
    RX = v[:9].reshape(3, 3, order="F")  # vec() stacks columns
    RY = v[9:].reshape(3, 3, order="F")
    scale = np.cbrt(np.linalg.det(RX))
    RX, RY = _nearest_rotation(RX / scale), _nearest_rotation(RY / scale)
    M, rhs = [], []
    for G, C in zip(T_base_link, T_camera_board):
        B = invert_transform(C)
        M.append(np.hstack([G[:3, :3], -np.eye(3)]))
        rhs.append(RY @ B[:3, 3] - G[:3, 3])
    t = np.linalg.lstsq(np.concatenate(M), np.concatenate(rhs), rcond=None)[0]
    return transform_from_rt(RX, t[:3]), transform_from_rt(RY, t[3:])


NUMPY_METHODS = {"tsai": solve_tsai, "park": solve_park, "daniilidis": solve_daniilidis}
_CV_FLAGS = {"tsai": cv2.CALIB_HAND_EYE_TSAI, "park": cv2.CALIB_HAND_EYE_PARK, "horaud": cv2.CALIB_HAND_EYE_HORAUD,
             "andreff": cv2.CALIB_HAND_EYE_ANDREFF, "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS}


def available_methods() -> list[str]:
    """Methods :func:`hand_eye` can run with this OpenCV."""
    return list(_CV_FLAGS) if hasattr(cv2, "calibrateHandEye") else list(NUMPY_METHODS)


def hand_eye(method: str, T_base_link: list, T_camera_board: list, use_opencv: bool | None = None) -> np.ndarray:
    """``X = T_link_camera`` by one method.

    Parameters
    ----------
    method : str
        ``tsai``, ``park``, ``daniilidis`` (and ``horaud``, ``andreff`` with OpenCV's binding).
    T_base_link, T_camera_board : list of ndarray (4, 4)
    use_opencv : bool, optional
        Default: OpenCV when ``cv2.calibrateHandEye`` exists.
    """
    if use_opencv is None:
        use_opencv = hasattr(cv2, "calibrateHandEye")
    if use_opencv:
        R, t = cv2.calibrateHandEye([T[:3, :3] for T in T_base_link], [T[:3, 3] for T in T_base_link],
                                    [T[:3, :3] for T in T_camera_board], [T[:3, 3] for T in T_camera_board],
                                    method=_CV_FLAGS[method])
        return transform_from_rt(R, np.ravel(t))
    As, Bs = motion_pairs(T_base_link, T_camera_board)
    return NUMPY_METHODS[method](As, Bs)


def robot_world_hand_eye(T_base_link: list, T_camera_board: list, use_opencv: bool | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """``(X, Y) = (T_link_camera, T_base_board)`` by Shah's method: OpenCV's
    ``calibrateRobotWorldHandEye`` when bound, else :func:`solve_robot_world_shah`."""
    if use_opencv is None:
        use_opencv = hasattr(cv2, "calibrateRobotWorldHandEye")
    if not use_opencv:
        return solve_robot_world_shah(T_base_link, T_camera_board)
    # OpenCV: world = board, cam = camera, base2gripper = T_link_base.
    R_b2w, t_b2w, R_g2c, t_g2c = cv2.calibrateRobotWorldHandEye(
        [T[:3, :3] for T in T_camera_board], [T[:3, 3] for T in T_camera_board],
        [invert_transform(T)[:3, :3] for T in T_base_link], [invert_transform(T)[:3, 3] for T in T_base_link],
        method=cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH)
    X = invert_transform(transform_from_rt(R_g2c, np.ravel(t_g2c)))
    Y = invert_transform(transform_from_rt(R_b2w, np.ravel(t_b2w)))
    return X, Y
