"""Choice of the corners to measure, per camera, among the visible candidates.

Two selectors on the same plain-array inputs (what the visibility module gives
per camera and frame, plus the projection Jacobians of :mod:`vespro.projection`):

- :func:`select_quality`: the classic quality-index selection in the spirit of
  Lippiello, Siciliano and Villani (image spread, angular spread around the
  centroid, per-feature reliability from border / silhouette distance and
  viewing angle), maximised greedily.
- :func:`select_information`: greedy maximisation of the log-determinant of the
  6x6 pose information ``P6^-1 + sum_i J_i^T R^-1 J_i`` (D-optimal design). With
  the filter's current ``P6`` it picks the corners that shrink the current
  uncertainty most. :func:`select_information_joint` does the same across all
  cameras at once (each pick accounts for what the other cameras already give).

Both return indices into the candidate arrays, in the order picked, distinct,
deterministic (ties go to the lowest index), and only among *eligible*
candidates (:func:`eligible_mask`: finite, at least ``border_px`` inside the
image, viewing angle below ``max_view_angle``). Fewer than ``k`` eligible
candidates: all of them are returned.
"""

from __future__ import annotations

import math

import numpy as np

from .jit import njit

__all__ = [
    "eligible_mask",
    "feature_weights",
    "quality_index",
    "select_quality",
    "select_information",
    "select_information_joint",
    "pose_information_logdet",
    "window_clearance",
]

DEFAULT_K = 8
DEFAULT_BORDER_PX = 8.0
DEFAULT_MAX_VIEW_ANGLE = np.deg2rad(80.0)
#: Silhouette distance (px) beyond which a corner counts as fully interior.
DEFAULT_SIL_REF_PX = 10.0
#: Prior information used when no P6 is given (m^-2 / rad^-2): weak enough to
#: be negligible, strong enough to keep the first picks' log-determinant finite.
WEAK_PRIOR_INFO = 1e-6


def _check(uv, n_name="uv"):
    uv = np.asarray(uv, dtype=float)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"{n_name}: expected shape (N, 2), got {uv.shape}")
    return uv


def _vec(a, n, name, default):
    if a is None:
        return np.full(n, default, dtype=float)
    a = np.asarray(a, dtype=float)
    if a.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {a.shape}")
    return a


def eligible_mask(uv, image_size, border_px=DEFAULT_BORDER_PX, view_angle=None, max_view_angle=DEFAULT_MAX_VIEW_ANGLE, J=None, min_separation_px=0.0):
    """Candidates that may be selected.

    Parameters
    ----------
    uv : ndarray, shape (N, 2)
        Predicted pixels.
    image_size : (width, height)
        Pixels.
    border_px : float
        Minimum distance to the image border (the search window must fit).
    view_angle : ndarray (N,), optional
        Angle (rad) between line of sight and surface normal.
    max_view_angle : float
        rad; grazing corners are unreliable.
    J : ndarray (N, 2, 6), optional
        Rows with non-finite Jacobians are excluded.
    min_separation_px : float
        Exclude corners with another candidate closer than this (px): the
        extractor cannot tell them apart (ambiguous / shared corner). 0: off.

    Returns
    -------
    ndarray, shape (N,), bool
    """
    uv = _check(uv)
    w, h = image_size
    ok = np.all(np.isfinite(uv), axis=1)
    with np.errstate(invalid="ignore"):
        ok &= (uv[:, 0] >= border_px) & (uv[:, 0] <= w - 1 - border_px)
        ok &= (uv[:, 1] >= border_px) & (uv[:, 1] <= h - 1 - border_px)
        if view_angle is not None:
            va = np.asarray(view_angle, dtype=float)
            ok &= np.isfinite(va) & (va < max_view_angle)
    if J is not None:
        ok &= np.all(np.isfinite(np.asarray(J)), axis=(1, 2))
    if min_separation_px > 0 and len(uv) > 1:
        with np.errstate(invalid="ignore"):
            d = np.hypot(uv[:, None, 0] - uv[None, :, 0], uv[:, None, 1] - uv[None, :, 1])
            np.fill_diagonal(d, np.inf)
            ok &= ~np.any(d < min_separation_px, axis=1)
    return ok


