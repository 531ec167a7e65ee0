"""Kinematics: MuJoCo vs NumPy chain vs finite differences; CLIK accuracy; singularities."""

import numpy as np
import pytest

from servo.kinematics import (
    ArmKinematics,
    Clik,
    ClikConfig,
    chain_from_model,
    damping_squared,
    dls_solve_into,
    fk_chain,
    jacobian_chain,
    solve_ik,
)
from servo.rotation import quat_from_matrix, rotvec_error
from vespro.se3 import log_so3  # tests may use vespro.se3 as an independent reference

# Elbow stretched: link3's vector (0.64, 0, 0.13) parallel to the upper arm when
# tan(q3) = -0.64 / 0.13 (see models/arm.xml); the wrist is singular at q5 = 0.
Q3_STRETCHED = float(np.arctan2(-0.64, 0.13))


@pytest.fixture(scope="module")
def kin():
    return ArmKinematics()


def random_configs(kin, rng, n, margin=0.0):
    return rng.uniform(kin.q_min + margin, kin.q_max - margin, size=(n, kin.n))


def test_model_read_from_mjcf(kin):
    assert kin.n == 6
    np.testing.assert_allclose(kin.qd_max, [2.97, 2.62, 3.14, 6.11, 6.11, 8.38])
    np.testing.assert_allclose(kin.q_min[1], -1.57)
    np.testing.assert_allclose(kin.q_max[2], 1.40)


def test_fk_zero_pose_by_hand(kin):
    # Worked by hand from the MJCF: x = 0.15 + 0.64 + 0.10 + 0.10 (tool site),
    # z = 0.16 + 0.29 + 0.60 + 0.13; the flange z axis (approach) along world +x.
    T = kin.forward(np.zeros(6))
    np.testing.assert_allclose(T[:3, 3], [0.99, 0.0, 1.18], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [1.0, 0.0, 0.0], atol=1e-12)


def test_mujoco_matches_numpy_chain(kin):
    chain = chain_from_model(kin.model)
    rng = np.random.default_rng(0)
    for q in random_configs(kin, rng, 50):
        # Both are exact products of the same transforms: only rounding differs.
        np.testing.assert_allclose(kin.forward(q), fk_chain(chain, q), atol=1e-12)
        np.testing.assert_allclose(kin.jacobian(q), jacobian_chain(chain, q), atol=1e-12)


def test_jacobian_matches_finite_differences(kin):
    rng = np.random.default_rng(1)
    h = 1e-6
    for q in random_configs(kin, rng, 20):
        J = kin.jacobian(q)
        Jfd = np.zeros((6, 6))
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = h
            Tp, Tm = kin.forward(q + dq), kin.forward(q - dq)
            Jfd[:3, i] = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
            # world-frame angular velocity: log(R+ R-^T) / 2h
            Jfd[3:, i] = log_so3(Tp[:3, :3] @ Tm[:3, :3].T) / (2 * h)
        # central differences: truncation O(h^2) ~ 1e-12, rounding ~ 1e-16 / h = 1e-10
        np.testing.assert_allclose(J, Jfd, atol=1e-8)


def _reachable_configs(kin, rng, n):
    """Random configurations away from the joint limits and from singularities."""
    out = []
    while len(out) < n:
        q = random_configs(kin, rng, 1, margin=0.3)[0]
        if abs(q[4]) < 0.3:
            continue
        if np.linalg.svd(kin.jacobian(q), compute_uv=False)[-1] < 0.1:
            continue
        out.append(q)
    return out


def _pose_err(kin, q, T):
    Tq = kin.forward(q)
    return np.linalg.norm(Tq[:3, 3] - T[:3, 3]), np.linalg.norm(rotvec_error(quat_from_matrix(T[:3, :3]), quat_from_matrix(Tq[:3, :3])))


def test_solve_ik_reaches_random_poses(kin):
    rng = np.random.default_rng(2)
    for q_true in _reachable_configs(kin, rng, 30):
        T = kin.forward(q_true)
        q, ok = solve_ik(kin, T, q_true + rng.normal(0, 0.2, 6))
        e_p, e_r = _pose_err(kin, q, T)
        assert ok
        assert e_p < 1e-4 and e_r < np.radians(0.01)


def test_clik_ticks_reach_random_poses(kin):
    """The 500 Hz CLIK itself (velocity limited) converges onto fixed poses."""
    rng = np.random.default_rng(3)
    clik = Clik(kin)
    z3 = np.zeros(3)
    qd = np.zeros(6)
    worst = (0.0, 0.0)
    for q_true in _reachable_configs(kin, rng, 20):
        T = kin.forward(q_true)
        p, quat = T[:3, 3].copy(), quat_from_matrix(T[:3, :3])
        q = q_true + rng.normal(0, 0.15, 6)
        for _ in range(1000):  # 2 s at 500 Hz; gain 60/s -> e^-120 after the rate-limited part
            clik.step(q, p, quat, z3, z3, 0.002, q, qd)
        e_p, e_r = _pose_err(kin, q, T)
        worst = max(worst[0], e_p), max(worst[1], e_r)
    assert worst[0] < 1e-4, worst
    assert worst[1] < np.radians(0.01), worst


def test_damping_is_smooth_and_bounded():
    eps, lm = 0.06, 0.05
    s = np.linspace(0, 0.1, 1001)
    lam2 = np.array([damping_squared(x, eps, lm) for x in s])
    assert lam2[0] == pytest.approx(lm**2)
    assert np.all(lam2[s >= eps] == 0.0)
    assert np.all(np.diff(lam2) <= 1e-15)  # monotone non-increasing: no jump
    gain = s / (s**2 + lam2 + 1e-300)
    assert gain.max() <= 1 / eps * (1 + 1e-9)


