"""Windowed corner extraction around predicted feature positions.

For each selected feature a square window (half-size ``r`` px, e.g. 3 sigma of
its innovation covariance, :func:`window_half_sizes`) is searched for corners:
Shi-Tomasi response (``lambda_min`` of ``cv2.cornerEigenValsAndVecs``, the
measure behind ``cv2.goodFeaturesToTrack``) with non-maximum suppression, an
absolute, a relative and an isotropy threshold, then ``cv2.cornerSubPix`` and
(by default) an edge-intersection refinement that removes cornerSubPix's bias
at L/Y junctions (see :func:`_refine_lines`). The corner nearest to the
prediction is associated to the feature unless a second one is similarly close
(ambiguity) or another feature claims the same corner.

The function never raises: a missing image, a window outside the image, a
non-finite prediction or an OpenCV error give "not found" for the features
concerned, with a :class:`Why` code.

Pixels: ``(0, 0)`` is the centre of the top-left pixel (OpenCV).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import cv2
import numpy as np

from .jit import njit

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


# Plain ints for the per-frame code: an IntEnum member costs an attribute lookup through
# EnumType and a slow path in NumPy comparisons (1-2% of a frame).
_FOUND, _OUTSIDE = int(Why.FOUND), int(Why.OUTSIDE)


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
    S = np.ascontiguousarray(S, dtype=float).reshape(-1, 2, 2)
    return _half_sizes_kernel(S, float(n_sigma), float(min_px), float(max_px))


@njit
def _half_sizes_kernel(S, n_sigma, min_px, max_px):
    """:func:`window_half_sizes`, compiled: ``lambda_max`` of each 2x2 in closed form
    (NaN passes through ``max(., 0)`` as in ``np.maximum``), (K,) int64."""
    K = S.shape[0]
    out = np.empty(K, dtype=np.int64)
    for k in range(K):
        tr = S[k, 0, 0] + S[k, 1, 1]
        det = S[k, 0, 0] * S[k, 1, 1] - S[k, 0, 1] * S[k, 1, 0]
        q = 0.25 * tr * tr - det
        lam = 0.5 * tr + math.sqrt(q if (q > 0.0 or math.isnan(q)) else 0.0)
        r = np.ceil(n_sigma * math.sqrt(lam if (lam > 0.0 or math.isnan(lam)) else 0.0))
        if not math.isfinite(r):
            r = max_px
        out[k] = int(min(max(r, min_px), max_px))
    return out


def _refine_lines(img, q, radius, tip_px=2.0, min_edge_angle_deg=20.0, rel_grad=0.25, max_line_residual=0.6, max_shift=1.0):
    """Corner as the intersection of the edges leaving it (no tip bias).

    ``cv2.cornerSubPix`` solves ``sum g g^T (q - x) = 0`` over the window;
    at an L- or Y-junction (a polyhedron corner, not a chessboard X) the
    blurred tip and the pixel grid bias it by ~0.1-0.2 px towards the inside
    of the corner, for every corner, which shrinks the apparent object. Here the
    gradient pixels outside a ``tip_px`` disc are grouped by their direction
    seen from ``q`` (the edges are rays from the corner), each group gives a
    line ``n . x = c`` (normal from the gradient structure tensor, offset from
    the ``|g|^2``-weighted centroid, which is the edge centre for a symmetric
    blur), and the lines are intersected in least squares.

    With three or more edges the one farthest from the intersection is dropped
    while it misses it by more than ``max_line_residual`` px; a result more than
    ``max_shift`` px from ``q`` (cornerSubPix's bias is a few tenths) is refused.

    Returns the refined point (2,) or None (fewer than two usable, non-parallel edges).

    One corner at a time through :func:`_refine_lines_batch` (a batch of one);
    ``tests/vespro/test_extraction.py`` keeps the plain NumPy formulation this
    was first written as, and checks against it.
    """
    p = _refine_lines_batch(img, np.asarray(q, dtype=float).reshape(1, 2), np.array([float(radius)]), tip_px,
                            min_edge_angle_deg, rel_grad, max_line_residual, max_shift)[0]
    return None if np.isnan(p[0]) else p


def _refine_lines_batch(img, q, radius, tip_px=2.0, min_edge_angle_deg=20.0, rel_grad=0.25, max_line_residual=0.6,
                        max_shift=1.0):
    """:func:`_refine_lines` for many corners of one image at once.

    Each corner is refined on its own (:func:`_refine_lines` is this with one
    corner), so the results do not depend on the other corners of the batch.

    Parameters
    ----------
    img : ndarray (H, W) uint8
    q : ndarray, shape (n, 2)
        Corners to refine, px.
    radius : ndarray, shape (n,)
        px.

    Returns
    -------
    ndarray, shape (n, 2)
        Refined corners; NaN where :func:`_refine_lines` gives None.
    """
    q = np.ascontiguousarray(q, dtype=float).reshape(-1, 2)
    radius = np.ascontiguousarray(radius, dtype=float).reshape(-1)
    # Compiled: the gradients (3x3 Sobel / 8 of a uint8 image: small integers, exact in
    # any order, so cv2.Sobel's values), the pixel selection, the grouping and the line
    # fits. The pixel directions use NumPy's arctan2 (SIMD: it may differ from libm's
    # in the last bit), so a direction on a bin boundary falls where it always did.
    wi, dxm, dym, gxm, gym, w, npx = _edge_pixels(np.ascontiguousarray(img), q, radius, float(tip_px * tip_px),
                                                  np.float32(rel_grad**2))
    theta = np.arctan2(dym, dxm)
    P, live, cnt, a_, b_, c_, sw, swx, swy = _edge_groups(theta, wi, dxm, dym, gxm, gym, w, npx, _NB)
    return _edge_lines_meet(q, live, cnt, a_, b_, c_, sw, swx, swy, math.cos(math.radians(min_edge_angle_deg)),
                            max_line_residual, max_shift)


@njit
def _window_candidate(ev, iy0, iy1, ix0, ix1, px0, py0, u32, v32, min_eig, rel_quality32, min_isotropy32,
                      ambiguity32, nms_radius):
    """The corner candidate of one window, from its ``cv2.cornerEigenValsAndVecs`` patch.

    Shi-Tomasi response ``min(lambda_1, lambda_2)``, non-maximum suppression over
    ``(2 nms_radius + 1)^2`` pixels of the patch (as ``cv2.dilate``, which ignores
    pixels outside), the absolute and relative thresholds and the isotropy test
    on ``inner = [iy0, iy1] x [ix0, ix1]``; then the candidate nearest to the
    prediction ``(u32, v32)`` (float32, as NumPy computes with the float32
    response), or AMBIGUOUS when a second one is similarly close.

    Returns ``(why, n_candidates, cx, cy)``; ``cx, cy`` (float32, image pixels)
    only when ``why`` is FOUND.
    """
    hp, wp = ev.shape[0], ev.shape[1]
    resp = np.empty((hp, wp), dtype=np.float32)
    for y in range(hp):
        for x in range(wp):
            resp[y, x] = min(ev[y, x, 0], ev[y, x, 1])
    best = resp[iy0, ix0]
    for y in range(iy0, iy1 + 1):
        for x in range(ix0, ix1 + 1):
            if resp[y, x] > best:
                best = resp[y, x]
    t_rel = rel_quality32 * best
    thr = t_rel if t_rel > min_eig else np.float32(min_eig)
    n = 0
    nmax = (iy1 - iy0 + 1) * (ix1 - ix0 + 1)
    cxs = np.empty(nmax, dtype=np.float32)
    cys = np.empty(nmax, dtype=np.float32)
    for y in range(iy0, iy1 + 1):
        for x in range(ix0, ix1 + 1):
            rv = resp[y, x]
            if not rv >= thr:
                continue
            peak = True
            for yy in range(max(y - nms_radius, 0), min(y + nms_radius, hp - 1) + 1):
                for xx in range(max(x - nms_radius, 0), min(x + nms_radius, wp - 1) + 1):
                    if resp[yy, xx] > rv:
                        peak = False
                        break
                if not peak:
                    break
            if not peak:
                continue
            # straight edges have a small but non-zero lambda_min: the tensor must be 2-D as well
            if not rv >= min_isotropy32 * max(ev[y, x, 0], ev[y, x, 1]):
                continue
            cxs[n] = np.float32(x + px0)
            cys[n] = np.float32(y + py0)
            n += 1
    if n == 0:
        return 3, 0, np.float32(0.0), np.float32(0.0)  # Why.NO_CORNER
    # nearest and second nearest, float32 distances as np.hypot gives them (ties: the first)
    j, d1, d2 = -1, np.float32(0.0), np.float32(0.0)
    for k in range(n):
        dx = np.float64(cxs[k] - u32)
        dy = np.float64(cys[k] - v32)
        d = np.float32(math.sqrt(dx * dx + dy * dy))
        if j < 0 or d < d1:
            if j >= 0:
                d2 = d1
            j, d1 = k, d
        elif k == 1 or d < d2:
            d2 = d
    if n > 1 and d1 > ambiguity32 * d2:
        return 4, n, np.float32(0.0), np.float32(0.0)  # Why.AMBIGUOUS
    return 0, n, cxs[j], cys[j]


@njit
def _window_candidates(buf, offs, geo, done, uv32, min_eig, rel_quality32, min_isotropy32, ambiguity32, nms_radius):
    """:func:`_window_candidate` of each window whose ``cv2.cornerEigenValsAndVecs`` patch
    is stored in ``buf[offs[n]:offs[n + 1]]`` (``done[n]``; ``geo``: its rows of
    :func:`_window_geometry`). Returns (why (N,) int8, n_candidates (N,), candidates (N, 2)
    float32, meaningful where why is FOUND)."""
    N = geo.shape[0]
    why = np.full(N, 6, dtype=np.int8)  # Why.INVALID where not done
    n_cand = np.zeros(N, dtype=np.int64)
    cxy = np.zeros((N, 2), dtype=np.float32)
    for n in range(N):
        if not done[n]:
            continue
        py0, py1, px0, px1 = geo[n, 1], geo[n, 2], geo[n, 3], geo[n, 4]
        ev = buf[offs[n] : offs[n + 1]].reshape((py1 - py0 + 1, px1 - px0 + 1, 6))
        code, k, cx, cy = _window_candidate(ev, geo[n, 5], geo[n, 6], geo[n, 7], geo[n, 8], px0, py0, uv32[n, 0],
                                            uv32[n, 1], min_eig, rel_quality32, min_isotropy32, ambiguity32, nms_radius)
        why[n] = code
        n_cand[n] = k
        cxy[n, 0] = cx
        cxy[n, 1] = cy
    return why, n_cand, cxy


@njit
def _edge_pixels(img, q, radius, tip2, rel_grad2_32):
    """Gradient pixels around each corner that :func:`_refine_lines` uses.

    Corner ``k`` at ``q[k]`` (px) looks at the ``(2 R + 1)^2`` pixels around the
    nearest pixel ``(u0, v0)`` (``R = ceil(radius[k])``; none when that square
    and its 1-pixel rim do not fit in the image). Gradients: the 3x3 Sobel / 8,
    float32. A pixel counts when outside the tip disc (``d^2 > tip2``), within
    the radius and with ``|g|^2`` above ``rel_grad^2`` times the square's
    largest (float32, as NumPy computes it).

    Returns, in the order of ``np.nonzero`` (corner, row, column): ``wi``
    (corner), ``dxm``, ``dym`` (offsets from ``q``), ``gxm``, ``gym`` (float64
    gradients), ``w = |g|^2`` (float64), and ``npx`` (m,) the count per corner.
    """
    H, W = img.shape
    m = q.shape[0]
    n_max = 0
    for k in range(m):
        Rk = int(math.ceil(radius[k]))
        n_max += (2 * Rk + 1) * (2 * Rk + 1)
    wi = np.empty(n_max, dtype=np.int64)
    dxm = np.empty(n_max)
    dym = np.empty(n_max)
    gxm = np.empty(n_max)
    gym = np.empty(n_max)
    w = np.empty(n_max)
    npx = np.zeros(m, dtype=np.int64)
    eight = np.float32(8.0)
    n = 0
    for k in range(m):
        R = int(math.ceil(radius[k]))
        u0, v0 = int(np.rint(q[k, 0])), int(np.rint(q[k, 1]))  # round half to even, as round()
        if u0 - R - 1 < 0 or v0 - R - 1 < 0 or u0 + R + 1 > W - 1 or v0 + R + 1 > H - 1:
            continue
        S = 2 * R + 1
        gx = np.empty((S, S), dtype=np.float32)
        gy = np.empty((S, S), dtype=np.float32)
        g2max = np.float32(-np.inf)
        for y in range(S):
            yy = v0 - R + y
            for x in range(S):
                xx = u0 - R + x
                a = np.int64(img[yy - 1, xx + 1]) - np.int64(img[yy - 1, xx - 1])
                b = np.int64(img[yy, xx + 1]) - np.int64(img[yy, xx - 1])
                c = np.int64(img[yy + 1, xx + 1]) - np.int64(img[yy + 1, xx - 1])
                gx[y, x] = np.float32(a + 2 * b + c) / eight
                a = np.int64(img[yy + 1, xx - 1]) - np.int64(img[yy - 1, xx - 1])
                b = np.int64(img[yy + 1, xx]) - np.int64(img[yy - 1, xx])
                c = np.int64(img[yy + 1, xx + 1]) - np.int64(img[yy - 1, xx + 1])
                gy[y, x] = np.float32(a + 2 * b + c) / eight
                g2 = gx[y, x] * gx[y, x] + gy[y, x] * gy[y, x]
                if g2 > g2max:
                    g2max = g2
        thr = rel_grad2_32 * g2max
        r2 = radius[k] * radius[k]
        for y in range(S):
            dy = np.float64(v0 - R + y) - q[k, 1]
            for x in range(S):
                dx = np.float64(u0 - R + x) - q[k, 0]
                d2 = dx * dx + dy * dy
                g2 = gx[y, x] * gx[y, x] + gy[y, x] * gy[y, x]
                if d2 > tip2 and d2 <= r2 and g2 > thr:
                    wi[n] = k
                    dxm[n] = dx
                    dym[n] = dy
                    a2 = np.float64(gx[y, x])
                    b2 = np.float64(gy[y, x])
                    gxm[n] = a2
                    gym[n] = b2
                    w[n] = a2 * a2 + b2 * b2
                    n += 1
                    npx[k] += 1
    return wi[:n], dxm[:n], dym[:n], gxm[:n], gym[:n], w[:n], npx


@njit
def _edge_groups(theta, wi, dxm, dym, gxm, gym, w, npx, nb):
    """Edge groups of each corner: direction histogram peaks, pixel labels and per-group sums.

    As the NumPy formulation of :func:`_refine_lines` (sums in pixel order, as
    ``np.bincount``; ``%`` on floats as ``np.remainder``). Returns ``P`` (most peaks
    of any corner), ``live`` (m,) and per (corner, group) (m, P): count, the
    structure tensor sums ``a``, ``b``, ``c``, the weight ``sw`` and the weighted
    offsets ``swx``, ``swy``.
    """
    m = npx.shape[0]
    n = theta.shape[0]
    pi = np.pi
    two_pi = 2 * np.pi
    scale = nb / (2 * np.pi)
    step = 2 * np.pi / nb
    hist = np.zeros((m, nb))
    for i in range(n):
        b = np.int64((theta[i] + pi) * scale) % nb
        hist[wi[i], b] += w[i]
    pk = np.zeros((m, nb), dtype=np.bool_)
    npk = np.zeros(m, dtype=np.int64)
    sm = np.empty(nb)
    for k in range(m):
        for b in range(nb):
            sm[b] = hist[k, b] + 0.5 * (hist[k, (b - 1) % nb] + hist[k, (b + 1) % nb])
        smax = sm[0]
        for b in range(1, nb):
            if sm[b] > smax:
                smax = sm[b]
        for b in range(nb):
            if sm[b] >= sm[(b - 1) % nb] and sm[b] > sm[(b + 1) % nb] and sm[b] > 0.15 * smax:
                pk[k, b] = True
                npk[k] += 1
    live = (npx >= 6) & (npk >= 2)
    P = 0
    for k in range(m):
        P = max(P, npk[k])
    cnt = np.zeros((m, P), dtype=np.int64)
    a_ = np.zeros((m, P))
    b_ = np.zeros((m, P))
    c_ = np.zeros((m, P))
    sw = np.zeros((m, P))
    swx = np.zeros((m, P))
    swy = np.zeros((m, P))
    if P < 2:
        return P, live, cnt, a_, b_, c_, sw, swx, swy
    centres = np.full((m, P), np.nan)
    for k in range(m):
        r = 0
        for b in range(nb):
            if pk[k, b]:
                centres[k, r] = (b + 0.5) * step - pi
                r += 1
    for i in range(n):
        k = wi[i]
        best, lab = np.inf, 0
        for p in range(P):
            a = theta[i] - centres[k, p] + pi
            # np.remainder(a, 2 pi), which is fmod then + 2 pi when negative; a lies in
            # [-pi, 3 pi], where fmod is a itself or (exactly, Sterbenz) a - 2 pi
            if a >= two_pi and a < 2.0 * two_pi:
                mod = a - two_pi
            elif a >= -two_pi and a < two_pi:
                mod = a + two_pi if a < 0.0 else a
            else:
                mod = np.fmod(a, two_pi)
                if mod < 0.0:
                    mod += two_pi
            d = abs(mod - pi)
            if math.isnan(d):
                d = np.inf
            if d < best:
                best, lab = d, p
        cnt[k, lab] += 1
        a_[k, lab] += gxm[i] * gxm[i]
        b_[k, lab] += gxm[i] * gym[i]
        c_[k, lab] += gym[i] * gym[i]
        sw[k, lab] += w[i]
        swx[k, lab] += w[i] * dxm[i]
        swy[k, lab] += w[i] * dym[i]
    return P, live, cnt, a_, b_, c_, sw, swx, swy


@njit
def _edge_lines_meet(q, live, cnt, a_, b_, c_, sw, swx, swy, cos_min, max_line_residual, max_shift):
    """Lines from the edge groups and their weighted least-squares meeting point, per corner.

    Per group: the normal ``n`` is the dominant eigenvector of the 2x2
    structure tensor ``[[a, b], [b, c]]`` and the offset ``n . (x - q)`` the
    ``|g|^2``-weighted mean; a group is a usable line when it has 3 or more
    pixels, is one-dimensional (``lambda_min <= 0.2 lambda_max``) and passes
    within 1.5 px of ``q``. Then, as :func:`_refine_lines` describes: no two
    lines more parallel than ``cos_min`` allows; solve; while more than two
    lines remain and one misses the point by more than ``max_line_residual``
    px, drop the farthest; refuse a shift beyond ``max_shift`` px.

    Returns (m, 2): ``q + p``, NaN where refused.
    """
    m, P = cnt.shape
    out = np.full((m, 2), np.nan)
    nx = np.empty(P)
    ny = np.empty(P)
    cr = np.empty(P)
    wt = np.empty(P)
    res = np.empty(P)
    for k in range(m):
        if not live[k]:
            continue
        L = 0
        for g in range(P):
            a, b, c = a_[k, g], b_[k, g], c_[k, g]
            half_tr = 0.5 * (a + c)
            disc = math.hypot(0.5 * (a - c), b)
            ev0, ev1 = half_tr - disc, half_tr + disc
            phi = 0.5 * math.atan2(2.0 * b, a - c)
            cx, cy = math.cos(phi), math.sin(phi)
            c_rel = (cx * swx[k, g] + cy * swy[k, g]) / sw[k, g]
            if cnt[k, g] >= 3 and ev1 > 0 and ev0 <= 0.2 * ev1 and abs(c_rel) <= 1.5:
                nx[L], ny[L], cr[L], wt[L] = cx, cy, c_rel, sw[k, g]
                L += 1
        while L >= 2:
            gmin = np.inf
            for i in range(L):
                for j in range(i + 1, L):
                    gmin = min(gmin, abs(nx[i] * nx[j] + ny[i] * ny[j]))
            if gmin > cos_min:  # all edges nearly parallel
                break
            A00 = A01 = A11 = r0 = r1 = 0.0
            for i in range(L):
                A00 += wt[i] * nx[i] * nx[i]
                A01 += wt[i] * nx[i] * ny[i]
                A11 += wt[i] * ny[i] * ny[i]
                r0 += wt[i] * nx[i] * cr[i]
                r1 += wt[i] * ny[i] * cr[i]
            det = A00 * A11 - A01 * A01
            p0 = (A11 * r0 - A01 * r1) / det
            p1 = (A00 * r1 - A01 * r0) / det
            worst = 0
            for i in range(L):
                res[i] = abs(nx[i] * p0 + ny[i] * p1 - cr[i])
                if res[i] > res[worst]:
                    worst = i
            # three or more edges must meet in one point; drop the one that does not
            if L > 2 and res[worst] > max_line_residual:
                for i in range(worst, L - 1):
                    nx[i], ny[i], cr[i], wt[i] = nx[i + 1], ny[i + 1], cr[i + 1], wt[i + 1]
                L -= 1
                continue
            if math.isfinite(p0) and math.isfinite(p1) and not math.hypot(p0, p1) > max_shift:
                out[k, 0] = q[k, 0] + p0
                out[k, 1] = q[k, 1] + p1
            break
    return out


@njit
def _grey_region(uv, r_all, margin):
    """Box around the searchable windows (finite prediction, half-size >= 1): their
    predictions' box grown by ``margin`` plus the largest half-size, as floats
    ``(x0, y0, x1, y1)``; NaN when there is none."""
    lo_x = lo_y = hi_x = hi_y = r_max = np.nan
    for i in range(uv.shape[0]):
        u, v, r = uv[i, 0], uv[i, 1], r_all[i]
        if not (math.isfinite(u) and math.isfinite(v) and math.isfinite(r) and r >= 1):
            continue
        if math.isnan(lo_x):
            lo_x, lo_y, hi_x, hi_y, r_max = u, v, u, v, r
        else:
            lo_x, lo_y, hi_x, hi_y, r_max = min(lo_x, u), min(lo_y, v), max(hi_x, u), max(hi_y, v), max(r_max, r)
    m = margin + r_max
    return lo_x - m, lo_y - m, hi_x + m, hi_y + m


@njit
def _window_geometry(uv, r_all, W, H, pad):
    """Search windows of all features, as integer pixel bounds.

    Row ``i``: ``(code, py0, py1, px0, px1, iy0, iy1, ix0, ix1)``: code -1 for a
    non-finite prediction or size below 1 (left INVALID), OUTSIDE, or FOUND (0)
    for a window to search; the patch ``[py0, py1] x [px0, px1]`` (the window
    plus ``pad``, clipped to the image) and, in patch coordinates, the window
    proper away from the image's outer two pixels. Also the half-sizes rounded
    half to even (as Python's ``round``), as floats (m,).
    """
    K = uv.shape[0]
    geo = np.full((K, 9), -1, dtype=np.int64)
    r_int = np.zeros(K)
    for i in range(K):
        u, v, r = uv[i, 0], uv[i, 1], r_all[i]
        if not (math.isfinite(u) and math.isfinite(v) and math.isfinite(r) and r >= 1):
            continue
        r = np.rint(r)
        r_int[i] = r
        # in floats until known to lie in the image (no integer overflow on wild input)
        wx0, wx1 = max(np.floor(u - r), 0.0), min(np.ceil(u + r), W - 1.0)
        wy0, wy1 = max(np.floor(v - r), 0.0), min(np.ceil(v + r), H - 1.0)
        if wx1 - wx0 < 4 or wy1 - wy0 < 4:
            geo[i, 0] = 2  # Why.OUTSIDE
            continue
        px0, px1 = max(int(wx0) - pad, 0), min(int(wx1) + pad, W - 1)
        py0, py1 = max(int(wy0) - pad, 0), min(int(wy1) + pad, H - 1)
        ix0, ix1 = max(int(wx0), 2) - px0, min(int(wx1), W - 3) - px0
        iy0, iy1 = max(int(wy0), 2) - py0, min(int(wy1), H - 3) - py0
        if ix1 < ix0 or iy1 < iy0:
            geo[i, 0] = 2  # Why.OUTSIDE
            continue
        geo[i, 0] = 0
        geo[i, 1], geo[i, 2], geo[i, 3], geo[i, 4] = py0, py1, px0, px1
        geo[i, 5], geo[i, 6], geo[i, 7], geo[i, 8] = iy0, iy1, ix0, ix1
    return geo, r_int


@njit
def _window_plan(geo, why):
    """The windows to search (code FOUND in :func:`_window_geometry`'s ``geo``): their
    indices, their rows of ``geo`` and the offsets of their tensor patches in one buffer
    (6 floats a pixel), (n,), (n, 9), (n + 1,); ``why`` set to OUTSIDE where ``geo`` says so
    (in place)."""
    K = geo.shape[0]
    n = 0
    for i in range(K):
        if geo[i, 0] == _OUTSIDE:
            why[i] = _OUTSIDE
        elif geo[i, 0] == _FOUND:
            n += 1
    go = np.empty(n, np.int64)
    geo_go = np.empty((n, 9), np.int64)
    offs = np.zeros(n + 1, np.int64)
    m = 0
    for i in range(K):
        if geo[i, 0] == _FOUND:
            go[m] = i
            geo_go[m] = geo[i]
            offs[m + 1] = offs[m] + (geo[i, 2] - geo[i, 1] + 1) * (geo[i, 4] - geo[i, 3] + 1) * 6
            m += 1
    return go, geo_go, offs


@njit
def _take_candidates(go, done, code, n_cand, ncand, why):
    """The windows' candidate searches (:func:`_window_candidates`, windows ``go``) into the
    features' ``ncand`` and ``why`` (in place) where done; which windows found one (bool)."""
    hit = np.zeros(go.shape[0], np.bool_)
    for n in range(go.shape[0]):
        if done[n]:
            ncand[go[n]] = n_cand[n]
            why[go[n]] = code[n]
            hit[n] = code[n] == _FOUND
    return hit


@njit
def _subpix_ok(ref, c0, uv, r, max_shift):
    """Sub-pixel results to keep: finite, moved at most ``max_shift`` px from the
    candidate ``c0`` (float32) and inside the window ``|ref - uv| <= r``; (n,) bool."""
    n = ref.shape[0]
    ok = np.zeros(n, dtype=np.bool_)
    for j in range(n):
        rx, ry = ref[j, 0], ref[j, 1]
        if not (math.isfinite(rx) and math.isfinite(ry)):
            continue
        if math.hypot(rx - np.float64(c0[j, 0]), ry - np.float64(c0[j, 1])) > max_shift:
            continue
        if abs(rx - uv[j, 0]) > r[j] or abs(ry - uv[j, 1]) > r[j]:
            continue
        ok[j] = True
    return ok


@njit
def _take_refined(uv_out, ii, P, uv, r):
    """Edge-line refinements that are finite and inside their window replace the
    sub-pixel corners ``uv_out[ii]`` (in place)."""
    for j in range(ii.shape[0]):
        i = ii[j]
        px, py = P[j, 0], P[j, 1]
        if math.isfinite(px) and math.isfinite(py) and abs(px - uv[i, 0]) <= r[i] and abs(py - uv[i, 1]) <= r[i]:
            uv_out[i, 0] = px
            uv_out[i, 1] = py


@njit
def _mark_shared(uv_out, why, shared_px):
    """Found corners closer than ``shared_px`` to another found corner become SHARED (in place)."""
    K = why.shape[0]
    clash = np.zeros(K, dtype=np.bool_)
    for i in range(K):
        if why[i] != 0:
            continue
        for j in range(K):
            if j != i and why[j] == 0 and math.hypot(uv_out[i, 0] - uv_out[j, 0], uv_out[i, 1] - uv_out[j, 1]) < shared_px:
                clash[i] = True
                break
    for i in range(K):
        if clash[i]:
            why[i] = 5  # Why.SHARED
            uv_out[i, 0] = np.nan
            uv_out[i, 1] = np.nan


#: Direction bins of :func:`_refine_lines` and each bin's circular neighbours.
_NB = 36
_PREV = np.r_[_NB - 1, np.arange(_NB - 1)]
_NEXT = np.r_[np.arange(1, _NB), 0]


#: Colour images are converted to grey only within this margin (px) around the
#: search windows: every read of the extractor (structure tensor, cornerSubPix,
#: edge refinement) stays well inside it.
GREY_MARGIN_PX = 32


def _as_grey(image, region=None):
    """uint8 grey image of the same size, or None.

    ``region`` ``(x0, y0, x1, y1)`` (inclusive pixels), optional: a colour
    image is converted only there (zeros elsewhere).
    """
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
        if region is None:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        else:
            H, W = img.shape[:2]
            x0, y0 = max(int(region[0]), 0), max(int(region[1]), 0)
            x1, y1 = min(int(region[2]), W - 1), min(int(region[3]), H - 1)
            grey = np.zeros((H, W), np.uint8)
            if x1 >= x0 and y1 >= y0:  # converted straight into the region
                cv2.cvtColor(img[y0 : y1 + 1, x0 : x1 + 1], cv2.COLOR_BGR2GRAY, dst=grey[y0 : y1 + 1, x0 : x1 + 1])
            img = grey
    if img.ndim != 2 or min(img.shape) < 8:
        return None
    return np.ascontiguousarray(img)


def extract_corners(
    image,
    uv_pred,
    half_size,
    *,
    min_eig: float = 2e-4,
    min_isotropy: float = 0.03,
    rel_quality: float = 0.2,
    block_size: int = 3,
    nms_radius: int = 2,
    subpix_half: int = 4,
    ambiguity_ratio: float = 0.6,
    max_subpix_shift: float = 4.0,
    shared_px: float = 1.0,
    refine_lines: bool = True,
    line_radius: float = 7.0,
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
    min_isotropy : float
        ``lambda_min / lambda_max`` of the structure tensor must reach this:
        0.07 at a 150 deg corner, 0.03 at 160 deg, ~0.004 on the staircase of
        a rasterised straight edge with 190 grey levels of contrast.
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
    refine_lines : bool
        After ``cornerSubPix``, intersect the edges leaving the corner
        (:func:`_refine_lines`), which removes most of cornerSubPix's tip bias at
        L/Y junctions (synthetic polyhedron faces: median error 0.22 -> 0.11 px,
        90 % 0.38 -> 0.22 px); falls back to the cornerSubPix point when fewer
        than two clean edges are found within ``line_radius``.
    line_radius : float
        px, clamped to the search window half-size + 2.

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
        r_all = np.asarray(half_size, dtype=float)
        if r_all.shape != (K,):  # (broadcast_to costs more than a frame's other checks)
            r_all = np.broadcast_to(r_all, (K,))
    except Exception:  # noqa: BLE001
        return ExtractionResult(uv_out, np.zeros(K, bool), why, ncand)

    uv_pred = np.ascontiguousarray(uv_pred)
    r_all = np.ascontiguousarray(r_all, dtype=float)
    lo_x, lo_y, hi_x, hi_y = _grey_region(uv_pred, r_all, float(GREY_MARGIN_PX))
    region = None if math.isnan(lo_x) else (math.floor(lo_x), math.floor(lo_y), math.ceil(hi_x), math.ceil(hi_y))
    img = _as_grey(image, region)
    if img is None:
        why[:] = Why.NO_IMAGE
        return ExtractionResult(uv_out, np.zeros(K, bool), why, ncand)
    H, W = img.shape
    pad = block_size // 2 + 2  # Sobel (1) + block support, so the response is valid at the window edge
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 40, 0.001)

    # Window bounds of every feature at once; then one OpenCV structure-tensor call and
    # one compiled candidate search per window (a patch of its own: the response at the
    # window's edge depends on the patch border, so patches are not merged).
    geo, r_int = _window_geometry(uv_pred, r_all, W, H, pad)
    # The windows' tensors side by side in one buffer (OpenCV writes each into its place),
    # then the candidate search of all windows in one compiled call.
    go, geo_go, offs = _window_plan(geo, why)
    uv32 = uv_pred[go].astype(np.float32)  # NumPy 2 computes with the float32 response in float32
    params = (float(min_eig), np.float32(rel_quality), np.float32(min_isotropy), np.float32(ambiguity_ratio),
              int(nms_radius))
    patches = geo_go[:, 1:5].tolist()
    at = offs.tolist()
    buf = np.empty(at[-1], np.float32)
    done = np.ones(go.size, np.bool_)
    for n, (py0, py1, px0, px1) in enumerate(patches):
        try:
            cv2.cornerEigenValsAndVecs(img[py0 : py1 + 1, px0 : px1 + 1], block_size, ksize=3,
                                       dst=buf[at[n] : at[n + 1]].reshape(py1 - py0 + 1, px1 - px0 + 1, 6))
        except cv2.error:
            why[go[n]] = Why.INVALID
            done[n] = False
    code, n_cand, c0 = _window_candidates(buf, offs, geo_go, done, uv32, *params)
    hit = _take_candidates(go, done, code, n_cand, ncand, why)
    if not hit.any():
        return ExtractionResult(uv_out, why == Why.FOUND, why, ncand)

    # Sub-pixel refinement, all corners of one sub-window size in one call (OpenCV refines
    # each point on its own: the same result as one call per corner).
    picked = go[hit]
    c0 = c0[hit].reshape(-1, 1, 2)
    ref = np.full((len(picked), 2), np.nan)
    sh_all = np.maximum(2, np.minimum(subpix_half, r_int[picked])).astype(int)
    for sh in sorted(set(sh_all.tolist())):
        rows = np.flatnonzero(sh_all == sh)
        try:
            ref[rows] = cv2.cornerSubPix(img, c0[rows].copy(), (sh, sh), (-1, -1), crit).reshape(-1, 2)
        except cv2.error:
            for j in rows:  # one by one, so that a failing corner does not take the others along
                try:
                    ref[j] = cv2.cornerSubPix(img, c0[j : j + 1].copy(), (sh, sh), (-1, -1), crit).reshape(2)
                except cv2.error:
                    pass
    ok = _subpix_ok(ref, c0.reshape(-1, 2), uv_pred[picked], r_int[picked], float(max_subpix_shift))
    why[picked[~ok]] = Why.NO_CORNER
    ii = picked[ok]
    uv_out[ii] = ref[ok]
    why[ii] = Why.FOUND
    if refine_lines and ii.size:
        # all windows at once (same results as one _refine_lines call per window)
        try:
            P = _refine_lines_batch(img, uv_out[ii], np.minimum(line_radius, r_int[ii] + 2.0))
        except (cv2.error, ValueError, IndexError, TypeError):
            P = np.full((len(ii), 2), np.nan)
        _take_refined(uv_out, ii, P, uv_pred, r_int)
    _mark_shared(uv_out, why, float(shared_px))
    found = why == _FOUND
    return ExtractionResult(uv_out, found, why, ncand)
