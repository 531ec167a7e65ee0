"""Planner: limits under random target jumps, workspace clamp, latency compensation,
approach/follow, stop, and the classic motions."""

import numpy as np
import pytest
from hypothesis import given, settings, HealthCheck
from hypothesis import strategies as st

from servo.planner import (
    CartesianLimits,
    CartesianTrapezoid,
    FollowTask,
    JointTrapezoid,
    Phase,
    Reference,
    TrackingPlanner,
    Trapezoid,
    ViaPath,
    Workspace,
)
from servo.rotation import quat_from_rotvec, quat_multiply, rotvec_error
from servo.target import TargetSample

DT = 0.002
DT_NS = 2_000_000
T_DOWN = np.diag([1.0, -1.0, -1.0, 1.0])  # TCP z pointing down (world -z)
T_DOWN[2, 3] = 0.15
Q_DOWN = np.array([0.0, 1.0, 0.0, 0.0])
LIM = CartesianLimits()
# Ruckig meets its limits up to the rounding of its profile roots (~1e-12
# relative); the orientation chart is exact at the current state. 1e-6
# relative + 1e-9 absolute is far above rounding and far below any real breach.
REL, ABS = 1e-6, 1e-9


def sample(t_ns, p, q=(1, 0, 0, 0), v=(0, 0, 0), w=(0, 0, 0)):
    return TargetSample(t_ns, p, q, v, w, np.eye(6) * 1e-6)


def make_planner(**kw):
    pl = TrackingPlanner(**kw)
    pl.set_task(FollowTask(T_DOWN, standoff_m=0.1))
    pl.reset([0.9, 0.0, 0.9], Q_DOWN)
    return pl


class LimitChecker:
    def __init__(self, lim=LIM):
        self.vmax = np.r_[[lim.v_lin] * 3, [lim.v_ang] * 3]
        self.amax = np.r_[[lim.a_lin] * 3, [lim.a_ang] * 3]
        self.jmax = np.r_[[lim.j_lin] * 3, [lim.j_ang] * 3]
        self.a_prev = np.zeros(6)
        self.worst = np.zeros(3)

    def check(self, ref: Reference, dt):
        v = np.r_[ref.v, ref.w]
        a = np.r_[ref.a, ref.alpha]
        j = (a - self.a_prev) / dt
        self.a_prev = a
        for k, (x, m) in enumerate(((v, self.vmax), (a, self.amax), (j, self.jmax))):
            r = np.max(np.abs(x) / m)
            self.worst[k] = max(self.worst[k], r)
            assert np.all(np.abs(x) <= m * (1 + REL) + ABS), (["v", "a", "j"][k], x, m)


@st.composite
def target_streams(draw):
    n = draw(st.integers(3, 12))
    events = []
    for _ in range(n):
        gap = draw(st.integers(1, 60))  # ticks until this sample (26 Hz is ~19)
        p = draw(st.tuples(*[st.floats(-0.6, 0.6)] * 3))
        rv = draw(st.tuples(*[st.floats(-2.5, 2.5)] * 3))
        v = draw(st.tuples(*[st.floats(-0.4, 0.4)] * 3))
        w = draw(st.tuples(*[st.floats(-1.0, 1.0)] * 3))
        events.append((gap, p, rv, v, w))
    dts = draw(st.lists(st.sampled_from([1, 1, 1, 2]), min_size=400, max_size=400))
    return events, dts


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(target_streams())
def test_reference_within_limits_under_random_jumps(stream):
    events, dts = stream
    pl = make_planner()
    chk = LimitChecker()
    base = np.array([0.9, 0.0, 0.5])
    t = 0
    due = []
    tick = 0
    for gap, p, rv, v, w in events:
        tick += gap
        due.append((tick, sample(0, base + p, quat_from_rotvec(rv), v, w)))
    for k, m in enumerate(dts):
        t += m * DT_NS
        while due and due[0][0] <= k:
            s = due.pop(0)[1]
            pl.set_sample(TargetSample(t - 40_000_000, s.p_world_object, s.q_world_object, s.v_world_object, s.w_world_object, s.cov))
        res = pl.step(t, m * DT)
        assert res >= 0
        chk.check(pl.ref, m * DT)
        assert abs(np.linalg.norm(pl.ref.quat) - 1) < 1e-12


