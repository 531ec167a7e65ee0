"""Board corners re-located along the board's own axes, given a camera model.

A corner detector working in the raw image (``cv2.cornerSubPix``) sees square
edges bent by the lens and tilted by perspective, weights pixels by their
squared gradient (pixel locking: the estimate is pulled towards pixel
centres), and on a ChArUco board must keep its window inside the narrow white
margin between a corner and the nearest marker. Once a calibration exists,
each view can be resampled on the board plane instead (Datta et al., "Accurate
camera calibration using iterative refinement of control points", 2009): with
the camera model and the view's board pose, a board point maps to a pixel, so
the image around each corner is read on a grid of board coordinates, where the
two edges through the corner are straight and lie along the board's x and y
axes.

:func:`refine_corners` does that per corner: for each edge through the corner
it reads short profiles across the edge, in strips that keep clear of the
markers, and finds the edge in each profile as the centroid of the intensity
step (linear in the pixel values, so not pixel-locked); a line through the
edge points of each edge gives the edge, the two lines cross at the corner.
The offset found on the board plane is mapped back to the raw image through
the same model, so where the model is still slightly wrong (the first,
noisier calibration) the error largely cancels; calibrating again from the
refined corners and refining again converges in two or three rounds.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..camera import CameraIntrinsics, project_points, undistort_pixels
from .board import BoardDetection, BoardSpec

__all__ = ["refine_corners", "extend_corners"]


def _strip_half_width(spec: BoardSpec) -> float:
    """Half-width of the strip read across an edge, in squares.

    ChArUco: the white margin between a square's edge and its marker is
    ``(square - marker) / 2``; the strip keeps to 60% of it so the marker's own
    edge stays out. Chessboard: a quarter square.
    """
    if spec.kind == "charuco":
        return 0.6 * 0.5 * (spec.square_size - spec.marker_size) / spec.square_size
    return 0.25


def _grey(image: np.ndarray) -> np.ndarray:
    g = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return g.astype(np.float32)


#: Samples across an edge (the strip) and along it (each half of the edge, from
#: 0.15 to 0.85 square from the corner: clear of the X-junction's centre and of
#: the next corner).
_N_ACROSS = 33
_ALONG = np.concatenate([np.linspace(-0.85, -0.15, 15), np.linspace(0.15, 0.85, 15)])


def _board_points(intr: CameraIntrinsics, T_camera_board: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Where pixels' rays meet the board plane, board frame, shape (N, 3)."""
    ideal = undistort_pixels(intr, uv)
    d = np.stack([(ideal[:, 0] - intr.cx) / intr.fx, (ideal[:, 1] - intr.cy) / intr.fy, np.ones(len(uv))], 1)
    R, t = T_camera_board[:3, :3], T_camera_board[:3, 3]
    lam = (R[:, 2] @ t) / (d @ R[:, 2])
    return (lam[:, None] * d - t) @ R


