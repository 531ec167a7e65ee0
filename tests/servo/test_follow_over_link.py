"""Following a conveyor part with ground-truth poses fed through the real link.

Lockstep: one simulated clock stamps capture, send and reception; each pose is
published over TCP loopback 40 ms (the vision latency) after its capture
instant and the test waits until the receiver has it, so the run is
deterministic. The arm is the MuJoCo arm stepped by the scheduler.
"""

import time

import numpy as np
import pytest

from servo.clock import SimClock
from servo.planner import follow_task
from servo.link_source import LinkSource
from servo.loop import LoopConfig, LoopState, Scheduler
from servo.receiver import PoseReceiver
from servo.robot import MujocoArm
from vespro.link import PosePublisher
from vespro.wire import HelloMsg, PoseMsg, PoseStatus

RATE = 26.0
LATENCY_NS = 40_000_000
SPEED = 0.1
STANDOFF = 0.15


def object_position(t_s: float) -> np.ndarray:
    return np.array([0.9, -0.3 + SPEED * t_s, 0.5])


def run_follow(latency_compensation: bool, seconds: float = 7.0) -> np.ndarray:
    clock = SimClock()
    pub = PosePublisher.tcp(HelloMsg(RATE, ("part",)), port=0, clock_ns=clock.now_ns, heartbeat_period_s=0)
    host, port = pub.address
    rx = PoseReceiver(f"socket://{host}:{port}", clock_ns=clock.now_ns)
    src = LinkSource(rx)
    cfg = LoopConfig(task=follow_task(STANDOFF), latency_compensation=latency_compensation)
    arm = MujocoArm(cfg.model_path)
    state = LoopState(cfg)
    errors = []
    nxt = {"k": 0, "seq": 0}
    deadline = time.monotonic() + 10
    while rx.stats().state.name != "CONNECTED" and time.monotonic() < deadline:
        rx.poll()
        time.sleep(0.01)

    def on_tick(t_ns, out):
        # Publish every capture whose processing (40 ms) has finished by now.
        while int(nxt["k"] * 1e9 / RATE) + LATENCY_NS <= t_ns:
            t_cap = int(nxt["k"] * 1e9 / RATE)
            cov = np.diag([1e-7] * 3 + [1e-6] * 3)
            pub.publish(PoseMsg(nxt["seq"], t_cap, t_ns, 0, PoseStatus.TRACKING, object_position(t_cap * 1e-9),
                                [1.0, 0, 0, 0], [0, SPEED, 0], [0, 0, 0], cov))
            until = time.monotonic() + 2.0
            while (rx.latest(t_ns)[0] is None or rx.latest(t_ns)[0].seq != nxt["seq"]) and time.monotonic() < until:
                rx.poll(t_ns)
            nxt["k"] += 1
            nxt["seq"] += 1
        if t_ns * 1e-9 > seconds - 2.0:  # steady state: the last two seconds
            goal = object_position(t_ns * 1e-9) + [0, 0, STANDOFF]
            errors.append(np.linalg.norm(arm.tcp_position() - goal))

    sched = Scheduler(clock, arm, state, src, realtime=False, on_tick=on_tick)
    try:
        sched.run(int(seconds * 500))
    finally:
        rx.close()
        pub.close()
    assert src.samples > 0.9 * (seconds - 0.1) * RATE, "poses did not come through the link"
    return np.array(errors)


@pytest.mark.slow
def test_follows_conveyor_through_the_link_thanks_to_latency_compensation():
    with_comp = run_follow(True)
    without = run_follow(False)
    # The bound: steady-state error under 2 mm with compensation.
    assert with_comp.max() < 2e-3, with_comp.max()
    # Without it the reference lags by about speed x (latency + half a frame period) = 6 mm.
    assert without.mean() > 3e-3, without.mean()
    print(f"steady-state error: with compensation mean {with_comp.mean() * 1e3:.3f} mm max {with_comp.max() * 1e3:.3f} mm; "
          f"without mean {without.mean() * 1e3:.3f} mm max {without.max() * 1e3:.3f} mm")