def feature_weights(uv, view_angle, silhouette_px, image_size, border_px=DEFAULT_BORDER_PX, sil_ref_px=DEFAULT_SIL_REF_PX, max_view_angle=DEFAULT_MAX_VIEW_ANGLE, min_separation_px=0.0):
    """Per-corner reliability in [0, 1] (0 for ineligible corners).

    Product of a viewing-angle term ``cos(angle)`` rescaled to reach 0 at
    ``max_view_angle``, a silhouette term (silhouette corners see the
    background and can be occluded by clutter: 0.5 at the silhouette, 1 beyond
    ``sil_ref_px``) and a border term (ramps from 0.5 at ``border_px`` to 1 at
    ``3 border_px``).
    """
    uv = _check(uv)
    n = len(uv)
    va = _vec(view_angle, n, "view_angle", 0.0)
    sil = _vec(silhouette_px, n, "silhouette_px", sil_ref_px)
    w, h = image_size
    el = eligible_mask(uv, image_size, border_px, va, max_view_angle, min_separation_px=min_separation_px)
    cmin = np.cos(max_view_angle)
    with np.errstate(invalid="ignore"):
        t_view = np.clip((np.cos(va) - cmin) / (1.0 - cmin), 0.0, 1.0)
        t_sil = 0.5 + 0.5 * np.clip(sil / sil_ref_px, 0.0, 1.0)
        d_border = np.minimum.reduce([uv[:, 0], uv[:, 1], w - 1 - uv[:, 0], h - 1 - uv[:, 1]])
        t_border = 0.5 + 0.5 * np.clip((d_border - border_px) / (2.0 * border_px), 0.0, 1.0)
    wts = t_view * t_sil * t_border
    # each factor is clipped into [0, 1] or NaN, so NaN is the only non-finite value
    wts[~el | np.isnan(wts)] = 0.0
    return wts


def quality_index(uv_sel, w_sel, image_size) -> float:
    """Quality index of a selected set (higher is better), in [0, 1].

    ``Q = mean(w) * Q_spatial * Q_angular``:

    - ``Q_spatial``: RMS distance of the points from their centroid divided
      by half the image diagonal (its largest possible value; spread-out
      points condition the pose better and average image-space errors);
    - ``Q_angular``: ``1 - (g_max - 2 pi/n) / (2 pi - 2 pi/n)`` with ``g_max`` the
      largest angular gap between consecutive points around the centroid (1 for
      evenly surrounding points, 0 when all lie on one ray); 1 for n < 3.
    """
    uv_sel = np.asarray(uv_sel, dtype=float).reshape(-1, 2)
    w_sel = np.asarray(w_sel, dtype=float).reshape(-1)
    n = len(uv_sel)
    if n == 0:
        return 0.0
    wdt, hgt = image_size
    c = uv_sel.mean(axis=0)
    d = uv_sel - c
    q_s = min(1.0, float(np.sqrt(np.mean(np.sum(d * d, axis=1)))) / (0.5 * np.hypot(wdt, hgt)))
    if n < 3:
        q_a = 1.0
    else:
        a = np.sort(np.arctan2(d[:, 1], d[:, 0]))
        gaps = np.diff(np.r_[a, a[0] + 2.0 * np.pi])
        even = 2.0 * np.pi / n
        q_a = 1.0 - (gaps.max() - even) / (2.0 * np.pi - even)
    return float(np.mean(w_sel) * q_s * q_a)