def test_limits_are_reached_not_just_respected():
    """The limit test is not vacuous: a big jump drives v, a and j to their limits."""
    pl = make_planner()
    chk = LimitChecker()
    pl.set_sample(sample(0, [0.9, 0.6, 0.5], quat_from_rotvec([0, 0, 2.0])))
    for k in range(1, 1500):
        pl.step(k * DT_NS, DT)
        chk.check(pl.ref, DT)
    assert np.all(chk.worst > 0.999)


def test_moving_target_is_tracked_exactly():
    """Constant-velocity target, fresh samples: the reference converges onto it."""
    pl = make_planner()
    pl.task = FollowTask(T_DOWN, standoff_m=0.0)
    v = np.array([0.0, 0.1, 0.0])
    for k in range(1, 2000):
        t = k * DT_NS
        if k % 19 == 0:
            pl.set_sample(sample(t - 40_000_000, np.array([0.9, -0.3, 0.5]) + v * (t * 1e-9 - 0.04), v=v))
        if pl.have_sample:
            pl.step(t, DT)
    goal = np.array([0.9, -0.3, 0.65]) + v * (2000 * DT)  # reference is for the next tick
    np.testing.assert_allclose(pl.ref.p, goal, atol=1e-9)
    np.testing.assert_allclose(pl.ref.v, v, atol=1e-12)


def _track_error(latency_compensation):
    pl = make_planner(latency_compensation=latency_compensation)
    pl.task = FollowTask(T_DOWN, standoff_m=0.0)
    v = np.array([0.0, 0.1, 0.0])
    p0 = np.array([0.9, -0.3, 0.5])
    period = int(1e9 / 26)
    errs = []
    last = None
    for k in range(1, 3000):
        t = k * DT_NS
        kc = (t - 40_000_000) // period  # newest capture available after 40 ms latency
        if kc >= 0 and kc != last:
            last = kc
            tc = kc * period
            pl.set_sample(sample(tc, p0 + v * tc * 1e-9, v=v))
        if pl.have_sample:
            pl.step(t, DT)
            if k > 1500:
                goal = p0 + v * (t + DT_NS) * 1e-9 + [0, 0, 0.15]
                errs.append(np.linalg.norm(pl.ref.p - goal))
    return np.max(errs)


def test_latency_compensation_removes_the_lag():
    with_c, without = _track_error(True), _track_error(False)
    assert with_c < 1e-6  # exact constant-velocity prediction
    # without: lag of v * (latency + up to one frame) = 4 ... 7.8 mm
    assert without > 4e-3
    assert without > 1000 * with_c


def test_workspace_clamp_waits_at_the_boundary_and_comes_back():
    ws = Workspace()
    pl = make_planner(workspace=ws)
    pl.task = FollowTask(T_DOWN, standoff_m=0.0)
    outside = np.array([0.9, 1.5, 0.5])  # y beyond box_max (0.9)
    pl.set_sample(sample(0, outside))
    chk = LimitChecker()
    for k in range(1, 3000):
        pl.step(k * DT_NS, DT)
        chk.check(pl.ref, DT)
        assert ws.contains(pl.ref.p, tol=1e-9)
    assert pl.clamped
    assert pl.ref.p[1] == pytest.approx(ws.box_max[1], abs=1e-9)
    assert np.linalg.norm(pl.ref.v) < 1e-9  # waiting, at rest
    inside = np.array([0.9, 0.2, 0.5])
    pl.set_sample(sample(3000 * DT_NS, inside))
    for k in range(3000, 6000):
        pl.step(k * DT_NS, DT)
    np.testing.assert_allclose(pl.ref.p, inside + [0, 0, 0.15], atol=1e-9)


def test_reach_sphere_clamp():
    ws = Workspace()
    p = np.array([1.3, 0.9, 1.4])  # in the box corner, beyond the reach sphere
    out = np.zeros(3)
    assert ws.clamp_into(p, out)
    assert np.linalg.norm(out - ws.reach_center) == pytest.approx(ws.reach_radius)


def test_approach_then_follow():
    pl = make_planner()
    obj = np.array([0.9, 0.1, 0.5])
    pl.set_sample(sample(0, obj))
    assert pl.phase == Phase.APPROACH
    k = 0
    while pl.phase == Phase.APPROACH and k < 5000:
        k += 1
        pl.step(k * DT_NS, DT)
        assert pl.ref.p[2] >= obj[2] + 0.15 + 0.1 - 1e-3 or pl.ref.p[2] >= 0.5 + 0.25 - 1e-3
    assert pl.phase == Phase.FOLLOW
    # at the switch the reference sat at the stand-off, 0.1 m above the follow pose
    assert pl.ref.p[2] == pytest.approx(obj[2] + 0.25, abs=2e-3)
    for j in range(k + 1, k + 2000):
        pl.step(j * DT_NS, DT)
    np.testing.assert_allclose(pl.ref.p, obj + [0, 0, 0.15], atol=1e-9)
    assert abs(rotvec_error(pl.ref.quat, Q_DOWN)).max() < 1e-9


