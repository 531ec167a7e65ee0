"""Batched P3P and absolute orientation against known poses."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vespro.init.p3p import kabsch_batch, p3p_grunert, triad_batch


def _problems(n, seed):
    rng = np.random.default_rng(seed)
    P = rng.uniform(-0.1, 0.1, (n, 3, 3))
    R = Rotation.random(n, random_state=seed).as_matrix()
    t = np.c_[rng.uniform(-0.2, 0.2, (n, 2)), rng.uniform(0.5, 2.0, n)]
    Q = np.einsum("nij,nkj->nki", R, P) + t[:, None]
    return P, R, t, Q


def test_p3p_recovers_true_pose_among_solutions():
    P, R, t, Q = _problems(2000, 0)
    j = Q / np.linalg.norm(Q, axis=2, keepdims=True)
    Rs, ts, prob = p3p_grunert(P, j)
    assert Rs.shape[0] == ts.shape[0] == prob.shape[0] <= 4 * len(P)
    err = np.full(len(P), np.inf)
    np.minimum.at(err, prob, np.linalg.norm(Rs - R[prob], axis=(1, 2)) + np.linalg.norm(ts - t[prob], axis=1))
    # Near-degenerate random triples (rays almost coplanar with the points)
    # lose precision; 98% exact to 1e-6 is far above any wrong formula.
    assert np.mean(err < 1e-6) > 0.98


def test_every_p3p_solution_reprojects_onto_the_rays():
    P, R, t, Q = _problems(300, 1)
    j = Q / np.linalg.norm(Q, axis=2, keepdims=True)
    Rs, ts, prob = p3p_grunert(P, j)
    X = np.einsum("nij,nkj->nki", Rs, P[prob]) + ts[:, None]
    assert np.all(X[..., 2] > 0)
    b = X / np.linalg.norm(X, axis=2, keepdims=True)
    cos = np.sum(b * j[prob], axis=2)
    assert np.percentile(1 - cos, 95) < 1e-9
    assert np.allclose(np.linalg.det(Rs), 1.0)


def test_p3p_matches_opencv_solution_count():
    cv2 = pytest.importorskip("cv2")
    P, R, t, Q = _problems(50, 2)
    j = Q / np.linalg.norm(Q, axis=2, keepdims=True)
    _, _, prob = p3p_grunert(P, j)
    ours = np.bincount(prob, minlength=50)
    agree = 0
    for k in range(50):
        n, _, _ = cv2.solveP3P(P[k], (Q[k, :, :2] / Q[k, :, 2:]).astype(np.float64), np.eye(3), None,
                               flags=cv2.SOLVEPNP_P3P)
        agree += int(n == ours[k])
    # Root-finding tolerances differ near double roots; nearly all must agree.
    assert agree >= 45


def test_triad_and_kabsch_agree_on_congruent_triples():
    P, R, t, Q = _problems(200, 3)
    R1, t1 = triad_batch(P, Q)
    R2, t2 = kabsch_batch(P, Q)
    assert np.allclose(R1, R, atol=1e-9) and np.allclose(t1, t, atol=1e-9)
    assert np.allclose(R2, R, atol=1e-9) and np.allclose(t2, t, atol=1e-9)


def test_kabsch_least_squares_with_noise_beats_perturbed_rotation():
    P, R, t, Q = _problems(100, 4)
    rng = np.random.default_rng(5)
    Qn = Q + rng.normal(0, 1e-3, Q.shape)
    R2, t2 = kabsch_batch(P, Qn)
    res = np.linalg.norm(np.einsum("nij,nkj->nki", R2, P) + t2[:, None] - Qn, axis=2).__pow__(2).sum(1)
    res_true = np.linalg.norm(np.einsum("nij,nkj->nki", R, P) + t[:, None] - Qn, axis=2).__pow__(2).sum(1)
    assert np.all(res <= res_true + 1e-12)


def test_quartic_roots_of_a_product_of_known_factors():
    """Golden roots: (x - r1)(x - r2)(x - r3)(x - r4) scaled, real and complex pairs."""
    from vespro.init.p3p import quartic_roots

    cases = [[1.0, -2.0, 3.5, 0.25], [0.5, 0.5 + 1e-3, 2.0, -7.0], [1 + 2j, 1 - 2j, -0.3, 4.0],
             [0.1 + 0.5j, 0.1 - 0.5j, -2 + 1j, -2 - 1j], [3.0, 3.0, 3.0, 3.0 + 1e-2]]
    for k, r in enumerate(cases):
        c = np.real(np.poly(r)) * (k + 0.5)  # leading coefficient not 1
        got = quartic_roots(*[np.array([x]) for x in c])[0]
        # Each golden root found (a near-quadruple root only to ~eps^(1/4)).
        tol = 1e-3 if k == 4 else 1e-9
        for x in r:
            assert np.min(np.abs(got - x)) < tol * max(1.0, abs(x)), (r, got)


def test_quartic_roots_match_companion_eigenvalues():
    """Against the eigenvalues of the companion matrix (the former route)."""
    from vespro.init.p3p import quartic_roots

    rng = np.random.default_rng(5)
    c = rng.normal(size=(5, 20000))
    c[0] += np.sign(c[0]) * 0.1
    C = np.zeros((c.shape[1], 4, 4))
    C[:, 0, :] = -(c[1:] / c[0]).T
    C[:, 1, 0] = C[:, 2, 1] = C[:, 3, 2] = 1.0
    ev = np.linalg.eigvals(C)
    got = quartic_roots(*c)
    # Each eigenvalue has a closed-form root next to it (sorted pairing can
    # mismatch conjugates, so nearest).
    d = np.abs(ev[:, :, None] - got[:, None, :]).min(2) / np.maximum(1.0, np.abs(ev))
    assert np.mean(d.max(1) < 1e-7) > 0.999
    real_ev = np.abs(ev.imag) <= 1e-6 * np.maximum(1.0, np.abs(ev.real))
    real_got = np.abs(got.imag) <= 1e-6 * np.maximum(1.0, np.abs(got.real))
    assert abs(int(real_ev.sum()) - int(real_got.sum())) <= 1e-3 * real_ev.sum()