def select_quality(
    uv,
    view_angle,
    silhouette_px,
    image_size,
    k: int = DEFAULT_K,
    border_px: float = DEFAULT_BORDER_PX,
    max_view_angle: float = DEFAULT_MAX_VIEW_ANGLE,
    sil_ref_px: float = DEFAULT_SIL_REF_PX,
    min_separation_px: float = 0.0,
) -> np.ndarray:
    """Greedy quality-index selection of up to ``k`` corners of one camera.

    Parameters
    ----------
    uv : ndarray, shape (N, 2)
        Predicted pixels of the visible candidates.
    view_angle : ndarray, shape (N,)
        rad.
    silhouette_px : ndarray, shape (N,)
        Pixel distance to the object's silhouette.
    image_size : (width, height)
    k : int
    border_px, max_view_angle, sil_ref_px, min_separation_px : see :func:`eligible_mask`, :func:`feature_weights`.

    Returns
    -------
    ndarray, shape (min(k, n_eligible),), intp
        Indices into the candidates, in the order picked.

    Notes
    -----
    Starts from the most reliable corner (ties: farthest from the candidates'
    centroid), then adds the corner that maximises :func:`quality_index` of the
    enlarged set. O(N k) index evaluations.
    """
    uv = _check(uv)
    n = len(uv)
    va = _vec(view_angle, n, "view_angle", 0.0)
    sil = _vec(silhouette_px, n, "silhouette_px", sil_ref_px)
    wdt, hgt = image_size
    w = _weights_kernel(np.ascontiguousarray(uv), np.ascontiguousarray(va), np.ascontiguousarray(sil), int(wdt), int(hgt),
                        float(border_px), float(sil_ref_px), float(max_view_angle), float(np.cos(max_view_angle)),
                        float(min_separation_px))
    return _greedy_quality_kernel(np.ascontiguousarray(uv), w, int(k), float(0.5 * np.hypot(wdt, hgt))).astype(np.intp)


@njit
def _weights_kernel(uv, va, sil, wdt, hgt, border_px, sil_ref_px, max_view_angle, cmin, min_separation_px):
    """:func:`feature_weights` (with its :func:`eligible_mask`), compiled; the same arithmetic, (N,)."""
    n = uv.shape[0]
    w = np.zeros(n)
    for i in range(n):
        u, v = uv[i, 0], uv[i, 1]
        if not (math.isfinite(u) and math.isfinite(v)):
            continue
        if not (u >= border_px and u <= wdt - 1 - border_px and v >= border_px and v <= hgt - 1 - border_px):
            continue
        if not (math.isfinite(va[i]) and va[i] < max_view_angle):
            continue
        if min_separation_px > 0 and n > 1:
            near = False
            for j in range(n):
                if j != i and math.hypot(u - uv[j, 0], v - uv[j, 1]) < min_separation_px:
                    near = True
                    break
            if near:
                continue
        t_view = min(max((math.cos(va[i]) - cmin) / (1.0 - cmin), 0.0), 1.0)
        t_sil = sil[i] / sil_ref_px
        if not math.isnan(t_sil):
            t_sil = min(max(t_sil, 0.0), 1.0)
        t_sil = 0.5 + 0.5 * t_sil
        d_border = min(min(min(u, v), wdt - 1 - u), hgt - 1 - v)
        t_border = 0.5 + 0.5 * min(max((d_border - border_px) / (2.0 * border_px), 0.0), 1.0)
        wi = t_view * t_sil * t_border
        if not math.isnan(wi):
            w[i] = wi
    return w


@njit
def _np_sum(a, n):
    """Sum of ``a[:n]`` in NumPy's order (pairwise summation, as ``np.sum`` of a contiguous row)."""
    if n < 8:
        res = -0.0
        for i in range(n):
            res += a[i]
        return res
    if n <= 128:
        r0, r1, r2, r3 = a[0], a[1], a[2], a[3]
        r4, r5, r6, r7 = a[4], a[5], a[6], a[7]
        i = 8
        while i < n - (n % 8):
            r0 += a[i]
            r1 += a[i + 1]
            r2 += a[i + 2]
            r3 += a[i + 3]
            r4 += a[i + 4]
            r5 += a[i + 5]
            r6 += a[i + 6]
            r7 += a[i + 7]
            i += 8
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        while i < n:
            res += a[i]
            i += 1
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _np_sum(a, n2) + _np_sum(a[n2:], n - n2)