def test_follow_orientation_of_a_rotated_object():
    pl = make_planner()
    pl.task = FollowTask(T_DOWN, standoff_m=0.0)
    q_obj = quat_from_rotvec([0, 0, 0.8])
    pl.set_sample(sample(0, [0.9, 0.0, 0.5], q_obj))
    for k in range(1, 3000):
        pl.step(k * DT_NS, DT)
    q_goal = quat_multiply(q_obj, Q_DOWN)
    assert np.linalg.norm(rotvec_error(q_goal, pl.ref.quat)) < 1e-9


def test_upright_task_stays_above_a_tilted_object_and_keeps_its_heading():
    # A 10 degree tilt (an estimate's roll error, say) must not move the stand-off point
    # (0.15 m lever: 26 mm) nor tilt the TCP; the heading (0.8 rad about z) is followed.
    pl = make_planner()
    pl.task = FollowTask(T_DOWN, standoff_m=0.0, upright=True)
    # Heading 0.8 rad, then tilted 10 degrees about its own x axis (which keeps that heading).
    q_obj = quat_multiply(quat_from_rotvec([0, 0, 0.8]), quat_from_rotvec([np.deg2rad(10.0), 0, 0]))
    obj = np.array([0.9, 0.0, 0.5])
    pl.set_sample(sample(0, obj, q_obj, w=(0.3, -0.2, 0.0)))
    pl.latency_compensation = False
    for k in range(1, 3000):
        pl.step(k * DT_NS, DT)
    np.testing.assert_allclose(pl.ref.p, obj + [0, 0, 0.15], atol=1e-9)
    q_goal = quat_multiply(quat_from_rotvec([0, 0, 0.8]), Q_DOWN)
    assert np.linalg.norm(rotvec_error(q_goal, pl.ref.quat)) < 1e-6
    # The same sample without upright: the stand-off point swings with the tilt.
    pl2 = make_planner()
    pl2.task = FollowTask(T_DOWN, standoff_m=0.0)
    pl2.latency_compensation = False
    pl2.set_sample(sample(0, obj, q_obj))
    for k in range(1, 3000):
        pl2.step(k * DT_NS, DT)
    assert np.linalg.norm(pl2.ref.p - (obj + [0, 0, 0.15])) > 0.02


def test_stop_step_decelerates_within_limits_then_holds():
    pl = make_planner()
    pl.task = FollowTask(T_DOWN, standoff_m=0.0)
    pl.set_sample(sample(0, [0.9, 0.8, 0.5], v=[0, 0.2, 0]))
    for k in range(1, 200):
        pl.step(k * DT_NS, DT)
    assert np.linalg.norm(pl.ref.v) > 0.2
    chk = LimitChecker()
    chk.a_prev = np.r_[pl.ref.a, pl.ref.alpha]
    n = 0
    while not pl.stop_step(DT):
        chk.check(pl.ref, DT)
        n += 1
        assert n < 1000
    assert np.all(np.abs(pl.ref.v) < 1e-12) and np.all(np.abs(pl.ref.a) < 1e-12)
    p = pl.ref.p.copy()
    for _ in range(10):
        assert pl.stop_step(DT)
    np.testing.assert_array_equal(pl.ref.p, p)


# --- classic motions ---------------------------------------------------------


def test_trapezoid_golden():
    # distance 1, v 0.5, a 1: t_acc = 0.5 s, cruise 1.5 s, total 2.5 s (by hand)
    tr = Trapezoid(0.5, 1.0)
    assert tr.duration == pytest.approx(2.5)
    assert tr.sample(0.5)[:2] == pytest.approx((0.125, 0.5))
    assert tr.sample(0.4) == pytest.approx((0.08, 0.4, 1.0))
    assert tr.sample(1.25)[0] == pytest.approx(0.5)
    assert tr.sample(2.5) == (1.0, 0.0, 0.0)
    # triangle: v 2, a 1 -> t_acc = 1, T = 2
    assert Trapezoid(2.0, 1.0).duration == pytest.approx(2.0)


