"""The initialiser's compiled kernels against the NumPy code they replaced.

The NumPy implementations of ``rank_in_camera``, ``edge_residuals`` (with
``_bilinear``), ``_perturbed`` (``_rodrigues``), the sub-pixel edge search of
``refine_subpixel`` and the breadth-first walk of ``BSPTree.segments_blocked``
are kept here, verbatim, as the references. Inputs are realistic: the
project's parts (``models/objects``), their edge samples, features of images
rendered by ``test_init_search.render`` and P3P hypotheses from them.

Every comparison is to the last bit (signs of zeros and NaN positions
included): the kernels repeat the NumPy code's operations in its order. Two
facts of this platform make that possible, and are checked first: NumPy's
small matrix products (OpenBLAS gemm) accumulate each entry as an FMA chain
over k (``dot3``), and ``np.einsum("ij,ij->i")`` sums three products as
``(x0 y0 + x2 y2) + x1 y1``. On a BLAS or NumPy that accumulates otherwise
(another CPU's OpenBLAS kernel, another NumPy release) those two tests are
skipped and every comparison is to rounding instead (``assert_same_bits``):
the kernels are still right there, only not bit for bit.
"""

import numba
import numpy as np
import pytest
from test_init_search import CAMS, T_WO, K, _pose, render

from vespro import edgefit
from vespro.bsp import IN, _plane_dist, load_or_build_bsp
from vespro.imageedges import edge_visible, front_faces, projection_box, projection_box_numpy, visible_samples
from vespro.init import search
from vespro.init.features import extract_features, normal_bins
from vespro.init.modelfeat import model_features
from vespro.library import object_mesh_path
from vespro.model import load_model
from vespro.numerics import dot3, pairwise_sum
from vespro.se3 import exp_so3, invert_transform, transform_from_rt

NAMES = ("box", "lblock", "bracket")


def _bits_equal(a, b):
    a, b = np.atleast_1d(a), np.atleast_1d(b)
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    return bool(np.all(a.view(np.uint8) == b.view(np.uint8)))


@numba.njit
def _by_dot3(P, R):
    """``P @ R[h]^T`` for every h, each entry by ``dot3``."""
    out = np.empty((R.shape[0], P.shape[0], 3), P.dtype)
    for h in range(R.shape[0]):
        for s in range(P.shape[0]):
            for j in range(3):
                out[h, s, j] = dot3(P[s, 0], P[s, 1], P[s, 2], R[h, j, 0], R[h, j, 1], R[h, j, 2])
    return out


@numba.njit
def _all_plane_dist(P, N, D):
    """``einsum("ij,ij->i", P, N) - D`` by ``bsp._plane_dist``."""
    out = np.empty(P.shape[0])
    for i in range(P.shape[0]):
        out[i] = _plane_dist(P, i, N, D, i)
    return out


def _platform_facts():
    """(small matrix products as ``dot3``, einsum's three-term sums as ``_plane_dist``)."""
    rng = np.random.default_rng(11)
    P, R = rng.normal(size=(64, 3)), rng.normal(size=(3, 3, 3))
    gemm = all(_bits_equal(np.matmul(P.astype(d)[None], R.astype(d).transpose(0, 2, 1)),
                           _by_dot3(P.astype(d), R.astype(d))) for d in (np.float32, np.float64))
    N, D = rng.normal(size=(64, 3)), rng.normal(size=64)
    return gemm, _bits_equal(np.einsum("ij,ij->i", P, N) - D, _all_plane_dist(P, N, D))


_FACTS = None


def bitwise():
    """Whether this platform's NumPy rounds as the kernels do (then every comparison is exact)."""
    global _FACTS
    if _FACTS is None:
        _FACTS = _platform_facts()
    return all(_FACTS)


def assert_same_bits(a, b, atol=1e-6, max_flip=1e-3):
    """Equal to the last bit: shapes, dtypes, NaN positions and signs of zeros; where this
    platform rounds otherwise (``bitwise``), to rounding: floats within ``atol`` (and 1e-6
    relative) with the same NaNs, booleans and integers differing in at most ``max_flip``
    of the entries (a pixel or plane test on the rounding edge)."""
    a, b = np.atleast_1d(a), np.atleast_1d(b)
    assert a.shape == b.shape and a.dtype == b.dtype, (a.shape, a.dtype, b.shape, b.dtype)
    if not bitwise():
        if np.issubdtype(a.dtype, np.floating):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=atol, equal_nan=True)
        else:
            assert np.count_nonzero(a != b) <= max_flip * a.size
        return
    bad = ~np.all(a.view(np.uint8).reshape(a.shape + (-1,)) == b.view(np.uint8).reshape(b.shape + (-1,)), axis=-1)
    assert not np.any(bad), f"{np.count_nonzero(bad)} of {a.size} differ, e.g. {a[bad][:5]} vs {b[bad][:5]}"


# -- references: the NumPy code before the kernels ------------------------------

def _edge_bins_ref(uv_a, uv_b, n_bins):
    d = uv_b - uv_a
    return normal_bins(np.arctan2(d[..., 0], -d[..., 1]), n_bins)