def window_clearance(uv, half) -> np.ndarray:
    """How far each point's nearest other point lies outside its search window, px.

    ``sqrt(min_j |uv_i - uv_j|^2) - (half_i + 2)`` for points ``uv`` (N, 2) and window
    half-sizes ``half`` (N,): positive when no other predicted corner falls in the window
    (with 2 px to spare); ``inf`` for a lone point, NaN where a distance is NaN. One
    compiled pass; ``tests/vespro/test_selection.py`` checks it bit for bit against the
    NumPy formulation (pairwise differences, ``einsum``, ``min``).
    """
    return _clearance_kernel(np.ascontiguousarray(uv, dtype=float), np.ascontiguousarray(half, dtype=float))


@njit
def _clearance_kernel(uv, half):
    n = uv.shape[0]
    out = np.empty(n)
    for i in range(n):
        best = np.inf
        for j in range(n):
            if j == i:
                continue
            dx = uv[i, 0] - uv[j, 0]
            dy = uv[i, 1] - uv[j, 1]
            d2 = dx * dx + dy * dy
            if math.isnan(d2):  # NumPy's min propagates NaN
                best = d2
                break
            if d2 < best:
                best = d2
        out[i] = math.sqrt(best) - (half[i] + 2.0)
    return out


@njit
def _greedy_quality_kernel(uv, w, k, half_diag):
    """Compiled greedy selection of :func:`select_quality` from the weights ``w`` (N,).

    The eligible candidates are those with ``w > 0``; with at most ``k`` of them, all,
    by decreasing weight (stable). Otherwise the first pick is the most reliable (ties:
    the farthest from their centroid, then the earliest), and each step adds the
    candidate that maximises :func:`quality_index` of the enlarged set (ties: the
    earliest). Scores are computed as :func:`_quality_index_batch` computes them (same
    operations and summation order), one candidate at a time.
    """
    two_pi = 2.0 * np.pi
    n_all = w.shape[0]
    el = np.empty(n_all, dtype=np.int64)
    m = 0
    for i in range(n_all):
        if w[i] > 0.0:
            el[m] = i
            m += 1
    if m <= k:
        out = el[:m].copy()
        for i in range(1, m):  # stable insertion sort by decreasing weight
            e = out[i]
            j = i - 1
            while j >= 0 and w[out[j]] < w[e]:
                out[j + 1] = out[j]
                j -= 1
            out[j + 1] = e
        return out
    # centroid (NumPy's axis-0 mean adds row after row) and distances to it
    sx, sy = 0.0, 0.0
    for i in range(m):
        sx += uv[el[i], 0]
        sy += uv[el[i], 1]
    cx, cy = sx / m, sy / m
    first, bw, bd = -1, 0.0, 0.0
    for i in range(m):
        dx, dy = uv[el[i], 0] - cx, uv[el[i], 1] - cy
        d = math.sqrt(dx * dx + dy * dy)
        if first < 0 or w[el[i]] > bw or (w[el[i]] == bw and d > bd):
            first, bw, bd = el[i], w[el[i]], d
    chosen = np.empty(k, dtype=np.int64)
    chosen[0] = first
    nc = 1
    rem = np.empty(m - 1, dtype=np.int64)
    nr = 0
    for i in range(m):
        if el[i] != first:
            rem[nr] = el[i]
            nr += 1
    X = np.empty(k)
    Y = np.empty(k)
    sq = np.empty(k)
    ang = np.empty(k)
    ws = np.empty(k)
    while nc < k:
        n = nc + 1
        sx, sy = 0.0, 0.0
        for i in range(nc):
            X[i] = uv[chosen[i], 0]
            Y[i] = uv[chosen[i], 1]
            ws[i] = w[chosen[i]]
            sx, sy = sx + X[i], sy + Y[i]
        w_sum = _np_sum(ws, nc)
        even = two_pi / n
        best, best_j = -np.inf, -1
        for j in range(nr):
            c = rem[j]
            X[nc] = uv[c, 0]
            Y[nc] = uv[c, 1]
            mx = (sx + uv[c, 0]) / n
            my = (sy + uv[c, 1]) / n
            for i in range(n):
                dx = X[i] - mx
                dy = Y[i] - my
                sq[i] = dx * dx + dy * dy
                ang[i] = math.atan2(dy, dx)
            q_s = min(1.0, math.sqrt(_np_sum(sq, n) / n) / half_diag)
            if n < 3:
                q_a = 1.0
            else:
                for i in range(1, n):  # insertion sort: a handful of angles
                    v = ang[i]
                    m = i - 1
                    while m >= 0 and ang[m] > v:
                        ang[m + 1] = ang[m]
                        m -= 1
                    ang[m + 1] = v
                gmax = (ang[0] + two_pi) - ang[n - 1]
                g_in = ang[1] - ang[0]
                for i in range(2, n):
                    g_in = max(g_in, ang[i] - ang[i - 1])
                gmax = max(g_in, gmax)
                q_a = 1.0 - (gmax - even) / (two_pi - even)
            score = (w_sum + w[c]) / n * q_s * q_a
            if score > best or best_j < 0:
                best, best_j = score, j
        chosen[nc] = rem[best_j]
        nc += 1
        for j in range(best_j, nr - 1):
            rem[j] = rem[j + 1]
        nr -= 1
    return chosen