def _numeric_check(sample_fn, duration, d, vmax, amax):
    ts = np.linspace(0, duration, 4001)
    X = np.zeros((len(ts), d))
    V = np.zeros((len(ts), d))
    A = np.zeros((len(ts), d))
    for i, t in enumerate(ts):
        sample_fn(t, X[i], V[i], A[i])
    dt = ts[1] - ts[0]
    # velocity is the derivative of position (midpoint rule, O(dt^2 a') + blend kinks)
    np.testing.assert_allclose(np.diff(X, axis=0) / dt, 0.5 * (V[1:] + V[:-1]), atol=np.max(amax) * dt)
    assert np.all(np.abs(V) <= vmax * (1 + 1e-9))
    assert np.all(np.abs(A) <= amax * (1 + 1e-9))
    return X, V


def test_joint_trapezoid_synchronised_within_limits():
    q0 = np.array([0.0, 0.2, -0.3, 0.0, 1.0, 0.0])
    q1 = np.array([1.0, -0.2, 0.4, 2.0, -0.5, 3.0])
    qd, qdd = np.array([2.97, 2.62, 3.14, 6.11, 6.11, 8.38]), np.full(6, 5.0)
    m = JointTrapezoid(q0, q1, qd, qdd)
    X, V = _numeric_check(m.sample, m.duration, 6, qd, qdd)
    np.testing.assert_allclose(X[-1], q1, atol=1e-12)
    np.testing.assert_allclose(V[-1], 0, atol=1e-12)
    # straight line in joint space: all joints at the same fraction
    frac = (X - q0) / (q1 - q0)
    np.testing.assert_allclose(frac, frac[:, :1].repeat(6, 1), atol=1e-12)
    # at least one joint hits a limit (time-optimal for the line)
    assert np.max(np.abs(V) / qd) > 0.999 or np.max(np.abs(np.diff(V, axis=0))) > 0


def test_cartesian_trapezoid_line_and_slerp():
    T0 = np.eye(4)
    T0[:3, 3] = [0.8, -0.2, 0.6]
    T1 = np.eye(4)
    T1[:3, :3] = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])  # 90 deg about z
    T1[:3, 3] = [1.0, 0.3, 0.7]
    m = CartesianTrapezoid(T0, T1, LIM)
    ref = Reference()
    d = T1[:3, 3] - T0[:3, 3]
    for t in np.linspace(0, m.duration, 300):
        m.sample(t, ref)
        # on the line
        r = ref.p - T0[:3, 3]
        assert np.linalg.norm(np.cross(r, d)) < 1e-12
        assert np.linalg.norm(ref.v) <= LIM.v_lin * (1 + 1e-9)
        assert np.linalg.norm(ref.w) <= LIM.v_ang * (1 + 1e-9)
        assert np.linalg.norm(ref.a) <= LIM.a_lin * (1 + 1e-9)
    m.sample(m.duration, ref)
    np.testing.assert_allclose(ref.p, T1[:3, 3], atol=1e-12)
    assert np.linalg.norm(rotvec_error(ref.quat, [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])) < 1e-12


def test_via_path_lspb():
    P = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [2.0, 1.5]])
    vmax, amax = np.array([0.5, 0.4]), np.array([1.0, 0.8])
    m = ViaPath(P, vmax, amax)
    X, V = _numeric_check(m.sample, m.duration, 2, vmax, amax)
    np.testing.assert_allclose(X[0], P[0], atol=1e-12)
    np.testing.assert_allclose(X[-1], P[-1], atol=1e-12)
    np.testing.assert_allclose(V[[0, -1]], 0, atol=1e-12)
    # passes each interior via point within the corner-cut bound |dv| tb / 8
    for j in (1, 2):
        bound = np.linalg.norm(m.Vx[j + 1] - m.Vx[j]) * m.tb[j] / 8
        assert np.min(np.linalg.norm(X - P[j], axis=1)) <= bound + 1e-3
    # continuous velocity everywhere (no jumps bigger than amax * dt)
    dt = m.duration / 4000
    assert np.all(np.abs(np.diff(V, axis=0)) <= amax * dt * (1 + 1e-6) + 1e-12)


def test_via_path_short_segments_are_slowed_to_fit_blends():
    P = np.array([[0.0], [0.01], [-0.01], [1.0]])
    m = ViaPath(P, 1.0, 0.5)
    seg = np.diff(m.t_knot)
    assert np.all(0.5 * (m.tb[:-1] + m.tb[1:]) <= seg * (1 + 1e-9))