def rank_in_camera_ref(R, t, feat, mf, tol_px=3.0, chunk=8192, min_inside=0.3, samples=None, tree=None):
    H = len(R)
    score = np.full(H, np.nan)
    inside_frac = np.zeros(H)
    samples = mf.coarse if samples is None else samples
    P = mf.sample_p[samples].astype(np.float32)
    se = mf.sample_edge[samples]
    used_e = np.unique(se)
    remap = np.zeros(len(mf.edge_a), np.int64)
    remap[used_e] = np.arange(len(used_e))
    se_l = remap[se]
    ends = np.concatenate([mf.edge_a[used_e], mf.edge_b[used_e]]).astype(np.float32)
    E = len(used_e)
    f = np.array([feat.K[0, 0], feat.K[1, 1]], np.float32)
    c = feat.K[:2, 2].astype(np.float32)
    nb = feat.dt.shape[0]
    ef = mf.edge_faces[used_e]
    faces_u, ef_l = np.unique(ef, return_inverse=True)
    ef_l = ef_l.reshape(-1, 2)
    n_f = mf.face_normals[faces_u].astype(np.float32)
    d_f = mf.face_offsets[faces_u].astype(np.float32)
    convex_u = mf.edge_convex[used_e]
    H_img, W_img = feat.dt.shape[1:]
    dt_flat = feat.dt.reshape(-1)
    for s in range(0, H, chunk):
        Rc = R[s:s + chunk].astype(np.float32)
        tc = t[s:s + chunk].astype(np.float32)
        RT = Rc.transpose(0, 2, 1)
        w = np.matmul(RT, tc[:, :, None])[..., 0]
        front = (w @ n_f.T + d_f) < 0
        f0, f1 = front[:, ef_l[:, 0]], front[:, ef_l[:, 1]]
        vis_e = np.where(convex_u, f0 | f1, f0 & f1)
        Xe = np.matmul(ends[None], RT) + tc[:, None]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            ue = Xe[..., :2] / Xe[..., 2:3] * f + c
        bins = _edge_bins_ref(ue[:, :E], ue[:, E:], nb)
        X = np.matmul(P[None], RT) + tc[:, None]
        z = X[..., 2]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            uv = X[..., :2] / z[..., None] * f + c
            ui = np.rint(uv[..., 0])
            vi = np.rint(uv[..., 1])
        vis = vis_e[:, se_l]
        inside = (ui >= 0) & (ui <= W_img - 1) & (vi >= 0) & (vi <= H_img - 1) & (z > 0)
        if tree is not None and not mf.convex:
            hh, ss = np.nonzero(vis & inside)
            if hh.size:
                A = mf.sample_p[samples[ss]]
                cam = -w[hh].astype(float)
                seg = np.linalg.norm(cam - A, axis=1)
                blocked = segments_blocked_ref(tree, A, cam, t_lo=np.minimum(2e-4 / seg, 0.1), t_hi=1.0,
                                               min_length=1e-9)
                vis = vis.copy()
                vis[hh[blocked], ss[blocked]] = False
        with np.errstate(invalid="ignore"):
            flat = (bins[:, se_l].astype(np.int32) * H_img + np.where(inside, vi, 0).astype(np.int32)) * W_img \
                + np.where(inside, ui, 0).astype(np.int32)
        d = dt_flat[flat]
        ins = inside & vis
        nvis = vis.sum(1)
        agree = np.where(ins, np.maximum(0.0, 1.0 - d / tol_px), 0.0).sum(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            fr = ins.sum(1) / nvis
            sc = agree / nvis
        behind = np.any(z <= 0, axis=1)
        ok = (nvis > 0) & ~behind & (fr >= min_inside)
        score[s:s + chunk] = np.where(ok, sc, np.nan)
        inside_frac[s:s + chunk] = np.where(nvis > 0, fr, 0.0)
    return score, inside_frac


def _rodrigues_ref(w):
    th = float(np.sqrt(w @ w))
    Kx = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < 1e-8:
        return np.eye(3) + Kx
    return np.eye(3) + np.sin(th) / th * Kx + (1.0 - np.cos(th)) / th ** 2 * (Kx @ Kx)


def _perturbed_ref(T0, x):
    return transform_from_rt(T0[:3, :3] @ _rodrigues_ref(x[:3]), T0[:3, 3] + x[3:])


def _bilinear_ref(img2d_stack, bins, uv, outside, grad=False):
    _, H, W = img2d_stack.shape
    u, v = uv[:, 0], uv[:, 1]
    ok = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (v >= 0) & (u <= W - 1.001) & (v <= H - 1.001)
    u0 = np.where(ok, np.floor(u), 0).astype(np.int64)
    v0 = np.where(ok, np.floor(v), 0).astype(np.int64)
    fu = np.where(ok, u - u0, 0.0)
    fv = np.where(ok, v - v0, 0.0)
    a = img2d_stack[bins, v0, u0]
    b = img2d_stack[bins, v0, u0 + 1]
    c = img2d_stack[bins, v0 + 1, u0]
    d = img2d_stack[bins, v0 + 1, u0 + 1]
    val = np.where(ok, (a * (1 - fu) + b * fu) * (1 - fv) + (c * (1 - fu) + d * fu) * fv, outside)
    if not grad:
        return val
    gu = np.where(ok, (b - a) * (1 - fv) + (d - c) * fv, 0.0)
    gv = np.where(ok, (c - a) * (1 - fu) + (d - b) * fu, 0.0)
    return val, gu, gv


def edge_residuals_ref(x, T0, setups, want_jac, dmax=20.0):
    Tx = _perturbed_ref(T0, x)
    rs, js = [], []
    Rwo = Tx[:3, :3]
    for v, T_cw, P, bins in setups:
        K_ = v.feat.K
        T_co = T_cw @ Tx
        X = P @ T_co[:3, :3].T + T_co[:3, 3]
        z = X[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = X[:, :2] / z[:, None] * K_[[0, 1], [0, 1]] + K_[:2, 2]
        uv[z <= 1e-6] = np.nan
        if not want_jac:
            rs.append(_bilinear_ref(v.feat.dt, bins, uv, dmax))
            continue
        _, gu, gv = _bilinear_ref(v.feat.dt, bins, uv, dmax, grad=True)
        zz = np.where(z > 1e-6, z, 1.0)
        du = np.stack([K_[0, 0] / zz, np.zeros_like(zz), -K_[0, 0] * X[:, 0] / zz ** 2], 1)
        dv = np.stack([np.zeros_like(zz), K_[1, 1] / zz, -K_[1, 1] * X[:, 1] / zz ** 2], 1)
        g_w = (gu[:, None] * du + gv[:, None] * dv) @ T_cw[:3, :3]
        js.append(np.concatenate([np.cross(P @ Rwo.T, g_w) @ Rwo, g_w], 1))
    return np.concatenate(js) if want_jac else np.concatenate(rs)


def normal_search_ref(grad, uv, n, offs, min_grad, near_frac=0.0, expect=None, ratio_lo=0.0, ratio_hi=np.inf):
    """The edge search inside ``refine_subpixel``'s loop, as it was (the highest peak, no contrast expected)."""
    assert near_frac == 0.0 and expect is None
    q = uv[:, None, :] + offs[None, :, None] * n[:, None, :]
    S, O = q.shape[:2]
    zeros = np.zeros(S * O, np.int64)
    gx = _bilinear_ref(grad, zeros, q.reshape(-1, 2), np.nan).reshape(S, O)
    gy = _bilinear_ref(grad, zeros + 1, q.reshape(-1, 2), np.nan).reshape(S, O)
    c = gx * n[:, 0:1] + gy * n[:, 1:2]
    c = np.where(np.isfinite(c), c, 0.0)
    g = np.abs(c)
    k = np.argmax(g, axis=1)
    peak = g[np.arange(S), k]
    ok = (peak >= min_grad) & (k > 0) & (k < O - 1)
    kk = np.clip(k, 1, O - 2)
    gm, g0, gp = g[np.arange(S), kk - 1], g[np.arange(S), kk], g[np.arange(S), kk + 1]
    den = gm - 2 * g0 + gp
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(np.abs(den) > 1e-9, 0.5 * (gm - gp) / den, 0.0)
    sstar = offs[kk] + np.clip(frac, -0.5, 0.5) * 0.5
    return sstar, ok, c[np.arange(S), kk], np.ascontiguousarray(c[:, np.argmin(np.abs(offs))])


def visible_samples_ref(T_camera_object, mf, tree=None):
    """``imageedges.visible_samples`` in NumPy, as it was."""
    R, t = T_camera_object[None, :3, :3], T_camera_object[None, :3, 3]
    vis_e = edge_visible(front_faces(R, t, mf), mf)[0]
    idx = np.flatnonzero(vis_e[mf.sample_edge])
    if tree is not None and not mf.convex and idx.size:
        cam_o = invert_transform(T_camera_object)[:3, 3]
        A = mf.sample_p[idx]
        seg = np.linalg.norm(cam_o - A, axis=1)
        blocked = tree.segments_blocked(A, np.broadcast_to(cam_o, A.shape), t_lo=np.minimum(2e-4 / seg, 0.1),
                                        t_hi=1.0, min_length=1e-9)
        idx = idx[~blocked]
    return idx


def test_visible_samples_match_numpy(scene):
    """The compiled culling and lines of sight against the NumPy code: the same samples at
    random poses about both cameras' (and without the tree), and where a face is seen
    exactly edge on (the camera centre in its plane)."""
    _, mf, tree, views = scene
    rng = np.random.default_rng(3)
    n_front = []
    for k in range(40):
        T_co = invert_transform(views[k % 2].T_world_camera) @ T_WO @ _pose(rng.normal(size=3) * 0.6,
                                                                            rng.normal(size=3) * 0.02)
        for tr in (tree, None):
            a, b = visible_samples(T_co, mf, tr), visible_samples_ref(T_co, mf, tr)
            assert a.dtype == b.dtype and np.array_equal(a, b)
        n_front.append(front_faces(T_co[None, :3, :3], T_co[None, :3, 3], mf)[0].sum())
    assert len(set(n_front)) > 1  # poses that see different faces
    # A camera centre on the plane of face 0: its offset n.c - d is 0 up to rounding.
    n, d = mf.face_normals[0], mf.face_offsets[0]
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    c = -d * n + 3.0 * mf.diameter * u / np.linalg.norm(u)
    z = -c / np.linalg.norm(c)  # looking at the object origin
    x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R_oc = np.stack([x, np.cross(z, x), z], 1)
    T_co = invert_transform(transform_from_rt(R_oc, c))
    assert np.array_equal(visible_samples(T_co, mf, tree), visible_samples_ref(T_co, mf, tree))


def test_projection_box_matches_numpy(scene):
    """The compiled box around a model's projection against the NumPy code: random poses
    about both cameras', with margins that put the box's sides on exact integers, part of
    the model behind the camera, off the image, a NaN pose and a far one."""
    if not bitwise():
        pytest.skip("this platform's BLAS accumulates otherwise: the box may differ on a rounding edge")
    model, mf, _, views = scene
    rng = np.random.default_rng(9)
    n_none = 0
    for k in range(200):
        T_co = invert_transform(views[k % 2].T_world_camera) @ T_WO @ _pose(rng.normal(size=3) * 0.3,
                                                                            rng.normal(size=3) * 0.05)
        if k % 10 == 7:
            T_co[2, 3] = rng.uniform(-0.2, 0.1)  # straddling the camera plane
        if k % 10 == 8:
            T_co[0, 3] += rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 2.0)  # off the image, or partly
        margin = float(rng.choice([0.0, 11.0, rng.uniform(0.0, 20.0)]))
        a = projection_box(K, T_co, mf.vertices, margin, 640, 480)
        assert a == projection_box_numpy(K, T_co, mf.vertices, margin, 640, 480)
        n_none += a is None
        if a is not None:
            uv = (mf.vertices @ T_co[:3, :3].T + T_co[:3, 3])
            u = uv[:, 0] / uv[:, 2] * K[0, 0] + K[0, 2]
            edge = float(np.floor(u.min() - margin))  # a margin putting the box's left side on an integer
            if 0 < edge < 600:
                m2 = margin + (u.min() - margin - edge)
                assert projection_box(K, T_co, mf.vertices, m2, 640, 480) == \
                    projection_box_numpy(K, T_co, mf.vertices, m2, 640, 480)
    assert 0 < n_none < 200
    far = np.eye(4)
    far[:3, 3] = [1e18, 0.0, 1.0]
    nan = np.full((4, 4), np.nan)
    for T in (far, nan):
        assert projection_box(K, T, mf.vertices, 3.0, 640, 480) == projection_box_numpy(K, T, mf.vertices, 3.0, 640, 480)


def face_widths_px_ref(T_camera_object, K, mf, edge_len_px):
    """``edgefit.face_widths_px`` in NumPy, as it was."""
    R, t = T_camera_object[:3, :3], T_camera_object[:3, 3]
    X = mf.tri_p @ R.T + t  # (T, 3, 3)
    F = len(mf.face_normals)
    if np.any(X[..., 2] <= 1e-9):
        return np.full(F, np.inf)
    uv = X[..., :2] / X[..., 2:3] * K[[0, 1], [0, 1]]
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    area = np.bincount(mf.tri_face, 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]), F)
    longest = np.zeros(F)
    with np.errstate(invalid="ignore"):  # (a NaN length, of a pose made to test it, propagates)
        for k in range(2):
            np.maximum.at(longest, mf.edge_faces[:, k], edge_len_px)
    return area / np.maximum(longest, 1e-9)


