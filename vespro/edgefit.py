"""A pose measured against image edges: chamfer refinement on oriented distance maps and
sub-pixel refinement along edge normals.

Both the initialiser (:mod:`vespro.init`) and the tracker's edge aid and
re-detection (:mod:`vespro.edgeaid`, :mod:`vespro.redetect`) measure a pose this way.
:func:`refine_pose` minimises the (bilinear) oriented distances of the visible model
edge samples (:mod:`vespro.init.features`: a sample projected at pixel (u, v) with
edge normal in bin k reads ``dt[k][v, u]``) over all cameras; :func:`refine_subpixel`
then searches each sample's projected normal for its image edge, to sub-pixel, and
fits the pose to those edge points (Gauss-Newton, as in RAPiD-style edge trackers),
reporting how the fit was supported (:class:`EdgeFit`). Visibility of model edges
comes from back-face culling and, for non-convex models, the BSP line-of-sight query
(:func:`vespro.imageedges.visible_samples`).

The inner loops (the edge residuals and their Jacobian, the sub-pixel edge search,
the pose perturbation) are compiled kernels (:mod:`vespro.jit`) that repeat the NumPy
formulation's arithmetic operation for operation: their results are the NumPy code's,
bit for bit (``tests/vespro/test_init_kernels.py`` keeps that code as the reference).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .imageedges import project_points as _project
from .imageedges import visible_samples
from .init.features import CameraFeatures, normal_bins
from .init.modelfeat import ModelFeatures
from .jit import njit
from .numerics import dot3
from .se3 import invert_transform

__all__ = ["CameraView", "EdgeFit", "camera_setup", "edge_residuals", "face_widths_px", "refine_pose",
           "refine_subpixel", "shared_edge_losers", "sweep_shared_losers", "SHARED_EDGE_PX", "PARALLEL_DEG",
           "COS_PARALLEL"]


#: An image edge point within this of two nearly parallel model edges serves only the nearer, px
#: (:func:`shared_edge_losers`) ...
SHARED_EDGE_PX = 1.5
#: ... the edges counting as parallel within this angle, deg; |cos| of it.
PARALLEL_DEG = 10.0
COS_PARALLEL = float(np.cos(np.deg2rad(PARALLEL_DEG)))


def _edge_bins(uv_a, uv_b, n_bins):
    d = uv_b - uv_a
    return normal_bins(np.arctan2(d[..., 0], -d[..., 1]), n_bins)


@dataclass(frozen=True)
class CameraView:
    """One camera's image features and its pose at the frame set's instant."""

    feat: CameraFeatures
    T_world_camera: np.ndarray
    fixed: bool = True


def face_widths_px(T_camera_object: np.ndarray, K: np.ndarray, mf: ModelFeatures,
                   edge_len_px: np.ndarray) -> np.ndarray:
    """Each face's width in the image, px: projected area over its longest projected edge.

    A face seen nearly edge on is a strip this wide (inf for every face when
    part of the model is behind the camera: no face is judged thin there).
    ``edge_len_px`` (E,): the model edges' projected lengths. Compiled
    (:func:`_face_widths_kernel`).
    """
    return _face_widths_kernel(np.ascontiguousarray(T_camera_object, dtype=float), float(K[0, 0]), float(K[1, 1]),
                               mf.tri_p, mf.tri_face, mf.edge_faces, len(mf.face_normals),
                               np.ascontiguousarray(edge_len_px, dtype=float))


@njit
def _face_widths_kernel(T_co, fx, fy, tri_p, tri_face, edge_faces, F, edge_len):
    """:func:`face_widths_px`: the triangles' projected areas summed per face (in triangle
    order, as ``np.bincount``), over the longest projected edge of each face (at least
    1e-9); the points in the camera by ``dot3`` (as OpenBLAS's product). inf for every
    face when a triangle's corner is within 1e-9 of the camera plane or behind it."""
    n_tri = tri_p.shape[0]
    X = np.empty((n_tri, 3, 3))
    for i in range(n_tri):
        for k in range(3):
            for r in range(3):
                X[i, k, r] = dot3(tri_p[i, k, 0], tri_p[i, k, 1], tri_p[i, k, 2],
                                  T_co[r, 0], T_co[r, 1], T_co[r, 2]) + T_co[r, 3]
            if X[i, k, 2] <= 1e-9:
                return np.full(F, np.inf)
    area = np.zeros(F)
    for i in range(n_tri):
        u0, v0 = X[i, 0, 0] / X[i, 0, 2] * fx, X[i, 0, 1] / X[i, 0, 2] * fy
        u1, v1 = X[i, 1, 0] / X[i, 1, 2] * fx, X[i, 1, 1] / X[i, 1, 2] * fy
        u2, v2 = X[i, 2, 0] / X[i, 2, 2] * fx, X[i, 2, 1] / X[i, 2, 2] * fy
        d1u, d1v, d2u, d2v = u1 - u0, v1 - v0, u2 - u0, v2 - v0
        area[tri_face[i]] += 0.5 * abs(d1u * d2v - d1v * d2u)
    longest = np.zeros(F)
    for e in range(edge_faces.shape[0]):
        for k in range(2):
            f = edge_faces[e, k]
            if f < 0:
                f += F  # (NumPy's negative index)
            if edge_len[e] > longest[f] or np.isnan(edge_len[e]):
                longest[f] = edge_len[e]  # np.maximum: NaN wins
    out = np.empty(F)
    for f in range(F):
        out[f] = area[f] / max(longest[f], 1e-9) if not np.isnan(longest[f]) else np.nan
    return out


@njit
def _normal_search(grad, uv, n, offs, min_grad, near_frac=0.0, expect=None, ratio_lo=0.0, ratio_hi=np.inf):
    """The 1D edge search of :func:`refine_subpixel` for each sample, compiled.

    At ``q = uv + offs[o] n`` the bilinear gradient ``(gx, gy)`` of ``grad``
    (2, H, W) float32 (NaN outside ``[0, W - 1.001] x [0, H - 1.001]``) gives
    the signed contrast ``c = gx n_u + gy n_v`` (0 where not finite) and
    ``g = |c|``; its first maximum over the offsets, and a parabola through it
    and its neighbours, give the edge point's offset ``sstar`` (S,); ``ok``
    (S,) where the peak is at least ``min_grad`` and not at either end. With
    ``near_frac`` > 0, the peak taken is the local maximum nearest the sample
    (smallest ``|offs|``) among those at least ``near_frac`` times the highest
    (and ``min_grad``). With ``near_frac`` 0, the NumPy code's operations in
    its order: the same bits.

    ``expect`` (S,), optional: each sample's expected signed contrast (NaN:
    unknown, the search above). Where known, only local maxima of ``c`` of
    its sign, inside the ends, with ``max(ratio_lo |e|, min_grad) <= |c| <=
    ratio_hi |e|`` count as peaks (no upper bound where ``|e| < min_grad``: a
    sample that saw no edge of its own, its pose a little off, must still
    take its edge when it comes within reach); the highest of them, or with
    ``near_frac`` the nearest of those at least ``near_frac`` times it.

    Returns ``(sstar, ok, c_peak, c0)``: ``c_peak`` (S,) the signed contrast
    at the peak taken (valid where ``ok``), ``c0`` (S,) at the offset nearest
    0 (the sample's own position).
    """
    _, H, W = grad.shape
    gxi, gyi = grad[0], grad[1]
    one = np.uint64(1)
    umax, vmax = W - 1.001, H - 1.001
    S, O = uv.shape[0], offs.shape[0]
    sstar = np.empty(S)
    ok = np.empty(S, np.bool_)
    c0 = np.empty(S)
    c_peak = np.empty(S)
    g = np.empty(O)
    cs = np.empty(O)
    o0 = 0
    for o in range(1, O):
        if abs(offs[o]) < abs(offs[o0]):
            o0 = o
    for s in range(S):
        n0, n1 = n[s, 0], n[s, 1]
        for o in range(O):
            u = uv[s, 0] + offs[o] * n0
            v = uv[s, 1] + offs[o] * n1
            if np.isfinite(u) and np.isfinite(v) and u >= 0 and v >= 0 and u <= umax and v <= vmax:
                fu0, fv0 = np.floor(u), np.floor(v)
                u0, v0 = np.uint64(fu0), np.uint64(fv0)  # (unsigned: no negative-index wrap to test)
                u1, v1 = u0 + one, v0 + one
                fu, fv = u - fu0, v - fv0
                gx = (gxi[v0, u0] * (1 - fu) + gxi[v0, u1] * fu) * (1 - fv) \
                    + (gxi[v1, u0] * (1 - fu) + gxi[v1, u1] * fu) * fv
                gy = (gyi[v0, u0] * (1 - fu) + gyi[v0, u1] * fu) * (1 - fv) \
                    + (gyi[v1, u0] * (1 - fu) + gyi[v1, u1] * fu) * fv
                co = gx * n0 + gy * n1
                cs[o] = co if np.isfinite(co) else 0.0
            else:
                cs[o] = 0.0  # NaN outside the image, then not finite
            g[o] = abs(cs[o])
        c0[s] = cs[o0]
        if expect is None:
            e = np.nan
        else:
            e = expect[s]
        if np.isfinite(e):
            sg = 1.0 if e > 0 else -1.0
            lo = max(ratio_lo * abs(e), min_grad)
            hi = ratio_hi * abs(e) if abs(e) >= min_grad else np.inf
            for o in range(O):
                g[o] = max(sg * cs[o], 0.0)
            k = -1
            for o in range(1, O - 1):
                if g[o] >= lo and g[o] <= hi and g[o] >= g[o - 1] and g[o] >= g[o + 1] and (k < 0 or g[o] > g[k]):
                    k = o
            if k >= 0 and near_frac > 0:
                floor = max(near_frac * g[k], lo)
                for o in range(1, O - 1):
                    if g[o] >= floor and g[o] <= hi and g[o] >= g[o - 1] and g[o] >= g[o + 1] \
                            and abs(offs[o]) < abs(offs[k]):
                        k = o
            ok[s] = k >= 0
            k = max(k, 1)
        else:
            k = 0
            for o in range(1, O):
                if g[o] > g[k]:
                    k = o
            if near_frac > 0:
                floor = max(near_frac * g[k], min_grad)
                for o in range(1, O - 1):
                    if g[o] >= floor and g[o] >= g[o - 1] and g[o] >= g[o + 1] and abs(offs[o]) < abs(offs[k]):
                        k = o
            ok[s] = g[k] >= min_grad and k > 0 and k < O - 1
        kk = min(max(k, 1), O - 2)
        gm, g0, gp = g[kk - 1], g[kk], g[kk + 1]
        den = gm - 2 * g0 + gp
        frac = 0.5 * (gm - gp) / den if abs(den) > 1e-9 else 0.0
        sstar[s] = offs[kk] + min(max(frac, -0.5), 0.5) * 0.5
        c_peak[s] = cs[kk]
    return sstar, ok, c_peak, c0


def shared_edge_losers(uv: np.ndarray, edge: np.ndarray, edge_dir: np.ndarray, cost: np.ndarray,
                       radius_px: float = SHARED_EDGE_PX, max_angle_deg: float = PARALLEL_DEG) -> np.ndarray:
    """Samples that share their image edge with a nearer sample of another, parallel model edge.

    Two nearly parallel model edges projected close together (a face seen
    nearly edge-on: a thin strip) can both find the one image edge between
    them; counted twice, that image edge pulls the strip thinner, i.e. the
    pose to a wrong depth or tilt. Of each pair of samples of different
    edges (directions within ``max_angle_deg``) whose points lie within
    ``radius_px``, the one with the larger ``cost`` (its distance to the
    image edge) is a loser: an image edge point serves one model edge.

    Parameters
    ----------
    uv : ndarray, shape (S, 2)
        Projected samples (or their image edge points), px.
    edge : ndarray, shape (S,), int
        Model edge of each sample.
    edge_dir : ndarray, shape (E, 2)
        Projected direction of each model edge (any length).
    cost : ndarray, shape (S,)
    radius_px, max_angle_deg : float

    Returns
    -------
    ndarray, shape (S,), bool
    """
    lose = np.zeros(len(uv), bool)
    sel = np.flatnonzero(np.all(np.isfinite(uv), axis=1))
    if sel.size < 2:
        return lose
    d = np.asarray(edge_dir, float)
    dn = d / (np.linalg.norm(d, axis=1, keepdims=True) + 1e-12)
    lose[sel] = sweep_shared_losers(np.ascontiguousarray(uv[sel, 0], float), np.ascontiguousarray(uv[sel, 1], float),
                                    np.ascontiguousarray(edge[sel], np.int64), np.ascontiguousarray(dn),
                                    np.ascontiguousarray(cost[sel], float), float(radius_px),
                                    float(np.cos(np.deg2rad(max_angle_deg))))
    return lose


@njit
def sweep_shared_losers(u, v, edge, dn, cost, radius, cos_par):
    """Compiled: the losers of :func:`shared_edge_losers` among points ``(u, v)`` (m,) of model edges
    ``edge`` (m,) with unit projected directions ``dn`` (E, 2): the pairs within ``radius``
    (a sweep along ``u``; the pairs of ``cKDTree.query_pairs``), of different edges at most
    ``arccos(cos_par)`` apart, the one of larger ``cost`` losing (the later on a tie)."""
    m = u.shape[0]
    lose = np.zeros(m, np.bool_)
    order = np.argsort(u)
    r2 = radius * radius
    for a in range(m):
        ia = order[a]
        for b in range(a + 1, m):
            ib = order[b]
            du = u[ib] - u[ia]
            if du > radius:
                break
            dv = v[ib] - v[ia]
            if du * du + dv * dv > r2:
                continue
            i, j = min(ia, ib), max(ia, ib)
            ei, ej = edge[i], edge[j]
            if ei == ej or abs(dn[ei, 0] * dn[ej, 0] + dn[ei, 1] * dn[ej, 1]) < cos_par:
                continue
            if cost[i] > cost[j]:
                lose[i] = True
            else:
                lose[j] = True
    return lose


def camera_setup(T_world_object, view: CameraView, mf, tree):
    """The edge samples ``view`` sees of the part at ``T_world_object`` (indices into
    ``mf.sample_p``) and the orientation bin of each (its model edge's projected normal):
    which distance map its residual reads."""
    T_co = invert_transform(view.T_world_camera) @ T_world_object
    idx = visible_samples(T_co, mf, tree)
    K = view.feat.K
    ua, _ = _project(K, T_co, mf.edge_a)
    ub, _ = _project(K, T_co, mf.edge_b)
    bins = _edge_bins(ua, ub, view.feat.dt.shape[0])[mf.sample_edge[idx]]
    return idx, bins


def _perturbed(T0, x):
    """``T0`` with its rotation times ``Exp(x[:3])`` and ``x[3:]`` added to its translation, (4, 4).

    ``Exp`` in closed form (Rodrigues; SciPy's Rotation costs more than the
    rest of a residual). The scalars are Python/NumPy floats as they always
    were (``th ** 2`` is libm's ``pow``, which LLVM would turn into ``th *
    th``); the matrices are built by :func:`_perturbed_kernel`.
    """
    w = x[:3]
    th = float(np.sqrt(w @ w))
    if th < 1e-8:
        return _perturbed_kernel(T0, x, 1.0, 0.0)
    return _perturbed_kernel(T0, x, np.sin(th) / th, (1.0 - np.cos(th)) / th ** 2)


@njit
def _perturbed_kernel(T0, x, a, b):
    """``transform_from_rt(T0[:3, :3] @ R, T0[:3, 3] + x[3:])`` with ``R = I + a Kx + b Kx Kx``
    (``Kx`` the cross-product matrix of ``x[:3]``), matrix products as ``dot3``: the NumPy
    code's bits. ``a = 1, b = 0`` gives the small-angle ``I + Kx`` exactly (``1 * k`` is
    ``k``; ``I + Kx`` holds no -0, so adding a signed zero changes nothing)."""
    Kx = np.zeros((3, 3))
    Kx[0, 1], Kx[0, 2] = -x[2], x[1]
    Kx[1, 0], Kx[1, 2] = x[2], -x[0]
    Kx[2, 0], Kx[2, 1] = -x[1], x[0]
    R = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            e = 1.0 if i == j else 0.0
            R[i, j] = (e + a * Kx[i, j]) + b * dot3(Kx[i, 0], Kx[i, 1], Kx[i, 2], Kx[0, j], Kx[1, j], Kx[2, j])
    T = np.eye(4)
    for i in range(3):
        for j in range(3):
            T[i, j] = dot3(T0[i, 0], T0[i, 1], T0[i, 2], R[0, j], R[1, j], R[2, j])
        T[i, 3] = T0[i, 3] + x[3 + i]
    return T


def edge_residuals(x: np.ndarray, T0: np.ndarray, setups: list, want_jac: bool, dmax: float = 20.0) -> np.ndarray:
    """Oriented-distance residuals of edge samples at a perturbed pose, or their Jacobian.

    Parameters
    ----------
    x : ndarray, shape (6,)
        Perturbation ``[w, dp]``: ``R = R0 Exp(w)``, ``p = p0 + dp`` (rad, m).
    T0 : ndarray, shape (4, 4)
        ``T_world_object`` about which to perturb.
    setups : list of (CameraView, T_camera_world (4, 4), P_object (S, 3), bins (S,))
        Per camera: the visible samples and their orientation bins.
    want_jac : bool
    dmax : float
        Residual of a sample outside the image, px.

    Returns
    -------
    ndarray, shape (N,) or (N, 6)

    Notes
    -----
    One compiled pass per camera (:func:`_edge_residuals_kernel`). A camera
    with a single sample is the one case that rounds differently from the
    NumPy formulation (its one-row products went to BLAS's gemv).
    """
    Tx = _perturbed(T0, x)
    Rwo = np.ascontiguousarray(Tx[:3, :3])
    n = sum(len(P) for _, _, P, _ in setups)
    r = np.empty(0 if want_jac else n)
    J = np.empty((n if want_jac else 0, 6))
    k = 0
    for v, T_cw, P, bins in setups:
        K = v.feat.K
        T_co = T_cw @ Tx
        m = len(P)
        _edge_residuals_kernel(T_co, T_cw, Rwo, P, bins, v.feat.dt, K[0, 0], K[1, 1], K[0, 2], K[1, 2], float(dmax),
                               want_jac, r if want_jac else r[k:k + m], J[k:k + m])
        k += m
    return J if want_jac else r


@njit
def _pose_row(p0, p1, p2, g0, g1, g2, R_wo, J, i):
    """Row ``i`` of a pose Jacobian from ``g`` = d(residual)/d(world point) at object point ``p``:
    ``X_w = R0 Exp(w) p + p0 + dp``, so ``dr/dw = (R0 p x g) R0`` and ``dr/ddp = g``
    (products as ``dot3``)."""
    q0 = dot3(p0, p1, p2, R_wo[0, 0], R_wo[0, 1], R_wo[0, 2])
    q1 = dot3(p0, p1, p2, R_wo[1, 0], R_wo[1, 1], R_wo[1, 2])
    q2 = dot3(p0, p1, p2, R_wo[2, 0], R_wo[2, 1], R_wo[2, 2])
    c0 = q1 * g2 - q2 * g1
    c1 = q2 * g0 - q0 * g2
    c2 = q0 * g1 - q1 * g0
    J[i, 0] = dot3(c0, c1, c2, R_wo[0, 0], R_wo[1, 0], R_wo[2, 0])
    J[i, 1] = dot3(c0, c1, c2, R_wo[0, 1], R_wo[1, 1], R_wo[2, 1])
    J[i, 2] = dot3(c0, c1, c2, R_wo[0, 2], R_wo[1, 2], R_wo[2, 2])
    J[i, 3], J[i, 4], J[i, 5] = g0, g1, g2


@njit
def _edge_residuals_kernel(T_co, T_cw, R_wo, P, bins, dt, fx, fy, cx, cy, dmax, want_jac, r, J):
    """Compiled body of :func:`edge_residuals` for one camera, one sample at a time.

    Projection ``X = P R_co^T + t_co``, ``uv = X[:2] / z * f + c`` (NaN for
    ``z <= 1e-6``); the bilinear distance ``dt[bin]`` at ``uv`` (``dmax``
    outside ``[0, W - 1.001] x [0, H - 1.001]``) into ``r`` (S,), or with
    ``want_jac`` its slope through the pinhole, ``g = (gu du + gv dv) R_cw``,
    and ``[(P R_wo^T x g) R_wo, g]`` into ``J`` (S, 6). The NumPy code's
    operations in its order (matrix products as ``dot3``): the same bits.
    """
    _, H, W = dt.shape
    umax, vmax = W - 1.001, H - 1.001
    for i in range(P.shape[0]):
        p0, p1, p2 = P[i, 0], P[i, 1], P[i, 2]
        X0 = dot3(p0, p1, p2, T_co[0, 0], T_co[0, 1], T_co[0, 2]) + T_co[0, 3]
        X1 = dot3(p0, p1, p2, T_co[1, 0], T_co[1, 1], T_co[1, 2]) + T_co[1, 3]
        z = dot3(p0, p1, p2, T_co[2, 0], T_co[2, 1], T_co[2, 2]) + T_co[2, 3]
        u = X0 / z * fx + cx
        v = X1 / z * fy + cy
        if z <= 1e-6:
            u = np.nan
            v = np.nan
        val, gu, gv = dmax, 0.0, 0.0
        if np.isfinite(u) and np.isfinite(v) and u >= 0 and v >= 0 and u <= umax and v <= vmax:
            u0, v0 = np.int64(np.floor(u)), np.int64(np.floor(v))
            fu, fv = u - u0, v - v0
            b = bins[i]
            a, bb = dt[b, v0, u0], dt[b, v0, u0 + 1]
            c, d = dt[b, v0 + 1, u0], dt[b, v0 + 1, u0 + 1]
            val = (a * (1 - fu) + bb * fu) * (1 - fv) + (c * (1 - fu) + d * fu) * fv
            gu = (bb - a) * (1 - fv) + (d - c) * fv  # differences of the float32 maps in float32
            gv = (c - a) * (1 - fu) + (d - bb) * fu
        if not want_jac:
            r[i] = val
            continue
        zz = z if z > 1e-6 else 1.0
        du0, du2 = fx / zz, -fx * X0 / (zz * zz)
        dv1, dv2 = fy / zz, -fy * X1 / (zz * zz)
        m0 = gu * du0 + gv * 0.0
        m1 = gu * 0.0 + gv * dv1
        m2 = gu * du2 + gv * dv2
        g0 = dot3(m0, m1, m2, T_cw[0, 0], T_cw[1, 0], T_cw[2, 0])  # dr/dX_world
        g1 = dot3(m0, m1, m2, T_cw[0, 1], T_cw[1, 1], T_cw[2, 1])
        g2 = dot3(m0, m1, m2, T_cw[0, 2], T_cw[1, 2], T_cw[2, 2])
        _pose_row(p0, p1, p2, g0, g1, g2, R_wo, J, i)


def refine_pose(T_world_object: np.ndarray, views: list[CameraView], mf: ModelFeatures, tree=None,
                rounds: int = 3, f_scale: float = 1.5, max_nfev: int = 20, dmax: float = 20.0) -> np.ndarray:
    """Multi-camera least squares on the oriented edge distances.

    Residual of a visible edge sample: the (bilinear) oriented distance at its
    projection, clipped at the distance maps' range; a soft-L1 loss keeps
    clutter and missing edges from dragging the pose. The pose is perturbed as
    ``R = R0 Exp(w)``, ``p = p0 + dp`` (``x = [w, dp]``); the Jacobian is
    analytic (the distance map's bilinear slope through the pinhole).
    Visibility and orientation bins are recomputed between rounds.

    Returns
    -------
    ndarray, shape (4, 4)
        Refined ``T_world_object``.
    """
    T = np.array(T_world_object, float)
    for _ in range(rounds):
        setups = []
        for v in views:
            idx, bins = camera_setup(T, v, mf, tree)
            if idx.size:
                setups.append((v, invert_transform(v.T_world_camera), mf.sample_p[idx], bins))
        if not setups:
            return T
        T0 = T

        def resid_jac(x, want_jac):
            return edge_residuals(x, T0, setups, want_jac, dmax)

        # Gauss-Newton with Huber weights (IRLS), Levenberg damping.
        x = np.zeros(6)
        lam = 1e-3
        r = resid_jac(x, False)

        def cost(r):
            a = np.abs(r)
            return float(np.sum(np.where(a <= f_scale, 0.5 * a * a, f_scale * (a - 0.5 * f_scale))))

        c = cost(r)
        J = None
        for _ in range(max_nfev):
            if J is None:  # unchanged after a rejected step
                J = resid_jac(x, True)
            w = np.where(np.abs(r) <= f_scale, 1.0, f_scale / np.maximum(np.abs(r), 1e-12))
            JW = J * w[:, None]
            A = JW.T @ J
            g = JW.T @ r
            step = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-9), -g)
            xn = x + step
            rn = resid_jac(xn, False)
            cn = cost(rn)
            if cn < c:
                x, r, c, J = xn, rn, cn, None
                lam = max(lam * 0.3, 1e-6)
                # 1e-4 rad, 10 um: far below what the sub-pixel stage settles.
                if np.linalg.norm(step[:3]) < 1e-4 and np.linalg.norm(step[3:]) < 1e-5:
                    break
            else:
                lam *= 10.0
                if lam > 1e4:
                    break
        T = _perturbed(T0, x)
        if np.linalg.norm(x[:3]) < 1e-4 and np.linalg.norm(x[3:]) < 1e-4:
            break
    return T


