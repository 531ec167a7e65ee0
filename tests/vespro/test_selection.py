import itertools

import numpy as np
import pytest

from vespro import se3
from vespro import selection as sel
from vespro.camera import CameraIntrinsics
from vespro.projection import project_with_jacobian

SIZE = (640, 480)
INTR = CameraIntrinsics.from_fovy(640, 480, 45.0)


def _candidates(seed, n=30, spread=0.1):
    """n random model corners of a ~20 cm part 0.8 m in front of a camera."""
    rng = np.random.default_rng(seed)
    T_wc = np.eye(4)
    T_wo = se3.transform_from_rt(se3.exp_so3(rng.normal(0, 1, 3)), [rng.normal(0, 0.05), rng.normal(0, 0.05), 0.8])
    P = rng.uniform(-spread, spread, (n, 3))
    uv, _, J = project_with_jacobian(INTR, T_wc, T_wo, P)
    va = rng.uniform(0, np.deg2rad(85), n)
    sil = rng.uniform(0, 30, n)
    P6 = np.diag(np.r_[np.full(3, 0.003**2), np.full(3, np.deg2rad(1.0) ** 2)])
    return uv, J, va, sil, P6


@pytest.mark.parametrize("seed", range(5))
def test_both_choose_k_distinct_eligible_indices_deterministically(seed):
    uv, J, va, sil, P6 = _candidates(seed)
    el = sel.eligible_mask(uv, SIZE, view_angle=va, J=J)
    assert el.sum() >= 8
    a = sel.select_quality(uv, va, sil, SIZE, k=8)
    b = sel.select_information(uv, J, va, sil, SIZE, P6=P6, k=8)
    for idx in (a, b):
        assert idx.shape == (8,) and idx.dtype == np.intp
        assert len(set(idx.tolist())) == 8
        assert el[idx].all()
    np.testing.assert_array_equal(a, sel.select_quality(uv, va, sil, SIZE, k=8))
    np.testing.assert_array_equal(b, sel.select_information(uv, J, va, sil, SIZE, P6=P6, k=8))


def test_selection_is_invariant_to_candidate_order():
    uv, J, va, sil, P6 = _candidates(11)
    perm = np.random.default_rng(0).permutation(len(uv))
    a = sel.select_information(uv, J, va, sil, SIZE, P6=P6)
    b = sel.select_information(uv[perm], J[perm], va[perm], sil[perm], SIZE, P6=P6)
    assert set(a.tolist()) == set(perm[b].tolist())
    a = sel.select_quality(uv, va, sil, SIZE)
    b = sel.select_quality(uv[perm], va[perm], sil[perm], SIZE)
    assert set(a.tolist()) == set(perm[b].tolist())


def test_border_margin_and_grazing_corners_are_respected():
    uv, J, va, sil, P6 = _candidates(1)
    # push half the candidates into the 20 px border band, or make them grazing
    uv = uv.copy()
    uv[::4, 0] = 5.0
    uv[1::4, 1] = 470.0
    va = va.copy()
    va[2::4] = np.deg2rad(85)
    for idx in (
        sel.select_quality(uv, va, sil, SIZE, k=8, border_px=20),
        sel.select_information(uv, J, va, sil, SIZE, P6=P6, k=8, border_px=20),
    ):
        assert np.all((uv[idx] >= 20) & (uv[idx] <= np.array(SIZE) - 1 - 20))
        assert np.all(va[idx] < sel.DEFAULT_MAX_VIEW_ANGLE)
    # fewer eligible than k: all eligible are returned, nothing else
    el = sel.eligible_mask(uv, SIZE, 20, va, J=J)
    idx = sel.select_information(uv, J, va, sil, SIZE, P6=P6, k=len(uv), border_px=20)
    assert set(idx.tolist()) == set(np.flatnonzero(el).tolist())
    # non-finite candidates never picked
    uv[3] = np.nan
    J = J.copy()
    J[6, 0, 0] = np.inf
    assert 3 not in sel.select_quality(uv, va, sil, SIZE, k=30)
    picked = sel.select_information(uv, J, va, sil, SIZE, k=30)
    assert 3 not in picked and 6 not in picked