def _read(grey: np.ndarray, P0: np.ndarray, spec: BoardSpec, intr: CameraIntrinsics, T_camera_board: np.ndarray,
          rounds: int, min_strip_px: float, min_step: float, off0: np.ndarray | None = None):
    """Read corners near the board points ``P0`` (N, 3), starting ``off0``
    (N, 2) squares from them (default 0).

    Returns
    -------
    off : ndarray (N, 2)
        Corner offset from ``P0`` on the board plane, squares.
    good : ndarray (N,), bool
        Every round's read succeeded: both edges seen in both halves (at least
        5 rows each, inside the image, a step of at least ``min_step`` grey
        levels), the step changing sign across the corner (an X-junction, not a
        plain edge) and the strip at least ``min_strip_px`` wide in the image.
    resid_px : ndarray (N,)
        RMS distance of the edge points from their fitted lines, image pixels.
    """
    h, w = grey.shape
    s = spec.square_size
    n = len(P0)
    uv0, _ = project_points(intr, T_camera_board, P0)
    ux, _ = project_points(intr, T_camera_board, P0 + [s, 0, 0])
    uy, _ = project_points(intr, T_camera_board, P0 + [0, s, 0])
    px_per_sq = np.minimum(np.linalg.norm(ux - uv0, axis=1), np.linalg.norm(uy - uv0, axis=1))
    hw = _strip_half_width(spec)
    a = np.linspace(-hw, hw, _N_ACROSS)  # across the edge, squares
    amid = 0.5 * (a[1:] + a[:-1])
    b = _ALONG
    half = len(b) // 2
    A, Bq = np.meshgrid(a, b)  # (len(b), n_across)
    off = np.zeros((n, 2)) if off0 is None else np.array(off0, float)
    good_all = (hw * px_per_sq >= min_strip_px) & np.isfinite(px_per_sq)
    resid = np.full(n, np.inf)
    for _ in range(rounds):
        # Vertical edge (along board y): points (x0 + a, y0 + b); horizontal: (x0 + b, y0 + a).
        x0 = (P0[:, 0] / s + off[:, 0])[:, None, None]
        y0 = (P0[:, 1] / s + off[:, 1])[:, None, None]
        X = np.concatenate([x0 + A[None], x0 + Bq[None]], axis=1) * s
        Y = np.concatenate([y0 + Bq[None], y0 + A[None]], axis=1) * s
        pts = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
        uv, z = project_points(intr, T_camera_board, pts)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        inside = inside.reshape(n, 2, len(b), _N_ACROSS).all(axis=3)  # whole rows only
        mx = np.nan_to_num(uv[:, 0], nan=-1e4).astype(np.float32).reshape(-1, _N_ACROSS)
        my = np.nan_to_num(uv[:, 1], nan=-1e4).astype(np.float32).reshape(-1, _N_ACROSS)
        vals = cv2.remap(grey, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        vals = vals.reshape(n, 2, len(b), _N_ACROSS)
        d = np.diff(vals, axis=3)
        step_ = d.sum(axis=3)  # signed step across the edge, grey levels
        sgn = np.sign(step_)
        d = d * sgn[..., None]
        mass = np.abs(step_)
        # Edge position in each row: the centroid of the step, linear in the pixel
        # values (a box-filtered edge moves it exactly with the edge).
        pos = (d * amid).sum(axis=3) / np.where(mass > 0, mass, 1.0)
        valid = inside & (mass >= min_step)
        valid &= mass > 0.25 * np.max(np.where(inside, mass, 0.0), axis=2, keepdims=True)
        good = good_all & (valid[..., :half].sum(2) >= 5).all(1) & (valid[..., half:].sum(2) >= 5).all(1)
        # An X-junction: each edge's step has opposite signs on the two sides of the corner.
        s_lo = np.sign((sgn * valid)[..., :half].sum(2))
        s_hi = np.sign((sgn * valid)[..., half:].sum(2))
        good &= np.all(s_lo * s_hi < 0, axis=1)
        # Edge lines: pos = c0 + c1 * b, least squares over valid rows.
        W = valid.astype(float)
        sw, sb, sbb = W.sum(2), (W * b).sum(2), (W * b * b).sum(2)
        sp, sbp = (W * pos).sum(2), (W * b * pos).sum(2)
        den = sw * sbb - sb * sb
        den = np.where(np.abs(den) > 1e-12, den, 1.0)
        c0 = (sbb * sp - sb * sbp) / den  # (n, 2): vertical edge's x, horizontal edge's y
        c1 = (sw * sbp - sb * sp) / den
        r = np.where(valid, pos - (c0[..., None] + c1[..., None] * b), 0.0)
        resid = np.sqrt((r ** 2).sum((1, 2)) / np.maximum(W.sum((1, 2)), 1)) * px_per_sq
        # Vertical edge x = c0v + c1v * y, horizontal edge y = c0h + c1h * x: their crossing.
        x = (c0[:, 0] + c1[:, 0] * c0[:, 1]) / (1.0 - c1[:, 0] * c1[:, 1])
        y = c0[:, 1] + c1[:, 1] * x
        step = np.stack([x, y], 1)
        good &= np.all(np.isfinite(step), axis=1)
        good_all &= good
        off = np.where(good[:, None], off + step, off)
    # Converged: the last round moved the corner by less than 0.02 px (a read that
    # started beside the edge is still walking towards it).
    good_all &= np.linalg.norm(step, axis=1) * px_per_sq < 0.02
    return off, good_all, resid


def refine_corners(image: np.ndarray, det: BoardDetection, spec: BoardSpec, intr: CameraIntrinsics,
                   T_camera_board: np.ndarray, rounds: int = 4, min_strip_px: float = 1.0,
                   max_shift: float = 0.1, min_step: float = 20.0, drop_failed: bool = False) -> BoardDetection:
    """Re-locate detected corners on the board plane (see the module docstring).

    Parameters
    ----------
    image : ndarray, shape (H, W) or (H, W, 3), uint8
        The view the corners were detected in.
    det : BoardDetection
    spec : BoardSpec
    intr : CameraIntrinsics
        Current estimate of the camera (distortion included).
    T_camera_board : ndarray (4, 4)
        Current estimate of the board pose in this view.
    rounds : int
        Re-centre and read again this many times (the profiles are read around
        the latest estimate).
    min_strip_px : float
        A corner whose strip is narrower than this in the image (small or
        steeply tilted squares: the edge's blur would reach the markers) keeps
        its detected position.
    max_shift : float
        A corner read more than this fraction of a square from its detected
        position counts as a failed read.
    min_step : float
        Least black-to-white step across an edge, grey levels.
    drop_failed : bool
        Leave out the corners whose read failed instead of keeping their
        detected position (mixing ~0.1 px detector corners, at worst ~0.7 px on
        small steep squares, into ~0.01 px read ones costs a calibration more
        than the corners give).

    Returns
    -------
    BoardDetection
        Same ids (``drop_failed``: those read); ``uv`` refined where the read succeeded.
    """
    P0 = spec.P_board[det.ids]
    # Start at the detected corner (~0.1 px), not at the model's prediction: where the
    # model is still off (a pixel, in the corners of a first calibration) the strips
    # would otherwise start beside the edge.
    grey = _grey(image)
    off0 = (_board_points(intr, T_camera_board, det.uv) - P0)[:, :2] / spec.square_size
    off0 = np.where(np.isfinite(off0), off0, 0.0)
    off, good, _ = _read(grey, P0, spec, intr, T_camera_board, rounds, min_strip_px, min_step, off0)
    good &= np.linalg.norm(off - off0, axis=1) < max_shift
    # A detector outlier (~1.5 px on small steep squares) starts beside the edge:
    # read those again from the model's prediction.
    redo = np.flatnonzero(~good)
    if len(redo):
        off_r, good_r, _ = _read(grey, P0[redo], spec, intr, T_camera_board, rounds, min_strip_px, min_step)
        good_r &= np.linalg.norm(off_r, axis=1) < max_shift
        off[redo[good_r]] = off_r[good_r]
        good[redo[good_r]] = True
    P = P0.copy()
    P[:, :2] += off * spec.square_size
    uv_new, _ = project_points(intr, T_camera_board, P)
    # The read measures where the corner is relative to the model's prediction;
    # the detected position of a failed read is kept.
    if drop_failed:
        return BoardDetection(det.ids[good], uv_new[good], det.image_size)
    out = det.uv.copy()
    out[good] = uv_new[good]
    return BoardDetection(det.ids, out, det.image_size)


def extend_corners(image: np.ndarray, det: BoardDetection, spec: BoardSpec, intr: CameraIntrinsics,
                   T_camera_board: np.ndarray, rounds: int = 4, min_strip_px: float = 1.0,
                   max_shift: float = 0.05, max_resid_px: float = 0.1,
                   min_step: float = 20.0) -> BoardDetection:
    """Add the corners the detector missed but the model places in the image.

    A ChArUco corner is reported only when both markers next to it are decoded,
    so near the image border, where a marker is cut, corners the board does
    show go missing: those closest to the image corners, where the distortion
    is strongest. With a calibration and the view's pose every other board
    corner is predicted; one is added when it reads (:func:`refine_corners`)
    as a clean X-junction within ``max_shift`` squares of the prediction, its
    edge points within ``max_resid_px`` (RMS) of straight lines. Its identity
    comes from the pose (fitted to the decoded corners), so it cannot be a
    neighbour's: they are a whole square away.

    Returns
    -------
    BoardDetection
        The detected corners (unchanged) and the added ones, ids increasing.
    """
    have = set(int(i) for i in det.ids)
    cand = np.array([k for k in range(spec.n_corners) if k not in have], int)
    if len(cand) == 0:
        return det
    P0 = spec.P_board[cand]
    uv0, z = project_points(intr, T_camera_board, P0)
    h, w = image.shape[:2]
    near = (z > 0) & (uv0[:, 0] > -0.5) & (uv0[:, 0] < w - 0.5) & (uv0[:, 1] > -0.5) & (uv0[:, 1] < h - 0.5)
    cand, P0 = cand[near], P0[near]
    if len(cand) == 0:
        return det
    off, good, resid = _read(_grey(image), P0, spec, intr, T_camera_board, rounds, min_strip_px, min_step)
    good &= (np.linalg.norm(off, axis=1) < max_shift) & (resid < max_resid_px)
    if not good.any():
        return det
    P = P0[good].copy()
    P[:, :2] += off[good] * spec.square_size
    uv_new, _ = project_points(intr, T_camera_board, P)
    ids = np.concatenate([det.ids, cand[good]])
    uv = np.concatenate([det.uv, uv_new])
    o = np.argsort(ids)
    return BoardDetection(ids[o], uv[o], det.image_size)