@dataclass(frozen=True)
class EdgeFit:
    """How the last round of :func:`refine_subpixel` was supported.

    Attributes
    ----------
    normal : ndarray (6, 6)
        ``J^T W J`` of the edge residuals (px) in the perturbation ``x = [w, dp]``
        (``R = R0 Exp(w)``, ``p = p0 + dp``) at the pose before the last step.
    rms_px : float
        Weighted RMS of those residuals, px.
    n_samples, n_edges : int
        Edge samples with an edge point found (and their edge not dropped as
        an outlier), and the model edges they lie on.
    n_searched : int
        Visible edge samples searched.
    weight : float
        Summed weight of the ``n_samples`` (each at most 1; see ``spacing_px``
        of :func:`refine_subpixel`).
    found_weight, searched_weight : float
        Summed weight of the samples that found their image edge (the fitted
        ones, and those on an edge of a face seen as a strip under twice
        ``shared_edge_px`` wide whose image edge a nearer parallel model edge
        took: such a face shows its two edges as one) and of all searched.
    offset_gram : ndarray (6, 6)
        ``G^T G``, ``G`` the per-edge sums of the weighted Jacobian rows
        (``sum w J`` over each fitted edge's samples): how the step answers an
        offset common to all samples of one edge (see :meth:`covariance`).
    sample_contrast : tuple of ndarray (S,)
        Per view, what each edge sample saw in the last round: the signed image
        contrast (the gradient along its edge's projected normal,
        ``rot90(b - a)``) of the image edge it took, or where it took none, at
        its own projected position; NaN for a sample not seen. For the next
        frame's search (``expect`` of :func:`refine_subpixel`).
    """

    normal: np.ndarray
    rms_px: float
    n_samples: int
    n_edges: int
    n_searched: int
    weight: float
    found_weight: float
    searched_weight: float
    offset_gram: np.ndarray
    sample_contrast: tuple = ()

    @property
    def found_frac(self) -> float:
        """Fraction of the visible outline (samples, weighted) that found its image edge (0 when none searched)."""
        return min(self.found_weight / max(self.searched_weight, 1e-12), 1.0)

    def covariance(self, R_world_object: np.ndarray, min_sigma_px: float = 0.3,
                   max_independent_edges: int = 12, edge_offset_px: float = 0.0) -> np.ndarray | None:
        """Covariance of the fitted pose, ``s^2 (J^T W J)^-1``, in the filter's ``[dp, dtheta]``.

        ``s`` is the weighted residual RMS (at least ``min_sigma_px``), raised by
        the number of samples per edge over two: samples along one straight edge
        share its errors (an edge measures an offset and an angle, not one
        independent distance per sample); edges beyond ``max_independent_edges``
        count as no more information (see :mod:`vespro.edgeaid`). With
        ``edge_offset_px``, each edge's image edge may also lie that far (std)
        off its model edge as a whole, the same for all its samples (a face seen
        edge on as a dark line a pixel wide, whose far side the search took; a
        bevel; a dark face's blur), which the residuals cannot show when the
        pose absorbs it: the covariance gains
        ``o^2 (J^T W J)^-1 G^T G (J^T W J)^-1`` (:attr:`offset_gram`). With one
        camera that is mostly depth, which one edge's offset shifts unseen.
        ``dtheta`` is a rotation on the left in the world frame
        (``R = Exp(dtheta) R0``), for the pose's rotation ``R_world_object``.
        None when the fit leaves a direction free.
        """
        try:
            C_x = np.linalg.inv(self.normal)
        except np.linalg.LinAlgError:
            return None
        n_indep = 2.0 * min(self.n_edges, max_independent_edges)
        s2 = max(self.rms_px, min_sigma_px) ** 2 * max(self.weight / n_indep, 1.0)
        C = s2 * C_x
        if edge_offset_px > 0:
            C = C + edge_offset_px ** 2 * (C_x @ self.offset_gram @ C_x)
        # x = [w, dp] with R = R0 Exp(w): dtheta (left, world) = R0 w.
        M = _SWAP6.copy()
        M[3:, :3] = R_world_object
        cov = M @ C @ M.T
        if not np.isfinite(cov).all():
            return None
        return 0.5 * (cov + cov.T)