def test_face_widths_match_numpy(scene):
    """The compiled face widths against the NumPy code, at poses about the scene's and with a
    NaN edge length (its faces' widths NaN), to rounding (1e-12 relative; the products'
    order may differ from NumPy's); inf for all faces with a corner behind the camera."""
    _, mf, _, views = scene
    rng = np.random.default_rng(5)
    for k in range(4):
        v = views[k % 2]
        T_co = invert_transform(v.T_world_camera) @ T_WO @ _pose(rng.normal(size=3) * 0.05, rng.normal(size=3) * 0.01)
        edge_len = rng.uniform(0.0, 80.0, len(mf.edge_a))
        if k == 3:
            edge_len[0] = np.nan
        a = edgefit.face_widths_px(T_co, v.feat.K, mf, edge_len)
        b = face_widths_px_ref(T_co, v.feat.K, mf, edge_len)
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=0)
        assert np.isnan(a).any() == (k == 3) and np.isfinite(a).sum() >= len(a) - 2
    behind = np.eye(4)
    behind[2, 3] = -1.0
    assert np.all(edgefit.face_widths_px(behind, views[0].feat.K, mf, np.ones(len(mf.edge_a))) == np.inf)


def refine_subpixel_ref(T_world_object: np.ndarray, views, mf, tree=None,
                    rounds: int = 4, search_px: float = 3.0, min_grad: float = 40.0, f_scale: float = 0.7,
                    shared_edge_px: float = 1.5, spacing_px: float = 0.0, edge_outlier_px: float = 0.0,
                    near_peak_frac: float = 0.0, expect: list | None = None,
                    contrast_ratio: tuple[float, float] = (0.4, 3.0), info: bool = False):
    """``edgefit.refine_subpixel`` with its per-camera work in NumPy, as it was."""
    T = np.array(T_world_object, float)
    offs = np.arange(-search_px, search_px + 1e-9, 0.5)
    fit = None
    for _ in range(rounds):
        rows_J, rows_r, rows_e, rows_d = [], [], [], []
        n_searched = 0
        w_searched = w_shared = 0.0  # summed sample weights: searched; found but lost to a parallel edge
        contrast = []
        for iv, v in enumerate(views):
            T_cw = invert_transform(v.T_world_camera)
            T_co = T_cw @ T
            idx = visible_samples(T_co, mf, tree)
            contrast.append(np.full(len(mf.sample_p), np.nan) if info else None)
            if idx.size == 0:
                continue
            n_searched += idx.size
            K = v.feat.K
            ua, _ = search._project(K, T_co, mf.edge_a)
            ub, _ = search._project(K, T_co, mf.edge_b)
            se = mf.sample_edge[idx]
            edge_len = np.linalg.norm(ub - ua, axis=1)
            dens = np.ones(idx.size)
            if spacing_px > 0:
                per_edge = np.bincount(se, minlength=len(mf.edge_a))
                dens = np.minimum(1.0, edge_len[se] / (spacing_px * per_edge[se]))
            w_searched += float(dens.sum())
            d = (ub - ua)[se]
            n = np.stack([-d[:, 1], d[:, 0]], 1)
            n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
            P = mf.sample_p[idx]
            X = P @ T_co[:3, :3].T + T_co[:3, 3]
            z = X[:, 2]
            uv = X[:, :2] / z[:, None] * K[[0, 1], [0, 1]] + K[:2, 2]
            exp = None if expect is None or expect[iv] is None else np.asarray(expect[iv], float)[idx]
            sstar, ok, c_peak, c0 = edgefit._normal_search(v.feat.grad, uv, n, offs, float(min_grad), float(near_peak_frac),
                                                   exp, float(contrast_ratio[0]), float(contrast_ratio[1]))
            if info:
                contrast[-1][idx] = c0
            if not ok.any():
                continue
            if shared_edge_px > 0:
                k_ok = np.flatnonzero(ok)
                tgt = uv[k_ok] + sstar[k_ok, None] * n[k_ok]
                lost = k_ok[edgefit.shared_edge_losers(tgt, se[k_ok], ub - ua, np.abs(sstar[k_ok]), shared_edge_px)]
                ok[lost] = False
                if lost.size:
                    # A face seen edge on shows its two edges as one image edge: there, the
                    # sample that lost it still found its outline.
                    thin = face_widths_px_ref(T_co, K, mf, edge_len) < 2.0 * shared_edge_px
                    ef = mf.edge_faces[se[lost]]
                    w_shared += float(dens[lost][np.any(thin[ef], axis=1)].sum())
            if info:
                contrast[-1][idx[ok]] = c_peak[ok]  # the image edge a sample took (or, above, none near it)
            # Residual: n . (uv - target) = -s*; Jacobian n^T d(uv)/dx.
            X, z, n, sstar, P = X[ok], z[ok], n[ok], sstar[ok], P[ok]
            rows_d.append(dens[ok])
            du = np.stack([K[0, 0] / z, 0 * z, -K[0, 0] * X[:, 0] / z ** 2], 1)
            dv = np.stack([0 * z, K[1, 1] / z, -K[1, 1] * X[:, 1] / z ** 2], 1)
            g_w = (n[:, :1] * du + n[:, 1:] * dv) @ T_cw[:3, :3]
            R = T[:3, :3]
            rows_J.append(np.concatenate([np.cross(P @ R.T, g_w) @ R, g_w], 1))
            rows_r.append(-sstar)
            rows_e.append(se[ok] + len(mf.edge_a) * len(rows_e))
        if not rows_J:
            break
        J = np.concatenate(rows_J)
        r = np.concatenate(rows_r)
        if len(r) < 12:
            break
        dens = np.concatenate(rows_d)
        eid = np.concatenate(rows_e)
        w = dens * np.where(np.abs(r) <= f_scale, 1.0, f_scale / np.maximum(np.abs(r), 1e-12))
        keep = np.ones(len(r), bool)
        u, inv = np.unique(eid, return_inverse=True)
        for drops in range(3):
            JW = J * w[:, None]
            A = JW.T @ J
            step = np.linalg.solve(A + 1e-6 * np.diag(np.diag(A) + 1e-9), -(JW.T @ r))
            if edge_outlier_px <= 0 or drops == 2:
                break
            # Edges the fitted pose leaves off on average found a neighbouring image edge: out,
            # and the step solved again without them (twice at most).
            wsum = np.bincount(inv, w, len(u))
            mean = np.bincount(inv, w * (r + J @ step), len(u)) / np.maximum(wsum, 1e-12)
            out = (np.abs(mean) > edge_outlier_px) & (wsum > 0)
            if not out.any() or np.count_nonzero(~out & (wsum > 0)) < 4:
                break
            keep &= ~out[inv]
            w = np.where(keep, w, 0.0)
        if keep.sum() < 12:
            break
        if info:  # the record of the round (what the caller asked for; not needed for the pose)
            # Per-edge sums of the weighted rows (JW is the last solve's, with the final weights).
            G = np.stack([np.bincount(inv, JW[:, j], len(u)) for j in range(6)], 1)
            fit = edgefit.EdgeFit(A, float(np.sqrt(np.sum(w * r * r) / np.sum(w))), int(keep.sum()),
                          len(np.unique(eid[keep])), n_searched, float(np.sum(dens[keep])),
                          float(np.sum(dens[keep])) + w_shared, w_searched, G.T @ G, tuple(contrast))
        T = edgefit._perturbed(T, step)
        if np.linalg.norm(step[:3]) < 1e-5 and np.linalg.norm(step[3:]) < 1e-6:
            break
    return (T, fit) if info else T