def _quality_index_batch(uv_S, w_S, uv_c, w_c, image_size) -> np.ndarray:
    """:func:`quality_index` of ``S + {j}`` for every candidate j at once, shape (M,).

    Works on x and y separately ((M, n) arrays), with fewer temporaries than
    the plain formulation (:func:`_quality_index_batch_plain`); the scores
    agree to rounding (a few 1e-16 relative; the plain one's own last bit
    depends on how NumPy's SIMD reductions meet the memory layout).
    """
    n = len(uv_S) + 1
    M = len(uv_c)
    wdt, hgt = image_size
    X = np.empty((M, n))
    Y = np.empty((M, n))
    X[:, :-1] = uv_S[:, 0]
    Y[:, :-1] = uv_S[:, 1]
    X[:, -1] = uv_c[:, 0]
    Y[:, -1] = uv_c[:, 1]
    sx, sy = 0.0, 0.0
    for px, py in uv_S.tolist():
        sx, sy = sx + px, sy + py
    dx = X - ((sx + uv_c[:, 0]) / n)[:, None]
    dy = Y - ((sy + uv_c[:, 1]) / n)[:, None]
    q_s = np.minimum(1.0, np.sqrt(np.mean(dx * dx + dy * dy, axis=1)) / (0.5 * np.hypot(wdt, hgt)))
    if n < 3:
        q_a = np.ones(M)
    else:
        a = np.sort(np.arctan2(dy, dx), axis=1)
        gmax = np.maximum((a[:, 1:] - a[:, :-1]).max(axis=1), (a[:, 0] + 2.0 * np.pi) - a[:, -1])
        even = 2.0 * np.pi / n
        q_a = 1.0 - (gmax - even) / (2.0 * np.pi - even)
    w_mean = (np.sum(w_S) + w_c) / n
    return w_mean * q_s * q_a


def _quality_index_batch_plain(uv_S, w_S, uv_c, w_c, image_size) -> np.ndarray:
    """Reference formulation of :func:`_quality_index_batch` (an (M, n, 2) stack)."""
    n = len(uv_S) + 1
    wdt, hgt = image_size
    sets = np.concatenate([np.broadcast_to(uv_S, (len(uv_c),) + uv_S.shape), uv_c[:, None, :]], axis=1)  # (M, n, 2)
    c = sets.mean(axis=1, keepdims=True)
    d = sets - c
    q_s = np.minimum(1.0, np.sqrt(np.mean(np.sum(d * d, axis=2), axis=1)) / (0.5 * np.hypot(wdt, hgt)))
    if n < 3:
        q_a = np.ones(len(uv_c))
    else:
        a = np.sort(np.arctan2(d[:, :, 1], d[:, :, 0]), axis=1)
        gaps = np.diff(np.concatenate([a, a[:, :1] + 2.0 * np.pi], axis=1), axis=1)
        even = 2.0 * np.pi / n
        q_a = 1.0 - (gaps.max(axis=1) - even) / (2.0 * np.pi - even)
    w_mean = (np.sum(w_S) + w_c) / n
    return w_mean * q_s * q_a