_SWAP6 = np.zeros((6, 6))  # EdgeFit.covariance's M less its rotation block: x = [w, dp] -> [dp, .]
_SWAP6[:3, 3:] = np.eye(3)
_SWAP6.setflags(write=False)


@njit
def _subpixel_view_kernel(grad, fx, fy, cx, cy, T_co, R_wo, R_cw, idx, sample_p, sample_edge, edge_a, edge_b, offs,
                          min_grad, near_frac, expect, ratio_lo, ratio_hi, spacing_px, shared_px, cos_par,
                          tri_p, tri_face, edge_faces, n_faces):
    """One camera's share of a :func:`refine_subpixel` round, compiled: for the visible
    samples ``idx`` (S,), their projection and normals, the edge search
    (:func:`_normal_search`), the samples losing their image edge to a nearer parallel
    edge's (:func:`shared_edge_losers`, with ``cos_par`` its parallel test) and the rows
    ``n^T d(uv)/dx``. The NumPy code's operations in its order (products with a
    rotation as ``dot3``), so the same bits.

    Returns ``(ok, sstar, c_peak, c0, dens, lost, w_strip, J)``: per sample (S,) whether
    it found its edge (and kept it), the edge point's offset along the normal, the
    contrast there and at the sample, its weight (``spacing_px``), whether it lost its
    image edge to another sample; the summed weight of the samples that lost theirs on
    an edge of a face seen as a strip under ``2 shared_px`` wide
    (:func:`face_widths_px`, summed in sample order); the rows (S, 6), valid where ``ok``.
    """
    E = edge_a.shape[0]
    S = idx.shape[0]
    ua = np.empty((E, 2))
    ub = np.empty((E, 2))
    edge_len = np.empty(E)
    for e in range(E):
        for k, (src, dst) in enumerate(((edge_a, ua), (edge_b, ub))):
            X0 = dot3(src[e, 0], src[e, 1], src[e, 2], T_co[0, 0], T_co[0, 1], T_co[0, 2]) + T_co[0, 3]
            X1 = dot3(src[e, 0], src[e, 1], src[e, 2], T_co[1, 0], T_co[1, 1], T_co[1, 2]) + T_co[1, 3]
            z = dot3(src[e, 0], src[e, 1], src[e, 2], T_co[2, 0], T_co[2, 1], T_co[2, 2]) + T_co[2, 3]
            dst[e, 0] = X0 / z * fx + cx
            dst[e, 1] = X1 / z * fy + cy
        dx, dy = ub[e, 0] - ua[e, 0], ub[e, 1] - ua[e, 1]
        edge_len[e] = np.sqrt(dx * dx + dy * dy)
    per_edge = np.zeros(E, np.int64)
    for i in range(S):
        per_edge[sample_edge[idx[i]]] += 1
    dens = np.ones(S)
    n = np.empty((S, 2))
    uv = np.empty((S, 2))
    X = np.empty((S, 3))
    for i in range(S):
        e = sample_edge[idx[i]]
        if spacing_px > 0:
            x = edge_len[e] / (spacing_px * per_edge[e])
            dens[i] = 1.0 if x >= 1.0 else x  # np.minimum: NaN stays NaN
        d0, d1 = ub[e, 0] - ua[e, 0], ub[e, 1] - ua[e, 1]
        nn = np.sqrt(-d1 * -d1 + d0 * d0) + 1e-12
        n[i, 0] = -d1 / nn
        n[i, 1] = d0 / nn
        p = sample_p[idx[i]]
        X[i, 0] = dot3(p[0], p[1], p[2], T_co[0, 0], T_co[0, 1], T_co[0, 2]) + T_co[0, 3]
        X[i, 1] = dot3(p[0], p[1], p[2], T_co[1, 0], T_co[1, 1], T_co[1, 2]) + T_co[1, 3]
        X[i, 2] = dot3(p[0], p[1], p[2], T_co[2, 0], T_co[2, 1], T_co[2, 2]) + T_co[2, 3]
        uv[i, 0] = X[i, 0] / X[i, 2] * fx + cx
        uv[i, 1] = X[i, 1] / X[i, 2] * fy + cy
    sstar, ok, c_peak, c0 = _normal_search(grad, uv, n, offs, min_grad, near_frac, expect, ratio_lo, ratio_hi)
    lost = np.zeros(S, np.bool_)
    if shared_px > 0:
        # Pairs of found samples whose edge points lie within shared_px (as cKDTree's
        # query_pairs, swept along u), of different, parallel edges: the farther loses.
        k_all = np.flatnonzero(ok)
        tu = np.empty(k_all.shape[0])
        tv = np.empty(k_all.shape[0])
        m = 0
        k_ok = np.empty(k_all.shape[0], np.int64)
        for i in k_all:  # points not finite take part in no pair
            u = uv[i, 0] + sstar[i] * n[i, 0]
            v = uv[i, 1] + sstar[i] * n[i, 1]
            if np.isfinite(u) and np.isfinite(v):
                tu[m], tv[m], k_ok[m] = u, v, i
                m += 1
        if m >= 2:
            dn = np.empty((E, 2))
            for e in range(E):
                dx, dy = ub[e, 0] - ua[e, 0], ub[e, 1] - ua[e, 1]
                nn = np.sqrt(dx * dx + dy * dy) + 1e-12
                dn[e, 0] = dx / nn
                dn[e, 1] = dy / nn
            edge_ok = np.empty(m, np.int64)
            cost_ok = np.empty(m)
            for a in range(m):
                edge_ok[a] = sample_edge[idx[k_ok[a]]]
                cost_ok[a] = abs(sstar[k_ok[a]])
            lose = sweep_shared_losers(tu[:m], tv[:m], edge_ok, dn, cost_ok, shared_px, cos_par)
            for a in range(m):
                if lose[a]:
                    lost[k_ok[a]] = True
        for i in range(S):
            if lost[i]:
                ok[i] = False
    w_strip = 0.0
    if lost.any():
        # A face seen edge on shows its two edges as one image edge: there, the
        # sample that lost it still found its outline.
        width = _face_widths_kernel(T_co, fx, fy, tri_p, tri_face, edge_faces, n_faces, edge_len)
        for i in range(S):
            if lost[i]:
                e = sample_edge[idx[i]]
                f0, f1 = edge_faces[e, 0], edge_faces[e, 1]
                if width[f0 + n_faces if f0 < 0 else f0] < 2.0 * shared_px or \
                        width[f1 + n_faces if f1 < 0 else f1] < 2.0 * shared_px:
                    w_strip += dens[i]
    J = np.empty((S, 6))
    for i in range(S):
        if not ok[i]:
            continue
        z = X[i, 2]
        X0, X1 = X[i, 0], X[i, 1]
        n0, n1 = n[i, 0], n[i, 1]
        zz = 0 * z
        m0 = n0 * (fx / z) + n1 * zz
        m1 = n0 * zz + n1 * (fy / z)
        m2 = n0 * (-fx * X0 / z ** 2) + n1 * (-fy * X1 / z ** 2)
        g0 = dot3(m0, m1, m2, R_cw[0, 0], R_cw[1, 0], R_cw[2, 0])
        g1 = dot3(m0, m1, m2, R_cw[0, 1], R_cw[1, 1], R_cw[2, 1])
        g2 = dot3(m0, m1, m2, R_cw[0, 2], R_cw[1, 2], R_cw[2, 2])
        p = sample_p[idx[i]]
        _pose_row(p[0], p[1], p[2], g0, g1, g2, R_wo, J, i)
    return ok, sstar, c_peak, c0, dens, lost, w_strip, J


