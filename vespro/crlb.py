"""Cramér-Rao lower bounds on the object pose from corner projections.

Pure functions: Jacobians in, information and bounds out.

The measurement model is the tracker's: every measured corner ``i`` gives a
pixel ``uv_i = h_i(T_world_object) + n_i`` with ``n_i ~ N(0, sigma^2 I_2)``,
independent between corners and cameras. With the pose error convention of
:mod:`vespro.projection` (``delta = [dp, dtheta]``, world frame, rotation on
the left: the same as :func:`vespro.metrics.pose_error_vector`) and
``J_i = d uv_i / d delta`` (2, 6), the Fisher information of one frame is::

    I = sum_i J_i^T J_i / sigma^2          (6, 6), over all cameras

and any unbiased estimator of the pose from that frame alone has error
covariance ``>= CRLB = I^-1``.

Two bounds are provided:

* the **per-frame (static, no-prior) bound** :func:`frame_crlb`: what a
  single-frame estimator (PnP, or least squares over all cameras) can reach at
  best. A filter with a motion model uses earlier frames too, so its error can
  lie *below* this bound: a ratio RMSE / CRLB < 1 is not a contradiction.
* the **posterior (filtered) bound** :func:`posterior_crlb`: the recursion of
  Tichavsky, Muravchik and Nehorai (1998) for the constant-velocity model of
  :mod:`vespro.ekf` (its transition Jacobian and process noise, evaluated at
  the true state), started from the tracker's initial covariance. It bounds
  a filter that knows the motion model, so RMSE / posterior bound >= 1 is
  expected up to the approximations (linearisation at the truth, model
  mismatch of the scripted motion).
"""

from __future__ import annotations

import numpy as np

from .projection import project_with_jacobian

__all__ = ["fisher_information", "frame_information", "crlb_from_information", "crlb_std",
           "frame_crlb", "posterior_crlb"]


def fisher_information(J: np.ndarray, sigma_px: float) -> np.ndarray:
    """Fisher information of pixel measurements with isotropic noise.

    Parameters
    ----------
    J : ndarray, shape (N, 2, 6)
        ``d uv / d [dp, dtheta]`` of each measured point (px/m, px/rad).
    sigma_px : float
        Std of each pixel coordinate's noise, px.

    Returns
    -------
    ndarray, shape (6, 6)
        ``sum_i J_i^T J_i / sigma^2`` in (m, rad)^-2 units.
    """
    J = np.asarray(J, dtype=float)
    if J.ndim != 3 or J.shape[1:] != (2, 6):
        raise ValueError(f"J must have shape (N, 2, 6), got {J.shape}")
    if not sigma_px > 0:
        raise ValueError(f"sigma_px must be positive, got {sigma_px}")
    J = J[np.all(np.isfinite(J), axis=(1, 2))]
    return np.einsum("nki,nkj->ij", J, J) / sigma_px**2


def frame_information(views, T_world_object: np.ndarray, sigma_px: float) -> np.ndarray:
    """Information of one frame's measured corners over all cameras.

    Parameters
    ----------
    views : iterable of (CameraIntrinsics, T_world_camera (4, 4), P_object (K, 3))
        Per camera: its intrinsics, pose in the world and the object-frame
        points measured in it.
    T_world_object : ndarray, shape (4, 4)
        Pose the Jacobians are evaluated at (the true pose for a bound).
    sigma_px : float

    Returns
    -------
    ndarray, shape (6, 6)
    """
    info = np.zeros((6, 6))
    for intr, T_wc, P in views:
        P = np.asarray(P, dtype=float).reshape(-1, 3)
        if len(P) == 0:
            continue
        _, _, J = project_with_jacobian(intr, T_wc, T_world_object, P)
        info += fisher_information(J, sigma_px)
    return info


def crlb_from_information(info: np.ndarray, rcond: float = 1e-12) -> np.ndarray | None:
    """``info^-1`` (6, 6), or None when the pose is not observable (singular info)."""
    info = np.asarray(info, dtype=float)
    w = np.linalg.eigvalsh(info)
    if w[0] <= rcond * max(w[-1], 1e-300):
        return None
    return np.linalg.inv(info)


def crlb_std(C: np.ndarray | None) -> tuple[float, float]:
    """``(sqrt(trace C_pos), sqrt(trace C_rot))`` in (m, rad); NaN for None.

    These bound the RMS of the Euclidean position error and of the rotation
    angle: ``E|e_p|^2 >= trace(C[:3, :3])``.
    """
    if C is None:
        return float("nan"), float("nan")
    return float(np.sqrt(np.trace(C[:3, :3]))), float(np.sqrt(np.trace(C[3:, 3:])))


def frame_crlb(views, T_world_object: np.ndarray, sigma_px: float) -> np.ndarray | None:
    """Per-frame (static, no-prior) CRLB (6, 6) of ``[dp, dtheta]``; None if unobservable."""
    return crlb_from_information(frame_information(views, T_world_object, sigma_px))


def posterior_crlb(T_true: np.ndarray, t: np.ndarray, infos: list, P0: np.ndarray, q_acc: float,
                   q_alpha: float) -> np.ndarray:
    """Posterior CRLB of the pose along a true trajectory (constant-velocity prior).

    Information recursion on the 12-state error ``[dp, dtheta, dv, dw]``::

        J_0 = P0^-1 + H_0
        J_k = (F_k J_{k-1}^-1 F_k^T + Q_k)^-1 + H_k

    with ``F_k``, ``Q_k`` from :mod:`vespro.ekf` evaluated at the true state
    (velocities by finite differences of the poses) and ``H_k`` the frame's
    pose information in the top-left 6x6 block.

    Parameters
    ----------
    T_true : ndarray, shape (N, 4, 4)
    t : ndarray, shape (N,)
        Capture times, s.
    infos : list of (6, 6)
        Per-frame pose information (zeros when nothing was measured).
    P0 : ndarray, shape (12, 12)
        Prior covariance at frame 0.
    q_acc, q_alpha : float
        The motion model's spectral densities (m^2/s^3, rad^2/s^3).

    Returns
    -------
    ndarray, shape (N, 6, 6)
        Pose block of the bound at each frame.
    """
    from .ekf import process_noise, state_from_pose, transition_jacobian
    from .se3 import log_so3

    n = len(T_true)
    out = np.empty((n, 6, 6))
    J = np.linalg.inv(P0)
    for k in range(n):
        if k > 0:
            dt = float(t[k] - t[k - 1])
            v = (T_true[k][:3, 3] - T_true[k - 1][:3, 3]) / dt
            w = log_so3(T_true[k][:3, :3] @ T_true[k - 1][:3, :3].T) / dt
            F = transition_jacobian(state_from_pose(T_true[k - 1], v, w), dt)
            P = F @ np.linalg.inv(J) @ F.T + process_noise(dt, q_acc, q_alpha)
            J = np.linalg.inv(0.5 * (P + P.T))
        J = J.copy()
        J[:6, :6] += infos[k]
        C = np.linalg.inv(J)
        out[k] = C[:6, :6]
    return out
