"""Projection of object points with analytic Jacobians w.r.t. the object pose error.

Pose error convention (used by :mod:`vespro.ekf` and :mod:`vespro.selection`)
----------------------------------------------------------------------------
The 6-D pose error ``delta = [dp, dtheta]`` perturbs ``T_world_object = (R, p)``
as::

    R <- Exp(dtheta) @ R        # rotation vector applied on the LEFT, world frame
    p <- p + dp                 # translation in the world frame

so a model point moves to ``P_world + dp + dtheta x (P_world - p)`` to first order.
``dp`` and ``dtheta`` are both expressed in the world frame, not in the object
frame, and ``dtheta`` rotates about the world axes through the object origin
``p`` (not about the world origin).

Pixels follow :mod:`vespro.camera`: OpenCV optical frame, plumb_bob distortion,
``(0, 0)`` at the centre of the top-left pixel.
"""

from __future__ import annotations

import numpy as np

from .camera import CameraIntrinsics
from .jit import njit
from .se3 import exp_so3, transform_from_rt

__all__ = ["project_with_jacobian", "apply_pose_error", "refine_pose_gauss_newton"]

#: Points closer than this to the camera plane (m) are treated as behind it.
MIN_DEPTH = 1e-6


def _check_T(T, name):
    # A copy: the kernel then always sees a writeable array (a fixed camera's pose is
    # read-only, an arm camera's is not), one compiled signature for both.
    T = np.array(T, dtype=float, order="C")
    if T.shape != (4, 4):
        raise ValueError(f"{name}: expected shape (4, 4), got {T.shape}")
    return T


def project_with_jacobian(
    intr: CameraIntrinsics,
    T_world_camera: np.ndarray,
    T_world_object: np.ndarray,
    P_object: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project object points into a camera, with d(uv)/d(pose error).

    Parameters
    ----------
    intr : CameraIntrinsics
        Camera matrix and plumb_bob distortion.
    T_world_camera : ndarray, shape (4, 4)
        Camera pose in the world (OpenCV optical camera frame).
    T_world_object : ndarray, shape (4, 4)
        Object pose in the world, the linearisation point.
    P_object : ndarray, shape (N, 3)
        Model points in the object frame, m.

    Returns
    -------
    uv : ndarray, shape (N, 2)
        Distorted pixel coordinates. NaN where the point is behind the camera
        (``depth <= MIN_DEPTH``).
    depth : ndarray, shape (N,)
        Z in the camera frame, m (always finite for finite inputs).
    J : ndarray, shape (N, 2, 6)
        ``d uv / d [dp, dtheta]`` with the module's error convention (world
        frame, rotation on the left). Columns: ``dp_x, dp_y, dp_z, dth_x,
        dth_y, dth_z``; units px/m and px/rad. NaN where ``uv`` is NaN.

    Notes
    -----
    Chain rule, all vectorised over points::

        P_c = R_cw (P_w - t_wc)                      d P_c / d delta = R_cw [I, -[P_w - p]x]
        x = X/Z, y = Y/Z                             d x / d P_c = [[1/Z, 0, -X/Z^2], [0, 1/Z, -Y/Z^2]]
        (xd, yd) = plumb_bob(x, y)                   2x2 Jacobian below
        u = fx xd + cx, v = fy yd + cy
    """
    T_world_camera = _check_T(T_world_camera, "T_world_camera")
    T_world_object = _check_T(T_world_object, "T_world_object")
    P_object = np.asarray(P_object, dtype=float)
    if P_object.ndim != 2 or P_object.shape[1] != 3:
        raise ValueError(f"P_object: expected shape (N, 3), got {P_object.shape}")

    return _project_kernel(np.ascontiguousarray(T_world_camera), np.ascontiguousarray(T_world_object),
                           np.ascontiguousarray(P_object), intr.fx, intr.fy, intr.cx, intr.cy,
                           np.ascontiguousarray(intr.dist, dtype=float), intr.has_distortion)


@njit
def _project_kernel(T_wc, T_wo, P, fx, fy, cx, cy, dist, has_dist):
    """Compiled body of :func:`project_with_jacobian`, one point at a time (the chain
    rule of its Notes). Returns ``uv`` (N, 2), ``Z`` (N,), ``J`` (N, 2, 6)."""
    n = P.shape[0]
    uv = np.empty((n, 2))
    Z = np.empty(n)
    J = np.empty((n, 2, 6))
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    dpx, dpy, dpz = T_wo[0, 3] - T_wc[0, 3], T_wo[1, 3] - T_wc[1, 3], T_wo[2, 3] - T_wc[2, 3]
    for i in range(n):
        # lever arm r = R_wo P (world) and the point in the camera, P_c = R_cw (r + p_wo - t_wc)
        r0 = T_wo[0, 0] * P[i, 0] + T_wo[0, 1] * P[i, 1] + T_wo[0, 2] * P[i, 2]
        r1 = T_wo[1, 0] * P[i, 0] + T_wo[1, 1] * P[i, 1] + T_wo[1, 2] * P[i, 2]
        r2 = T_wo[2, 0] * P[i, 0] + T_wo[2, 1] * P[i, 1] + T_wo[2, 2] * P[i, 2]
        w0, w1, w2 = r0 + dpx, r1 + dpy, r2 + dpz
        X = T_wc[0, 0] * w0 + T_wc[1, 0] * w1 + T_wc[2, 0] * w2
        Y = T_wc[0, 1] * w0 + T_wc[1, 1] * w1 + T_wc[2, 1] * w2
        Zc = T_wc[0, 2] * w0 + T_wc[1, 2] * w1 + T_wc[2, 2] * w2
        Z[i] = Zc
        iz = np.nan if Zc <= MIN_DEPTH else 1.0 / Zc
        x = X * iz
        y = Y * iz
        # D = d(u, v) / d(x, y): the distortion Jacobian scaled by the focal lengths
        if has_dist:
            rr = x * x + y * y
            radial = 1.0 + rr * (k1 + rr * (k2 + rr * k3))
            drad = k1 + rr * (2.0 * k2 + 3.0 * rr * k3)
            xd = x * radial + 2.0 * p1 * x * y + p2 * (rr + 2.0 * x * x)
            yd = y * radial + p1 * (rr + 2.0 * y * y) + 2.0 * p2 * x * y
            cross_term = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
            D00 = fx * (radial + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x)
            D01 = fx * cross_term
            D10 = fy * cross_term
            D11 = fy * (radial + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x)
        else:
            xd, yd = x, y
            D00, D01, D10, D11 = fx, 0.0, 0.0, fy
        uv[i, 0] = fx * xd + cx
        uv[i, 1] = fy * yd + cy
        # A = D d(x, y)/d P_c, B = A R_cw (position block), rotation block rows r x b
        A00, A01, A02 = D00 * iz, D01 * iz, -(D00 * x + D01 * y) * iz
        A10, A11, A12 = D10 * iz, D11 * iz, -(D10 * x + D11 * y) * iz
        for row in range(2):
            a0, a1, a2 = (A00, A01, A02) if row == 0 else (A10, A11, A12)
            b0 = a0 * T_wc[0, 0] + a1 * T_wc[0, 1] + a2 * T_wc[0, 2]
            b1 = a0 * T_wc[1, 0] + a1 * T_wc[1, 1] + a2 * T_wc[1, 2]
            b2 = a0 * T_wc[2, 0] + a1 * T_wc[2, 1] + a2 * T_wc[2, 2]
            J[i, row, 0], J[i, row, 1], J[i, row, 2] = b0, b1, b2
            J[i, row, 3] = r1 * b2 - r2 * b1
            J[i, row, 4] = r2 * b0 - r0 * b2
            J[i, row, 5] = r0 * b1 - r1 * b0
    return uv, Z, J


def apply_pose_error(T_world_object: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Perturb a pose by a 6-D error ``[dp, dtheta]`` (the module's convention).

    Parameters
    ----------
    T_world_object : ndarray, shape (4, 4)
    delta : ndarray, shape (6,)
        ``dp`` (m, world) then ``dtheta`` (rad, world, left).

    Returns
    -------
    ndarray, shape (4, 4)
        ``(Exp(dtheta) R, p + dp)``.
    """
    delta = np.asarray(delta, dtype=float)
    if delta.shape != (6,):
        raise ValueError(f"delta: expected shape (6,), got {delta.shape}")
    return transform_from_rt(exp_so3(delta[3:]) @ T_world_object[:3, :3], T_world_object[:3, 3] + delta[:3])