def pose_information_logdet(J_sel, P6=None, sigma_px=0.5) -> float:
    """``log det(P6^-1 + sum_i J_i^T J_i / sigma_i^2)`` of a selected set.

    Parameters
    ----------
    J_sel : ndarray, shape (K, 2, 6)
        Pixel Jacobians w.r.t. ``[dp, dtheta]``.
    P6 : ndarray (6, 6) or None
        Prior pose covariance; None: ``WEAK_PRIOR_INFO * I`` as information.
    sigma_px : float or ndarray (K,)
    """
    J_sel = np.asarray(J_sel, dtype=float).reshape(-1, 2, 6)
    info = np.eye(6) * WEAK_PRIOR_INFO if P6 is None else np.linalg.inv(np.asarray(P6, dtype=float))
    s2 = np.broadcast_to(np.asarray(sigma_px, dtype=float) ** 2, (len(J_sel),))
    info = info + np.einsum("kai,kaj,k->ij", J_sel, J_sel, 1.0 / s2)
    sign, ld = np.linalg.slogdet(info)
    return float(ld) if sign > 0 else -np.inf


def _greedy_info(J, eligible, group, caps, P6, sigma_px):
    """Greedy D-optimal picks over all candidates; ``group``/``caps`` cap per camera."""
    n = len(J)
    Sigma = np.eye(6) / WEAK_PRIOR_INFO if P6 is None else np.array(P6, dtype=float)
    s2 = np.broadcast_to(np.asarray(sigma_px, dtype=float) ** 2, (n,)).astype(float)
    Jc = np.where(eligible[:, None, None], J, 0.0)
    avail = eligible.copy()
    counts = np.zeros(len(caps), int)
    chosen = []
    I2 = np.eye(2)
    while True:
        open_group = counts[group] < np.asarray(caps)[group]
        cand = avail & open_group
        if not cand.any():
            break
        # matrix determinant lemma: gain = log det(I + J Sigma J^T / s2)
        A = I2 + np.einsum("nai,ij,nbj->nab", Jc, Sigma, Jc) / s2[:, None, None]
        gain = np.log(A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0])
        gain[~cand] = -np.inf
        j = int(np.argmax(gain))
        chosen.append(j)
        avail[j] = False
        counts[group[j]] += 1
        # Woodbury: Sigma <- Sigma - Sigma J^T (s2 I + J Sigma J^T)^-1 J Sigma
        SJt = Sigma @ Jc[j].T
        Sigma = Sigma - SJt @ np.linalg.solve(s2[j] * I2 + Jc[j] @ SJt, SJt.T)
        Sigma = 0.5 * (Sigma + Sigma.T)
    return np.array(chosen, dtype=np.intp)


