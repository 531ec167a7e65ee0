"""Poses of fixed cameras in the world from a board at known world poses.

Every camera that sees a board placement whose ``T_world_board`` is known gets
a first pose from PnP (``T_world_camera = T_world_board @ inv(T_camera_board)``,
from its best view); then one least-squares problem refines all camera poses
together over every view, minimising the reprojection error of the board
corners. Placements without a known pose (the board moved somewhere between
the cameras) enter the same problem as free 6-DoF unknowns: they tie cameras
together, so a camera that never sees a surveyed placement is still placed
through one that does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ..se3 import invert_transform
from .board import BoardSpec, require_unambiguous
from .errors import CalibrationError
from .pose import board_pose, perturb, residuals

__all__ = ["ExtrinsicsResult", "calibrate_extrinsics"]


@dataclass(frozen=True)
class ExtrinsicsResult:
    """Outcome of :func:`calibrate_extrinsics`.

    Attributes
    ----------
    T_world_camera : dict
        Camera name -> (4, 4), refined.
    T_world_camera_pnp : dict
        Camera name -> (4, 4), PnP from one view (the initial guess; a baseline).
    T_world_board : dict
        Placement -> (4, 4): the known ones as given, free ones as estimated.
    rms_px : dict
        Camera name -> reprojection RMS over its views, px.
    view_rms_px : dict
        ``(camera, placement)`` -> reprojection RMS, px (views used).
    rejected : dict
        ``(camera, placement)`` -> RMS (px) of views dropped as outliers.
    """

    T_world_camera: dict
    T_world_camera_pnp: dict
    T_world_board: dict
    rms_px: dict
    view_rms_px: dict
    rejected: dict


def calibrate_extrinsics(detections: dict, intrinsics: dict, T_world_board: dict, spec: BoardSpec,
                         outlier_factor: float = 3.0, outlier_floor_px: float = 0.3,
                         max_rounds: int = 3) -> ExtrinsicsResult:
    """Fixed cameras' ``T_world_camera`` from board views.

    Parameters
    ----------
    detections : dict
        ``(camera, placement)`` -> :class:`BoardDetection` or None (not found).
    intrinsics : dict
        Camera name -> :class:`CameraIntrinsics` (calibrated beforehand).
    T_world_board : dict
        Placement -> ``T_world_board`` (4, 4) for the placements whose pose is
        known; at least one.
    spec : BoardSpec
    outlier_factor, outlier_floor_px, max_rounds
        Views whose RMS exceeds both ``outlier_factor`` times the median view
        RMS and the median plus ``outlier_floor_px`` are dropped and the
        problem solved again (a grazing view's corners are biased), as in
        :func:`~vespro.calib.intrinsics.calibrate_intrinsics`; a camera keeps
        at least one view.

    Raises
    ------
    CalibrationError
        Ambiguous board, no known placement, a camera without intrinsics, or a
        camera that cannot be tied to a known placement (the message lists its
        images where the board was not found).
    """
    require_unambiguous(spec, "extrinsic calibration")
    if not T_world_board:
        raise CalibrationError("extrinsic calibration needs the world pose of at least one board placement")
    cams = sorted({c for c, _ in detections})
    missing = [c for c in cams if c not in intrinsics]
    if missing:
        raise CalibrationError(f"no intrinsics for camera(s) {missing}: calibrate them first")
    obs = {k: d for k, d in detections.items() if d is not None}
    placements = sorted({p for _, p in obs})
    known = {p: np.asarray(T, float) for p, T in T_world_board.items()}
    T_cb = {k: board_pose(intrinsics[k[0]], d, spec) for k, d in obs.items()}

    # Initial guesses, spreading out from the known placements.
    cam0, board0 = {}, dict(known)
    changed = True
    while changed:
        changed = False
        for c in cams:
            if c in cam0:
                continue
            views = [(len(obs[(c, p)]), p) for p in placements if (c, p) in obs and p in board0]
            if views:
                p = max(views)[1]
                cam0[c] = board0[p] @ invert_transform(T_cb[(c, p)])
                changed = True
        for p in placements:
            if p in board0:
                continue
            views = [(len(obs[(c, p)]), c) for c in cams if (c, p) in obs and c in cam0]
            if views:
                c = max(views)[1]
                board0[p] = cam0[c] @ T_cb[(c, p)]
                changed = True
    lost = [c for c in cams if c not in cam0]
    if lost:
        parts = []
        for c in lost:
            failed = [p for (cc, p), d in detections.items() if cc == c and d is None]
            seen = [p for (cc, p) in obs if cc == c]
            parts.append(f"{c} (board found in {seen or 'no image'}; not found in {failed or 'none'})")
        raise CalibrationError("cannot place camera(s) without a view of a board placement tied to a known pose: "
                               + "; ".join(parts))

    free = [p for p in placements if p not in known]
    keys = list(obs)
    rejected = {}
    for _ in range(max_rounds + 1):
        Tc, Tb = _refine(keys, obs, intrinsics, spec, cams, cam0, free, known, board0)
        view_rms = {}
        for c, p in keys:
            r = residuals(intrinsics[c], invert_transform(Tc[c]) @ Tb[p], obs[(c, p)], spec).reshape(-1, 2)
            view_rms[(c, p)] = float(np.sqrt(np.mean(np.sum(r ** 2, 1))))
        med = float(np.median(list(view_rms.values())))
        thr = max(outlier_factor * med, med + outlier_floor_px)
        bad = {k: v for k, v in view_rms.items() if v > thr}
        # Never drop a camera's or a free placement's last view.
        for k in list(bad):
            rest = [kk for kk in keys if kk not in bad]
            if not any(kk[0] == k[0] for kk in rest) or (k[1] in free and not any(kk[1] == k[1] for kk in rest)):
                del bad[k]
        if not bad:
            break
        rejected.update(bad)
        keys = [k for k in keys if k not in bad]
    per_cam = {c: [] for c in cams}
    for c, p in keys:
        r = residuals(intrinsics[c], invert_transform(Tc[c]) @ Tb[p], obs[(c, p)], spec).reshape(-1, 2)
        per_cam[c].append(np.sum(r ** 2, 1))
    rms = {c: float(np.sqrt(np.mean(np.concatenate(v)))) for c, v in per_cam.items()}
    return ExtrinsicsResult(Tc, cam0, Tb, rms, view_rms, rejected)


def _refine(keys, obs, intrinsics, spec, cams, cam0, free, known, board0):
    """Least squares over camera poses and free placements (local updates)."""
    def unpack(x):
        Tc = {c: perturb(cam0[c], x[6 * i:6 * i + 6]) for i, c in enumerate(cams)}
        off = 6 * len(cams)
        Tb = dict(known)
        for j, p in enumerate(free):
            Tb[p] = perturb(board0[p], x[off + 6 * j:off + 6 * j + 6])
        return Tc, Tb

    def fun(x):
        Tc, Tb = unpack(x)
        return np.concatenate([residuals(intrinsics[c], invert_transform(Tc[c]) @ Tb[p], obs[(c, p)], spec)
                               for c, p in keys])

    sol = least_squares(fun, np.zeros(6 * (len(cams) + len(free))), method="lm", xtol=1e-12, ftol=1e-12)
    return unpack(sol.x)
