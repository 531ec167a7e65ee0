"""Intrinsic calibration of one camera from board views.

:func:`calibrate_intrinsics` runs OpenCV's calibration (camera matrix and
plumb_bob ``k1 k2 p1 p2 k3``) on the views whose board was found, then drops
views whose reprojection RMS is an outlier and calibrates again without them.
Given the images too, it then re-locates every corner on the board plane
through that calibration (:func:`vespro.calib.refine.refine_corners`) and
calibrates again, a few rounds: the detector's corners are ~0.1 px noisy
(edges bent by the lens, pixel locking, ChArUco markers close to the corners),
and at that noise the distortion polynomial extrapolated into the image
corners is off by up to ~1 px; the re-located corners are ~0.01 px.
:func:`coverage` says how well the detected corners cover the image (a badly
covered image extrapolates the distortion model where it was never measured);
:func:`coverage_image` draws it. :func:`undistortion_error` compares two
calibrations of one camera where it matters: the distorted-to-ideal pixel map.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..camera import CameraIntrinsics, project_points, undistort_pixels
from ..se3 import exp_so3, transform_from_rt
from .board import BoardDetection, BoardSpec
from .errors import CalibrationError
from .refine import extend_corners, refine_corners

__all__ = ["IntrinsicsResult", "Coverage", "IMAGE_CORNERS", "calibrate_intrinsics", "coverage", "coverage_image",
           "undistortion_error", "reprojection_rms"]


@dataclass(frozen=True)
class Coverage:
    """Where the detected corners fall in the image.

    Attributes
    ----------
    counts : ndarray, shape (rows, cols), int
        Corners per grid cell.
    fraction : float
        Fraction of cells holding at least one corner.
    warnings : tuple of str
        Empty when the coverage is good.
    corner_gap_px : ndarray, shape (4,)
        Distance from each image corner pixel (top-left, top-right, bottom-left,
        bottom-right) to the nearest detected corner, px: how far the distortion
        model is extrapolated there (a grid cell holding one corner can still
        leave tens of pixels between it and the image corner).
    """

    counts: np.ndarray
    fraction: float
    warnings: tuple = ()
    corner_gap_px: np.ndarray = field(default=None)

    @property
    def ok(self) -> bool:
        return not self.warnings


@dataclass(frozen=True)
class IntrinsicsResult:
    """Outcome of :func:`calibrate_intrinsics`.

    Attributes
    ----------
    intrinsics : CameraIntrinsics
    rms_px : float
        Reprojection RMS over all corners of the views used, px.
    view_rms_px : dict
        View name -> reprojection RMS of that view, px (views used only).
    T_camera_board : dict
        View name -> board pose in the camera frame, (4, 4).
    used : tuple of str
    failed : tuple of str
        Views where the board was not found.
    rejected : dict
        View name -> its RMS (px) in the calibration that rejected it as an outlier;
        nan: too few of its corners read cleanly in a refinement round.
    std : ndarray, shape (9,)
        Standard deviations of ``fx fy cx cy k1 k2 p1 p2 k3`` reported by OpenCV.
    coverage : Coverage
    detections : dict
        View name -> the corners the result was computed from (re-located ones
        after refinement rounds), views used only.
    rms_px_detected : float
        Reprojection RMS of the first calibration, from the detector's corners, px.
    refine_rounds : int
        Refinement rounds run (0: no images given, or none could be used).
    refine_note : str
        Why the refinement stopped early (empty when it ran every round asked).
    """

    intrinsics: CameraIntrinsics
    rms_px: float
    view_rms_px: dict
    T_camera_board: dict
    used: tuple
    failed: tuple
    rejected: dict
    std: np.ndarray
    coverage: Coverage = field(default=None)
    detections: dict = field(default=None)
    rms_px_detected: float = float("nan")
    refine_rounds: int = 0
    refine_note: str = ""


def reprojection_rms(intr: CameraIntrinsics, T_camera_board: np.ndarray, det: BoardDetection,
                     spec: BoardSpec) -> float:
    """RMS (px) of the distance between detected and projected corners."""
    uv, _ = project_points(intr, T_camera_board, spec.P_board[det.ids])
    return float(np.sqrt(np.mean(np.sum((uv - det.uv) ** 2, axis=1))))


def _run(dets: dict, spec: BoardSpec, size: tuple, flags: int):
    names = list(dets)
    obj = [spec.P_board[dets[n].ids].astype(np.float32) for n in names]
    img = [dets[n].uv.astype(np.float32) for n in names]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, dist, rvecs, tvecs, std_i, _, _ = cv2.calibrateCameraExtended(
        obj, img, size, None, None, flags=flags, criteria=crit)
    intr = CameraIntrinsics(size[0], size[1], K, np.asarray(dist).ravel()[:5])
    poses = {n: transform_from_rt(exp_so3(np.ravel(r)), np.ravel(t)) for n, r, t in zip(names, rvecs, tvecs)}
    view_rms = {n: reprojection_rms(intr, poses[n], dets[n], spec) for n in names}
    return intr, poses, view_rms, np.asarray(std_i).ravel()


def calibrate_intrinsics(detections: dict, spec: BoardSpec, image_size: tuple, min_views: int = 6,
                         outlier_factor: float = 3.0, outlier_floor_px: float = 0.3,
                         max_rounds: int = 3, images: dict | None = None,
                         refine_rounds: int = 2, extend: bool = True,
                         min_corners_read: int = 8) -> IntrinsicsResult:
    """Camera matrix and plumb_bob distortion from board detections.

    Parameters
    ----------
    detections : dict
        View name -> :class:`BoardDetection`, or None where the board was not found.
    spec : BoardSpec
    image_size : tuple
        ``(width, height)``, pixels.
    min_views : int
        Fewer usable views than this is an error (5 coefficients + 4 camera
        matrix entries need several well-spread views).
    outlier_factor, outlier_floor_px : float
        A view is an outlier when its RMS exceeds both ``outlier_factor`` times
        the median view RMS and the median plus ``outlier_floor_px`` (the floor
        keeps a set of near-perfect views from losing its slightly worse ones).
    max_rounds : int
        Rejection rounds (each followed by a new calibration).
    images : dict, optional
        View name -> image (as detected). Given, the corners of the views used
        are re-located through the calibration and the camera calibrated
        again, ``refine_rounds`` times (two suffice: the second moves the
        corners by thousandths of a pixel).
    refine_rounds : int
    extend : bool
        In each refinement round, also add the corners the detector missed
        that the calibration places in the image and that read cleanly
        (:func:`vespro.calib.refine.extend_corners`): ChArUco corners next to
        the image border, whose markers are cut, reach into the image corners.
    min_corners_read : int
        A view with fewer corners read cleanly (the others are left out) is
        dropped into ``rejected`` (RMS nan).

    Raises
    ------
    CalibrationError
        Too few views with a detected board; the message names the failed ones.
    """
    failed = tuple(n for n, d in detections.items() if d is None)
    dets = {n: d for n, d in detections.items() if d is not None}
    for n, d in dets.items():
        if tuple(d.image_size) != tuple(image_size):
            raise CalibrationError(f"view {n}: image size {d.image_size} differs from {tuple(image_size)}")
    if len(dets) < min_views:
        raise CalibrationError(
            f"only {len(dets)} view(s) with the board ({spec.describe()}) found, need at least {min_views}"
            + (f"; board not found in: {', '.join(failed)}" if failed else "")
            + (f"; usable: {', '.join(dets)}" if dets else ""))
    rejected = {}
    dets, intr, poses, view_rms, std = _calibrate_rejecting(dets, spec, tuple(image_size), min_views, outlier_factor,
                                                            outlier_floor_px, max_rounds, rejected)
    rms_detected = _total_rms(dets, view_rms)
    rounds = 0
    note = ""
    if images is not None:
        missing = [n for n in dets if n not in images]
        if missing:
            raise ValueError(f"no image for view(s) {', '.join(missing)}")
        for r in range(1, refine_rounds + 1):
            refined, unread = {}, {}
            for n, d in dets.items():
                rd = refine_corners(images[n], d, spec, intr, poses[n], drop_failed=True)
                if extend:
                    rd = extend_corners(images[n], rd, spec, intr, poses[n])
                if len(rd) >= min_corners_read:
                    refined[n] = rd
                else:
                    unread[n] = float("nan")  # too few corners read cleanly
            if len(refined) < min_views:
                # Images the reading cannot use (blurred past the markers' margin, low
                # contrast): keep the calibration from the previous round's corners.
                note = (f"corner reading stopped before round {r}: only {len(refined)} view(s) with at least "
                        f"{min_corners_read} corners read cleanly, need {min_views}; the "
                        + ("detector's corners are used" if r == 1 else f"corners of round {r - 1} are used"))
                break
            rejected.update(unread)
            dets, intr, poses, view_rms, std = _calibrate_rejecting(refined, spec, tuple(image_size), min_views,
                                                                    outlier_factor, outlier_floor_px, max_rounds,
                                                                    rejected)
            rounds = r
    # Read corners (~0.005 px) extrapolate much further than the detector's (~0.08 px).
    cov = coverage(list(dets.values()), tuple(image_size), max_corner_gap=0.06 if rounds else 0.04)
    return IntrinsicsResult(intr, _total_rms(dets, view_rms), view_rms, poses, tuple(dets), failed, rejected, std, cov,
                            dict(dets), rms_detected, rounds, note)


def _total_rms(dets: dict, view_rms: dict) -> float:
    n_pts = sum(len(d) for d in dets.values())
    return float(np.sqrt(sum(view_rms[n] ** 2 * len(d) for n, d in dets.items()) / n_pts))


def _calibrate_rejecting(dets: dict, spec: BoardSpec, size: tuple, min_views: int, outlier_factor: float,
                         outlier_floor_px: float, max_rounds: int, rejected: dict):
    """Calibrate, drop outlier views (added to ``rejected``), calibrate again."""
    for _ in range(max_rounds + 1):
        intr, poses, view_rms, std = _run(dets, spec, size, 0)
        med = float(np.median(list(view_rms.values())))
        thr = max(outlier_factor * med, med + outlier_floor_px)
        bad = {n: r for n, r in view_rms.items() if r > thr}
        if not bad or len(dets) - len(bad) < min_views:
            break
        rejected.update(bad)
        dets = {n: d for n, d in dets.items() if n not in bad}
    return dets, intr, poses, view_rms, std


#: Names of the image corners, in the order of :attr:`Coverage.corner_gap_px`.
IMAGE_CORNERS = ("top-left", "top-right", "bottom-left", "bottom-right")


def coverage(detections: list, image_size: tuple, grid: tuple = (8, 6), min_fraction: float = 0.75,
             max_corner_gap: float = 0.04) -> Coverage:
    """How well corners cover the image.

    Parameters
    ----------
    detections : list of BoardDetection
    image_size : tuple
        ``(width, height)``, pixels.
    grid : tuple
        ``(cols, rows)`` of the coverage grid.
    min_fraction : float
        Fewer covered cells than this fraction gives a warning; so does an empty
        corner cell (distortion is strongest there).
    max_corner_gap : float
        Fraction of the image diagonal: a nearest detected corner farther than
        this from an image corner gives a warning (0.04: 32 px at 640x480).
        Against the simulator's truth (cam_left, k1=-0.22): from the
        detector's corners (~0.08 px noise) gaps of 46-67 px left 0.2-1.0 px
        of undistortion error in the extreme corners; from corners read on the
        board plane (~0.005 px, :func:`calibrate_intrinsics` with images, which
        passes 0.06: 48 px) gaps up to 46 px left at most 0.026 px.
    """
    w, h = image_size
    cols, rows = grid
    counts = np.zeros((rows, cols), int)
    for d in detections:
        c = np.clip((d.uv[:, 0] * cols / w).astype(int), 0, cols - 1)
        r = np.clip((d.uv[:, 1] * rows / h).astype(int), 0, rows - 1)
        np.add.at(counts, (r, c), 1)
    frac = float(np.mean(counts > 0))
    warns = []
    if frac < min_fraction:
        warns.append(f"board corners cover only {100 * frac:.0f}% of the image ({cols}x{rows} grid), "
                     f"want at least {100 * min_fraction:.0f}%: add views with the board in the empty areas")
    names = {(0, 0): "top-left", (0, cols - 1): "top-right", (rows - 1, 0): "bottom-left",
             (rows - 1, cols - 1): "bottom-right"}
    empty = [nm for rc, nm in names.items() if counts[rc] == 0]
    if empty:
        warns.append(f"no board corners in the image's {', '.join(empty)} corner(s): "
                     "the distortion there is extrapolated")
    uv = np.concatenate([d.uv for d in detections]) if detections else np.full((1, 2), np.inf)
    img_corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])
    gap = np.array([np.min(np.linalg.norm(uv - c, axis=1)) for c in img_corners])
    limit = max_corner_gap * np.hypot(w, h)
    far = [f"{nm} {g:.0f} px" for nm, g in zip(IMAGE_CORNERS, gap) if g > limit and nm not in empty]
    if far:
        warns.append(f"nearest board corner to the image corner: {', '.join(far)} (want <= {limit:.0f} px): "
                     "the distortion is extrapolated there; add views with the board reaching into "
                     "the image corners")
    return Coverage(counts, frac, tuple(warns), gap)


def coverage_image(cov: Coverage, detections: list, image_size: tuple) -> np.ndarray:
    """A picture of the coverage: grid cells shaded by corner count (red: empty),
    each view's corners as dots. Shape (height, width, 3), uint8 BGR."""
    w, h = image_size
    rows, cols = cov.counts.shape
    img = np.full((h, w, 3), 255, np.uint8)
    top = max(1, int(cov.counts.max()))
    for r in range(rows):
        for c in range(cols):
            x0, x1 = int(c * w / cols), int((c + 1) * w / cols) - 1
            y0, y1 = int(r * h / rows), int((r + 1) * h / rows) - 1
            n = cov.counts[r, c]
            colour = (60, 60, 230) if n == 0 else (255 - int(180 * n / top), 255, 255 - int(180 * n / top))
            cv2.rectangle(img, (x0, y0), (x1, y1), colour, -1)
            cv2.rectangle(img, (x0, y0), (x1, y1), (200, 200, 200), 1)
            cv2.putText(img, str(n), (x0 + 4, y0 + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (40, 40, 40), 1)
    rng = np.random.default_rng(0)  # stable view colours
    for d in detections:
        colour = tuple(int(v) for v in rng.integers(0, 200, 3))
        hull = cv2.convexHull(d.uv.astype(np.float32)).astype(np.int32)
        cv2.polylines(img, [hull], True, colour, 1, cv2.LINE_AA)
        for u, v in d.uv:
            cv2.circle(img, (int(round(u)), int(round(v))), 1, colour, -1)
    if cov.corner_gap_px is not None:
        # The gap at each image corner: an arc through the nearest detected corner.
        for (x, y), g in zip([(0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1)], cov.corner_gap_px):
            if np.isfinite(g):
                cv2.circle(img, (x, y), int(round(g)), (0, 0, 200), 1, cv2.LINE_AA)
                cv2.putText(img, f"{g:.0f}px", (min(max(x - 40, 4), w - 48), min(max(y + (18 if y == 0 else -24), 14), h - 24)),
                            cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 200), 1, cv2.LINE_AA)
    text = f"coverage {100 * cov.fraction:.0f}%  ({len(detections)} views)"
    cv2.putText(img, text, (8, h - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def undistortion_error(intr_est: CameraIntrinsics, intr_true: CameraIntrinsics, step_px: int = 4) -> tuple[float, float]:
    """Difference of two distorted-to-ideal pixel maps over the whole image.

    Each calibration maps a pixel ``u`` of the raw image to its ideal pixel
    ``K n(u)`` (what ``cv2.undistort`` with the same matrix does); the maps are
    compared on a grid of pixels covering the image every ``step_px``, the
    first and last rows and columns included (so the four extreme corner
    pixels, where an extrapolated polynomial is worst, always count).

    Returns
    -------
    max_px, rms_px : float
    """
    w, h = intr_true.width, intr_true.height
    u, v = np.meshgrid(np.r_[np.arange(0, w, step_px), w - 1], np.r_[np.arange(0, h, step_px), h - 1])
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    d = np.linalg.norm(undistort_pixels(intr_est, uv) - undistort_pixels(intr_true, uv), axis=1)
    return float(d.max()), float(np.sqrt(np.mean(d ** 2)))
