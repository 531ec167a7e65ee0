"""Windowed corner extraction around predicted feature positions.

For each selected feature a square window (half-size ``r`` px, e.g. 3 sigma of
its innovation covariance, :func:`window_half_sizes`) is searched for corners:
Shi-Tomasi response (``cv2.cornerMinEigenVal``, the measure behind
``cv2.goodFeaturesToTrack``) with non-maximum suppression, an absolute and a
relative threshold, then ``cv2.cornerSubPix``. The corner nearest to the
prediction is associated to the feature unless a second one is similarly close
(ambiguity) or another feature claims the same corner.

The function never raises: a missing image, a window outside the image, a
non-finite prediction or an OpenCV error give "not found" for the features
concerned, with a :class:`Why` code.

Pixels: ``(0, 0)`` is the centre of the top-left pixel (OpenCV).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Why", "ExtractionResult", "window_half_sizes", "extract_corners"]

MIN_HALF_SIZE = 4
MAX_HALF_SIZE = 24


class Why(enum.IntEnum):
    """Per-feature outcome."""

    FOUND = 0
    NO_IMAGE = 1      #: image is None or not a usable grey image
    OUTSIDE = 2       #: window (almost) entirely outside the image
    NO_CORNER = 3     #: no corner strong enough inside the window
    AMBIGUOUS = 4     #: two corners similarly close to the prediction
    SHARED = 5        #: the same corner is nearest for two features
    INVALID = 6       #: non-finite prediction / window size, or OpenCV failed


@dataclass(frozen=True)
class ExtractionResult:
    """Measured corners of K features.

    Attributes
    ----------
    uv : ndarray, shape (K, 2)
        Sub-pixel corner positions, px; NaN where not found.
    found : ndarray, shape (K,), bool
    why : ndarray, shape (K,), int8
        :class:`Why` codes.
    n_candidates : ndarray, shape (K,), int
        Corners detected inside each window (before association).
    """

    uv: np.ndarray
    found: np.ndarray
    why: np.ndarray
    n_candidates: np.ndarray


def window_half_sizes(S, n_sigma: float = 3.0, min_px: int = MIN_HALF_SIZE, max_px: int = MAX_HALF_SIZE) -> np.ndarray:
    """Search-window half-sizes from innovation covariances.

    Parameters
    ----------
    S : ndarray, shape (K, 2, 2)
        Innovation covariance per feature, px^2 (``J_i P6 J_i^T + R``).
    n_sigma : float
        Half-size in standard deviations along the worst direction.

    Returns
    -------
    ndarray, shape (K,), int
        ``ceil(n_sigma * sqrt(lambda_max(S_i)))`` clamped to ``[min_px, max_px]``;
        ``max_px`` where S is not finite.
    """
    S = np.asarray(S, dtype=float).reshape(-1, 2, 2)
    tr = S[:, 0, 0] + S[:, 1, 1]
    det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
    lam = 0.5 * tr + np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
    r = np.ceil(n_sigma * np.sqrt(np.maximum(lam, 0.0)))
    r = np.where(np.isfinite(r), r, max_px)
    return np.clip(r, min_px, max_px).astype(int)


def _as_grey(image):
    if image is None:
        return None
    try:
        img = np.asarray(image)
    except Exception:  # noqa: BLE001 - never raise on bad input
        return None
    if img.dtype != np.uint8:
        return None
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    elif img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.ndim != 2 or min(img.shape) < 8:
        return None
    return np.ascontiguousarray(img)


def extract_corners(
    image,
    uv_pred,
    half_size,
    *,
    min_eig: float = 2e-4,
    rel_quality: float = 0.2,
    block_size: int = 3,
    nms_radius: int = 2,
    subpix_half: int = 4,
    ambiguity_ratio: float = 0.6,
    max_subpix_shift: float = 4.0,
    shared_px: float = 1.0,
) -> ExtractionResult:
    """Find one corner per feature inside its window.

    Parameters
    ----------
    image : ndarray (H, W) uint8, or (H, W, 3) uint8 BGR, or None
    uv_pred : ndarray, shape (K, 2)
        Predicted (distorted) pixels of the selected features.
    half_size : int or ndarray (K,)
        Window half-size per feature, px (window is ``2 r + 1`` wide).
    min_eig : float
        Absolute threshold on the Shi-Tomasi response (``cornerMinEigenVal``,
        ``blockSize=3``, ``ksize=3`` on a uint8 image): about
        ``(contrast/255)^2 / 8`` at a clean right-angle corner, 0 on a clean
        straight edge, below 1.3e-4 in 99.99 % of pixels of flat noise with
        sigma = 2 grey levels. The default keeps right-angle corners from ~10
        grey levels of contrast (more for obtuse ones).
    rel_quality : float
        Candidates weaker than this fraction of the window's best are dropped.
    block_size : int
        Neighbourhood of the structure tensor, px.
    nms_radius : int
        Non-maximum suppression radius, px.
    subpix_half : int
        ``cv2.cornerSubPix`` half window, px (clamped to the search window).
    ambiguity_ratio : float
        Ambiguous when ``d1 > ambiguity_ratio * d2`` (distances of the two
        nearest candidates to the prediction).
    max_subpix_shift : float
        Sub-pixel refinement may move a candidate at most this far, px (the
        response peak of an obtuse corner sits up to ~3 px inside the tip).
    shared_px : float
        Two features whose corners are closer than this both get ``SHARED``.

    Returns
    -------
    ExtractionResult
    """
    try:
        uv_pred = np.asarray(uv_pred, dtype=float).reshape(-1, 2)
    except Exception:  # noqa: BLE001
        uv_pred = np.zeros((0, 2))
    K = len(uv_pred)
    uv_out = np.full((K, 2), np.nan)
    why = np.full(K, int(Why.INVALID), dtype=np.int8)
    ncand = np.zeros(K, dtype=int)
    try:
        r_all = np.broadcast_to(np.asarray(half_size, dtype=float), (K,))
    except Exception:  # noqa: BLE001
        return ExtractionResult(uv_out, np.zeros(K, bool), why, ncand)

    img = _as_grey(image)
    if img is None:
        why[:] = Why.NO_IMAGE
        return ExtractionResult(uv_out, np.zeros(K, bool), why, ncand)
    H, W = img.shape
    pad = block_size // 2 + 2  # Sobel (1) + block support, so the response is valid at the window edge
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 0.001)
    kernel = np.ones((2 * nms_radius + 1, 2 * nms_radius + 1), np.uint8)

    for i in range(K):
        u, v = uv_pred[i]
        r = r_all[i]
        if not (np.isfinite(u) and np.isfinite(v) and np.isfinite(r) and r >= 1):
            continue
        r = int(round(r))
        try:
            x0, x1 = int(np.floor(u - r)), int(np.ceil(u + r))
            y0, y1 = int(np.floor(v - r)), int(np.ceil(v + r))
            wx0, wx1, wy0, wy1 = max(x0, 0), min(x1, W - 1), max(y0, 0), min(y1, H - 1)
            if wx1 - wx0 < 4 or wy1 - wy0 < 4:
                why[i] = Why.OUTSIDE
                continue
            px0, px1 = max(wx0 - pad, 0), min(wx1 + pad, W - 1)
            py0, py1 = max(wy0 - pad, 0), min(wy1 + pad, H - 1)
            roi = img[py0 : py1 + 1, px0 : px1 + 1]
            resp = cv2.cornerMinEigenVal(roi, block_size, ksize=3)
            # only the window proper, away from the image's outer pixels (no valid gradient there)
            inner = np.zeros_like(resp, dtype=bool)
            ix0, ix1 = max(wx0, 2) - px0, min(wx1, W - 3) - px0
            iy0, iy1 = max(wy0, 2) - py0, min(wy1, H - 3) - py0
            if ix1 < ix0 or iy1 < iy0:
                why[i] = Why.OUTSIDE
                continue
            inner[iy0 : iy1 + 1, ix0 : ix1 + 1] = True
            peak = (resp >= cv2.dilate(resp, kernel)) & inner
            best = resp[inner].max()
            peak &= resp >= max(min_eig, rel_quality * best)
            ys, xs = np.nonzero(peak)
            ncand[i] = len(xs)
            if len(xs) == 0:
                why[i] = Why.NO_CORNER
                continue
            cand = np.stack([xs + px0, ys + py0], axis=1).astype(np.float32)
            d = np.hypot(cand[:, 0] - u, cand[:, 1] - v)
            order = np.argsort(d, kind="stable")
            if len(order) > 1 and d[order[0]] > ambiguity_ratio * d[order[1]]:
                why[i] = Why.AMBIGUOUS
                continue
            c0 = cand[order[0]].reshape(1, 1, 2).copy()
            sh = int(max(2, min(subpix_half, r)))
            ref = cv2.cornerSubPix(img, c0.copy(), (sh, sh), (-1, -1), crit).reshape(2).astype(float)
            if (
                not np.all(np.isfinite(ref))
                or np.hypot(*(ref - c0.reshape(2))) > max_subpix_shift
                or abs(ref[0] - u) > r
                or abs(ref[1] - v) > r
            ):
                why[i] = Why.NO_CORNER
                continue
            uv_out[i] = ref
            why[i] = Why.FOUND
        except (cv2.error, ValueError, IndexError, TypeError):
            why[i] = Why.INVALID
            uv_out[i] = np.nan

    found_idx = np.flatnonzero(why == Why.FOUND)
    if len(found_idx) > 1:
        P = uv_out[found_idx]
        dd = np.hypot(P[:, None, 0] - P[None, :, 0], P[:, None, 1] - P[None, :, 1])
        np.fill_diagonal(dd, np.inf)
        clash = found_idx[np.any(dd < shared_px, axis=1)]
        why[clash] = Why.SHARED
        uv_out[clash] = np.nan
    found = why == Why.FOUND
    return ExtractionResult(uv_out, found, why, ncand)
