"""Board pose from one view, and the small SE(3) helpers the solvers share."""

from __future__ import annotations

import cv2
import numpy as np

from ..camera import CameraIntrinsics, project_points
from ..se3 import exp_so3, log_so3, transform_from_rt
from .board import BoardDetection, BoardSpec

__all__ = ["board_pose", "perturb", "residuals", "mean_transform"]


def board_pose(intr: CameraIntrinsics, det: BoardDetection, spec: BoardSpec) -> np.ndarray:
    """``T_camera_board`` from one detection: planar PnP (IPPE), then
    Levenberg-Marquardt on the reprojection error.

    Parameters
    ----------
    intr : CameraIntrinsics
    det : BoardDetection
        At least 4 corners.
    spec : BoardSpec

    Returns
    -------
    ndarray (4, 4)
        Board frame in the optical camera frame.
    """
    obj = spec.P_board[det.ids].astype(np.float64)
    img = det.uv.astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, intr.K, intr.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rvec, tvec = cv2.solvePnP(obj, img, intr.K, intr.dist, flags=cv2.SOLVEPNP_ITERATIVE)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-12)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, intr.K, intr.dist, rvec, tvec, crit)
    return transform_from_rt(exp_so3(rvec.ravel()), tvec.ravel())


def perturb(T: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``T @ [exp(w), v]`` with ``delta = (w, v)``, shape (6,): a local
    (right-multiplied) update, rad and m."""
    return T @ transform_from_rt(exp_so3(delta[:3]), delta[3:])


def residuals(intr: CameraIntrinsics, T_camera_board: np.ndarray, det: BoardDetection, spec: BoardSpec) -> np.ndarray:
    """Projected minus detected corners, flattened, shape (2N,), px."""
    uv, _ = project_points(intr, T_camera_board, spec.P_board[det.ids])
    r = (uv - det.uv).ravel()
    return np.where(np.isfinite(r), r, 1e3)  # a point behind the camera: large but finite


def mean_transform(Ts: list) -> np.ndarray:
    """Mean of rigid transforms: arithmetic mean of positions, rotation by
    iterating the mean of log-map residuals (Karcher mean)."""
    Ts = np.asarray(Ts)
    R = Ts[0, :3, :3]
    for _ in range(20):
        w = np.mean([log_so3(R.T @ T[:3, :3]) for T in Ts], axis=0)
        R = R @ exp_so3(w)
        if np.linalg.norm(w) < 1e-12:
            break
    return transform_from_rt(R, Ts[:, :3, 3].mean(axis=0))
