"""Approaching a part on the belt from anywhere in the workspace, over the link, without a stop.

A fake pose server publishes a part moving at 0.1 m/s that enters from either
end of the belt; the arm starts at home or at four other poses in the
workspace, one of them wound so that the straight tool path runs into joint
limits. The plan keeps within the planner's limits (the CLIK caps the tool
speed at ``v_lin``, the reference waits for the arm when a joint limit cuts
the motion, and a blocked Cartesian approach is replaced by a joint-space
one), so the safety checks, which stay strict, never fire. Lockstep on
the simulated clock with a perfect plant (measured joints = commanded joints).
"""

import numpy as np
import pytest

from servo.clock import SimClock
from servo.planner import follow_task
from servo.events import EventKind
from servo.kinematics import ArmKinematics
from servo.link_source import LinkSource
from servo.loop import LoopConfig, LoopState, Scheduler
from servo.planner import Phase
from servo.receiver import PoseReceiver
from servo.safety import Status

from servo_helpers import BeltOverLink, FakePoseServer, MockRobot

STANDOFF = 0.15
STARTS = {
    "home": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    "left_tilted": [0.6, 0.4, -0.2, 0.5, 1.2, 0.3],
    "right_low": [-0.6, 0.8, -0.6, -0.8, 0.9, 1.0],
    "sideways": [-0.3, -0.2, 0.3, 1.5, -1.0, -1.0],
    # elbow and wrist wound so that the straight tool path drives joints 3 and 5 into their limits
    "wound": [0.8, 1.0, -1.5, 2.0, 1.5, -2.0],
}
ENDS = {"from_minus_y": ((0.9, -0.85, 0.5), (0.0, 0.1, 0.0)), "from_plus_y": ((0.9, 0.85, 0.5), (0.0, -0.1, 0.0))}


def run_over_link(q0, p0, v, seconds=10.0, follow_s=1.2, p_far=None):
    """Approach and follow; returns (state, tool speeds m/s, stand-off errors while following m, belt)."""
    kin = ArmKinematics()
    server = FakePoseServer()
    rx = PoseReceiver(server.url)
    server.accept(rx)
    belt = BeltOverLink(server, rx, p0, v)
    if p_far is not None:
        belt.position = lambda t_ns: np.asarray(p_far, float)
    state = LoopState(LoopConfig(task=follow_task(STANDOFF)))
    robot = MockRobot(q0)
    speeds, errors = [], []
    p_prev = [None]
    t_follow = [None]

    def on_tick(t_ns, out):
        belt.tick(t_ns)
        kin.update(out.q, jacobian=False)
        if p_prev[0] is not None:
            speeds.append(np.linalg.norm(kin.p - p_prev[0]) / 2e-3)
        p_prev[0] = kin.p.copy()
        if state.planner.phase == Phase.FOLLOW:
            if t_follow[0] is None:
                t_follow[0] = t_ns
            goal = belt.position(t_ns) + [0.0, 0.0, STANDOFF]
            if t_ns - t_follow[0] > 0.8e9:  # down from the approach height, settled on the moving part
                errors.append(np.linalg.norm(kin.p - goal))
            if t_ns - t_follow[0] > follow_s * 1e9:
                sched.request_stop()

    sched = Scheduler(SimClock(), robot, state, LinkSource(rx), on_tick=on_tick)
    try:
        sched.run(int(seconds * 500))
    finally:
        rx.close()
        server.close()
    return state, np.array(speeds), np.array(errors)


# Home with the part entering from either end; each other start with one end (alternating).
CASES = [("home", "from_minus_y"), ("home", "from_plus_y"), ("left_tilted", "from_minus_y"),
         ("right_low", "from_plus_y"), ("sideways", "from_minus_y"), ("wound", "from_minus_y")]


@pytest.mark.parametrize("start,end", CASES)
def test_approach_from_anywhere_then_follow_without_a_stop(start, end):
    p0, v = ENDS[end]
    state, speeds, errors = run_over_link(np.array(STARTS[start]), p0, v, seconds=14.0)
    v_lin = state.cfg.limits.v_lin
    assert state.planner.phase == Phase.FOLLOW, "the arm did not reach the stand-off"
    assert state.status == Status.TRACKING
    assert state.flags_seen == 0  # no check fired, not even for one tick
    assert state.record.count(EventKind.STOP) == 0 and state.record.count(EventKind.FAULT) == 0
    assert state.record.count(EventKind.REJECT) == 0
    # The tool never moves faster than the planner's limit (a norm), far below the safety limit.
    assert speeds.max() <= v_lin * 1.01, speeds.max()  # (1 %: FK vs the CLIK's linearised cap)
    assert errors.size > 100 and errors.max() < 2e-3, errors.max()
    if start == "wound":  # the Cartesian approach was blocked: it went through joint space
        planned = [e for e in state.record.recent() if e["kind"] == "joint_approach" and e["value"] is not None]
        assert planned and planned[0]["value"] > 0.5


def test_pose_far_outside_the_workspace_is_clamped_and_reported_not_a_stop():
    """A part reported 3 m away: the target is held at the workspace boundary, the arm goes
    there within the planner's limits, no check fires, and the clamp is in the record."""
    state, speeds, _ = run_over_link(np.zeros(6), (0.9, 0.0, 0.5), (0.0, 0.0, 0.0), seconds=4.0,
                                     p_far=(3.0, 0.5, 0.5))
    assert state.status == Status.TRACKING and state.flags_seen == 0
    assert state.record.count(EventKind.STOP) == 0
    assert state.record.count(EventKind.CLAMP) == 1  # reported once, when the target left the workspace
    ev = [e for e in state.record.recent() if e["kind"] == "clamp"][0]
    assert ev["value"] > 1.0  # moved by more than a metre
    assert speeds.max() <= state.cfg.limits.v_lin * 1.01
    # the reference went to the boundary (as far as the stretched arm reaches) and stays inside
    ws = state.cfg.workspace
    assert ws.contains(state.planner.ref.p, tol=1e-6)
    assert np.linalg.norm(state.planner.ref.p - state.planner.tgt_p) < 0.05
