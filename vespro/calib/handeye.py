"""Eye-in-hand calibration: the camera's pose on its link, ``T_link_camera``.

Inputs per view: the link's pose ``T_base_link`` (the robot's forward
kinematics, "gripper to base" in OpenCV's words) and the board's pose in the
camera ``T_camera_board`` (PnP). The board stays fixed, so for the right
``X = T_link_camera`` every view implies the same board pose

    T_base_board = T_base_link_i @ X @ T_camera_board_i.

:func:`calibrate_hand_eye` runs the closed-form solvers of OpenCV
(``cv2.calibrateHandEye``: Tsai, Park, Horaud, Andreff, Daniilidis;
``cv2.calibrateRobotWorldHandEye``: Shah), scores each by its consistency (the
spread of the implied ``T_base_board`` and the reprojection RMS of the board
corners at their mean), refines the best one by least squares on the
reprojection error over ``X`` and ``T_base_board`` jointly, and chooses the
candidate with the lowest reprojection RMS. OpenCV 5.0.0's Python package lacks
both functions (opencv/opencv#29565): :mod:`.axxb` then supplies Tsai, Park,
Daniilidis and Shah in NumPy.

Tsai's parametrisation is singular for a camera turned by 180 deg on its link
(the standard "hand" camera): its answer is then far off, and the consistency
score discards it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ..se3 import invert_transform, log_so3
from .axxb import available_methods, hand_eye, robot_world_hand_eye
from .board import BoardSpec, require_unambiguous
from .errors import CalibrationError
from .pose import board_pose, mean_transform, perturb, residuals

__all__ = ["HandEyeCandidate", "HandEyeResult", "calibrate_hand_eye",
           "consistency"]



@dataclass(frozen=True)
class HandEyeCandidate:
    """One solution and its consistency scores.

    Attributes
    ----------
    method : str
    T_link_camera : ndarray (4, 4)
    T_base_board : ndarray (4, 4)
        Mean of the board poses implied by the views.
    spread_m, spread_rad : float
        RMS deviation of the implied board positions (m) and orientations (rad)
        from their mean.
    rms_px : float
        Reprojection RMS of all corners with the board at ``T_base_board``, px.
    """

    method: str
    T_link_camera: np.ndarray
    T_base_board: np.ndarray
    spread_m: float
    spread_rad: float
    rms_px: float


@dataclass(frozen=True)
class HandEyeResult:
    """Outcome of :func:`calibrate_hand_eye`: the chosen candidate and all of them."""

    best: HandEyeCandidate
    candidates: dict
    used: tuple
    failed: tuple


def consistency(method: str, X: np.ndarray, T_base_link: list, T_camera_board: list, dets: list, intr,
                spec: BoardSpec, T_base_board: np.ndarray | None = None) -> HandEyeCandidate:
    """Score ``X = T_link_camera`` (see module doc); ``T_base_board`` defaults to the views' mean."""
    implied = [Tl @ X @ Tc for Tl, Tc in zip(T_base_link, T_camera_board)]
    Tm = mean_transform(implied) if T_base_board is None else T_base_board
    dp = [np.linalg.norm(T[:3, 3] - Tm[:3, 3]) for T in implied]
    da = [np.linalg.norm(log_so3(Tm[:3, :3].T @ T[:3, :3])) for T in implied]
    r2 = []
    for Tl, d in zip(T_base_link, dets):
        r = residuals(intr, invert_transform(Tl @ X) @ Tm, d, spec)
        r2.append(r ** 2)
    rms = float(np.sqrt(np.sum(np.concatenate(r2)) / (0.5 * sum(len(r) for r in r2))))
    return HandEyeCandidate(method, X, Tm, float(np.sqrt(np.mean(np.square(dp)))),
                            float(np.sqrt(np.mean(np.square(da)))), rms)


def calibrate_hand_eye(T_base_link: dict, detections: dict, intr, spec: BoardSpec, min_views: int = 5,
                       refine: bool = True) -> HandEyeResult:
    """``T_link_camera`` of an eye-in-hand camera from views of a fixed board.

    Parameters
    ----------
    T_base_link : dict
        View name -> (4, 4) pose of the camera's link in the robot base (world) frame.
    detections : dict
        View name -> :class:`BoardDetection` or None.
    intr : CameraIntrinsics
    spec : BoardSpec
    min_views : int
        At least 3 are needed for a unique solution; more, with rotations
        about different axes, for a good one.
    refine : bool
        Add the least-squares refinement of the best closed-form solution.

    Raises
    ------
    CalibrationError
        Ambiguous board, too few views with the board found (named), views
        without a link pose (named).
    """
    require_unambiguous(spec, "hand-eye calibration")
    no_pose = [n for n in detections if n not in T_base_link]
    if no_pose:
        raise CalibrationError(f"no link pose for image(s) {', '.join(no_pose)} in the pose file")
    failed = tuple(n for n, d in detections.items() if d is None)
    names = [n for n, d in detections.items() if d is not None]
    if len(names) < max(3, min_views):
        raise CalibrationError(f"only {len(names)} view(s) with the board found, need at least {max(3, min_views)}"
                               + (f"; board not found in: {', '.join(failed)}" if failed else ""))
    dets = [detections[n] for n in names]
    Tl = [np.asarray(T_base_link[n], float) for n in names]
    Tc = [board_pose(intr, d, spec) for d in dets]
    cands = {}
    for name in available_methods():
        X = hand_eye(name, Tl, Tc)
        if np.all(np.isfinite(X)):
            cands[name] = consistency(name, X, Tl, Tc, dets, intr, spec)
    X, Y = robot_world_hand_eye(Tl, Tc)
    if np.all(np.isfinite(X)) and np.all(np.isfinite(Y)):
        # Scored with its own board pose Y, which it estimated with X.
        cands["rw_shah"] = consistency("rw_shah", X, Tl, Tc, dets, intr, spec, Y)
    if not cands:
        raise CalibrationError("every hand-eye solver failed (degenerate motions: rotate the camera about several axes)")
    start = min(cands.values(), key=lambda c: c.rms_px)
    if refine:
        X0, B0 = start.T_link_camera, start.T_base_board

        def fun(x):
            X, B = perturb(X0, x[:6]), perturb(B0, x[6:])
            return np.concatenate([residuals(intr, invert_transform(T @ X) @ B, d, spec) for T, d in zip(Tl, dets)])

        sol = least_squares(fun, np.zeros(12), method="lm", xtol=1e-12, ftol=1e-12)
        X, B = perturb(X0, sol.x[:6]), perturb(B0, sol.x[6:])
        cands["refined"] = consistency(f"refined ({start.method})", X, Tl, Tc, dets, intr, spec, B)
    best = min(cands.values(), key=lambda c: c.rms_px)
    return HandEyeResult(best, cands, tuple(names), failed)
