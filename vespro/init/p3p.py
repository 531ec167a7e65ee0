"""Batched perspective-three-point and absolute orientation (pure NumPy).

The initialiser solves tens of thousands of P3P problems per camera, one per
(image corner triple, model corner triple) pairing; OpenCV's ``solveP3P`` costs
~70 us per call, so the whole batch is solved here at once: Grunert's quartic
(Haralick et al. 1994, "Review and analysis of solutions of the three point
perspective pose estimation problem"), its roots in closed form (Ferrari,
through a real root of the resolvent cubic) and polished by Newton steps, then
the rigid transform of the model triple onto the recovered camera-frame
points.
"""

from __future__ import annotations

import numpy as np

__all__ = ["p3p_grunert", "kabsch_batch", "triad_batch", "quartic_roots", "cubic_real_root"]


def kabsch_batch(P_object: np.ndarray, Q_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid transforms that best map point sets ``P`` onto ``Q`` (least squares).

    Parameters
    ----------
    P_object : ndarray, shape (N, k, 3)
        Source points (object frame), k >= 3.
    Q_camera : ndarray, shape (N, k, 3)
        Target points (camera frame).

    Returns
    -------
    R_camera_object : ndarray, shape (N, 3, 3)
    t_camera_object : ndarray, shape (N, 3)
        ``Q ~ R P + t``.
    """
    pc = P_object.mean(1)
    qc = Q_camera.mean(1)
    H = np.einsum("nki,nkj->nij", P_object - pc[:, None], Q_camera - qc[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("nij,njk->nik", U, Vt)))
    D = np.ones((len(d), 3))
    D[:, 2] = d
    R = np.einsum("nji,nj,nkj->nik", Vt, D, U)  # V diag(D) U^T
    t = qc - np.einsum("nij,nj->ni", R, pc)
    return R, t


def p3p_grunert(P_object: np.ndarray, bearings: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All poses putting three model points on three viewing rays, batched.

    Parameters
    ----------
    P_object : ndarray, shape (N, 3, 3)
        Three model points per problem (object frame, m), not collinear.
    bearings : ndarray, shape (N, 3, 3)
        Unit viewing rays of their images (camera frame).

    Returns
    -------
    R_camera_object : ndarray, shape (M, 3, 3)
    t_camera_object : ndarray, shape (M, 3)
        Up to four solutions per problem, M <= 4 N.
    problem : ndarray, shape (M,), int64
        Index of the problem each solution belongs to.
    """
    P = np.asarray(P_object, float)
    j = np.asarray(bearings, float)
    a2 = np.sum((P[:, 1] - P[:, 2]) ** 2, 1)
    b2 = np.sum((P[:, 0] - P[:, 2]) ** 2, 1)
    c2 = np.sum((P[:, 0] - P[:, 1]) ** 2, 1)
    ca = np.einsum("ni,ni->n", j[:, 1], j[:, 2])  # cos alpha (rays 2, 3)
    cb = np.einsum("ni,ni->n", j[:, 0], j[:, 2])  # cos beta  (rays 1, 3)
    cg = np.einsum("ni,ni->n", j[:, 0], j[:, 1])  # cos gamma (rays 1, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        amc = (a2 - c2) / b2
        apc = (a2 + c2) / b2
        bmc = (b2 - c2) / b2
        bma = (b2 - a2) / b2
        A4 = (amc - 1) ** 2 - 4 * c2 / b2 * ca * ca
        A3 = 4 * (amc * (1 - amc) * cb - (1 - apc) * ca * cg + 2 * c2 / b2 * ca * ca * cb)
        A2 = 2 * (amc * amc - 1 + 2 * amc * amc * cb * cb + 2 * bmc * ca * ca - 4 * apc * ca * cb * cg
                  + 2 * bma * cg * cg)
        A1 = 4 * (-amc * (1 + amc) * cb + 2 * a2 / b2 * cg * cg * cb - (1 - apc) * ca * cg)
        A0 = (1 + amc) ** 2 - 4 * a2 / b2 * cg * cg
    ok = np.isfinite(A4) & (np.abs(A4) > 1e-12) & np.isfinite(A3) & np.isfinite(A2) & np.isfinite(A1) & \
        np.isfinite(A0)
    idx = np.flatnonzero(ok)
    roots = quartic_roots(A4[idx], A3[idx], A2[idx], A1[idx], A0[idx])
    v = roots.real
    real = np.abs(roots.imag) <= 1e-6 * np.maximum(1.0, np.abs(roots.real))
    prob = np.repeat(idx, 4)
    v = v.ravel()
    keep = real.ravel() & (v > 0)
    prob, v = prob[keep], v[keep]
    # A few Newton steps polish roots that the eigenvalue route leaves a bit off.
    c4, c3, c2_, c1, c0 = A4[prob], A3[prob], A2[prob], A1[prob], A0[prob]
    for _ in range(2):
        f = (((c4 * v + c3) * v + c2_) * v + c1) * v + c0
        df = ((4 * c4 * v + 3 * c3) * v + 2 * c2_) * v + c1
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(np.abs(df) > 1e-12, f / df, 0.0)
        v = v - step
    am, caa, cbb, cgg = amc[prob], ca[prob], cb[prob], cg[prob]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = ((-1 + am) * v * v - 2 * am * cbb * v + 1 + am) / (2 * (cgg - v * caa))
        s1sq = c2[prob] / (1 + u * u - 2 * u * cgg)
    good = np.isfinite(u) & (u > 0) & np.isfinite(s1sq) & (s1sq > 0)
    prob, u, v, s1sq = prob[good], u[good], v[good], s1sq[good]
    s1 = np.sqrt(s1sq)
    s = np.stack([s1, u * s1, v * s1], 1)  # depths along the rays
    Q = j[prob] * s[:, :, None]
    R, t = triad_batch(P[prob], Q)
    return R, t, prob


def cubic_real_root(b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """One real root of each monic cubic ``x^3 + b x^2 + c x + d``, batched.

    Trigonometric form when the three roots are real (the largest), Cardano's
    otherwise (the single real one).
    """
    a13 = b / 3.0
    a2 = a13 * a13
    f = c / 3.0 - a2
    g = a13 * (2 * a2 - c) + d
    h = 0.25 * g * g + f * f * f
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        j = np.sqrt(np.maximum(-f, 0.0))
        k = np.arccos(np.clip(-0.5 * g / np.where(j > 0, j * j * j, 1.0), -1.0, 1.0))
        trig = 2 * j * np.cos(k / 3.0) - a13
        sh = np.sqrt(np.maximum(h, 0.0))
        card = np.cbrt(-0.5 * g + sh) + np.cbrt(-0.5 * g - sh) - a13
    return np.where(h <= 0, trig, card)


def quartic_roots(A4: np.ndarray, A3: np.ndarray, A2: np.ndarray, A1: np.ndarray, A0: np.ndarray) -> np.ndarray:
    """All four complex roots of ``A4 x^4 + ... + A0``, batched, in closed form (Ferrari).

    The depressed quartic is split into two quadratics through one real root
    of its resolvent cubic; ~6x cheaper than the eigenvalues of a batch of
    4 x 4 companion matrices, to the same roots (the caller polishes them with
    Newton steps).

    Parameters
    ----------
    A4, A3, A2, A1, A0 : ndarray, shape (N,)
        Real coefficients, ``A4 != 0``.

    Returns
    -------
    ndarray, shape (N, 4), complex
    """
    a, b, c, d = A3 / A4, A2 / A4, A1 / A4, A0 / A4
    a0 = 0.25 * a
    a02 = a0 * a0
    # x = y - a0 gives the depressed quartic y^4 - 2p y^2 + 2q y - r = 0.
    p = 3 * a02 - 0.5 * b
    q = a * a02 - b * a0 + 0.5 * c
    r = 3 * a02 * a02 - b * a02 + c * a0 - d
    z0 = cubic_real_root(p, r, p * r - 0.5 * q * q)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        s = np.sqrt(2 * p + 2 * z0 + 0j)
        big = np.abs(s) > 1e-12
        t = np.where(big, -q / np.where(big, s, 1.0), z0 * z0 + r)
        # y^2 + s y + (z0 + t) = 0 and y^2 - s y + (z0 - t) = 0
        D1 = np.sqrt(s * s - 4 * (z0 + t))
        D2 = np.sqrt(s * s - 4 * (z0 - t))
    return np.stack([(-s + D1) / 2, (-s - D1) / 2, (s + D2) / 2, (s - D2) / 2], 1) - a0[:, None]


def _triad(X):
    """Orthonormal frame (columns) of each point triple, shape (N, 3, 3)."""
    e1 = X[:, 1] - X[:, 0]
    e1 = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    e3 = np.cross(e1, X[:, 2] - X[:, 0])
    e3 = e3 / np.linalg.norm(e3, axis=1, keepdims=True)
    e2 = np.cross(e3, e1)
    return np.stack([e1, e2, e3], 2)


def triad_batch(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid transforms mapping point triples P onto congruent triples Q exactly.

    P3P's recovered points are congruent with the model triple, so the frame of
    each triangle fixes the rotation; far cheaper than an SVD per problem.

    Parameters
    ----------
    P, Q : ndarray, shape (N, 3, 3)

    Returns
    -------
    R : ndarray, shape (N, 3, 3)
    t : ndarray, shape (N, 3)
        ``Q ~ R P + t``.
    """
    R = np.matmul(_triad(Q), _triad(P).transpose(0, 2, 1))
    t = Q.mean(1) - np.einsum("nij,nj->ni", R, P.mean(1))
    return R, t
