"""Pose hypotheses, their chamfer scores and their verification.

All scores use the oriented distance maps of :mod:`vespro.init.features`: a
model edge point projected at pixel (u, v) with edge normal in bin k is
supported when ``dt[k][v, u]`` is small. Visibility of model edges comes from
back-face culling (a convex edge is seen when one of its faces faces the
camera, a concave edge when both do) and, for non-convex models, from the BSP
line-of-sight query (edge samples hidden by the part itself are dropped). The
refinement of a pose on the image edges is :mod:`vespro.edgefit`'s.

The inner loops of the ranking of many poses are compiled kernels
(:mod:`vespro.jit`) that repeat the NumPy formulation's arithmetic operation
for operation: their results are the NumPy code's, bit for bit
(``tests/vespro/test_init_kernels.py`` keeps that code as the reference).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..edgefit import CameraView, camera_setup
from ..imageedges import front_faces as _front
from ..imageedges import project_points as _project
from ..jit import njit
from ..numerics import dot3, pairwise_sum
from ..se3 import invert_transform
from .features import CameraFeatures, lookup_dt
from .modelfeat import ModelFeatures
from .p3p import p3p_grunert

__all__ = ["image_paths", "p3p_hypotheses", "rank_in_camera", "interior_clutter", "face_interiors", "PoseCheck",
           "check_pose", "unshared_px"]


# -- hypothesis generation ---------------------------------------------------

def image_paths(feat: CameraFeatures, min_angle_deg: float = 15.0, max_paths: int = 20000,
                one_end: bool = False) -> np.ndarray:
    """Image corner paths ``(a, b, c)``: corners a and c linked to b by edges ending at b.

    With ``one_end`` only one of the two links need end at b (the other's
    edge may run on past b, along a background line in line with it).
    Each unordered pair {a, c} appears once (the model paths hold both orders).
    Paths with nearly straight or folded angles at b are dropped; when there
    are more than ``max_paths`` the ones with the shortest links are kept
    (short links are the likelier ones to lie on a single part).

    Returns
    -------
    ndarray, shape (N, 3), int64
    """
    links = feat.links
    if len(links) == 0:
        return np.zeros((0, 3), np.int64)
    c = feat.corners
    # (b, other, the link's edge ends at b) for every link.
    both = np.concatenate([links, links[:, ::-1]])
    ends = np.concatenate([feat.link_ends[:, 0], feat.link_ends[:, 1]])
    if not one_end:
        both, ends = both[ends], ends[ends]
    order = np.argsort(both[:, 0], kind="stable")
    both, ends = both[order], ends[order]
    starts = np.searchsorted(both[:, 0], np.arange(len(c) + 1))
    out, cost = [], []
    cmax = np.cos(np.deg2rad(min_angle_deg))
    for b in range(len(c)):
        nb = both[starts[b]:starts[b + 1], 1]
        eb = ends[starts[b]:starts[b + 1]]
        if len(nb) < 2:
            continue
        i, j = np.triu_indices(len(nb), 1)
        da = c[nb[i]] - c[b]
        dc = c[nb[j]] - c[b]
        la, lc = np.linalg.norm(da, axis=1), np.linalg.norm(dc, axis=1)
        cosang = np.einsum("ij,ij->i", da, dc) / (la * lc)
        ok = (np.abs(cosang) < cmax) & (eb[i] | eb[j])
        out.append(np.stack([nb[i][ok], np.full(ok.sum(), b), nb[j][ok]], 1))
        cost.append(np.maximum(la, lc)[ok])
    if not out:
        return np.zeros((0, 3), np.int64)
    out = np.concatenate(out)
    cost = np.concatenate(cost)
    if len(out) > max_paths:
        out = out[np.argsort(cost, kind="stable")[:max_paths]]
    return out.astype(np.int64)


def p3p_hypotheses(feat: CameraFeatures, mf: ModelFeatures, vertices: np.ndarray, ipaths: np.ndarray,
                   max_depth: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """All P3P poses pairing image corner paths with model corner paths.

    Returns
    -------
    R_camera_object : ndarray, shape (M, 3, 3)
    t_camera_object : ndarray, shape (M, 3)
    """
    if len(ipaths) == 0 or len(mf.paths) == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    Kinv = np.linalg.inv(feat.K)
    uv1 = np.c_[feat.corners, np.ones(len(feat.corners))] @ Kinv.T
    bear = uv1 / np.linalg.norm(uv1, axis=1, keepdims=True)
    ii = np.repeat(np.arange(len(ipaths)), len(mf.paths))
    mm = np.tile(np.arange(len(mf.paths)), len(ipaths))
    R, t, prob = p3p_grunert(vertices[mf.paths[mm]], bear[ipaths[ii]])
    centre = 0.5 * (mf.edge_a.min(0) + mf.edge_a.max(0))
    zc = np.einsum("nij,j->ni", R, centre)[:, 2] + t[:, 2]
    ok = (zc > 0.5 * mf.diameter) & (zc < max_depth)
    return R[ok], t[ok]


# -- compiled kernels ----------------------------------------------------------
#
# The kernels keep the NumPy code's arithmetic operation for operation; their
# products with a rotation are :func:`vespro.numerics.dot3`, OpenBLAS's order.


@njit
def _project_all_f32(Rc, tc, i, Pt, f, c, u, v, z):
    """Pixel (u, v) and depth z of object points ``Pt`` (3, n) at pose ``i``, float32, into
    ``u, v, z`` (n,): ``X = P R^T + t``, ``uv = X[:2] / z * f + c``, as the NumPy code of
    :func:`rank_in_camera`. Branch-free, so the loop vectorises."""
    r00, r01, r02 = Rc[i, 0, 0], Rc[i, 0, 1], Rc[i, 0, 2]
    r10, r11, r12 = Rc[i, 1, 0], Rc[i, 1, 1], Rc[i, 1, 2]
    r20, r21, r22 = Rc[i, 2, 0], Rc[i, 2, 1], Rc[i, 2, 2]
    t0, t1, t2 = tc[i, 0], tc[i, 1], tc[i, 2]
    f0, f1, c0, c1 = f[0], f[1], c[0], c[1]
    for s in range(Pt.shape[1]):
        p0, p1, p2 = Pt[0, s], Pt[1, s], Pt[2, s]
        zs = dot3(p0, p1, p2, r20, r21, r22) + t2
        u[s] = (dot3(p0, p1, p2, r00, r01, r02) + t0) / zs * f0 + c0
        v[s] = (dot3(p0, p1, p2, r10, r11, r12) + t1) / zs * f1 + c1
        z[s] = zs


@njit
def _rank_edge_dirs(Rc, tc, ends_t, f, c):
    """Projected edge directions ``d = uv(b) - uv(a)`` at every pose, as ``d[..., 0]`` and
    ``-d[..., 1]`` (h, E) float32 (the arguments of the ``arctan2`` of
    :func:`vespro.edgefit.camera_setup`'s orientation bins).

    ``ends_t`` (3, 2E) float32: the edges' first ends, then their second ends."""
    h, E = Rc.shape[0], ends_t.shape[1] // 2
    dx = np.empty((h, E), np.float32)
    ndy = np.empty((h, E), np.float32)
    u = np.empty(2 * E, np.float32)
    v = np.empty(2 * E, np.float32)
    z = np.empty(2 * E, np.float32)
    for i in range(h):
        _project_all_f32(Rc, tc, i, ends_t, f, c, u, v, z)
        for e in range(E):
            dx[i, e] = u[E + e] - u[e]
            ndy[i, e] = -(v[E + e] - v[e])
    return dx, ndy


@njit
def _normal_bin_i32(angle, n_bins):
    """``normal_bins`` of one float32 angle (``np.mod`` by pi, times ``n_bins / pi``, in
    float32 as NumPy does with Python floats), as the int32 the NumPy code indexes with:
    a NaN angle, cast to int64's minimum there, keeps its low 32 bits, 0."""
    pi32 = np.float32(np.pi)
    m = angle if abs(angle) < pi32 else np.fmod(angle, pi32)  # fmod(a, p) is a when |a| < p: arctan2's range
    if m != 0:
        if m < 0:  # Python's (and np.mod's) sign convention
            m = m + pi32
    else:
        m = np.float32(0.0)
    x = m * np.float32(n_bins / np.pi)
    if np.isnan(x):
        return np.int32(0)
    return np.int32(min(np.int64(x), n_bins - 1))


@njit
def _edges_seen(front, i, ef_l, convex, vis_e):
    """Visible edges at pose ``i`` from its front-facing faces (as :func:`vespro.imageedges.edge_visible`) into ``vis_e``."""
    for e in range(ef_l.shape[0]):
        a = front[i, ef_l[e, 0]]
        b = front[i, ef_l[e, 1]]
        vis_e[e] = (a or b) if convex[e] else (a and b)


@njit
def _rank_seen(Rc, tc, Pt, se_l, front, ef_l, convex, f, c, H_img, W_img):
    """(h, S) bool: the samples on a visible edge that project inside the image (``vis & inside``)."""
    h, S = Rc.shape[0], Pt.shape[1]
    out = np.zeros((h, S), np.bool_)
    vis_e = np.empty(ef_l.shape[0], np.bool_)
    u = np.empty(S, np.float32)
    v = np.empty(S, np.float32)
    z = np.empty(S, np.float32)
    for i in range(h):
        _edges_seen(front, i, ef_l, convex, vis_e)
        _project_all_f32(Rc, tc, i, Pt, f, c, u, v, z)
        for s in range(S):
            if vis_e[se_l[s]]:
                ui, vi = np.rint(u[s]), np.rint(v[s])
                out[i, s] = ui >= 0 and ui <= W_img - 1 and vi >= 0 and vi <= H_img - 1 and z[s] > 0
    return out


@njit
def _rank_score(Rc, tc, Pt, se_l, front, ef_l, convex, angle, n_bins, f, c, dt_flat, H_img, W_img, tol, min_inside,
                blocked, score, inside_frac):
    """Compiled body of :func:`rank_in_camera` for one chunk of poses.

    Per pose: edge visibility from ``front``, less the ``blocked`` (h, S)
    samples (an empty array: none); orientation bins from the edges'
    ``angle`` (h, E); projection, rounding to the pixel and the oriented
    distance lookup in float32; agreement ``max(0, 1 - d / tol)`` summed with
    NumPy's pairwise float32 summation. Writes ``score`` and ``inside_frac``
    (h,); the same bits as the NumPy code (``tol`` float32, as a Python float
    becomes in that code).
    """
    h, S, E = Rc.shape[0], Pt.shape[1], ef_l.shape[0]
    vis_e = np.empty(E, np.bool_)
    bin_e = np.zeros(E, np.int32)
    agree = np.empty(S, np.float32)
    u = np.empty(S, np.float32)
    v = np.empty(S, np.float32)
    z = np.empty(S, np.float32)
    one, zero = np.float32(1.0), np.float32(0.0)
    use_blocked = blocked.shape[0] > 0
    for i in range(h):
        _edges_seen(front, i, ef_l, convex, vis_e)
        for e in range(E):
            if vis_e[e]:
                bin_e[e] = _normal_bin_i32(angle[i, e], n_bins)
        _project_all_f32(Rc, tc, i, Pt, f, c, u, v, z)
        behind = False
        for s in range(S):
            behind |= z[s] <= 0
        nvis, nins = 0, 0
        for s in range(S):
            agree[s] = zero
            e = se_l[s]
            if not vis_e[e] or (use_blocked and blocked[i, s]):
                continue
            nvis += 1
            ui, vi = np.rint(u[s]), np.rint(v[s])
            if ui >= 0 and ui <= W_img - 1 and vi >= 0 and vi <= H_img - 1 and z[s] > 0:
                nins += 1
                k = (bin_e[e] * np.int32(H_img) + np.int32(vi)) * np.int32(W_img) + np.int32(ui)
                q = one - dt_flat[k] / tol
                agree[s] = zero if q < zero else q
        if nvis > 0:
            fr = nins / nvis
            inside_frac[i] = fr
            ok = not behind and fr >= min_inside
            score[i] = np.float64(pairwise_sum(agree, S)) / nvis if ok else np.nan
        else:
            inside_frac[i] = 0.0
            score[i] = np.nan


def rank_in_camera(R: np.ndarray, t: np.ndarray, feat: CameraFeatures, mf: ModelFeatures, tol_px: float = 3.0,
                   chunk: int = 8192, min_inside: float = 0.3, samples: np.ndarray | None = None, tree=None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Fast chamfer agreement of many camera-frame poses with one image.

    Edge samples (``samples``, indices into ``mf.sample_p``; the coarse set by
    default), back-face culling only, or with ``tree`` (a BSP tree of a
    non-convex model) also the line of sight: samples the part hides from
    itself are dropped (~0.5 ms a pose on the coarse set, so for the best few
    hundred). Without it, the hidden edges of a non-convex part count as
    unsupported: its true pose scored 0.44 on a bracket view where flatter
    wrong poses scored 0.7, and ranked out. The agreement of a
    sample is ``max(0, 1 - d / tol_px)`` with ``d`` its oriented edge distance;
    the score is the mean over visible samples.

    Projections, pixel rounding and the agreement sums are float32. The
    per-pose loops are compiled (``_rank_edge_dirs``, ``_rank_score``); the
    face culling, the edges' image angles (NumPy's ``arctan2``) and the line of
    sight stay in NumPy.

    Returns
    -------
    score : ndarray, shape (H,)
        In [0, 1]; NaN where the camera cannot judge (fewer than
        ``min_inside`` of the visible samples inside the image, or the part
        behind the camera).
    inside : ndarray, shape (H,)
        Fraction of visible samples inside the image.
    """
    H = len(R)
    score = np.full(H, np.nan)
    inside_frac = np.zeros(H)
    samples = mf.coarse if samples is None else samples
    Pt = np.ascontiguousarray(mf.sample_p[samples].astype(np.float32).T)  # (3, S)
    se = mf.sample_edge[samples]
    used_e = np.unique(se)
    remap = np.zeros(len(mf.edge_a), np.int64)
    remap[used_e] = np.arange(len(used_e))
    se_l = remap[se]
    ends_t = np.ascontiguousarray(np.concatenate([mf.edge_a[used_e], mf.edge_b[used_e]]).astype(np.float32).T)
    f = np.array([feat.K[0, 0], feat.K[1, 1]], np.float32)
    c = feat.K[:2, 2].astype(np.float32)
    nb = feat.dt.shape[0]
    # Faces and edges the samples need; front-facing test n.(R^T t) + d < 0.
    ef = mf.edge_faces[used_e]
    faces_u, ef_l = np.unique(ef, return_inverse=True)
    ef_l = np.ascontiguousarray(ef_l.reshape(-1, 2))
    n_f = mf.face_normals[faces_u].astype(np.float32)
    d_f = mf.face_offsets[faces_u].astype(np.float32)
    convex_u = np.ascontiguousarray(mf.edge_convex[used_e])
    H_img, W_img = feat.dt.shape[1:]
    dt_flat = np.ascontiguousarray(feat.dt, dtype=np.float32).reshape(-1)
    # As a Python float meets the float32 distances in NumPy (NEP 50).
    tol = np.float32(tol_px)
    no_block = np.zeros((0, 0), bool)
    for s in range(0, H, chunk):
        Rc = np.ascontiguousarray(R[s:s + chunk].astype(np.float32))
        tc = np.ascontiguousarray(t[s:s + chunk].astype(np.float32))
        w = np.matmul(Rc.transpose(0, 2, 1), tc[:, :, None])[..., 0]  # R^T t, (h, 3)
        front = (w @ n_f.T + d_f) < 0
        angle = np.arctan2(*_rank_edge_dirs(Rc, tc, ends_t, f, c))  # NumPy's (SIMD) arctan2, as camera_setup
        blocked = no_block
        if tree is not None and not mf.convex:
            hh, ss = np.nonzero(_rank_seen(Rc, tc, Pt, se_l, front, ef_l, convex_u, f, c, H_img, W_img))
            if hh.size:
                A = mf.sample_p[samples[ss]]
                cam = -w[hh].astype(float)  # camera centre, object frame
                seg = np.linalg.norm(cam - A, axis=1)
                hit = tree.segments_blocked(A, cam, t_lo=np.minimum(2e-4 / seg, 0.1), t_hi=1.0, min_length=1e-9)
                blocked = np.zeros((len(Rc), Pt.shape[1]), bool)
                blocked[hh[hit], ss[hit]] = True
        _rank_score(Rc, tc, Pt, se_l, front, ef_l, convex_u, angle, nb, f, c, dt_flat, H_img, W_img, tol,
                    float(min_inside), blocked, score[s:s + chunk], inside_frac[s:s + chunk])
    return score, inside_frac


# -- verification ----------------------------------------------------------------

def interior_clutter(T_camera_object: np.ndarray, feat: CameraFeatures, mf: ModelFeatures,
                     margin_px: float = 3.0) -> tuple[float, int]:
    """Edge pixels inside the projected faces of a pose (an untextured part has none).

    At the true pose of a part with plain faces the face interiors hold only
    image noise; a pose fitted to clutter, or a shifted or flipped copy of the
    part, covers image edges (the real part's own edges among them). Returns
    ``(frac, n_interior)`` of :func:`face_interiors`.
    """
    frac, n, _, _ = face_interiors(T_camera_object, feat, mf, margin_px)
    return frac, n


def face_interiors(T_camera_object: np.ndarray, feat: CameraFeatures, mf: ModelFeatures,
                   margin_px: float = 3.0, min_face_px: int = 50, min_side: float = 0.15,
                   min_step_grey: float = 2.0) -> tuple[float, int, float, float]:
    """What lies inside the projected faces of a pose: image edges, and the shading.

    The front-facing mesh triangles are painted far to near into a face-label
    image (painter's order by triangle depth: enough for these parts); pixels
    more than ``margin_px`` from any face or silhouette boundary are the face
    interiors.

    The shading: a plane face of one material under distant light shows one
    shade (plus the image noise). A pose whose faces straddle a boundary of
    the image's shades (a face of the part turned over onto two faces of the
    real part, a box's top face pulled over its side) is less uniform, even
    where that boundary is too faint for an edge (2-4 grey levels between two
    faces of a grey part): the RMS of the interior grey levels about each
    face's own mean measures it. A face lying over two shades with a sharp
    boundary between them splits its grey levels in two groups far apart
    for their spread (:func:`_shade_step`); a shading gradient across a face
    spreads them evenly (a ratio of about 0.29 for an even spread).

    Parameters
    ----------
    T_camera_object : ndarray, shape (4, 4)
    feat : CameraFeatures
    mf : ModelFeatures
    margin_px : float

    Returns
    -------
    frac : float
        Fraction of the interior pixels on Canny edges (NaN when the part is
        behind the camera, off the image or has no interior).
    n_interior : int
        Interior pixels.
    shade_rms : float
        RMS of the interior pixels' grey levels about their face's mean (NaN
        when there is no interior or ``feat`` has no grey image).
    shade_step : float
        Least, over the faces with at least ``min_face_px`` interior pixels,
        ratio of the RMS within the two groups of a face's grey levels
        (Otsu's split) to the step between their means, where the smaller
        group holds at least ``min_side`` of the face and the step is at least
        ``min_step_grey``; inf where no face splits so (NaN without a grey
        image). Image noise adds to the spread: on a noisy image only a step
        of many times the noise gives a small ratio.
    """
    nan = float("nan")
    R, t = T_camera_object[:3, :3], T_camera_object[:3, 3]
    front = _front(R[None], t[None], mf)[0]
    keep = front[mf.tri_face]
    X = mf.tri_p[keep] @ R.T + t  # (T, 3, 3)
    if len(X) == 0 or np.any(X[..., 2] <= 1e-6):
        return nan, 0, nan, nan
    K = feat.K
    uv = X[..., :2] / X[..., 2:3] * K[[0, 1], [0, 1]] + K[:2, 2]
    lo = np.floor(uv.reshape(-1, 2).min(0)).astype(int) - 2
    hi = np.ceil(uv.reshape(-1, 2).max(0)).astype(int) + 3
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [feat.width, feat.height])
    if np.any(hi - lo < 3):
        return nan, 0, nan, nan
    w, h = hi - lo
    label = np.zeros((h, w), np.int32)
    order = np.argsort(-X[..., 2].mean(1))
    faces = mf.tri_face[keep]
    pts = np.rint((uv - lo) * 4).astype(np.int32)  # 2 bits of sub-pixel precision
    for k in order:
        cv2.fillPoly(label, [pts[k]], int(faces[k]) + 1, lineType=cv2.LINE_8, shift=2)
    bnd = np.zeros((h, w), bool)
    bnd[:, 1:] |= label[:, 1:] != label[:, :-1]
    bnd[:, :-1] |= label[:, 1:] != label[:, :-1]
    bnd[1:, :] |= label[1:, :] != label[:-1, :]
    bnd[:-1, :] |= label[1:, :] != label[:-1, :]
    bnd[0, :] = bnd[-1, :] = True
    bnd[:, 0] = bnd[:, -1] = True
    dist = cv2.distanceTransform(np.where(bnd, 0, 255).astype(np.uint8), cv2.DIST_L2, 3)
    interior = (label > 0) & (dist > margin_px)
    n = int(interior.sum())
    if n == 0:
        return nan, 0, nan, nan
    e = feat.edges[lo[1]:hi[1], lo[0]:hi[0]] > 0
    frac = float(np.count_nonzero(e & interior)) / n
    if feat.grey is None:
        return frac, n, nan, nan
    gi = feat.grey[lo[1]:hi[1], lo[0]:hi[0]][interior]
    g = gi.astype(np.float64)
    f = label[interior]
    cnt = np.bincount(f)
    mean = np.bincount(f, g) / np.maximum(cnt, 1)
    step = min((_shade_step(gi[f == k], min_side, min_step_grey) for k in np.flatnonzero(cnt >= min_face_px)),
               default=float("inf"))
    return frac, n, float(np.sqrt(np.mean((g - mean[f]) ** 2))), step


def _shade_step(grey: np.ndarray, min_side: float, min_step: float) -> float:
    """RMS within the two groups of grey levels ``grey`` (uint8) split by Otsu's threshold, over
    the step between the groups' means; inf when the smaller group holds under ``min_side`` of
    the values or the step is under ``min_step`` grey levels."""
    h = np.bincount(grey, minlength=256).astype(np.float64)
    p = h / h.sum()
    lv = np.arange(256.0)
    w0 = np.cumsum(p)[:-1]  # the lower group: levels <= t
    m0 = np.cumsum(p * lv)[:-1]
    mt = float(p @ lv)
    w1 = 1.0 - w0
    ok = (w0 >= min_side) & (w1 >= min_side)
    if not ok.any():
        return float("inf")
    between = np.where(ok, (mt * w0 - m0) ** 2 / np.maximum(w0 * w1, 1e-12), -1.0)
    t = int(np.argmax(between))
    mu0, mu1 = m0[t] / w0[t], (mt - m0[t]) / w1[t]
    d = mu1 - mu0
    if d < min_step:
        return float("inf")
    within = max(float(p @ (lv - mt) ** 2) - between[t], 0.0)
    return float(np.sqrt(within) / d)


@dataclass(frozen=True)
class PoseCheck:
    """How well a world pose explains every camera's image.

    Attributes
    ----------
    inlier_frac : float
        Fraction of the visible edge samples (in cameras that can judge)
        within ``tol_px`` of an edge of matching orientation.
    per_camera : dict[str, float]
        Same per camera (NaN where the part is mostly outside the image).
    n_samples : int
        Visible samples counted.
    supported_edges : int
        Visible edges (projected longer than ``min_edge_px``) with at least
        half their samples inliers.
    visible_edges : int
    n_cameras : int
        Cameras that judged.
    mean_dist : float
        Mean clipped oriented distance of the visible samples, px.
    unseen_fixed : int
        Fixed cameras that cannot see the part at this pose (counted only
        with ``require_fixed``).
    min_size_px : float
        Smallest projected size (bounding-box diagonal of the edge samples)
        over the judging cameras, px.
    inlier_px : float
        Projected length of model edge explained by image edges, summed over
        cameras, px (a fit of part of the image by a smaller, farther copy
        explains less).
    overrun_frac : float
        Fraction of the visible model edge ends past which the image edge
        runs straight on: a true corner ends its edges, a smaller copy fitted
        inside the part (or to a longer background line) does not.
    open_faces : int
        Least number, over the judging cameras, of faces (of at least 5% of
        the part's area) seen within ``open_face_deg`` of their normal: a view
        along a face (an accidental viewpoint) collapses it to a line and
        lets a part match flat clutter.
    interior_edge_frac : float
        Largest fraction, over the judging cameras, of the projected face
        interiors lying on image edges (:func:`interior_clutter`).
    shade_rms : float
        Largest, over the judging cameras, RMS of the face interiors' grey
        levels about their face's mean (:func:`face_interiors`), grey levels
        (NaN where no camera could say).
    shade_step : float
        Least, over the judging cameras, :func:`face_interiors`'s
        ``shade_step``: a face lying over two shades (inf where none does).
    shade_noise : float
        The intensity noise of that camera's image
        (:attr:`vespro.init.features.CameraFeatures.grey_noise`), grey levels:
        what ``shade_rms`` is at most on faces of one shade each.
    crease_edges, crease_supported : int
        Visible edges between two faces that both face the camera (inside
        the silhouette), summed over cameras, and how many are supported.
        Two faces at an angle rarely have the same shade, so a crease shows
        in the image even where a face matches its background.
    distinct_supported : int
        Supported edges that stand apart in the image, summed over cameras:
        supported edges lying nearly parallel within ``2 tol_px`` of each
        other over a common stretch count once (one image edge can support
        both; :func:`_distinct_segments`). A face seen nearly edge-on (the
        strip of a box's side face beside its top face seen head-on) adds
        its far edge to ``supported_edges`` for nothing: that edge lies on
        the crease's image edge whatever the tilt.
    strips_apart : int
        Supported far edges of strips (faces toward the camera, not seen
        openly) standing apart from their creases, parallel to them, summed
        over cameras (:func:`_strips_apart`): the side faces' widths seen.
    open_edges_apart : int
        Supported edges of the openly seen faces standing apart in the image
        (as ``distinct_supported``), summed over cameras: four for a
        rectangle seen head-on, six for an L-block's L.
    outer_parallel : int
        Silhouette edges with an image edge of their orientation running beside
        them just outside (:func:`_outer_parallel`), summed over
        the cameras that see at most one face openly and no strip apart (the
        views :attr:`vespro.init.initializer.InitOptions.max_outer_parallel_confirm`
        judges; 0 elsewhere, not looked at).
    hidden : str
        A camera left out of these statistics because the part is hidden
        there (``InitOptions.hidden_camera``); empty when none is.
    explained : tuple
        Per judging camera ``(name, uv (n, 2), spacing (n,), bin (n,), n_bins)``:
        the projected edge samples within ``tol_px`` of an image edge of their
        orientation, each sample's projected spacing along its edge (px) and
        orientation bin; for :func:`unshared_px`.
    """

    inlier_frac: float
    per_camera: dict
    n_samples: int
    supported_edges: int
    visible_edges: int
    n_cameras: int
    mean_dist: float
    unseen_fixed: int = 0
    min_size_px: float = 0.0
    inlier_px: float = 0.0
    open_faces: int = 0
    overrun_frac: float = 0.0
    interior_edge_frac: float = 0.0
    crease_edges: int = 0
    crease_supported: int = 0
    hidden: str = ""
    explained: tuple = ()
    distinct_supported: int = 0
    strips_apart: int = 0
    open_edges_apart: int = 0
    outer_parallel: int = 0
    shade_rms: float = float("nan")
    shade_noise: float = 0.0
    shade_step: float = float("inf")


def _outer_parallel(k_sil, ue, ub, elen, uv, e, bins, n_bins, dt, inward_uv, min_px: float, lo_px: float,
                    hi_px: float, min_frac: float) -> int:
    """How many silhouette edges have an image edge of their orientation running beside them just outside.

    For each silhouette edge projected at least ``min_px`` long, its visible
    samples look ``lo_px`` to ``hi_px`` outward (away from ``inward_uv``, a
    point of its front face) for an image edge of their orientation bin
    (within 1 px) that no other visible edge of the pose lies on (a sample of
    another edge, of a neighbouring bin, within 2.5 px: a bracket's flange
    beyond the silhouette of its web is the part's own); the edge counts when
    at least ``min_frac`` of its samples find one, unless that line (at the
    median offset found) runs on 6-15 px past either end of the edge where no
    edge of the pose lies. Beyond a true outline lies the background: a line
    beside it, all along and ending with it, says the part goes on past the
    pose's outline (the far edge of a side face the pose does not have); a
    line running on is the background's (L-block 801 lying along the belt's
    border, 11 px off its inner edge: the true pose, refused without this).

    Parameters
    ----------
    k_sil : ndarray of int
        Silhouette edges with visible samples.
    ue, ub : ndarray, shape (E, 2)
        Projected edge ends, px; ``elen`` their lengths.
    uv, e, bins : ndarray
        Visible samples: pixels, edges, orientation bins (``n_bins`` over pi).
    dt : ndarray, shape (n_bins, H, W)
        The image's oriented distance transform.
    inward_uv : ndarray, shape (len(k_sil), 2)
    """
    n = 0
    s_ = np.arange(lo_px, hi_px + 0.5, 1.0)
    run_px = np.arange(6.0, 15.5, 1.5)
    for k, c in zip(k_sil, inward_uv):
        m = np.flatnonzero(e == k)
        if elen[k] < min_px or len(m) < 5:
            continue
        d = (ub[k] - ue[k]) / elen[k]
        nrm = np.array([-d[1], d[0]])
        if nrm @ (c - ue[k]) > 0:
            nrm = -nrm
        q = uv[m][:, None, :] + s_[None, :, None] * nrm  # (samples, offsets, 2)
        hit = lookup_dt(dt, np.broadcast_to(bins[m][:, None], q.shape[:2]), q, np.inf) <= 1.0
        # Other edges' samples that can lie within 2.5 px of the band looked at (the
        # samples of edge k lie on its line): the band's rectangle grown by 2.5 px.
        rel = uv - ue[k]
        along, across = rel @ d, rel @ nrm
        # (as far as the look past its ends below, which takes the same samples)
        other = np.flatnonzero((e != k) & (across >= lo_px - 2.5) & (across <= hi_px + 2.5)
                               & (along >= -run_px[-1] - 2.5) & (along <= elen[k] + run_px[-1] + 2.5))
        hit &= ~_own_samples(q, bins[m], uv[other], bins[other], n_bins)
        rows = np.any(hit, axis=1)
        if np.mean(rows) < min_frac:
            continue
        # The line (at its median offset) running on past an end of the edge, where
        # no edge of the pose lies, is the background's (a belt's border along the part).
        off = float(np.median(s_[np.argmax(hit[rows], axis=1)]))
        b_k = bins[m[len(m) // 2]]
        runs_on = False
        for end, sgn in ((ub[k], 1.0), (ue[k], -1.0)):
            pts = end + run_px[:, None] * sgn * d + off * nrm
            on = lookup_dt(dt, np.full(len(pts), b_k), pts, np.inf) <= 1.5
            on &= ~_own_samples(pts[:, None, :], np.full(len(pts), b_k), uv[other], bins[other], n_bins)[:, 0]
            runs_on |= bool(np.mean(on) >= 0.7)
        n += int(not runs_on)
    return n


def _own_samples(q, q_bins, uv_o, bins_o, n_bins, r_px: float = 2.5):
    """Which points ``q`` (n, j, 2) lie within ``r_px`` of a sample ``uv_o`` of a neighbouring
    orientation bin (``q_bins`` (n,) per row): where an edge of the pose lies."""
    if len(uv_o) == 0:
        return np.zeros(q.shape[:2], bool)
    near_bin = _bins_near(q_bins, bins_o, n_bins)  # (n, other)
    d2 = np.sum((q[:, :, None, :] - uv_o[None, None]) ** 2, axis=3)  # (n, j, other)
    return np.any((d2 <= r_px ** 2) & near_bin[:, None, :], axis=2)


def _bins_near(b1: np.ndarray, b2: np.ndarray, n_bins: int) -> np.ndarray:
    """(len(b1), len(b2)): orientation bins the same or neighbours (cyclic over ``n_bins``)."""
    db = np.abs(b1[:, None] - b2[None]) % n_bins
    return np.minimum(db, n_bins - db) <= 1


def _distinct_segments(a: np.ndarray, b: np.ndarray, sep_px: float, max_deg: float = 10.0,
                       min_overlap: float = 0.3) -> int:
    """How many groups the image segments ``a[i]-b[i]`` (px) form when near ones merge.

    Two segments merge when they run within ``max_deg`` of parallel, both ends
    of the shorter lie within ``sep_px`` of the longer's line, and they overlap
    along it by at least ``min_overlap`` of the shorter (groups are the
    connected components of the merged pairs). The longer one's line is the
    reference: a short segment's direction is the less sure, and its line
    carried 70 px along sweeps a collinear long one 5 px off (a box face seen
    edge on, box 4610: its 13 px end edge lying on the 92 px crease was
    counted apart from it, so a head-on face with a line for a strip passed
    as a face and a strip).
    """
    from scipy.sparse.csgraph import connected_components

    if len(a) == 0:
        return 0
    d = b - a
    L = np.linalg.norm(d, axis=1)
    u = d / np.maximum(L, 1e-9)[:, None]
    nrm = np.stack([-u[:, 1], u[:, 0]], axis=1)
    ra, rb = a[None, :, :] - a[:, None, :], b[None, :, :] - a[:, None, :]  # [i, j]: j's ends from i's start
    off = np.maximum(np.abs(np.einsum("ijk,ik->ij", ra, nrm)), np.abs(np.einsum("ijk,ik->ij", rb, nrm)))
    ta, tb = np.einsum("ijk,ik->ij", ra, u), np.einsum("ijk,ik->ij", rb, u)
    t0, t1 = np.minimum(ta, tb), np.maximum(ta, tb)
    overlap = np.minimum(t1, L[:, None]) - np.maximum(t0, 0.0)
    merge = (np.abs(u @ u.T) >= np.cos(np.deg2rad(max_deg))) & (off <= sep_px) & \
        (overlap >= min_overlap * np.minimum(L[:, None], t1 - t0))
    rank = np.argsort(np.argsort(-L, kind="stable"))  # 0 for the longest (ties: the first)
    merge = merge & (rank[:, None] < rank[None, :])  # [i, j] judged from i's line: i the longer
    return int(connected_components(merge | merge.T, directed=False)[0])


def _strips_apart(supported, visible, ua: np.ndarray, ub: np.ndarray, edge_faces: np.ndarray, open_face: np.ndarray,
                  front: np.ndarray, sep_px: float, max_deg: float = 10.0) -> int:
    """How many supported far edges of strips stand apart from their creases in the image.

    A strip is a face toward the camera but not seen openly; its crease a
    visible edge it shares with an open face. A supported edge of the strip
    bordering no open face counts when it runs within ``max_deg`` of parallel
    to one of the strip's creases and its midpoint lies more than ``sep_px``
    off that crease's line: the strip's width is seen, which is what fixes the
    tilt and depth of a face seen head-on. A strip's end edges (across it) and
    far edges on the crease do not count, nor edges of a strip with no crease
    in view.

    Parameters
    ----------
    supported, visible : sequence of int
        Model edge indices supported by image edges / with visible samples
        (a crease is looked for among the latter, however short).
    ua, ub : ndarray, shape (E, 2)
        Projected edge end points, px.
    edge_faces : ndarray of int, shape (E, 2)
    open_face, front : ndarray of bool, shape (F,)
        Faces seen openly / toward the camera.
    """
    strip = front & ~open_face
    vis = np.zeros(len(edge_faces), bool)
    vis[np.asarray(visible, np.int64)] = True
    d = ub - ua
    u = d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
    cos_max = np.cos(np.deg2rad(max_deg))
    n = 0
    for k in supported:
        f0, f1 = edge_faces[k]
        if open_face[f0] or open_face[f1] or not (strip[f0] or strip[f1]):
            continue
        mid = 0.5 * (ua[k] + ub[k])
        for s_ in (f for f in (f0, f1) if strip[f]):
            creases = np.flatnonzero(vis & ((edge_faces[:, 0] == s_) & open_face[edge_faces[:, 1]]
                                            | (edge_faces[:, 1] == s_) & open_face[edge_faces[:, 0]]))
            # (distance of the midpoint from the crease's line: the 2-D cross product)
            if any(abs(u[c] @ u[k]) >= cos_max and abs(_cross2(u[c], mid - ua[c])) > sep_px for c in creases):
                n += 1
                break
    return n


def _cross2(a: np.ndarray, b: np.ndarray) -> float:
    """z of the cross product of two 2-D vectors (``np.cross`` on 2-D vectors is deprecated)."""
    return float(a[0] * b[1] - a[1] * b[0])


def _continued_in_view(ends_xyz: np.ndarray, dirs: np.ndarray, mf: ModelFeatures, ua: np.ndarray, ub: np.ndarray,
                       edges: np.ndarray, min_deg: float = 4.0, max_deg: float = 15.0) -> np.ndarray:
    """Which edge ends another supported model edge continues nearly straight in the image.

    Parameters
    ----------
    ends_xyz : ndarray, shape (n, 3)
        The model vertex at each end (object frame).
    dirs : ndarray, shape (n, 2)
        Unit image direction pointing past each end (away from its edge).
    mf : ModelFeatures
    ua, ub : ndarray, shape (E, 2)
        Projected model edge end points, px.
    edges : ndarray of int
        The edges supported in this view (a continuation counts only where
        the image shows it: in a grazing view of a wrong pose, edges of the
        part line up everywhere).
    min_deg, max_deg : float
        Least and most angle between the continuation and the other edge
        leaving the vertex, deg. Nearer than ``min_deg`` the two edges lie on
        one line in the image: the face between them is seen edge-on (an
        accidental view, the edges of a wrong pose lining up exactly: 0.5-2.1
        deg on three fresh wrong locks, 5-13 deg on the true poses of held-out
        trials that the overrun test had rejected).

    Returns
    -------
    ndarray, shape (n,), bool
    """
    A, B = mf.edge_a[edges], mf.edge_b[edges]
    d = ub[edges] - ua[edges]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    at_a = np.linalg.norm(ends_xyz[:, None, :] - A[None], axis=2) < 1e-9  # (n, k): edge leaves the vertex as a->b
    at_b = np.linalg.norm(ends_xyz[:, None, :] - B[None], axis=2) < 1e-9  # ... as b->a
    cos_ = dirs @ d.T
    cos_ = np.where(at_a, cos_, -cos_)
    lo, hi = np.cos(np.deg2rad(max_deg)), np.cos(np.deg2rad(min_deg))
    return np.any((at_a | at_b) & (cos_ >= lo) & (cos_ <= hi), axis=1)


def check_pose(T_world_object: np.ndarray, views: list[CameraView], mf: ModelFeatures, tree=None,
               tol_px: float = 2.0, min_inside: float = 0.5, min_edge_px: float = 10.0,
               require_fixed: bool = False, open_face_deg: float = 75.0, outer_min_px: float = 30.0,
               outer_max_px: float = 12.0) -> PoseCheck:
    """Verification statistics of a pose against all cameras (full visibility).

    ``outer_min_px`` and ``outer_max_px``: the least projected length of a
    silhouette edge looked beside, and how far out (from 4 px) it is looked
    (:attr:`PoseCheck.outer_parallel`).
    """
    per, n_in, n_all, sup_e, vis_e, ncam, dsum, unseen = {}, 0, 0, 0, 0, 0, 0.0, 0
    size = np.inf
    inl_px = 0.0
    per_edge = np.bincount(mf.sample_edge, minlength=len(mf.edge_a))
    open_min = 10 ** 9
    big = mf.face_areas >= 0.05 * mf.face_areas.sum()
    n_over, n_ends = 0, 0
    clutter = 0.0
    shade, shade_noise, shade_step = float("nan"), 0.0, float("inf")
    cr_e, cr_sup = 0, 0
    n_distinct, n_strips, n_open_apart = 0, 0, 0
    n_outer = 0
    explained = []
    cos_open = np.cos(np.deg2rad(open_face_deg))
    for v in views:
        idx, bins = camera_setup(T_world_object, v, mf, tree)
        T_co = invert_transform(v.T_world_camera) @ T_world_object
        if idx.size == 0:
            per[v.feat.name] = float("nan")
            unseen += int(require_fixed and v.fixed)
            continue
        uv, z = _project(v.feat.K, T_co, mf.sample_p[idx])
        d = lookup_dt(v.feat.dt, bins, uv, np.inf)
        inside = np.isfinite(d) & (z > 0)
        if inside.mean() < min_inside:
            per[v.feat.name] = float("nan")
            unseen += int(require_fixed and v.fixed)
            continue
        dd = np.where(inside, d, v.feat.dt.max())
        size = min(size, float(np.linalg.norm(np.nanmax(uv, 0) - np.nanmin(uv, 0))))
        inl = dd <= tol_px
        per[v.feat.name] = float(inl.mean())
        n_in += int(inl.sum())
        n_all += int(len(inl))
        dsum += float(dd.sum())
        ncam += 1
        Xf = mf.face_centroids @ T_co[:3, :3].T + T_co[:3, 3]
        nc = mf.face_normals @ T_co[:3, :3].T
        cosv = -np.sum(nc * Xf, 1) / np.linalg.norm(Xf, axis=1)
        open_f = big & (cosv >= cos_open)
        open_min = min(open_min, int(np.sum(open_f)))
        cf, _, rms, stp = face_interiors(T_co, v.feat, mf)
        clutter = max(clutter, cf if np.isfinite(cf) else 1.0)
        shade_step = float(np.fmin(shade_step, stp))  # (NaN: no grey image, not counted)
        if np.isfinite(rms) and not rms <= shade:  # (NaN only where no camera says)
            shade, shade_noise = rms, v.feat.grey_noise
        e = mf.sample_edge[idx]
        ue, _ = _project(v.feat.K, T_co, mf.edge_a)
        ub, _ = _project(v.feat.K, T_co, mf.edge_b)
        elen = np.linalg.norm(ub - ue, axis=1)
        spacing = elen[e] / np.maximum(per_edge[e], 1)
        inl_px += float(np.sum(spacing[inl]))
        explained.append((v.feat.name, uv[inl], spacing[inl], bins[inl], v.feat.dt.shape[0]))
        front = _front(T_co[None, :3, :3], T_co[None, :3, 3], mf)[0]
        crease = front[mf.edge_faces[:, 0]] & front[mf.edge_faces[:, 1]]
        # Visible edges (long enough, sampled), which are supported, and the
        # supported ends to look 3 to 8 px past.
        ends_uv, dirs, ebins, ends_xyz, sup_k = [], [], [], [], []
        for k in np.unique(e):
            m = np.flatnonzero(e == k)
            if elen[k] < min_edge_px or len(m) < 3:
                continue
            vis_e += 1
            s_k = bool(inl[m].mean() >= 0.5)
            sup_e += s_k
            if crease[k]:
                cr_e += 1
                cr_sup += s_k
            if not s_k:
                continue
            sup_k.append(k)
            allk = np.flatnonzero(mf.sample_edge == k)
            u = (ub[k] - ue[k]) / elen[k]
            if idx[m[0]] == allk[0] and inl[m[0]] and mf.end_free[k, 0]:
                ends_uv.append(ue[k]); dirs.append(-u); ebins.append(bins[m[0]]); ends_xyz.append(mf.edge_a[k])
            if idx[m[-1]] == allk[-1] and inl[m[-1]] and mf.end_free[k, 1]:
                ends_uv.append(ub[k]); dirs.append(u); ebins.append(bins[m[-1]]); ends_xyz.append(mf.edge_b[k])
        strips_v = 0
        if sup_k:
            n_distinct += _distinct_segments(ue[sup_k], ub[sup_k], 2.0 * tol_px)
            strips_v = _strips_apart(sup_k, np.unique(e), ue, ub, mf.edge_faces, open_f, front, 2.0 * tol_px)
            n_strips += strips_v
            on_open = [k for k in sup_k if open_f[mf.edge_faces[k, 0]] or open_f[mf.edge_faces[k, 1]]]
            n_open_apart += _distinct_segments(ue[on_open], ub[on_open], 2.0 * tol_px)
        # Silhouette edges (convex, one face toward the camera), each with a point of its
        # front face; looked at only where the initialiser asks (one face seen openly, no
        # strip apart: InitOptions.max_outer_parallel_confirm).
        if np.sum(open_f) <= 1 and strips_v == 0:
            ff = front[mf.edge_faces]
            k_sil = np.flatnonzero((ff[:, 0] != ff[:, 1]) & mf.edge_convex)
            k_sil = k_sil[np.isin(k_sil, e)]
            if len(k_sil):
                fin = np.where(ff[k_sil, 0], mf.edge_faces[k_sil, 0], mf.edge_faces[k_sil, 1])
                cin, _ = _project(v.feat.K, T_co, mf.face_centroids[fin])
                n_outer += _outer_parallel(k_sil, ue, ub, elen, uv, e, bins, v.feat.dt.shape[0], v.feat.dt, cin,
                                           outer_min_px, 4.0, outer_max_px, 0.6)
        if ends_uv:
            s_ = np.linspace(3.0, 8.0, 5)
            q = np.asarray(ends_uv)[:, None, :] + s_[None, :, None] * np.asarray(dirs)[:, None, :]
            dq = lookup_dt(v.feat.dt, np.broadcast_to(np.asarray(ebins)[:, None], q.shape[:2]), q, np.inf)
            # An end at a vertex where another supported edge of the part
            # leaves nearly (not exactly) straight on in this view says
            # nothing: the image edge running on is the part's own.
            own = _continued_in_view(np.asarray(ends_xyz), np.asarray(dirs), mf, ue, ub, np.asarray(sup_k, np.int64))
            n_over += int(np.sum((np.mean(dq <= 1.5, axis=1) >= 0.8) & ~own))
            n_ends += int(np.sum(~own))
    return PoseCheck(n_in / n_all if n_all else 0.0, per, n_all, sup_e, vis_e, ncam,
                     dsum / n_all if n_all else float("inf"), unseen, size if np.isfinite(size) else 0.0,
                     inl_px, open_min if ncam else 0, n_over / n_ends if n_ends else 0.0, clutter, cr_e, cr_sup,
                     explained=tuple(explained), distinct_supported=n_distinct, strips_apart=n_strips,
                     open_edges_apart=n_open_apart, outer_parallel=n_outer, shade_rms=shade,
                     shade_noise=shade_noise, shade_step=shade_step)


def unshared_px(a: PoseCheck, b: PoseCheck, tol_px: float = 2.0) -> float:
    """Image edge length pose ``a`` explains that pose ``b`` does not, px (summed over cameras).

    An explained sample of ``a`` is shared when a sample of ``b`` explained in
    the same camera, of the same or a neighbouring orientation bin, lies within
    ``2 tol_px`` plus half that sample's spacing (both then lie on one image
    edge); every sample of ``a`` in a camera where ``b`` explains nothing is
    unshared.
    """
    other = {name: (uv, sp, b_) for name, uv, sp, b_, _ in b.explained}
    total = 0.0
    for name, uv, sp, bins, n_bins in a.explained:
        if name not in other or len(other[name][0]) == 0:
            total += float(sp.sum())
            continue
        uv2, sp2, bins2 = other[name]
        d2 = np.sum((uv[:, None, :] - uv2[None]) ** 2, axis=2)
        near = _bins_near(bins, bins2, n_bins) & (d2 <= (2.0 * tol_px + 0.5 * sp2[None]) ** 2)
        total += float(sp[~near.any(axis=1)].sum())
    return total