def segments_blocked_ref(tree, A, B, t_lo=0.0, t_hi=1.0, min_length=0.0):
    """``BSPTree.segments_blocked`` as the breadth-first NumPy walk it was."""
    B = np.asarray(B, dtype=float).reshape(-1, 3)
    A = np.asarray(A, dtype=float)
    N, D = tree.normal, tree.offset
    if A.shape == (3,):
        h_start = N @ A - D

        def ha_of(seg, node):
            return h_start[node]
    else:
        A = A.reshape(-1, 3)

        def ha_of(seg, node):
            return np.einsum("ij,ij->i", A[seg], N[node]) - D[node]

    def hb_of(seg, node):
        return np.einsum("ij,ij->i", B[seg], N[node]) - D[node]

    with np.errstate(invalid="ignore"):
        t_lo, t_hi = tree.clip_to_bounds(A, B, t_lo, t_hi)
    k = B.shape[0]
    ids = np.arange(k)
    pe = tree.plane_eps
    CHf = tree._children.reshape(-1)
    blocked = np.zeros(k, dtype=bool)
    t0 = np.broadcast_to(np.asarray(t_lo, dtype=float), (k,)).copy()
    t1 = np.broadcast_to(np.asarray(t_hi, dtype=float), (k,)).copy()
    live = t1 - t0 > min_length
    seg, t0, t1 = ids[live], t0[live], t1[live]
    node = np.zeros(seg.size, dtype=np.int64)
    while seg.size:
        ha = ha_of(seg, node)
        dh = hb_of(seg, node) - ha
        h0 = ha + t0 * dh
        h1 = ha + t1 * dh
        b0, b1 = h0 < -pe, h1 < -pe
        f0, f1 = h0 > pe, h1 > pe
        side0 = b0 | (~f0 & b1)
        sp = np.flatnonzero((b0 & f1) | (f0 & b1))
        node2 = node + node
        new_node = CHf.take(node2 + side0)
        if sp.size:
            ts = -ha[sp] / dh[sp]
            other = CHf.take(node2[sp] + ~side0[sp])
            t1_sp = t1[sp]
            t1[sp] = ts
            seg = np.concatenate([seg, seg[sp]])
            node = np.concatenate([new_node, other])
            t0 = np.concatenate([t0, ts])
            t1 = np.concatenate([t1, t1_sp])
        else:
            node = new_node
        leaf = node < 0
        if leaf.any():
            inside = node == IN
            if min_length > 0:
                inside &= t1 - t0 > min_length
            blocked[seg[inside]] = True
            keep = ~leaf & ~blocked[seg]
            seg, node, t0, t1 = seg[keep], node[keep], t0[keep], t1[keep]
    return blocked


