"""The safety record in ``--stats-json`` and the status line: a run over a fake pose server
with a watchdog stop, a rejected pose of each kind and a late tick shows each event by cause."""

import json

import numpy as np

from servo.clock import SimClock
from servo.planner import follow_task
from servo.report import status_line, write_stats_json
from servo.events import EventKind
from servo.link_source import LinkSource
from servo.loop import LoopConfig, LoopState, Scheduler
from servo.receiver import PoseReceiver
from servo.safety import Check, Reject, Status
from vespro.wire import PoseStatus

from servo_helpers import BeltOverLink, FakePoseServer, MockRobot, pose_msg, q_above

MS = 1_000_000


class LateOnceClock(SimClock):
    """Simulated clock whose wake-up at ``late_at_ns`` comes ``late_ns`` late (a loaded machine)."""

    def __init__(self, late_at_ns: int, late_ns: int):
        super().__init__()
        self.late_at_ns, self.late_ns = late_at_ns, late_ns

    def sleep_until(self, t_ns: int) -> int:
        t = super().sleep_until(t_ns)
        if self.late_at_ns is not None and t_ns >= self.late_at_ns:
            self.late_at_ns = None
            t = self.advance(self.late_ns)
        return t


def test_stats_json_shows_every_event_by_cause(tmp_path):
    server = FakePoseServer()
    rx = PoseReceiver(server.url)
    server.accept(rx, hello=False)
    server.send(rx, pose_msg(0, 0, 0, (0.9, 0.0, 0.5)), 0)  # before the HELLO: no_hello
    server.send(rx, server.hello, 0)
    belt = BeltOverLink(server, rx, (0.9, 0.0, 0.5), (0.0, 0.0, 0.0))
    belt.seq = 1
    state = LoopState(LoopConfig(task=follow_task(0.15)))
    src = LinkSource(rx)
    p = (0.9, 0.0, 0.5)
    # one bad pose per tick from 1.0 s on, each sent right after a good one
    specials = {
        "duplicate": lambda t, s: pose_msg(s - 1, t - 40 * MS, t, p),
        "out_of_order": lambda t, s: pose_msg(s - 5, t - 40 * MS, t, p),
        "future_stamp": lambda t, s: pose_msg(s, t + 400 * MS, t, p),
        "unknown_object": lambda t, s: pose_msg(s, t - 40 * MS, t, p, object_id=4),
        "lost": lambda t, s: pose_msg(s, t - 40 * MS, t, p, status=PoseStatus.LOST),
        "stale": lambda t, s: pose_msg(s, t - 600 * MS, t, p),
        "uncertain": lambda t, s: pose_msg(s, t - 40 * MS, t, p, std_m=0.2),
    }
    plan = {1000 * MS + 40 * MS * i: name for i, name in enumerate(specials)}
    sent = []

    def on_tick(t_ns, out):
        if 1500 * MS <= t_ns < 1800 * MS:
            belt.paused_until_ns = t_ns  # the tracker is silent for 0.3 s: the watchdog stops the arm
        belt.tick(t_ns)
        name = plan.get(t_ns)
        if name is not None:
            msg = specials[name](t_ns, belt.seq)
            if msg.seq == belt.seq:
                belt.seq += 1
            server.send(rx, msg, t_ns)
            sent.append(name)

    clock = LateOnceClock(late_at_ns=2500 * MS, late_ns=5 * MS)  # one 7 ms tick at 2.5 s
    sched = Scheduler(clock, MockRobot(q_above()), state, src, realtime=True, rt_setup=False, on_tick=on_tick)
    try:
        stats = sched.run(1500)  # 3 s
    finally:
        rx.close()
        server.close()
    assert sent == list(specials)
    info = write_stats_json(tmp_path / "stats.json", stats, rx, src.samples, state.cfg.period_ns, False, state=state)
    assert json.loads((tmp_path / "stats.json").read_text()) == info
    saf = info["safety"]
    assert info["controlled_stops"] == 1 and saf["stops"] == {"WATCHDOG": 1}
    assert saf["immediate_stops"] == {} and saf["faults"] == {}
    assert saf["late_ticks"] == 1 and np.isclose(saf["late_tick_max_s"], 0.007)
    assert saf["rejected"] == {"lost": 1, "stale": 1, "uncertain": 1}
    assert info["link"]["poses_rejected"] == {"no_hello": 1, "unknown_object": 1, "future_stamp": 1,
                                              "duplicate": 1, "out_of_order": 1}
    # poses used: those the loop took, not the rejected ones
    assert info["poses_used"] == state.n_used == src.samples - 3
    # the events, with when and what tripped them
    assert [e["kind"] + ":" + e["cause"] for e in saf["recent_stops"]] == ["stop:WATCHDOG"]
    ev = {e["kind"] + ":" + e["cause"]: e for e in saf["recent_stops"] + saf["recent_late_ticks_and_rejects"]}
    wd = ev["stop:WATCHDOG"]
    assert 1.5 < wd["t_s"] < 1.8 and wd["value"] >= wd["limit"] == state.safety.cfg.watchdog_timeout_s
    late = ev["late_tick:late"]
    assert late["t_s"] == 2.505 and np.isclose(late["value"], 0.007) and np.isclose(late["limit"], 0.003)
    stale = ev["reject:stale"]
    assert np.isclose(stale["value"], 0.6, atol=0.01) and stale["limit"] == 0.5
    assert np.isclose(ev["reject:uncertain"]["value"], 0.2)
    # the arm resumed after the stop, and the status line says what happened
    assert Status(stats.status[-1]) == Status.TRACKING
    line = status_line(state, rx, 3000 * MS)
    assert "stops WATCHDOG:1" in line and "rejected lost:1,stale:1,uncertain:1" in line and "late 1" in line
    assert "duplicate:1" in line and "no_hello:1" in line


def test_recorder_rows_carry_the_check_the_reject_and_the_value():
    """The time histories: the tick of a rejection has its code; the stop tick its check and value."""
    from servo.recorder import Recorder

    from servo_helpers import ScriptedStream

    class Src:
        def __init__(self):
            self.s = ScriptedStream()

        def latest(self, t):
            if 1000 * MS <= t < 1300 * MS:
                return None, 0
            s = self.s.at(t)
            if t == 600 * MS:  # a stale sample
                s = type(s)(t - 700 * MS, s.p_world_object, s.q_world_object, s.v_world_object,
                            s.w_world_object, s.cov)
            return s, 0

    rec = Recorder(1000)
    state = LoopState(LoopConfig(task=follow_task(0.15)))
    Scheduler(SimClock(), MockRobot(q_above()), state, Src(), recorder=rec).run(1000)
    a = rec.arrays()
    k_rej = np.flatnonzero(a["reject"])
    assert list(a["t_ns"][k_rej]) == [600 * MS] and a["reject"][k_rej[0]] == Reject.STALE
    k_stop = np.flatnonzero(a["flags"] & Check.WATCHDOG)
    assert len(k_stop) == 1
    assert a["trip_value"][k_stop[0]] >= a["trip_limit"][k_stop[0]] > 0
    assert np.isnan(a["trip_value"][a["flags"] == 0]).all()
    assert state.record.count(EventKind.STOP, Check.WATCHDOG) == 1