def test_quality_prefers_spread_and_surrounding_points():
    # a tight cluster of good corners plus four corners around the image
    rng = np.random.default_rng(0)
    cluster = 320 + rng.normal(0, 5, (20, 2))
    ring = np.array([[100.0, 100.0], [540.0, 100.0], [540.0, 380.0], [100.0, 380.0]])
    uv = np.vstack([cluster, ring])
    idx = sel.select_quality(uv, np.zeros(24), np.full(24, 50.0), SIZE, k=4)
    assert set(idx.tolist()) == {20, 21, 22, 23}
    assert sel.quality_index(ring, np.ones(4), SIZE) > sel.quality_index(ring[[0, 1, 1, 0]] + [[0, 0], [0, 0], [0, 5], [0, 5]], np.ones(4), SIZE)
    # a grazing / silhouette / border corner is worth less than a clean one
    w = sel.feature_weights(np.array([[320.0, 240], [320, 240], [320, 240], [12, 240]]), np.array([0.0, 1.3, 0.0, 0.0]), np.array([50.0, 50, 0, 50]), SIZE)
    assert w[0] == 1.0 and w[1] < 0.5 and w[2] == 0.5
    assert w[3] == pytest.approx(0.5 + 0.5 * (12 - 8) / 16)  # 4 px past the 8 px margin of a 16 px ramp


def test_information_beats_quality_and_random_on_average():
    lq, li, lr = [], [], []
    rng = np.random.default_rng(123)
    for seed in range(20):
        uv, J, va, sil, P6 = _candidates(seed)
        el = np.flatnonzero(sel.eligible_mask(uv, SIZE, view_angle=va, J=J))
        iq = sel.select_quality(uv, va, sil, SIZE, k=8)
        ii = sel.select_information(uv, J, va, sil, SIZE, P6=P6, k=8)
        lq.append(sel.pose_information_logdet(J[iq], P6))
        li.append(sel.pose_information_logdet(J[ii], P6))
        lr.append(np.mean([sel.pose_information_logdet(J[rng.choice(el, 8, replace=False)], P6) for _ in range(20)]))
    lq, li, lr = map(np.array, (lq, li, lr))
    assert li.mean() > lq.mean() and li.mean() > lr.mean()
    # greedy log-det also wins trial by trial against the quality index here
    assert np.mean(li >= lq) >= 0.9


@pytest.mark.parametrize("seed", range(6))
def test_greedy_information_within_submodular_bound_of_brute_force(seed):
    uv, J, va, sil, P6 = _candidates(seed, n=11)
    va[:] = 0.0
    k = 4
    el = np.flatnonzero(sel.eligible_mask(uv, SIZE, J=J))
    f0 = sel.pose_information_logdet(J[:0], P6)
    best = max(sel.pose_information_logdet(J[list(c)], P6) for c in itertools.combinations(el, k))
    g = sel.pose_information_logdet(J[sel.select_information(uv, J, va, sil, SIZE, P6=P6, k=k)], P6)
    assert g - f0 >= (1 - 1 / np.e) * (best - f0)
    # in practice greedy is much closer than the guarantee
    assert g - f0 >= 0.95 * (best - f0)


def test_information_uses_the_prior():
    # if the prior already pins translation, picks go to rotation information
    uv, J, va, sil, _ = _candidates(4)
    tight_p = np.diag(np.r_[np.full(3, 1e-8), np.full(3, 1.0)])
    tight_r = np.diag(np.r_[np.full(3, 1.0), np.full(3, 1e-10)])
    a = sel.select_information(uv, J, va, sil, SIZE, P6=tight_p, k=8)
    b = sel.select_information(uv, J, va, sil, SIZE, P6=tight_r, k=8)
    assert set(a.tolist()) != set(b.tolist())


