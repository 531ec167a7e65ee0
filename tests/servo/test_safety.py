"""Safety: sample validation, command checks, watchdog (controlled stop, resume),
immediate stop latched until reset, non-finite command -> FAULT."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from servo.kinematics import ArmKinematics
from servo.loop import step
from servo.safety import Check, Safety, SafetyConfig, Status, StopPolicy
from servo.target import SampleStatus

from servo_helpers import DT_NS, ScriptedStream, make_loop, obj_sample

KIN = ArmKinematics()


@pytest.fixture
def safety():
    return Safety(SafetyConfig.from_kinematics(KIN))


def test_sample_validation(safety):
    t = 1_000_000_000
    assert safety.sample_valid(obj_sample(t - 40_000_000), t)
    assert not safety.sample_valid(obj_sample(t, p=(np.nan, 0, 0.5)), t)
    assert not safety.sample_valid(obj_sample(t, v=(0, np.inf, 0)), t)
    assert not safety.sample_valid(obj_sample(t, q=(np.nan, 0, 0, 0)), t)
    assert not safety.sample_valid(obj_sample(t, q=(2.0, 0, 0, 0)), t)  # not unit
    assert not safety.sample_valid(obj_sample(t, status=SampleStatus.LOST), t)
    assert not safety.sample_valid(obj_sample(t - 600_000_000), t)  # older than 0.5 s
    s = obj_sample(t)
    bad_cov = type(s)(t, s.p_world_object, s.q_world_object, s.v_world_object, s.w_world_object, np.eye(6) * 0.01)
    assert not safety.sample_valid(bad_cov, t)  # 10 cm std


def test_check_command_flags(safety):
    q = np.zeros(6)
    p = np.array([0.9, 0.0, 0.8])
    assert safety.check_command(q, q, 0.002, p, p) == 0
    q1 = q.copy()
    q1[1] = KIN.q_min[1] - 1e-3
    assert safety.check_command(q1, q1, 0.002, p, p) & Check.JOINT_POSITION
    q2 = q.copy()
    q2[0] = KIN.qd_max[0] * 0.002 * 1.01  # 1 % too fast
    assert safety.check_command(q2, q, 0.002, p, p) == Check.JOINT_VELOCITY
    q2[0] = KIN.qd_max[0] * 0.002 * 0.99
    assert safety.check_command(q2, q, 0.002, p, p) == 0
    assert safety.check_command(q, q, 0.002, np.array([2.0, 0, 0.8]), np.array([2.0, 0, 0.8])) == Check.WORKSPACE
    assert safety.check_command(q, q, 0.002, p + [0.003, 0, 0], p) == Check.TCP_SPEED  # 1.5 m/s
    q3 = q.copy()
    q3[2] = np.nan
    assert safety.check_command(q3, q, 0.002, p, p) == Check.NONFINITE
    assert safety.policy(Check.JOINT_VELOCITY | Check.TCP_SPEED) == StopPolicy.IMMEDIATE
    assert safety.policy(Check.TCP_SPEED) == StopPolicy.CONTROLLED
    assert safety.policy(0) is None


def _run_until(state, out, stream, t, t_end, statuses=None, feed=True):
    while t < t_end:
        t += DT_NS
        s = stream.at(t) if feed else None
        st_ = step(state, s, t, out)
        if statuses is not None:
            statuses.append((t, st_))
    return t


def test_watchdog_controlled_stop_within_one_tick_then_resume_after_hold():
    state, out = make_loop()
    stream = ScriptedStream(p=(0.9, -0.3, 0.5), v=(0.0, 0.1, 0.0))  # moving: stopping takes time
    t = _run_until(state, out, stream, 0, 2_000_000_000)
    assert out.status == Status.TRACKING
    deadline = state.safety.watchdog_deadline_ns()
    # stream stops: tick by tick up to the deadline
    log = []
    t = _run_until(state, out, stream, t, deadline + 3 * DT_NS, log, feed=False)
    before = [s for tt, s in log if tt < deadline]
    after = [(tt, s) for tt, s in log if tt >= deadline]
    assert all(s == Status.TRACKING for s in before)
    t_first, s_first = after[0]
    assert t_first - deadline < DT_NS  # the first tick at/after the deadline ...
    assert s_first == Status.STOPPING  # ... already stops
    assert state.flags_seen & Check.WATCHDOG
    # decelerate to rest within the planner limits, then hold (drives on)
    v_prev = None
    while out.status == Status.STOPPING:
        t += DT_NS
        step(state, None, t, out)
        assert np.all(np.abs(out.ref.v) <= state.cfg.limits.v_lin * (1 + 1e-6))
        assert out.drives_on
    assert out.status == Status.HOLD
    q_hold = out.q.copy()
    p_hold = out.ref.p.copy()
    t = _run_until(state, out, stream, t, t + 500_000_000, feed=False)
    np.testing.assert_allclose(out.ref.p, p_hold, atol=1e-12)  # the reference holds still
    # the CLIK only settles its last micro-radians of lag onto it
    np.testing.assert_allclose(out.q, q_hold, atol=1e-4)
    assert np.all(np.abs(out.qd) < 1e-6)
    # stream comes back: HOLD for resume_hold_s after the first new valid sample, then TRACKING
    log = []
    stream2 = ScriptedStream()
    t_back = None
    hold_ns = int(round(state.safety.cfg.resume_hold_s * 1e9))
    while True:
        t += DT_NS
        s = stream2.at(t)
        if s is not None and t - s.t_capture_ns > 0.3e9:
            s = None  # the stream restarts with fresh frames only
        n_before = state.last_capture_ns
        st_ = step(state, s, t, out)
        if t_back is None and s is not None and state.last_capture_ns != n_before:
            t_back = t
        if st_ == Status.TRACKING:
            break
        assert st_ == Status.HOLD
    assert t_back is not None
    assert 0 <= t - (t_back + hold_ns) < DT_NS


def test_immediate_stop_holds_until_reset():
    state, out = make_loop(safety={"policy_watchdog": StopPolicy.IMMEDIATE})
    stream = ScriptedStream()
    t = _run_until(state, out, stream, 0, 1_500_000_000)
    assert out.status == Status.TRACKING
    deadline = state.safety.watchdog_deadline_ns()
    t = _run_until(state, out, stream, t, deadline - DT_NS, feed=False)
    q_last = out.q.copy()
    t += DT_NS
    while t < deadline:
        step(state, None, t, out)
        q_last = out.q.copy()
        t += DT_NS
    assert step(state, None, t, out) == Status.STOPPED
    assert not out.drives_on
    np.testing.assert_array_equal(out.q, q_last)  # holds the last commanded position
    # samples come back: still stopped, for as long as we like
    for _ in range(1000):
        t += DT_NS
        assert step(state, ScriptedStream().at(t), t, out) == Status.STOPPED
        assert not out.drives_on
        np.testing.assert_array_equal(out.q, q_last)
    # explicit reset: restart from the measured joints, at rest, then track again
    state.reset(q_last, t)
    seen = set()
    for _ in range(600):
        t += DT_NS
        seen.add(step(state, stream.at(t), t, out))
    assert out.drives_on and Status.TRACKING in seen and Status.STOPPED not in seen


def test_nonfinite_command_is_a_fault(monkeypatch):
    state, out = make_loop()
    stream = ScriptedStream()
    t = _run_until(state, out, stream, 0, 1_000_000_000)
    q_last = out.q.copy()

    def broken(q, p, quat, v, w, dt, q_out, qd_out):
        q_out[:] = q
        q_out[3] = np.nan
        return 0.1

    monkeypatch.setattr(state.clik, "step", broken)
    t += DT_NS
    assert step(state, stream.at(t), t, out) == Status.FAULT
    assert out.flags & Check.NONFINITE
    assert not out.drives_on
    np.testing.assert_array_equal(out.q, q_last)
    assert np.all(np.isfinite(out.q))
    monkeypatch.undo()
    t += DT_NS
    assert step(state, stream.at(t), t, out) == Status.FAULT  # latched


def test_controlled_stop_by_tcp_speed_is_latched():
    # a TCP speed limit below the approach speed: controlled stop, no auto-resume
    state, out = make_loop(safety={"tcp_speed_max": 0.05})
    stream = ScriptedStream(p=(0.9, 0.3, 0.5))
    log = []
    t = _run_until(state, out, stream, 0, 4_000_000_000, log)
    statuses = [s for _, s in log]
    assert Status.STOPPING in statuses
    assert statuses[-1] == Status.HOLD
    assert state.latched
    assert state.flags_seen & Check.TCP_SPEED


@st.composite
def random_streams(draw):
    n = draw(st.integers(20, 60))
    ev = []
    for _ in range(n):
        kind = draw(st.sampled_from(["ok", "ok", "ok", "nan", "gap", "jump", "lost"]))
        gap = draw(st.integers(1, 80))
        p = draw(st.tuples(st.floats(0.2, 1.6), st.floats(-1.2, 1.2), st.floats(0.0, 1.2)))
        v = draw(st.tuples(*[st.floats(-0.5, 0.5)] * 3))
        ev.append((kind, gap, p, v))
    dts = draw(st.lists(st.sampled_from([1, 1, 1, 1, 2]), min_size=700, max_size=700))
    return ev, dts


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(random_streams())
def test_commanded_joints_never_exceed_limits(stream):
    """Random streams (jumps, NaN, LOST, gaps, doubled dt): the commands stay legal."""
    events, dts = stream
    state, out = make_loop()
    q_prev = out.q.copy()
    q_prev[:] = state.q_cmd
    t = 0
    k_next, i = 0, 0
    cur = None
    kin = state.kin
    for k, m in enumerate(dts):
        t += m * DT_NS
        if i < len(events) and k >= k_next:
            kind, gap, p, v = events[i]
            i += 1
            k_next = k + gap
            if kind == "nan":
                cur = obj_sample(t - 40_000_000, p=(np.nan, 0, 0))
            elif kind == "lost":
                cur = obj_sample(t - 40_000_000, status=SampleStatus.LOST)
            elif kind == "gap":
                cur = None
            else:
                cur = obj_sample(t - 40_000_000, p=p, v=v)
        st_ = step(state, cur, t, out)
        assert st_ != Status.FAULT, out.flags
        assert np.all(np.isfinite(out.q))
        assert np.all(out.q >= kin.q_min) and np.all(out.q <= kin.q_max)
        assert np.all(np.abs(out.q - q_prev) <= kin.qd_max * m * 0.002 * (1 + 1e-9))
        q_prev[:] = out.q