@njit
def _solve_edges(J, r, dens, eid, f_scale, edge_outlier_px):
    """The Gauss-Newton step of a :func:`refine_subpixel` round, compiled: Huber weights
    (``f_scale``) times the samples' ``dens``; ``(J^T W J + 1e-6 diag) step = -J^T W r``;
    with ``edge_outlier_px``, edges the step leaves more than that off on average (weighted)
    out and the step solved again (twice at most, keeping four edges). Sums run in sample
    order (NumPy's matrix products and pairwise sums round differently: the step agrees
    with the NumPy formulation to rounding).

    Returns ``(step, A, n_keep, rms, n_edges, weight, GtG)``: ``A = J^T W J`` of the last
    solve, the samples kept, their weighted residual RMS, the edges they lie on, their
    summed ``dens``, and ``G^T G`` with ``G`` the per-edge sums of the weighted rows.
    """
    N = r.shape[0]
    w = np.empty(N)
    for i in range(N):
        a = abs(r[i])
        w[i] = dens[i] * (1.0 if a <= f_scale else f_scale / max(a, 1e-12))
    # Edges: the sorted distinct ids, and each sample's index among them.
    order = np.argsort(eid, kind="mergesort")
    inv = np.empty(N, np.int64)
    n_u = 0
    for k in range(N):
        i = order[k]
        if k > 0 and eid[i] != eid[order[k - 1]]:
            n_u += 1
        inv[i] = n_u
    n_u = n_u + 1 if N else 0
    keep = np.ones(N, np.bool_)
    A = np.zeros((6, 6))
    b = np.zeros(6)
    step = np.zeros(6)
    for drops in range(3):
        A[:] = 0.0
        b[:] = 0.0
        for i in range(N):
            wi = w[i]
            if wi == 0.0:
                continue
            for j in range(6):
                jw = J[i, j] * wi
                b[j] -= jw * r[i]
                for k in range(6):
                    A[j, k] += jw * J[i, k]
        M = A.copy()
        for j in range(6):
            M[j, j] += 1e-6 * (A[j, j] + 1e-9)
        step = np.linalg.solve(M, b)
        if edge_outlier_px <= 0 or drops == 2:
            break
        wsum = np.zeros(n_u)
        msum = np.zeros(n_u)
        for i in range(N):
            res = r[i]
            for k in range(6):
                res += J[i, k] * step[k]
            wsum[inv[i]] += w[i]
            msum[inv[i]] += w[i] * res
        n_out = 0
        n_in = 0
        out = np.zeros(n_u, np.bool_)
        for e in range(n_u):
            if wsum[e] > 0:
                if abs(msum[e] / max(wsum[e], 1e-12)) > edge_outlier_px:
                    out[e] = True
                    n_out += 1
                else:
                    n_in += 1
        if n_out == 0 or n_in < 4:
            break
        for i in range(N):
            if out[inv[i]]:
                keep[i] = False
                w[i] = 0.0
    n_keep = 0
    weight = 0.0
    wrr = 0.0
    wtot = 0.0
    G = np.zeros((n_u, 6))
    seen = np.zeros(n_u, np.bool_)
    for i in range(N):
        wtot += w[i]
        wrr += w[i] * r[i] * r[i]
        for k in range(6):
            G[inv[i], k] += J[i, k] * w[i]
        if keep[i]:
            n_keep += 1
            weight += dens[i]
            seen[inv[i]] = True
    GtG = np.zeros((6, 6))
    for e in range(n_u):
        for j in range(6):
            for k in range(6):
                GtG[j, k] += G[e, j] * G[e, k]
    rms = np.sqrt(wrr / wtot) if wtot > 0 else np.nan
    return step, A, n_keep, rms, int(seen.sum()), weight, GtG