def test_joint_selection_caps_per_camera_and_uses_other_cameras():
    gains = []
    for seed in range(10):
        c1 = _candidates(seed)
        c2 = _candidates(100 + seed)
        P6 = c1[4]
        joint = sel.select_information_joint([(c1[0], c1[1], c1[2], SIZE), (c2[0], c2[1], c2[2], SIZE)], P6=P6, k_per_camera=4)
        assert [len(j) for j in joint] == [4, 4]
        sep = [sel.select_information(c[0], c[1], c[2], c[3], SIZE, P6=P6, k=4) for c in (c1, c2)]
        ld = lambda picks: sel.pose_information_logdet(np.concatenate([c1[1][picks[0]], c2[1][picks[1]]]), P6)  # noqa: E731
        gains.append(ld(joint) - ld(sep))
    assert np.mean(gains) >= 0.0


def test_shape_errors_raise():
    uv, J, va, sil, P6 = _candidates(0)
    with pytest.raises(ValueError, match=r"J: expected shape \(30, 2, 6\)"):
        sel.select_information(uv, J[:, :, :3], va, sil, SIZE)
    with pytest.raises(ValueError, match="view_angle"):
        sel.select_quality(uv, va[:-1], sil, SIZE)


def test_batched_quality_index_matches_the_scalar_one():
    rng = np.random.default_rng(2)
    uv = rng.uniform(0, 600, (12, 2))
    w = rng.uniform(0.2, 1, 12)
    for n in (1, 2, 5):
        S, C = np.arange(n), np.arange(n, 12)
        batch = sel._quality_index_batch(uv[S], w[S], uv[C], w[C], SIZE)
        ref = [sel.quality_index(uv[np.r_[S, j]], w[np.r_[S, j]], SIZE) for j in C]
        np.testing.assert_allclose(batch, ref, rtol=1e-12)


def test_min_separation_excludes_crowded_corners():
    uv, J, va, sil, P6 = _candidates(3)
    uv = uv.copy()
    uv[1] = uv[0] + [3.0, 0.0]  # two corners 3 px apart: the extractor cannot tell them apart
    el = sel.eligible_mask(uv, SIZE, J=J, min_separation_px=5.0)
    assert not el[0] and not el[1]
    for idx in (
        sel.select_quality(uv, va, sil, SIZE, k=30, min_separation_px=5.0),
        sel.select_information(uv, J, va, sil, SIZE, P6=P6, k=30, min_separation_px=5.0),
        sel.select_information_joint([(uv, J, va, SIZE)], P6=P6, k_per_camera=30, min_separation_px=5.0)[0],
    ):
        assert 0 not in idx and 1 not in idx
    # off by default
    assert sel.eligible_mask(uv, SIZE, J=J)[[0, 1]].all()


def test_weight_by_quality_prefers_reliable_corners():
    uv, J, va, sil, P6 = _candidates(6)
    plain = sel.select_information(uv, J, va, sil, SIZE, P6=P6, k=8)
    # make the plain choice's corners grazing-but-eligible and on the silhouette
    va, sil = va.copy(), sil.copy()
    va[plain] = np.deg2rad(78.0)
    sil[plain] = 0.0
    w = sel.feature_weights(uv, va, sil, SIZE)
    weighted = sel.select_information(uv, J, va, sil, SIZE, P6=P6, k=8, weight_by_quality=True)
    assert w[weighted].mean() > 2 * w[plain].mean()
    assert len(set(weighted.tolist()) & set(plain.tolist())) < 4
    # unchanged criterion when every corner is equally reliable
    same = sel.select_information(uv, J, np.zeros(30), np.full(30, 50.0), SIZE, P6=P6, k=8, weight_by_quality=True)
    np.testing.assert_array_equal(same, sel.select_information(uv, J, np.zeros(30), np.full(30, 50.0), SIZE, P6=P6, k=8))


def test_quality_index_batch_matches_plain_formulation():
    """The x/y-split batch scores equal the (M, n, 2)-stack formulation to rounding."""
    from vespro.selection import _quality_index_batch, _quality_index_batch_plain

    rng = np.random.default_rng(3)
    for _ in range(300):
        n, m = int(rng.integers(1, 9)), int(rng.integers(1, 40))
        S, C = rng.uniform(0, 640, (n, 2)), rng.uniform(0, 640, (m, 2))
        C[: min(m, 3)] = S[0]  # coincident points: zero-length offsets and angle ties
        wS, wC = rng.random(n), rng.random(m)
        got = _quality_index_batch(S, wS, C, wC, (640, 480))
        want = _quality_index_batch_plain(S, wS, C, wC, (640, 480))
        # 1e-12: rounding of sums of <= 9 terms (~1e-16 relative), well above
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)