def refine_pose_gauss_newton(
    cameras,
    uv_observed,
    P_object,
    T_world_object_init: np.ndarray,
    iterations: int = 10,
    tol: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray]:
    """Multi-camera least-squares pose (Gauss-Newton on the reprojection error).

    This is the per-frame baseline the filter is measured against and a
    (re)initialisation tool. It needs a starting pose inside the basin of
    convergence (e.g. the last estimate or a ``cv2.solvePnP`` result).

    Parameters
    ----------
    cameras : sequence of (CameraIntrinsics, T_world_camera (4, 4))
    uv_observed : sequence of ndarray (N_c, 2)
        Observed pixels per camera; rows with non-finite values are ignored.
    P_object : sequence of ndarray (N_c, 3)
        Model points per camera, object frame, m.
    T_world_object_init : ndarray, shape (4, 4)
    iterations : int
    tol : float
        Stop when the step norm falls below this.

    Returns
    -------
    T_world_object : ndarray, shape (4, 4)
    JtJ : ndarray, shape (6, 6)
        Gauss-Newton information at the solution, px^-2 units (multiply by
        ``1/sigma_px^2`` for the pose information).
    """
    T = np.array(T_world_object_init, dtype=float)
    JtJ = np.zeros((6, 6))
    for _ in range(iterations):
        JtJ = np.zeros((6, 6))
        Jtr = np.zeros(6)
        for (intr, T_wc), z, P in zip(cameras, uv_observed, P_object):
            uv, depth, J = project_with_jacobian(intr, T_wc, T, P)
            r = np.asarray(z, dtype=float) - uv
            ok = np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(J), axis=(1, 2))
            Jf = J[ok].reshape(-1, 6)
            JtJ += Jf.T @ Jf
            Jtr += Jf.T @ r[ok].reshape(-1)
        try:
            step = np.linalg.solve(JtJ, Jtr)
        except np.linalg.LinAlgError:
            break
        T = apply_pose_error(T, step)
        if np.linalg.norm(step) < tol:
            break
    return T, JtJ