# -- scenes --------------------------------------------------------------------

@pytest.fixture(scope="module", params=NAMES)
def scene(request):
    """(model, features, BSP tree, views of the part at T_WO in both CAMS)."""
    model = load_model(object_mesh_path(request.param))
    views = []
    for i, T_wc in enumerate(CAMS):
        img = render(model, invert_transform(T_wc) @ T_WO, np.random.default_rng(10 + i))
        views.append(edgefit.CameraView(extract_features(f"c{i}", img, K), T_wc))
    return model, model_features(model), load_or_build_bsp(model), views


def _hypotheses(scene, n_max=4000):
    """P3P poses of the first camera's image (mostly wrong, off-image or behind), the true pose first."""
    model, mf, _, views = scene
    feat = views[0].feat
    R, t = search.p3p_hypotheses(feat, mf, model.vertices, search.image_paths(feat))
    keep = np.random.default_rng(0).permutation(len(R))[:n_max]
    T_co = invert_transform(CAMS[0]) @ T_WO
    R = np.concatenate([T_co[None, :3, :3], R[keep]])
    t = np.concatenate([T_co[None, :3, 3], t[keep]])
    # A few poses straddling the camera plane and far off the image.
    t[1:40, 2] = np.linspace(-0.2, 0.05, 39)
    t[40:60, 0] += 3.0
    return R, t


# -- the platform's arithmetic ---------------------------------------------------

@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_dot3_is_how_numpy_multiplies_points_by_a_rotation(dtype):
    if not bitwise():
        pytest.skip("this platform's BLAS accumulates otherwise: the kernels are compared to rounding")
    rng = np.random.default_rng(0)
    P = rng.normal(size=(500, 3)).astype(dtype)
    R = rng.normal(size=(7, 3, 3)).astype(dtype)
    P[rng.random(P.shape) < 0.2] = 0.0  # zero products: the sign of a zero sum
    R[0, :, 1] = 0.0
    # P @ R^T (the batched and the single products of the NumPy code).
    assert_same_bits(np.matmul(P[None], R.transpose(0, 2, 1)), _by_dot3(P, R))
    assert_same_bits(P @ R[3].T, _by_dot3(P, R[3:4])[0])


def test_plane_distances_sum_as_einsum_does():
    if not bitwise():
        pytest.skip("this platform's NumPy sums otherwise: the kernels are compared to rounding")
    rng = np.random.default_rng(1)
    for n in (1, 2, 3, 7, 64, 1000):
        P, N, D = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=n)
        assert_same_bits(np.einsum("ij,ij->i", P, N) - D, _all_plane_dist(P, N, D))


def test_pairwise_sum_is_numpys():
    rng = np.random.default_rng(2)
    for n in [*range(140), 255, 256, 257, 1057, 5000]:
        a = (rng.random(n) * (rng.random(n) < 0.7)).astype(np.float32)
        assert_same_bits(np.float32(a.sum()), np.float32(pairwise_sum(a, n)))
        A = np.tile(a, (3, 1))
        assert_same_bits(A.sum(1)[1], np.float32(pairwise_sum(a, n)))
        b = rng.normal(size=n) * 10.0 ** rng.uniform(-3, 3, n)
        assert_same_bits(b.sum(), np.float64(pairwise_sum(b, n)))
        assert_same_bits(np.mean(b) if n else np.float64(0.0), np.float64(pairwise_sum(b, n) / max(n, 1)))


def test_normal_bin_is_normal_bins():
    @numba.njit
    def bins(a, nb):
        out = np.empty(a.size, np.int32)
        for i in range(a.size):
            out[i] = search._normal_bin_i32(a[i], nb)
        return out

    rng = np.random.default_rng(3)
    a = np.concatenate([rng.uniform(-4, 4, 200000), [0.0, -0.0, np.pi, -np.pi, 2 * np.pi, -1e-30, 1e-30, np.nan]])
    a = a.astype(np.float32)
    a = np.concatenate([a, np.float32(np.pi) * np.arange(-3, 4, dtype=np.float32),
                        np.nextafter(np.float32(np.pi), np.float32(0)) * np.arange(-3, 4, dtype=np.float32)])
    with np.errstate(invalid="ignore"):
        ref = normal_bins(a, 12).astype(np.int32)  # the int32 the ranking indexes with
    assert_same_bits(ref, bins(a, 12))


# -- kernels ---------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["sparse", "coarse", "tree", "half_inside"])
def test_rank_in_camera_matches_numpy(scene, kind):
    _, mf, tree, views = scene
    R, t = _hypotheses(scene, 600 if kind == "tree" else 4000)
    feat = views[0].feat
    kw = {"sparse": {"samples": mf.sparse}, "coarse": {"chunk": 1500}, "tree": {"tree": tree, "chunk": 250},
          "half_inside": {"min_inside": 0.5, "tol_px": 2.0}}[kind]
    ref = rank_in_camera_ref(R, t, feat, mf, **kw)
    got = search.rank_in_camera(R, t, feat, mf, **kw)
    assert_same_bits(ref[0], got[0], atol=0.02)  # to rounding: a sample may round to the next pixel
    assert_same_bits(ref[1], got[1], atol=0.02)
    # Real work: judged and unjudged poses, the true one among the best.
    assert 0.2 < np.isfinite(ref[0]).mean() < 1.0
    assert ref[0][0] > np.nanpercentile(ref[0], 95)


def test_rank_with_the_tree_drops_samples_only_for_non_convex_parts(scene):
    _, mf, tree, views = scene
    R, t = _hypotheses(scene, 300)
    with_tree = search.rank_in_camera(R, t, views[0].feat, mf, tree=tree)[0]
    culled = search.rank_in_camera(R, t, views[0].feat, mf)[0]
    if mf.convex:
        assert_same_bits(with_tree, culled)
    else:
        assert np.nanmax(np.abs(with_tree - culled)) > 0.01


def _setups(scene, T, n_views=2):
    _, mf, tree, views = scene
    out = []
    for v in views[:n_views]:
        idx, bins = edgefit.camera_setup(T, v, mf, tree)
        out.append((v, invert_transform(v.T_world_camera), mf.sample_p[idx], bins))
    return out


@pytest.mark.parametrize("want_jac", [False, True])
def test_edge_residuals_match_numpy(scene, want_jac):
    rng = np.random.default_rng(4)
    T0 = T_WO @ _pose([0.01, -0.02, 0.015], [0.003, -0.002, 0.001])
    setups = _setups(scene, T0)
    # Large steps move samples off the image (dmax) and, the last, behind the camera.
    steps = [np.zeros(6), np.r_[1e-9, 0, 0, 0, 0, 0]] + [np.r_[rng.normal(size=3) * s, rng.normal(size=3) * s / 10]
                                                        for s in (1e-3, 0.05, 0.5, 2.0)]
    steps.append(np.r_[0, 0, 0, invert_transform(CAMS[0])[:3, :3][2] * -1.0])
    n_out = 0
    for x in steps:
        ref = edge_residuals_ref(x, T0, setups, want_jac)
        got = edgefit.edge_residuals(x, T0, setups, want_jac)
        assert_same_bits(ref, got)
        if not want_jac:
            n_out += np.count_nonzero(ref == 20.0)
    assert n_out > 0 or want_jac