@pytest.mark.parametrize(
    "q, exact",
    [
        ([0.2, 0.5, -0.8, 0.3, 0.0, 0.4], True),  # wrist singular: j4 and j6 aligned
        ([0.2, 0.5, -0.8, 0.3, 1e-5, 0.4], False),
        ([0.0, 0.3, Q3_STRETCHED, 0.0, 0.8, 0.0], True),  # elbow singular: arm stretched
        ([0.0, 0.3, Q3_STRETCHED + 1e-5, 0.0, 0.8, 0.0], False),
        ([0.0, 0.3, Q3_STRETCHED, 0.0, 0.0, 0.0], True),  # both
    ],
)
def test_dls_rates_bounded_at_singularities(kin, q, exact):
    cfg = ClikConfig()
    J = kin.jacobian(np.array(q))
    s = np.linalg.svd(J, compute_uv=False)
    assert s[-1] < 1e-4  # really (near) singular: the test would be vacuous otherwise
    rng = np.random.default_rng(4)
    qd = np.zeros(6)
    for _ in range(200):
        x = rng.normal(size=6)
        x /= np.linalg.norm(x)
        dls_solve_into(J, x, cfg.eps, cfg.lambda_max, qd)
        # max_s s / (s^2 + lambda(s)^2) = 1/eps for these settings (see test_damping...)
        assert np.linalg.norm(qd) <= 1.0 / cfg.eps * (1 + 1e-9)
    if not exact:  # the undamped inverse is huge there
        assert 1.0 / s[-1] > 1e3 / cfg.eps


def test_clik_through_wrist_singularity(kin):
    """Follow a reference whose joint path crosses q5 = 0: rates bounded, tracking recovers."""
    q_a = np.array([-0.3, 0.3, -0.5, 0.4, 0.3, 0.2])
    q_b = np.array([0.3, 0.5, -0.7, 0.4, -0.3, -0.2])
    clik = Clik(kin)
    q = q_a.copy()
    qd = np.zeros(6)
    seconds, dt = 2.0, 0.002
    n = int(seconds / dt)
    raw, smin, err = [], [], []
    for k in range(n + 250):  # the path, then 0.5 s holding the end pose
        s = min((k + 1) / n, 1.0)
        q_ref = q_a + s * (q_b - q_a)
        T = kin.forward(q_ref)
        tw = kin.jacobian(q_ref) @ ((q_b - q_a) / seconds) if s < 1.0 else np.zeros(6)
        clik.step(q, T[:3, 3], quat_from_matrix(T[:3, :3]), tw[:3], tw[3:], dt, q, qd)
        assert np.all(np.abs(qd) <= kin.qd_max * (1 + 1e-12))
        raw.append(np.linalg.norm(clik.qd_raw))
        smin.append(clik.s_min)
        err.append(_pose_err(kin, q, T))
    assert min(smin) < 0.01  # the path really crossed the singular region
    # |qd_raw| <= |x| / eps (x = ff twist + gain * error, |x| < 1.2 here): 20 rad/s
    assert max(raw) < 20.0
    assert err[-1][0] < 1e-4 and err[-1][1] < np.radians(0.01)


def test_clik_at_elbow_singularity_reaching_out(kin):
    """Ask the TCP to go 25 cm beyond the stretched arm: bounded rates, no blow-up."""
    q0 = np.array([0.0, 0.3, Q3_STRETCHED + 0.15, 0.0, 0.8, 0.0])
    T0 = kin.forward(q0)
    clik = Clik(kin)
    c = np.array([0.15, 0.0, 0.45])  # shoulder
    out_dir = (T0[:3, 3] - c) / np.linalg.norm(T0[:3, 3] - c)
    quat = quat_from_matrix(T0[:3, :3])
    q = q0.copy()
    qd = np.zeros(6)
    z3 = np.zeros(3)
    v = 0.25 * out_dir
    raw, smin = [], []
    for k in range(750):
        p = T0[:3, 3] + v * min((k + 1) * 0.002, 1.0)
        clik.step(q, p, quat, v if k < 500 else z3, z3, 0.002, q, qd)
        assert np.all(np.abs(qd) <= kin.qd_max * (1 + 1e-12))
        raw.append(np.linalg.norm(clik.qd_raw))
        smin.append(clik.s_min)
    assert min(smin) < 0.03  # pushed into the singular region
    assert max(raw) < 1.0 / ClikConfig().eps * (0.25 + 60 * 0.25) * 1.01  # the DLS bound
    assert np.all(np.isfinite(q))


def test_clik_brakes_before_joint_limits(kin):
    """A reference the arm cannot reach without passing j2's limit: j2 slows, then stops inside."""
    cfg = ClikConfig()
    clik = Clik(kin, cfg)
    q = np.array([0.0, 1.8, -0.5, 0.0, 0.9, 0.0])
    T = kin.forward(np.array([0.0, 2.6, -0.5, 0.0, 0.9, 0.0]))  # j2 = 2.6 > 2.36
    p, quat = T[:3, 3].copy(), quat_from_matrix(T[:3, :3])
    z3, qd = np.zeros(3), np.zeros(6)
    hi = kin.q_max[1] - cfg.joint_margin_rad
    for _ in range(1500):
        d = hi - q[1]
        clik.step(q, p, quat, z3, z3, 0.002, q, qd)
        assert q[1] <= hi + 1e-12
        assert qd[1] <= np.sqrt(2 * cfg.joint_brake_acc * max(d, 0.0)) + 1e-9
    assert q[1] == pytest.approx(hi, abs=1e-3)  # it got there, and stays