def refine_subpixel(T_world_object: np.ndarray, views: list[CameraView], mf: ModelFeatures, tree=None,
                    rounds: int = 4, search_px: float = 3.0, min_grad: float = 40.0, f_scale: float = 0.7,
                    shared_edge_px: float = SHARED_EDGE_PX, spacing_px: float = 0.0, edge_outlier_px: float = 0.0,
                    near_peak_frac: float = 0.0, expect: list | None = None,
                    contrast_ratio: tuple[float, float] = (0.4, 3.0), info: bool = False):
    """Final sub-pixel refinement by 1D edge search along the projected normals.

    Each visible edge sample looks along its projected edge normal (within
    ``search_px``) for the strongest gradient of matching direction (the image
    gradient projected on the normal), located to sub-pixel by a parabola
    through the peak; the pose then minimises the Huber-weighted normal
    distances of all cameras' samples to their edge points (Gauss-Newton, as
    in RAPiD-style trackers). An image edge point found by samples of two
    nearly parallel model edges (within ``shared_edge_px``) serves only the
    nearer one (:func:`shared_edge_losers`): counted for both, it pulled the
    thin strip of a face seen edge-on onto one image edge and the pose of a
    single-camera L-block view 12% of the diameter off along the ray, even
    when refined from the true pose (0 turns it off). With ``spacing_px``,
    an edge's samples weigh together at most one per ``spacing_px`` of its
    projected length: the samples are spaced evenly along the model edge, so
    an edge that points at the camera packs many of them into a few pixels
    between two junctions, where the blurs of the edges meeting there mix,
    and would count as much as a long edge seen square on (see
    :class:`vespro.edgeaid.EdgeAid` for what that did to one-camera fits).
    With ``edge_outlier_px``, an edge whose residuals the solved step leaves
    more than that off on average (weighted) has found a neighbouring image
    edge (its own too faint: a dark face on a dark background); it is left out
    of the round and the step solved again (twice at most, keeping four
    edges). With ``near_peak_frac``, a sample takes the nearest gradient peak
    of those at least that fraction of the highest (a face seen edge on is a
    line a pixel wide whose far side may be the stronger edge; see
    :class:`vespro.edgeaid.EdgeAid`). With ``expect`` (per view, each edge
    sample's expected signed contrast, NaN where unknown; see
    :attr:`EdgeFit.sample_contrast`), a sample takes only gradient peaks
    of that sign whose strength is within ``contrast_ratio`` times the expected
    (as the moving-edge trackers check each site's contrast against its last;
    see :class:`vespro.edgeaid.EdgeContrast`). Canny pixels and the distance
    maps are only pixel-accurate; this removes that quantisation from the
    final pose.

    Returns
    -------
    ndarray, shape (4, 4)
        The refined pose; with ``info``, ``(pose, EdgeFit or None)`` (None when
        too few samples found an edge point to fit).
    """
    T = np.array(T_world_object, float)
    offs = np.arange(-search_px, search_px + 1e-9, 0.5)
    fit = None
    cams = []  # per view: T_camera_world and its rotation, the same every round
    for v in views:
        T_cw = invert_transform(v.T_world_camera)
        cams.append((T_cw, np.ascontiguousarray(T_cw[:3, :3])))
    for _ in range(rounds):
        rows_J, rows_r, rows_e, rows_d = [], [], [], []
        n_searched = 0
        w_searched = w_shared = 0.0  # summed sample weights: searched; found but lost to a parallel edge
        contrast = []
        R = np.ascontiguousarray(T[:3, :3])
        for iv, v in enumerate(views):
            T_cw, R_cw = cams[iv]
            T_co = T_cw @ T
            idx = visible_samples(T_co, mf, tree)
            contrast.append(np.full(len(mf.sample_p), np.nan) if info else None)
            if idx.size == 0:
                continue
            n_searched += idx.size
            K = v.feat.K
            exp = np.full(idx.size, np.nan) if expect is None or expect[iv] is None else \
                np.asarray(expect[iv], float)[idx]
            ok, sstar, c_peak, c0, dens, lost, w_strip, Jv = _subpixel_view_kernel(
                v.feat.grad, K[0, 0], K[1, 1], K[0, 2], K[1, 2], T_co, R, R_cw, idx,
                mf.sample_p, mf.sample_edge, mf.edge_a, mf.edge_b, offs, float(min_grad), float(near_peak_frac), exp,
                float(contrast_ratio[0]), float(contrast_ratio[1]), float(spacing_px), float(shared_edge_px),
                COS_PARALLEL, mf.tri_p, mf.tri_face, mf.edge_faces, len(mf.face_normals))
            se = mf.sample_edge[idx]
            w_searched += float(dens.sum())
            if info:
                contrast[-1][idx] = c0
            w_shared += w_strip
            if not ok.any():
                continue
            if info:
                contrast[-1][idx[ok]] = c_peak[ok]  # the image edge a sample took (or, above, none near it)
            # Residual: n . (uv - target) = -s*; Jacobian n^T d(uv)/dx (the kernel's rows).
            rows_d.append(dens[ok])
            rows_J.append(Jv[ok])
            rows_r.append(-sstar[ok])
            rows_e.append(se[ok] + len(mf.edge_a) * len(rows_e))
        if not rows_J:
            break
        one = len(rows_J) == 1  # (one view: its rows as they are, no copy)
        J = rows_J[0] if one else np.concatenate(rows_J)
        r = rows_r[0] if one else np.concatenate(rows_r)
        if len(r) < 12:
            break
        dens = rows_d[0] if one else np.concatenate(rows_d)
        eid = rows_e[0] if one else np.concatenate(rows_e)
        step, A, n_keep, rms, n_edges, weight, GtG = _solve_edges(J, r, dens, eid, float(f_scale),
                                                                 float(edge_outlier_px))
        if n_keep < 12:
            break
        if info:  # the record of the round (what the caller asked for; not needed for the pose)
            fit = EdgeFit(A, rms, n_keep, n_edges, n_searched, weight, weight + w_shared, w_searched, GtG,
                          tuple(contrast))
        T = _perturbed(T, step)
        dw, dp = step[:3], step[3:]
        if math.sqrt(dw @ dw) < 1e-5 and math.sqrt(dp @ dp) < 1e-6:  # (np.linalg.norm of a vector)
            break
    return (T, fit) if info else T