def test_perturbed_matches_numpy():
    rng = np.random.default_rng(5)
    for scale in (0.0, 1e-12, 5e-9, 1e-8, 2e-8, 1e-4, 0.05, 1.0, 3.0, 20.0):
        for k in range(300):
            T0 = transform_from_rt(exp_so3(rng.normal(size=3)), rng.normal(size=3))
            x = np.r_[rng.normal(size=3) * scale, rng.normal(size=3) * 0.01]
            if k % 5 == 0:
                x[k % 3] = 0.0
            assert_same_bits(_perturbed_ref(T0, x), edgefit._perturbed(T0, x))


def test_normal_search_matches_numpy(scene):
    _, mf, tree, views = scene
    v = views[0]
    offs = np.arange(-3.0, 3.0 + 1e-9, 0.5)
    for dp in ([0.0, 0.0, 0.0], [0.004, -0.003, 0.002], [0.3, 0.0, 0.0]):  # the last: mostly off the image
        T_co = invert_transform(v.T_world_camera) @ T_WO @ _pose([0.02, 0.0, -0.01], dp)
        idx = visible_samples(T_co, mf, tree)
        ua, _ = search._project(K, T_co, mf.edge_a)
        ub, _ = search._project(K, T_co, mf.edge_b)
        d = (ub - ua)[mf.sample_edge[idx]]
        n = np.stack([-d[:, 1], d[:, 0]], 1)
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
        uv, _ = search._project(K, T_co, mf.sample_p[idx])
        for min_grad in (40.0, 0.0):
            ref = normal_search_ref(v.feat.grad, uv, n, offs, min_grad)
            got = edgefit._normal_search(v.feat.grad, uv, n, offs, min_grad)
            for a, b in zip(ref, got):
                assert_same_bits(a, b)


def test_refinements_unchanged(scene, monkeypatch):
    """``refine_pose`` and ``refine_subpixel`` with the reference pieces swapped in: the same bits."""
    _, mf, tree, views = scene
    rng = np.random.default_rng(6)
    starts = [T_WO @ _pose(rng.normal(size=3) * 0.03, rng.normal(size=3) * 0.004) for _ in range(3)]
    got = [(edgefit.refine_pose(T, views[:1 + k % 2], mf, tree),
            edgefit.refine_subpixel(T, views[:1 + k % 2], mf, tree, info=True)) for k, T in enumerate(starts)]
    monkeypatch.setattr(edgefit, "edge_residuals", edge_residuals_ref)
    monkeypatch.setattr(edgefit, "_perturbed", _perturbed_ref)
    monkeypatch.setattr(edgefit, "_normal_search", normal_search_ref)
    for k, (T, (Tr, (Ts, fit))) in enumerate(zip(starts, got)):
        assert_same_bits(edgefit.refine_pose(T, views[:1 + k % 2], mf, tree), Tr)
        Ts_ref, fit_ref = edgefit.refine_subpixel(T, views[:1 + k % 2], mf, tree, info=True)
        assert_same_bits(Ts_ref, Ts)
        assert_same_bits(fit_ref.normal, fit.normal)
        assert (fit_ref.rms_px, fit_ref.n_samples, fit_ref.n_edges, fit_ref.n_searched) == \
            (fit.rms_px, fit.n_samples, fit.n_edges, fit.n_searched)
        assert not np.array_equal(Tr, T)  # the refinement moved


