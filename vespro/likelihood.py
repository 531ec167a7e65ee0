"""How well a pose explains the images: a log-likelihood from the model's edges.

Each visible model edge sample projects to a point with a normal (the
projected edge's); the image gradient read along that normal within
``line_px`` (a correspondence line, as in the probabilistic contour trackers
SRT3D and ICG) shows gradient peaks: local maxima of ``|g . n|`` above what the
image's own noise makes (``min_snr`` times the gradient noise std, measured in
the image by :func:`vespro.imageedges.image_noise`, and at least
``min_contrast``). Along one line the peaks are modelled as (the probabilistic
data association of target tracking):

- the model edge's own image edge, present with probability ``p_detect``,
  at an offset ``d ~ N(0, sigma_px^2)`` from the projected point;
- clutter: any number of peaks spread uniformly over the line, at the line's
  own density ``lambda`` (its peaks per px, at least one over the line).

Against the hypothesis that every peak on the line is clutter, the line's
likelihood ratio is ``(1 - p_detect) + p_detect * sum_k N(d_k; 0, sigma^2) /
lambda``. Texture inside a face or a busy background raises ``lambda``, and a
line through uniform clutter gives a ratio near 1 (no evidence either way),
so a textured part's faces neither support nor refute a pose; a line whose
own edge is missing costs ``log(1 - p_detect)``; a line with a sharp peak at
its centre and few others gains up to ``log(2 line_px N(0) / 1)``.

Two nearly parallel model edges projected within 1.5 px of each other (a
face seen edge on) show as one image edge: each image edge point serves the
nearer model edge (:func:`vespro.edgefit.shared_edge_losers`, as in the
sub-pixel fit), so a pose that turns a face edge on does not read one image
edge twice.

Samples along one straight model edge share its errors (a pose off by a
little moves all of them at once): an edge's samples weigh together at most
one per ``spacing_px`` of its projected length, as in the sub-pixel fit
(:func:`vespro.edgefit.refine_subpixel`). The camera's log-likelihood is
the weighted sum of its lines' log ratios; cameras add.

The region term (``LikelihoodOptions.region``; the region modality of SRT3D
and ICG) judges the outline by what lies either side of it. A line of an
outline sample (:func:`vespro.imageedges.silhouette_sides`: its edge convex,
one face seen and the other not) reads the smoothed grey image, one pixel per
px, the part on one side of it. The part's and the background's grey-level
histograms are the pose's own: the pixels of its outline lines at least
``2 sigma_px`` inside and outside (32 bins of 8 grey levels, one count added
to every bin: the uniform Dirichlet prior). Per pixel they give the posterior
``p_f`` that it shows the part (equal priors), ``p_b = 1 - p_f``. Along the
line, at offset ``x`` towards the part, a contour at ``d`` makes the pixel the
part's with probability ``h(x - d) = Phi((x - d) / w)`` (``w``: the smoothing
``blur_sigma`` and the pixel's own width, ``sqrt(blur^2 + 1/12)``), so
``P(pixel | d) ~ h p_f + (1 - h) p_b`` (SRT3D's pixel-wise posteriors). The
line's ratio sets "the contour at ``d ~ N(0, sigma_px^2)``" against "no
contour on the line" (every pixel the part's, or every one the
background's, equally likely):

    sum_d N(d) prod_x P(x | d)^a  /  (prod_x p_f^a + prod_x p_b^a) / 2.

The pixels of one side of a line show one surface, so they are one
observation: each pixel weighs ``a = 1 / line_px`` (its log divided by the
pixels on its side). A line across a true outline gains up to about
``log(2 / (p_b(in) p_f(out)))``; a line whose two sides look alike gains 0
(the histograms do not tell them apart) or loses (both sides look like one
region); a model edge inside the outline is not read at all, so an edge
between two faces lit alike costs nothing here. Outline lines weigh per edge
as the edge lines do (``spacing_px``); the camera's region part
(``CameraLikelihood.region_log_lik``) adds to its log-likelihood. It is off
by default: grey levels cannot tell a part face in the background's shade
from the background, and with one camera a pose that calls such a face
background can then outscore the part's own (``bench/results/region_trials.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .edgefit import COS_PARALLEL, SHARED_EDGE_PX, sweep_shared_losers
from .imageedges import EdgeImage, projection_box, silhouette_sides, visible_samples
from .jit import njit
from .se3 import invert_transform

__all__ = ["LikelihoodOptions", "CameraLikelihood", "PoseLikelihood", "ImageLikelihood", "line_evidence",
           "camera_lines", "region_evidence"]


@dataclass(frozen=True)
class LikelihoodOptions:
    """Settings of the edge likelihood (each a property of the images, not of a case).

    Attributes
    ----------
    sigma_px : float
        Std of an image edge's offset from its projected model edge, px.
    line_px : float
        Half-length of each correspondence line, px.
    p_detect : float
        Probability that a visible model edge point shows as an image edge.
    min_snr : float
        A gradient peak counts when at least this many gradient noise stds.
    min_contrast : float
        ... and at least this strong (Sobel units: 4 per grey level of a step).
    spacing_px : float
        Samples of one edge weigh together at most one per this length, px.
    blur_sigma : float
        Smoothing before the gradient, px.
    region : bool
        Also weigh the outline by the grey levels either side of it (the region term, see the module).
    """

    sigma_px: float = 1.0
    line_px: float = 6.0
    p_detect: float = 0.7
    min_snr: float = 4.0
    min_contrast: float = 20.0
    spacing_px: float = 2.0
    blur_sigma: float = 0.8
    region: bool = False

    def __post_init__(self):
        for name in ("sigma_px", "line_px", "spacing_px"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 < self.p_detect < 1.0:
            raise ValueError(f"p_detect must be in (0, 1), got {self.p_detect}")


@dataclass(frozen=True)
class CameraLikelihood:
    """One camera's share of a pose's likelihood.

    Attributes
    ----------
    log_lik : float
        Weighted sum of the lines' log likelihood ratios (against all clutter), the region
        part included.
    n_visible : int
        Edge samples the camera sees at the pose.
    n_observed : int
        Of those, with their point inside the image.
    n_found : int
        Of those, with a gradient peak within 2 ``sigma_px`` of the point.
    weight : float
        Summed weight of the observed samples (see ``spacing_px``).
    found_frac : float
        Weighted fraction of the observed samples that found their edge.
    edge_log_lik : ndarray, shape (E,)
        Per model edge, its samples' weighted log ratios (0 for an edge not seen).
    edge_found : ndarray, shape (E,)
        Per model edge, the weighted fraction of its observed samples found (NaN: none observed).
    noise : float
        The image's gradient noise std the peaks were judged by.
    region_log_lik : float
        The region term's part of ``log_lik`` (0 without it).
    n_outline : int
        Observed samples on the outline (the region term's lines).
    edge_region_log_lik : ndarray, shape (E,), or None
        Per model edge, its outline lines' weighted region log ratios (None without the term).
    """

    log_lik: float
    n_visible: int
    n_observed: int
    n_found: int
    weight: float
    found_frac: float
    edge_log_lik: np.ndarray
    edge_found: np.ndarray
    noise: float
    region_log_lik: float = 0.0
    n_outline: int = 0
    edge_region_log_lik: np.ndarray | None = None


@dataclass(frozen=True)
class PoseLikelihood:
    """A pose's log-likelihood (sum over the cameras) and each camera's part."""

    log_lik: float
    cameras: tuple


@njit
def line_evidence(grad, uv, n, offs, thr, sigma, p_detect, llr, nearest, n_peaks):
    """The correspondence lines of :mod:`vespro.likelihood`, compiled.

    Parameters
    ----------
    grad : ndarray, shape (2, H, W), float32
    uv : ndarray, shape (S, 2)
        Projected sample points, px.
    n : ndarray, shape (S, 2)
        Unit normals, px.
    offs : ndarray, shape (O,)
        Evenly spaced offsets along the normal, from ``-line_px`` to ``line_px``.
    thr, sigma, p_detect : float
        Least peak strength; offset std, px; detection probability.
    llr, nearest, n_peaks : ndarray, shape (S,)
        Out: each line's log likelihood ratio (0 for a point outside the
        image: no data), the smallest ``|offset|`` of a peak (inf: none), the
        number of peaks. The gradient is read bilinearly; beyond the image
        it reads 0.

    Returns
    -------
    int
        Lines whose point lies inside the image.
    """
    _, H, W = grad.shape
    umax, vmax = W - 1.001, H - 1.001
    S, O = uv.shape[0], offs.shape[0]
    step = offs[1] - offs[0]
    length = offs[O - 1] - offs[0]
    norm = 1.0 / (np.sqrt(2.0 * np.pi) * sigma)
    g = np.empty(O)
    inside = 0
    for s in range(S):
        u0c, v0c = uv[s, 0], uv[s, 1]
        if not (np.isfinite(u0c) and np.isfinite(v0c) and u0c >= 0 and v0c >= 0 and u0c <= umax and v0c <= vmax):
            llr[s] = 0.0
            nearest[s] = np.inf
            n_peaks[s] = 0
            continue
        inside += 1
        n0, n1 = n[s, 0], n[s, 1]
        for o in range(O):
            u = u0c + offs[o] * n0
            v = v0c + offs[o] * n1
            if u >= 0 and v >= 0 and u <= umax and v <= vmax:
                iu, iv = np.int64(u), np.int64(v)
                fu, fv = u - iu, v - iv
                gx = (grad[0, iv, iu] * (1 - fu) + grad[0, iv, iu + 1] * fu) * (1 - fv) \
                    + (grad[0, iv + 1, iu] * (1 - fu) + grad[0, iv + 1, iu + 1] * fu) * fv
                gy = (grad[1, iv, iu] * (1 - fu) + grad[1, iv, iu + 1] * fu) * (1 - fv) \
                    + (grad[1, iv + 1, iu] * (1 - fu) + grad[1, iv + 1, iu + 1] * fu) * fv
                g[o] = abs(gx * n0 + gy * n1)
            else:
                g[o] = 0.0
        count = 0
        acc = 0.0
        best = np.inf
        for o in range(1, O - 1):
            if g[o] >= thr and g[o] > g[o - 1] and g[o] >= g[o + 1]:
                den = g[o - 1] - 2.0 * g[o] + g[o + 1]
                frac = 0.5 * (g[o - 1] - g[o + 1]) / den if abs(den) > 1e-9 else 0.0
                d = offs[o] + min(max(frac, -0.5), 0.5) * step
                acc += norm * np.exp(-0.5 * (d / sigma) ** 2)
                count += 1
                best = min(best, abs(d))
        lam = max(count, 1) / length
        llr[s] = np.log((1.0 - p_detect) + p_detect * acc / lam)
        nearest[s] = best
        n_peaks[s] = count
    return inside


@njit
def camera_lines(grad, K, T_co, idx, sample_p, sample_edge, edge_a, edge_b, offs, thr, sigma, p_detect, spacing,
                 radius, cos_par):
    """One camera's correspondence lines of :mod:`vespro.likelihood` at a pose, compiled.

    The visible samples ``idx`` and the model edges are projected (``K``, ``T_co``; a point
    at depth 1e-6 m or less, or on an edge with such an end, is not observed), each line
    read along its edge's projected normal (:func:`line_evidence`), weighed one per
    ``spacing`` px of its edge's projected length, and an image edge point within
    ``radius`` of two nearly parallel edges (``cos_par``) left to the nearer
    (:func:`vespro.edgefit.sweep_shared_losers`).

    Returns
    -------
    uv, nrm : ndarray, shape (S, 2)
        Projected points (NaN: not in front) and unit normals.
    llr, nearest : ndarray, shape (S,)
        As :func:`line_evidence`.
    w : ndarray, shape (S,)
        Each line's weight (0: not observed, or its image edge served a nearer edge).
    observed : ndarray, shape (S,), bool
        Point inside the image.
    """
    E, S = edge_a.shape[0], idx.shape[0]
    H, W = grad.shape[1], grad.shape[2]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    ends = np.empty((2, E, 2))
    zend = np.empty((2, E))
    for k in range(2):
        P = edge_a if k == 0 else edge_b
        for e in range(E):
            x = P[e, 0] * T_co[0, 0] + P[e, 1] * T_co[0, 1] + P[e, 2] * T_co[0, 2] + T_co[0, 3]
            y = P[e, 0] * T_co[1, 0] + P[e, 1] * T_co[1, 1] + P[e, 2] * T_co[1, 2] + T_co[1, 3]
            z = P[e, 0] * T_co[2, 0] + P[e, 1] * T_co[2, 1] + P[e, 2] * T_co[2, 2] + T_co[2, 3]
            ends[k, e, 0] = x / z * fx + cx
            ends[k, e, 1] = y / z * fy + cy
            zend[k, e] = z
    dn = np.empty((E, 2))
    elen = np.empty(E)
    for e in range(E):
        dx, dy = ends[1, e, 0] - ends[0, e, 0], ends[1, e, 1] - ends[0, e, 1]
        elen[e] = np.sqrt(dx * dx + dy * dy)
        dn[e, 0] = dx / (elen[e] + 1e-12)
        dn[e, 1] = dy / (elen[e] + 1e-12)
    uv = np.empty((S, 2))
    nrm = np.empty((S, 2))
    edge = np.empty(S, np.int64)
    for s in range(S):
        e = sample_edge[idx[s]]
        edge[s] = e
        p = sample_p[idx[s]]
        x = p[0] * T_co[0, 0] + p[1] * T_co[0, 1] + p[2] * T_co[0, 2] + T_co[0, 3]
        y = p[0] * T_co[1, 0] + p[1] * T_co[1, 1] + p[2] * T_co[1, 2] + T_co[1, 3]
        z = p[0] * T_co[2, 0] + p[1] * T_co[2, 1] + p[2] * T_co[2, 2] + T_co[2, 3]
        if z > 1e-6 and zend[0, e] > 1e-6 and zend[1, e] > 1e-6:
            uv[s, 0] = x / z * fx + cx
            uv[s, 1] = y / z * fy + cy
        else:
            uv[s, 0] = np.nan
            uv[s, 1] = np.nan
        nrm[s, 0] = -dn[e, 1]
        nrm[s, 1] = dn[e, 0]
    llr = np.empty(S)
    nearest = np.empty(S)
    n_peaks = np.empty(S, np.int64)
    line_evidence(grad, uv, nrm, offs, thr, sigma, p_detect, llr, nearest, n_peaks)
    observed = np.zeros(S, np.bool_)
    count = np.zeros(E, np.int64)
    for s in range(S):
        u, v = uv[s, 0], uv[s, 1]
        observed[s] = u >= 0 and v >= 0 and u <= W - 1.001 and v <= H - 1.001  # (False for NaN)
        if observed[s]:
            count[edge[s]] += 1
    w = np.zeros(S)
    m = 0
    for s in range(S):
        if observed[s]:
            w[s] = min(1.0, elen[edge[s]] / (spacing * max(count[edge[s]], 1)))
        if np.isfinite(uv[s, 0]) and np.isfinite(uv[s, 1]):
            m += 1
    if m >= 2:
        pu, pv, pe, pc = np.empty(m), np.empty(m), np.empty(m, np.int64), np.empty(m)
        rows = np.empty(m, np.int64)
        k = 0
        for s in range(S):
            if np.isfinite(uv[s, 0]) and np.isfinite(uv[s, 1]):
                pu[k], pv[k], pe[k], pc[k], rows[k] = uv[s, 0], uv[s, 1], edge[s], nearest[s], s
                k += 1
        lose = sweep_shared_losers(pu, pv, pe, dn, pc, radius, cos_par)
        for k in range(m):
            if lose[k]:
                w[rows[k]] = 0.0
    return uv, nrm, llr, nearest, w, observed


REGION_SHIFT = 3  # grey levels to histogram bins: 8 levels a bin, 32 bins


@njit
def region_evidence(grey, uv, n, offs, sigma, width, llr):
    """The region term's outline lines of :mod:`vespro.likelihood`, compiled.

    Parameters
    ----------
    grey : ndarray, shape (H, W), uint8
        The smoothed image.
    uv : ndarray, shape (S, 2)
        Projected outline points, px (NaN: no line).
    n : ndarray, shape (S, 2)
        Unit normals pointing into the part, px.
    offs : ndarray, shape (O,)
        Offsets along the normal, one per px, from ``-line_px`` to ``line_px``.
    sigma : float
        Std of the contour's offset from the projected point, px.
    width : float
        Std of the smoothed step of grey level across a contour, px.
    llr : ndarray, shape (S,)
        Out: each line's log likelihood ratio (0 for a point outside the image). The image is
        read bilinearly; pixels beyond it are left out of both hypotheses.

    Returns
    -------
    int
        Lines whose point lies inside the image.
    """
    H, W = grey.shape
    umax, vmax = W - 1.001, H - 1.001
    S, O = uv.shape[0], offs.shape[0]
    nb = 256 >> REGION_SHIFT
    bins = np.full((S, O), -1, np.int64)
    ok = np.zeros(S, np.bool_)
    hf = np.zeros(nb)
    hb = np.zeros(nb)
    inner = 2.0 * sigma
    inside = 0
    for s in range(S):
        u0c, v0c = uv[s, 0], uv[s, 1]
        if not (np.isfinite(u0c) and np.isfinite(v0c) and u0c >= 0 and v0c >= 0 and u0c <= umax and v0c <= vmax):
            continue
        ok[s] = True
        inside += 1
        for o in range(O):
            u = u0c + offs[o] * n[s, 0]
            v = v0c + offs[o] * n[s, 1]
            if u >= 0 and v >= 0 and u <= umax and v <= vmax:
                iu, iv = np.int64(u), np.int64(v)
                fu, fv = u - iu, v - iv
                g = (grey[iv, iu] * (1 - fu) + grey[iv, iu + 1] * fu) * (1 - fv) \
                    + (grey[iv + 1, iu] * (1 - fu) + grey[iv + 1, iu + 1] * fu) * fv
                b = min(np.int64(g + 0.5) >> REGION_SHIFT, nb - 1)
                bins[s, o] = b
                if offs[o] >= inner:
                    hf[b] += 1.0
                elif offs[o] <= -inner:
                    hb[b] += 1.0
    pf = np.empty(nb)
    tf, tb = hf.sum() + nb, hb.sum() + nb
    for b in range(nb):
        qf, qb = (hf[b] + 1.0) / tf, (hb[b] + 1.0) / tb
        pf[b] = qf / (qf + qb)
    m = np.int64(np.ceil(3.0 * sigma / 0.5))  # the contour's offsets d: 0.5 px apart over 3 sigma
    D = 2 * m + 1
    logw = np.empty(D)
    h = np.empty((D, O))
    for k in range(D):
        d = (k - m) * 0.5
        logw[k] = -0.5 * (d / sigma) ** 2
        for o in range(O):
            h[k, o] = 0.5 * (1.0 + math.erf((offs[o] - d) / (np.sqrt(2.0) * width)))
    top = logw.max()
    logw -= top + np.log(np.sum(np.exp(logw - top)))
    a = (offs[1] - offs[0]) / offs[O - 1]  # the pixels of one side of a line: one observation
    L = np.empty(D)
    P = np.empty(D)
    for s in range(S):
        llr[s] = 0.0
        if not ok[s]:
            continue
        # Products over the line's pixels, one log each: every factor is at least about one over
        # the histograms' pixels, so 2 line_px + 1 of them stay far above the least double.
        qf = 1.0
        qb = 1.0
        for k in range(D):
            P[k] = 1.0
        for o in range(O):
            b = bins[s, o]
            if b < 0:
                continue
            p = pf[b]
            qf *= p
            qb *= 1.0 - p
            for k in range(D):
                P[k] *= h[k, o] * p + (1.0 - h[k, o]) * (1.0 - p)
        for k in range(D):
            L[k] = logw[k] + a * np.log(P[k])
        top = L.max()
        switch = top + np.log(np.sum(np.exp(L - top)))
        lf = a * np.log(qf)
        lb = a * np.log(qb)
        top = max(lf, lb)
        llr[s] = switch - (top + np.log(0.5 * (np.exp(lf - top) + np.exp(lb - top))))
    return inside


class ImageLikelihood:
    """The edge likelihood of poses of one model (set-up: its edge samples and tree).

    Parameters
    ----------
    mf : ModelFeatures
        :func:`vespro.init.modelfeat.model_features` of the part.
    tree : BSPTree, optional
        The part's tree (self-occlusion of a non-convex part's edges).
    options : LikelihoodOptions
    """

    def __init__(self, mf, tree=None, options: LikelihoodOptions = LikelihoodOptions()):
        self.mf = mf
        self.tree = None if mf.convex else tree
        self.options = options
        step = 0.5
        m = int(np.ceil(options.line_px / step))
        self.offs = np.arange(-m, m + 1) * step
        r = max(int(round(options.line_px)), 1)
        self.region_offs = np.arange(-r, r + 1, dtype=float)  # the region lines: one pixel per px
        self.region_width = float(np.hypot(options.blur_sigma, np.sqrt(1.0 / 12.0)))

    def edge_image(self, img: np.ndarray, K: np.ndarray, box=None) -> EdgeImage:
        """An undistorted image's :class:`~vespro.imageedges.EdgeImage` (of ``box`` only, if given)."""
        return EdgeImage.from_image(img, K, box, self.options.blur_sigma, keep_grey=self.options.region)

    def box(self, K: np.ndarray, T_camera_object: np.ndarray, width: int, height: int, margin_px: float = 0.0):
        """Pixel box ``(x0, y0, x1, y1)`` around the part's projection with room for the lines, or
        None (behind the camera, or outside the image)."""
        m = self.options.line_px + 6.0 + margin_px  # the lines, the gradient and blur kernels
        return projection_box(K, T_camera_object, self.mf.vertices, m, width, height)

    def camera(self, T_world_object: np.ndarray, T_world_camera: np.ndarray, eimg: EdgeImage) -> CameraLikelihood:
        """One camera's :class:`CameraLikelihood` of a pose."""
        o = self.options
        mf = self.mf
        E = len(mf.edge_a)
        T_co = invert_transform(np.asarray(T_world_camera, float)) @ np.asarray(T_world_object, float)
        idx = visible_samples(T_co, mf, self.tree) if T_co[2, 3] > 0 else np.zeros(0, np.int64)
        empty = CameraLikelihood(0.0, int(idx.size), 0, 0, 0.0, 0.0, np.zeros(E), np.full(E, np.nan), eimg.noise)
        if idx.size == 0:
            return empty
        K = eimg.K
        se = mf.sample_edge[idx]
        S = idx.size
        thr = max(o.min_snr * eimg.noise, o.min_contrast)
        uv, nrm, llr, nearest, w, observed = camera_lines(
            eimg.grad, np.ascontiguousarray(K, float), np.ascontiguousarray(T_co, float), idx, mf.sample_p,
            mf.sample_edge, mf.edge_a, mf.edge_b, self.offs, float(thr), float(o.sigma_px), float(o.p_detect),
            float(o.spacing_px), SHARED_EDGE_PX, COS_PARALLEL)
        found = observed & (nearest <= 2.0 * o.sigma_px)
        wsum = float(w.sum())
        edge_ll = np.bincount(se, w * llr, E)
        ew = np.bincount(se, w, E)
        with np.errstate(invalid="ignore", divide="ignore"):
            edge_found = np.where(ew > 0, np.bincount(se, w * found, E) / ew, np.nan)
        region_ll, n_outline, edge_region = 0.0, 0, None
        if o.region and eimg.grey is not None:
            side = silhouette_sides(T_co, mf, idx, nrm, K, self.tree)
            line = observed & (side != 0)
            n_outline = int(line.sum())
            rllr = np.zeros(S)
            if n_outline:
                region_evidence(eimg.grey, np.ascontiguousarray(np.where(line[:, None], uv, np.nan)),
                                np.ascontiguousarray(nrm * side[:, None]), self.region_offs, float(o.sigma_px),
                                self.region_width, rllr)
            region_ll = float(np.dot(w, rllr))
            edge_region = np.bincount(se, w * rllr, E)
        return CameraLikelihood(float(np.dot(w, llr)) + region_ll, int(S), int(observed.sum()), int(found.sum()),
                                wsum, float(np.dot(w, found)) / wsum if wsum > 0 else 0.0, edge_ll, edge_found,
                                eimg.noise, region_ll, n_outline, edge_region)

    def __call__(self, T_world_object: np.ndarray, views) -> PoseLikelihood:
        """The pose's :class:`PoseLikelihood` over ``views``: (T_world_camera, EdgeImage) per camera."""
        cams = tuple(self.camera(T_world_object, T_wc, e) for T_wc, e in views)
        return PoseLikelihood(float(sum(c.log_lik for c in cams)), cams)