def select_information(
    uv,
    J,
    view_angle,
    silhouette_px,
    image_size,
    P6=None,
    k: int = DEFAULT_K,
    sigma_px=0.5,
    border_px: float = DEFAULT_BORDER_PX,
    max_view_angle: float = DEFAULT_MAX_VIEW_ANGLE,
    min_separation_px: float = 0.0,
    weight_by_quality: bool = False,
    sil_ref_px: float = DEFAULT_SIL_REF_PX,
) -> np.ndarray:
    """Greedy information (log-det) selection of up to ``k`` corners of one camera.

    Parameters
    ----------
    uv : ndarray, shape (N, 2)
        Predicted pixels (eligibility only).
    J : ndarray, shape (N, 2, 6)
        ``d uv / d [dp, dtheta]`` (:func:`vespro.projection.project_with_jacobian`).
    view_angle : ndarray (N,) or None
        rad (eligibility only).
    silhouette_px : ndarray (N,) or None
        Used only with ``weight_by_quality``.
    image_size : (width, height)
    P6 : ndarray (6, 6) or None
        Current pose covariance ``[dp, dtheta]``; None: a negligible prior.
    k : int
    sigma_px : float or ndarray (N,)
        Pixel noise per corner.
    border_px, max_view_angle, min_separation_px : see :func:`eligible_mask`.
    weight_by_quality : bool
        Inflate each corner's pixel sigma by ``1 / sqrt(w_i)`` with ``w_i`` the
        reliability of :func:`feature_weights` (view angle, silhouette, border),
        so that information from corners the extractor handles badly counts less.
    sil_ref_px : float
        See :func:`feature_weights`.

    Returns
    -------
    ndarray, shape (min(k, n_eligible),), intp
        Indices in the order picked.

    Notes
    -----
    Each pick maximises ``log det(I + J_i Sigma J_i^T / sigma_i^2)`` (matrix
    determinant lemma), then ``Sigma`` is downdated by Woodbury: O(N) 2x2
    work per pick. ``log det`` of information is monotone submodular in the
    set, so greedy is within ``1 - 1/e`` of the best gain over the prior.
    """
    uv = _check(uv)
    J = np.asarray(J, dtype=float)
    if J.shape != (len(uv), 2, 6):
        raise ValueError(f"J: expected shape ({len(uv)}, 2, 6), got {J.shape}")
    _vec(silhouette_px, len(uv), "silhouette_px", 0.0)
    el = eligible_mask(uv, image_size, border_px, view_angle, max_view_angle, J, min_separation_px)
    if weight_by_quality:
        w = feature_weights(uv, view_angle, silhouette_px, image_size, border_px, sil_ref_px, max_view_angle, min_separation_px)
        el &= w > 0.0
        sigma_px = np.broadcast_to(np.asarray(sigma_px, dtype=float), (len(uv),)) / np.sqrt(np.maximum(w, 1e-12))
    return _greedy_info(J, el, np.zeros(len(uv), int), [k], P6, sigma_px)


def select_information_joint(
    candidates,
    P6=None,
    k_per_camera: int = DEFAULT_K,
    sigma_px=0.5,
    border_px: float = DEFAULT_BORDER_PX,
    max_view_angle: float = DEFAULT_MAX_VIEW_ANGLE,
    min_separation_px: float = 0.0,
):
    """Greedy information selection across all cameras at once.

    Parameters
    ----------
    candidates : sequence of (uv (N_c, 2), J (N_c, 2, 6), view_angle (N_c,) or None, image_size)
        One entry per camera.
    P6 : ndarray (6, 6) or None
    k_per_camera : int
        Cap per camera (each camera's extraction budget).
    sigma_px : float

    Returns
    -------
    list of ndarray (intp)
        Per camera, indices into its candidates in the order picked.
    """
    Js, els, groups = [], [], []
    for c, (uv, J, va, size) in enumerate(candidates):
        uv = _check(uv)
        J = np.asarray(J, dtype=float)
        if J.shape != (len(uv), 2, 6):
            raise ValueError(f"camera {c}: J: expected shape ({len(uv)}, 2, 6), got {J.shape}")
        Js.append(J)
        els.append(eligible_mask(uv, size, border_px, va, max_view_angle, J, min_separation_px))
        groups.append(np.full(len(uv), c))
    if not Js:
        return []
    J_all = np.concatenate(Js)
    picks = _greedy_info(J_all, np.concatenate(els), np.concatenate(groups), [k_per_camera] * len(Js), P6, sigma_px)
    offsets = np.cumsum([0] + [len(J) for J in Js])
    return [picks[(picks >= offsets[c]) & (picks < offsets[c + 1])] - offsets[c] for c in range(len(Js))]