def test_segments_blocked_matches_the_breadth_first_walk(scene):
    model, mf, tree, _ = scene
    rng = np.random.default_rng(7)
    n = 6000
    A = mf.sample_p[rng.integers(0, len(mf.sample_p), n)]  # edge samples to camera centres, as ranked
    cams = rng.normal(size=(n, 3))
    cams *= rng.uniform(0.05, 1.0, (n, 1)) / np.linalg.norm(cams, axis=1, keepdims=True)
    lo, hi = model.bounds
    A2 = np.concatenate([A, rng.uniform(lo - 0.02, hi + 0.02, size=(2000, 3))])
    B2 = np.concatenate([cams, rng.uniform(lo - 0.02, hi + 0.02, size=(2000, 3))])
    # Degenerate: along an axis (inside and outside a slab), zero length, NaN.
    A2[-4:] = [[lo[0], 0.0, 0.0], [hi[0] + 1, 0.0, 0.0], [0.01, 0.01, 0.01], [np.nan, 0, 0]]
    B2[-4:] = [[hi[0], 0.0, 0.0], [hi[0] + 1, 1.0, 0.0], [0.01, 0.01, 0.01], [1.0, 1.0, 1.0]]
    seg = np.linalg.norm(B2 - A2, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_lo = np.minimum(2e-4 / seg, 0.1)
    for min_length in (0.0, 1e-9, 0.05):
        ref = segments_blocked_ref(tree, A2, B2, t_lo=t_lo, t_hi=1.0, min_length=min_length)
        assert_same_bits(ref, tree.segments_blocked(A2, B2, t_lo=t_lo, t_hi=1.0, min_length=min_length))
        assert 0.05 < ref.mean() < 0.95
        c = cams[0]  # one common start
        ref1 = segments_blocked_ref(tree, c, A, t_lo=0.0, t_hi=0.999, min_length=min_length)
        assert_same_bits(ref1, tree.segments_blocked(c, A, t_lo=0.0, t_hi=0.999, min_length=min_length))
        assert_same_bits(ref1[:50], tree.segments_blocked(c, A[:50], 0.0, 0.999, min_length))


def test_normal_search_can_take_the_nearest_of_comparable_peaks():
    """Two gradient peaks along a sample's normal, 80 at the sample and 100 two pixels
    out (a face seen edge on as a one-pixel line shows both its sides): the highest is
    taken by default; with ``near_frac`` 0.6 the nearest of those at least 0.6 times the
    highest; with 0.9 the nearer one is too weak and the highest is taken again."""
    grad = np.zeros((2, 20, 20), np.float32)
    grad[0, :, 10] = 80.0
    grad[0, :, 12] = 100.0
    uv = np.array([[10.0, 10.0]])
    n = np.array([[1.0, 0.0]])
    offs = np.arange(-3.0, 3.0 + 1e-9, 0.5)
    s_hi, ok_hi = edgefit._normal_search(grad, uv, n, offs, 40.0)[:2]
    s_near, ok_near = edgefit._normal_search(grad, uv, n, offs, 40.0, 0.6)[:2]
    s_far = edgefit._normal_search(grad, uv, n, offs, 40.0, 0.9)[0]
    assert ok_hi[0] and ok_near[0]
    assert abs(s_hi[0] - 2.0) < 0.3 and abs(s_near[0]) < 0.3 and abs(s_far[0] - 2.0) < 0.3


def test_normal_search_takes_only_edges_like_the_expected_contrast():
    """Along a sample's normal: a rising edge of 100 at the sample, a falling one of 60 two
    pixels out (a dark seam beside an edge) and a rising one of 400 two pixels in. Unknown
    contrast (NaN) takes the strongest; a falling edge expected takes the falling one; a
    rising one of about 100 the one at the sample, not the one 4 times as strong; a rising
    one of 400 that one; a falling one of 300 none (60 is under 0.4 times it); a sample that
    saw no edge (5, under ``min_grad``) the strongest of its sign (``ratio_lo``/``ratio_hi``
    0.4 and 3). The contrasts at the peak taken and at the sample's own position come back
    signed; the normal the other way round flips every sign."""
    grad = np.zeros((2, 20, 20), np.float32)
    grad[0, :, 8] = 400.0
    grad[0, :, 10] = 100.0
    grad[0, :, 12] = -60.0
    expect = np.array([np.nan, -60.0, 90.0, 400.0, -300.0, 5.0])
    uv = np.array([[10.0, 10.0]] * len(expect))
    n = np.array([[1.0, 0.0]] * len(expect))
    offs = np.arange(-3.0, 3.0 + 1e-9, 0.5)
    for sign in (1.0, -1.0):
        s, ok, c_peak, c0 = edgefit._normal_search(grad, uv, sign * n, offs, 40.0, 0.6, sign * expect, 0.4, 3.0)
        assert list(ok) == [True, True, True, True, False, True]
        assert np.allclose(sign * s[ok], [-2.0, 2.0, 0.0, -2.0, -2.0], atol=0.3)
        assert np.allclose(sign * c_peak[ok], [400.0, -60.0, 100.0, 400.0, 400.0])
        assert np.allclose(sign * c0, 100.0)


def _view_rows_ref(T, v, mf, tree, offs, expect, spacing_px=2.0, shared_px=1.5):
    """One camera's share of a ``refine_subpixel`` round in NumPy, as it was: (idx, ok, sstar, c_peak, c0,
    dens, lost, rows of the found samples)."""
    T_cw = invert_transform(v.T_world_camera)
    T_co = T_cw @ T
    idx = visible_samples(T_co, mf, tree)
    K_ = v.feat.K
    ua, _ = search._project(K_, T_co, mf.edge_a)
    ub, _ = search._project(K_, T_co, mf.edge_b)
    se = mf.sample_edge[idx]
    edge_len = np.linalg.norm(ub - ua, axis=1)
    per_edge = np.bincount(se, minlength=len(mf.edge_a))
    dens = np.minimum(1.0, edge_len[se] / (spacing_px * per_edge[se]))
    d = (ub - ua)[se]
    n = np.stack([-d[:, 1], d[:, 0]], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    P = mf.sample_p[idx]
    X = P @ T_co[:3, :3].T + T_co[:3, 3]
    z = X[:, 2]
    uv = X[:, :2] / z[:, None] * K_[[0, 1], [0, 1]] + K_[:2, 2]
    exp = None if expect is None else expect[idx]
    sstar, ok, c_peak, c0 = edgefit._normal_search(v.feat.grad, uv, n, offs, 40.0, 0.6, exp, 0.4, 3.0)
    k_ok = np.flatnonzero(ok)
    tgt = uv[k_ok] + sstar[k_ok, None] * n[k_ok]
    lost = np.zeros(idx.size, bool)
    lost[k_ok[edgefit.shared_edge_losers(tgt, se[k_ok], ub - ua, np.abs(sstar[k_ok]), shared_px)]] = True
    ok = ok & ~lost
    X, z, n, P = X[ok], z[ok], n[ok], P[ok]
    du = np.stack([K_[0, 0] / z, 0 * z, -K_[0, 0] * X[:, 0] / z ** 2], 1)
    dv = np.stack([0 * z, K_[1, 1] / z, -K_[1, 1] * X[:, 1] / z ** 2], 1)
    g_w = (n[:, :1] * du + n[:, 1:] * dv) @ T_cw[:3, :3]
    R = T[:3, :3]
    return idx, ok, sstar, c_peak, c0, dens, lost, np.concatenate([np.cross(P @ R.T, g_w) @ R, g_w], 1)


def test_subpixel_view_kernel_matches_numpy(scene):
    """The compiled per-camera round (projection, search, shared edges, rows) against the NumPy code:
    the same bits, with the tracker's settings (nearest peak, spacing, expected contrast)."""
    _, mf, tree, views = scene
    rng = np.random.default_rng(11)
    offs = np.arange(-3.0, 3.0 + 1e-9, 0.5)
    for k in range(4):
        T = T_WO @ _pose(rng.normal(size=3) * 0.01, rng.normal(size=3) * 0.002)
        v = views[k % 2]
        expect = None
        if k >= 2:  # a contrast known for most samples, from the search at the true pose
            _, fit0 = edgefit.refine_subpixel(T_WO, [v], mf, tree, rounds=1, near_peak_frac=0.6, info=True)
            expect = np.where(rng.random(len(mf.sample_p)) < 0.7, fit0.sample_contrast[0], np.nan)
        idx, ok, sstar, c_peak, c0, dens, lost, rows = _view_rows_ref(T, v, mf, tree, offs, expect)
        T_cw = invert_transform(v.T_world_camera)
        K_ = v.feat.K
        got = edgefit._subpixel_view_kernel(
            v.feat.grad, K_[0, 0], K_[1, 1], K_[0, 2], K_[1, 2], T_cw @ T, np.ascontiguousarray(T[:3, :3]),
            np.ascontiguousarray(T_cw[:3, :3]), idx, mf.sample_p, mf.sample_edge, mf.edge_a, mf.edge_b, offs, 40.0,
            0.6, np.full(idx.size, np.nan) if expect is None else expect[idx], 0.4, 3.0, 2.0, 1.5,
            edgefit.COS_PARALLEL, mf.tri_p, mf.tri_face, mf.edge_faces, len(mf.face_normals))
        for a, b in zip((ok, sstar, c_peak, c0, dens, lost), got[:6]):
            assert_same_bits(a, b)
        assert_same_bits(rows, got[7][got[0]])
        assert ok.sum() > 40


@pytest.mark.parametrize("expect_known", [False, True])
def test_refine_subpixel_matches_numpy(scene, expect_known):
    """The whole refinement against the NumPy code: the same edges and samples, the pose and the
    fit's matrices to rounding (the compiled step sums in sample order, BLAS otherwise)."""
    _, mf, tree, views = scene
    rng = np.random.default_rng(11)
    kw = dict(rounds=2, spacing_px=2.0, edge_outlier_px=1.0, near_peak_frac=0.6, info=True)
    for k in range(3):
        T = T_WO @ _pose(rng.normal(size=3) * 0.01, rng.normal(size=3) * 0.002)
        vs = views[:1 + k % 2]
        expect = None
        if expect_known:
            _, fit0 = edgefit.refine_subpixel(T, vs, mf, tree, **kw)
            expect = [np.where(rng.random(c.size) < 0.7, c, np.nan) for c in fit0.sample_contrast]
        Ta, fa = edgefit.refine_subpixel(T, vs, mf, tree, expect=expect, **kw)
        Tb, fb = refine_subpixel_ref(T, vs, mf, tree, expect=expect, **kw)
        np.testing.assert_allclose(Ta, Tb, rtol=0, atol=1e-12)
        for name in ("normal", "offset_gram"):
            a, b = getattr(fa, name), getattr(fb, name)
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9 * np.abs(b).max())
        assert (fb.n_samples, fb.n_edges, fb.n_searched) == (fa.n_samples, fa.n_edges, fa.n_searched)
        np.testing.assert_allclose([fa.rms_px, fa.weight, fa.found_weight, fa.searched_weight],
                                   [fb.rms_px, fb.weight, fb.found_weight, fb.searched_weight], rtol=1e-12)
        for a, b in zip(fb.sample_contrast, fa.sample_contrast):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)
        assert fa.n_samples > 40 and not np.array_equal(Ta, T)


