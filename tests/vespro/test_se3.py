import numpy as np
import pytest

from vespro import se3


def random_T(rng):
    q = se3.quat_normalize(rng.normal(size=4))
    return se3.transform_from_rt(se3.matrix_from_quat(q), rng.normal(size=3))


def test_hamilton_ijk():
    i, j, k = np.eye(4)[1], np.eye(4)[2], np.eye(4)[3]
    np.testing.assert_allclose(se3.quat_multiply(i, j), k)
    np.testing.assert_allclose(se3.quat_multiply(j, i), -k)


def test_quat_matrix_roundtrip_and_product_matches_matrix_product():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q1, q2 = se3.quat_normalize(rng.normal(size=(2, 4)))
        R1, R2 = se3.matrix_from_quat(q1), se3.matrix_from_quat(q2)
        np.testing.assert_allclose(se3.matrix_from_quat(se3.quat_multiply(q1, q2)), R1 @ R2, atol=1e-12)
        back = se3.quat_from_matrix(R1)
        assert back[0] >= 0
        np.testing.assert_allclose(back, se3.quat_canonical(q1), atol=1e-12)


def test_matrix_from_quat_known_case():
    # 90 degrees about z maps x to y (worked by hand).
    q = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(se3.matrix_from_quat(q) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_transform_inverse_and_pq_roundtrip():
    rng = np.random.default_rng(1)
    for _ in range(20):
        T = random_T(rng)
        np.testing.assert_allclose(T @ se3.invert_transform(T), np.eye(4), atol=1e-12)
        np.testing.assert_allclose(se3.transform_from_pq(se3.pq_from_transform(T)), T, atol=1e-12)
        se3.check_transform(T)


def test_exp_log_and_angle():
    rng = np.random.default_rng(2)
    for _ in range(20):
        v = rng.normal(size=3)
        v *= rng.uniform(0, 3.0) / np.linalg.norm(v)
        R = se3.exp_so3(v)
        np.testing.assert_allclose(se3.log_so3(R), v, atol=1e-9)
        assert se3.rotation_angle(R) == pytest.approx(np.linalg.norm(v), abs=1e-9)
    assert se3.rotation_angle(se3.exp_so3([1e-9, 0, 0])) == pytest.approx(1e-9, rel=1e-6)


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="shape"):
        se3.check_transform(np.eye(3))
    with pytest.raises(ValueError, match="proper rotation"):
        se3.check_transform(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="7 numbers"):
        se3.transform_from_pq([0, 0, 0, 1, 0, 0])
    with pytest.raises(ValueError):
        se3.transform_from_pq([0, 0, 0, 0, 0, 0, 0])


def test_matrix_from_quat_single_equals_scipy_bit_for_bit():
    """The written-out path for one quaternion gives SciPy's matrix exactly (the filter
    relies on it to keep its results independent of the path)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    for _ in range(2000):
        q = rng.normal(size=4) * rng.choice([1e-3, 1.0, 1e3])
        qn = se3.quat_normalize(q)
        want = Rotation.from_quat(np.roll(qn, -1)).as_matrix()
        assert np.array_equal(se3.matrix_from_quat(q), want)
    # and the batch path agrees with the single one
    Q = rng.normal(size=(50, 4))
    assert np.array_equal(se3.matrix_from_quat(Q), np.array([se3.matrix_from_quat(q) for q in Q]))


def test_log_so3_is_scipys_rotation_vector():
    """The compiled log is SciPy's ``from_matrix(R).as_rotvec()`` to rounding: random
    rotations, small angles (its series), angles at and near pi, the identity, the
    coordinate flips (each branch of the quaternion's largest term); a matrix a little
    off orthonormal gives a rotation within its error."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    Rs = list(Rotation.random(2000, random_state=rng).as_matrix())
    axes = rng.normal(size=(60, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for a, ang in zip(axes, np.concatenate([np.geomspace(1e-12, 2e-3, 20), np.pi - np.geomspace(1e-12, 1e-2, 20),
                                            np.full(20, np.pi)])):
        Rs.append(Rotation.from_rotvec(a * ang).as_matrix())
    Rs += [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]
    off = Rs[0] + 1e-6 * rng.normal(size=(3, 3))
    np.testing.assert_allclose(se3.log_so3(off), Rotation.from_matrix(off).as_rotvec(), rtol=0, atol=1e-5)
    for R in Rs:
        want = Rotation.from_matrix(R).as_rotvec()
        got = se3.log_so3(R)
        if np.linalg.norm(want) > np.pi - 1e-6:  # at pi, v and -v are the same rotation
            assert min(np.abs(got - want).max(), np.abs(got + want).max()) < 1e-9
        else:
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    with pytest.raises(ValueError):
        se3.log_so3(np.eye(4))