def _select_quality_numpy(uv, view_angle, silhouette_px, image_size, k, min_separation_px=0.0):
    """select_quality as first written, a NumPy greedy loop over _quality_index_batch."""
    w = sel.feature_weights(uv, view_angle, silhouette_px, image_size, min_separation_px=min_separation_px)
    el = np.flatnonzero(w > 0.0)
    if el.size <= k:
        return el[np.argsort(-w[el], kind="stable")]
    c = uv[el].mean(axis=0)
    dist = np.linalg.norm(uv[el] - c, axis=1)
    chosen = [int(el[np.lexsort((-dist, -w[el]))[0]])]
    remaining = el[el != chosen[0]]
    while len(chosen) < k:
        scores = sel._quality_index_batch(uv[chosen], w[chosen], uv[remaining], w[remaining], image_size)
        best = int(np.argmax(scores))
        chosen.append(int(remaining[best]))
        remaining = np.delete(remaining, best)
    return np.array(chosen)


def test_compiled_quality_selection_equals_the_numpy_loop():
    """The compiled selection picks what the NumPy loop picks, in the same order, on
    random candidate sets (ties from integer pixels, NaN inputs, separation on), and
    its weights are feature_weights' bit for bit."""
    rng = np.random.default_rng(7)
    for it in range(1500):
        n = int(rng.integers(1, 50))
        k = int(rng.choice([3, 6, 8, 12]))
        uv = rng.uniform([-20, -20], [660, 500], (n, 2))
        if it % 3 == 0:
            uv = np.round(uv)
        va = rng.uniform(0, 1.6, n)
        va[rng.random(n) < 0.05] = np.nan
        sil = rng.uniform(0, 20, n)
        sil[rng.random(n) < 0.05] = np.nan
        sep = float(rng.choice([0.0, 0.0, 5.0]))
        want = _select_quality_numpy(uv, va, sil, SIZE, k, sep)
        got = sel.select_quality(uv, va, sil, SIZE, k=k, min_separation_px=sep)
        assert np.array_equal(got, want), it
        w = sel._weights_kernel(uv, va, sil, SIZE[0], SIZE[1], sel.DEFAULT_BORDER_PX, sel.DEFAULT_SIL_REF_PX,
                                sel.DEFAULT_MAX_VIEW_ANGLE, float(np.cos(sel.DEFAULT_MAX_VIEW_ANGLE)), sep)
        assert np.array_equal(w, sel.feature_weights(uv, va, sil, SIZE, min_separation_px=sep))


def _clearance_numpy(uv, half):
    """The NumPy formulation of :func:`vespro.selection.window_clearance`."""
    diff = uv[:, None, :] - uv[None, :, :]
    d2 = np.einsum("ijk,ijk->ij", diff, diff)
    np.fill_diagonal(d2, np.inf)
    with np.errstate(invalid="ignore"):
        return np.sqrt(d2.min(axis=1)) - (half + 2.0)


@pytest.mark.parametrize("seed", range(6))
def test_window_clearance_equals_the_numpy_formulation_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 40))
    uv = rng.uniform(-50, 700, (n, 2)) * rng.choice([1e-3, 1.0, 1e3])
    if n > 3:
        uv[1] = uv[0]  # coincident corners
        uv[2] = uv[0] + rng.normal(0, 1e-9, 2)
    if seed % 3 == 2 and n > 4:
        uv[4, 1] = np.nan  # a corner behind the camera
    half = rng.integers(4, 25, n)
    got, ref = sel.window_clearance(uv, half), _clearance_numpy(uv, half)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    ok = ~np.isnan(ref)
    assert got[ok].tobytes() == ref[ok].tobytes()
    if n == 1:
        assert got[0] == np.inf