def _corners_whole_image(grey, opt):
    """``detect_corners`` as a whole-image search masked to each tile (the reference)."""
    import cv2

    H, W = grey.shape
    grey = cv2.GaussianBlur(grey, (0, 0), opt.corner_blur_sigma) if opt.corner_blur_sigma > 0 else grey
    nx, ny = max(1, round(W / opt.corner_tile_px)), max(1, round(H / opt.corner_tile_px))
    per = max(8, opt.max_corners // (nx * ny))
    out = []
    for iy in range(ny):
        for ix in range(nx):
            x0, x1 = ix * W // nx, (ix + 1) * W // nx
            y0, y1 = iy * H // ny, (iy + 1) * H // ny
            mask = np.zeros_like(grey)
            mask[y0:y1, x0:x1] = 255
            p = cv2.goodFeaturesToTrack(grey, per, opt.corner_quality, opt.corner_min_distance, mask=mask,
                                        blockSize=opt.corner_block)
            if p is not None:
                out.append(p.reshape(-1, 2))
    pts = np.concatenate(out)
    keep = np.ones(len(pts), bool)
    for i in range(len(pts)):
        if keep[i]:
            d = np.linalg.norm(pts[i + 1:] - pts[i], axis=1)
            keep[i + 1:][d < opt.corner_min_distance] = False
    return pts[keep].reshape(-1, 1, 2).astype(np.float32)


def test_corners_and_links_are_those_of_the_whole_image_and_all_samples():
    """Each tile searched in its own pixels (and the margin its response reads) finds the
    whole-image search's corners to the last bit, at a tile's cost instead of the image's;
    the corner links, screened on two samples first, are those of all twelve. On rendered
    views of the parts over clutter, with noise, and on ViSP's real cube."""
    import glob

    import cv2

    from vespro.init.features import EdgeOptions, detect_corners, edge_maps, link_corners

    opt = EdgeOptions()
    links_seen = []
    rng = np.random.default_rng(3)
    images = []
    for name in NAMES:
        model = load_model(object_mesh_path(name))
        for T_wc in CAMS[:1]:
            img = cv2.cvtColor(render(model, invert_transform(T_wc) @ T_WO, rng), cv2.COLOR_BGR2GRAY)
            images.append(np.clip(img + rng.normal(0, 2, img.shape), 0, 255).astype(np.uint8))
    images.append(rng.integers(0, 256, (240, 320), dtype=np.uint8))  # another size, all texture
    real = sorted(glob.glob("/usr/share/visp-images-data/ViSP-images/mbt/cube/image0*.pgm"))[::100]
    images += [cv2.imread(f, cv2.IMREAD_GRAYSCALE) for f in real]
    for img in images:
        got, want = detect_corners(img, opt), _corners_whole_image(img, opt)
        assert len(want) > 20
        assert _bits_equal(got, want)
        # The corner links: two samples first, to the same links as all twelve on every pair.
        corners = want.reshape(-1, 2).astype(np.float64)
        dt = edge_maps("c", img, K, opt).dt
        diag = np.hypot(*img.shape)
        links = link_corners(corners, dt, opt, diag)
        assert _bits_equal(links, _links_all_samples(corners, dt, opt, diag))
        links_seen.append(len(links))
    assert min(links_seen[:-len(real) - 1]) > 5  # (the parts' views have links to compare)


def _links_all_samples(corners, dt, opt, diag):
    """``link_corners`` with all twelve samples on every pair (the reference)."""
    from vespro.init.features import lookup_dt

    i, j = np.triu_indices(len(corners), 1)
    d = corners[j] - corners[i]
    L = np.hypot(d[:, 0], d[:, 1])
    ok = (L >= opt.link_min_px) & (L <= opt.link_max_frac * diag)
    i, j, d = i[ok], j[ok], d[ok]
    fr = np.linspace(0.12, 0.88, 12)
    pts = corners[i][:, None, :] + fr[None, :, None] * d[:, None, :]
    bins = normal_bins(np.arctan2(d[:, 0], -d[:, 1]), dt.shape[0])
    dist = lookup_dt(dt, np.broadcast_to(bins[:, None], pts.shape[:2]), pts, np.inf)
    keep = np.mean(dist <= opt.link_tol_px, axis=1) >= opt.link_support
    return np.stack([i[keep], j[keep]], 1).astype(np.int64)


def test_shared_edge_losers_are_those_of_the_k_d_tree_pairs():
    """The compiled sweep against the pairs of SciPy's k-d tree within the radius (the
    formulation it replaced): random points of a few parallel and crossing edges, ties in
    cost included, NaN points in no pair; the same losers."""
    from scipy.spatial import cKDTree

    from vespro.edgefit import shared_edge_losers

    def reference(uv, edge, edge_dir, cost, radius_px=1.5, max_angle_deg=10.0):
        lose = np.zeros(len(uv), bool)
        sel = np.flatnonzero(np.all(np.isfinite(uv), axis=1))
        if sel.size < 2:
            return lose
        pairs = cKDTree(uv[sel]).query_pairs(radius_px, output_type="ndarray")
        if len(pairs) == 0:
            return lose
        i, j = sel[pairs[:, 0]], sel[pairs[:, 1]]
        dn = edge_dir / (np.linalg.norm(edge_dir, axis=1, keepdims=True) + 1e-12)
        par = np.abs(np.sum(dn[edge[i]] * dn[edge[j]], axis=1)) >= np.cos(np.deg2rad(max_angle_deg))
        m = (edge[i] != edge[j]) & par
        i, j = i[m], j[m]
        lose[np.where(cost[i] > cost[j], i, j)] = True
        return lose

    rng = np.random.default_rng(5)
    for trial in range(40):
        E = 6
        dirs = rng.normal(size=(E, 2))
        dirs[1] = dirs[0] * -2.0 + rng.normal(0, 0.05, 2)  # nearly parallel pairs
        dirs[3] = dirs[2] * 0.5
        S = int(rng.integers(2, 400))
        uv = rng.uniform(0, 30, (S, 2))
        uv[rng.random(S) < 0.05] = np.nan
        edge = rng.integers(0, E, S)
        cost = np.round(rng.uniform(0, 2, S), 1)  # ties
        got = shared_edge_losers(uv, edge, dirs, cost)
        assert np.array_equal(got, reference(uv, edge, dirs, cost)), trial
        assert trial > 0 or got.any()
