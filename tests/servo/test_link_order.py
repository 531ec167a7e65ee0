"""Poses the servo side does not use: out of order, duplicated, stamped in the future, of an
object nobody announced, before any HELLO; and a restarted server, which is accepted."""

import numpy as np

from servo.link_source import LinkSource
from servo.receiver import PoseReceiver
from servo.safety import Reject, Status
from servo.loop import step

from servo_helpers import DT_NS, FakePoseServer, make_loop, obj_sample, pose_msg

MS = 1_000_000


def _connected(names=("part",)):
    server = FakePoseServer(names)
    rx = PoseReceiver(server.url)
    server.accept(rx)
    return server, rx


def test_out_of_order_duplicate_future_and_unknown_object_are_rejected_and_counted():
    server, rx = _connected()
    try:
        t = 1000 * MS
        server.send(rx, pose_msg(10, t - 40 * MS, t, (0.9, 0.0, 0.5)), t)
        assert rx.latest(t)[0].seq == 10
        bad = {
            "out_of_order": pose_msg(9, t - 30 * MS, t, (0.9, -0.2, 0.5)),  # older seq: would pull the part back
            "duplicate": pose_msg(10, t - 20 * MS, t, (0.9, -0.2, 0.5)),
            "future_stamp": pose_msg(11, t + 400 * MS, t, (0.9, -0.2, 0.5)),  # captured 0.4 s after sent
            "unknown_object": pose_msg(12, t - 20 * MS, t, (0.9, -0.2, 0.5), object_id=1),
        }
        for msg in bad.values():
            server.send(rx, msg, t)
            assert rx.latest(t)[0].seq == 10  # still the good pose
        st = rx.stats()
        assert st.pose_rejected == {"no_hello": 0, **{k: 1 for k in bad}}
        assert st.poses == 1
        # within the clock tolerance (5 ms) a capture after the send stamp is accepted
        server.send(rx, pose_msg(13, t + 3 * MS, t, (0.9, 0.01, 0.5)), t)
        assert rx.latest(t)[0].seq == 13 and rx.stats().poses == 2
    finally:
        rx.close()
        server.close()


def test_a_pose_before_any_hello_is_rejected():
    server = FakePoseServer()
    rx = PoseReceiver(server.url)
    try:
        server.accept(rx, hello=False)
        server.send(rx, pose_msg(0, 0, 1, (0.9, 0.0, 0.5)), 0)
        assert rx.latest(0)[0] is None and rx.stats().pose_rejected["no_hello"] == 1
        server.send(rx, server.hello, 0)
        server.send(rx, pose_msg(1, 0, 1, (0.9, 0.0, 0.5)), 0)
        assert rx.latest(0)[0].seq == 1
    finally:
        rx.close()
        server.close()


def test_server_restart_with_a_new_hello_is_accepted_on_the_same_line_and_after_a_reconnect():
    server, rx = _connected()
    try:
        t = 0
        for seq in range(100, 105):
            server.send(rx, pose_msg(seq, t, t + 40 * MS, (0.9, 0.0, 0.5)), t)
        # the server restarts on the same line (a serial link): HELLO, then seq from 0
        server.send(rx, server.hello, t)
        server.send(rx, pose_msg(0, t, t + 40 * MS, (0.9, 0.1, 0.5)), t)
        assert rx.latest(t)[0].seq == 0
        server.send(rx, pose_msg(1, t, t + 40 * MS, (0.9, 0.1, 0.5)), t)
        assert rx.latest(t)[0].seq == 1
        # but without a HELLO, going back is out of order
        server.send(rx, pose_msg(0, t, t + 40 * MS, (0.9, 0.1, 0.5)), t)
        assert rx.latest(t)[0].seq == 1
        # the server process is killed and started again: a new connection, a new HELLO, seq from 0
        server.drop()
        for _ in range(100):
            rx.poll(t)
            if rx.stats().disconnects:
                break
        t += 200 * MS  # after the reconnect backoff
        server.accept(rx, now_ns=t)
        server.send(rx, pose_msg(0, t, t + 40 * MS, (0.9, 0.2, 0.5)), t)
        assert rx.latest(t)[0].seq == 0 and rx.latest(t)[0].p_world_object[1] == 0.2
        st = rx.stats()
        assert st.seq_restarts == 1 and st.hellos == 3 and st.connects == 2
        assert st.pose_rejected["out_of_order"] == 1 and st.pose_rejected_total == 1
        assert st.poses == 8
    finally:
        rx.close()
        server.close()


def test_older_poses_do_not_pull_the_reference_back():
    """Through the link source into the loop: the loop only ever sees the newest pose."""
    server, rx = _connected()
    src = LinkSource(rx)
    try:
        t = 1000 * MS
        server.send(rx, pose_msg(50, t - 40 * MS, t, (0.9, 0.3, 0.5)), t)
        s1, _ = src.latest(t)
        for k in range(5):  # five stale poses of an earlier position arrive late
            server.send(rx, pose_msg(40 + k, t - 300 * MS, t, (0.9, 0.1, 0.5)), t)
            s, _ = src.latest(t)
            assert s is s1 and s.p_world_object[1] == 0.3
        assert rx.stats().pose_rejected["out_of_order"] == 5
    finally:
        rx.close()
        server.close()


def test_loop_rejects_a_sample_stamped_after_the_tick_beyond_the_clock_tolerance():
    state, out = make_loop()
    t = DT_NS
    assert step(state, obj_sample(t + 10 * MS), t, out) == Status.HOLD  # 10 ms in the future
    assert out.reject == Reject.FUTURE and state.n_rejected == 1 and state.n_used == 0
    assert np.isclose(state.record.recent()[-1]["value"], 0.010)
    t += DT_NS
    step(state, obj_sample(t + 3 * MS), t, out)  # within the 5 ms tolerance
    assert out.reject == 0 and state.n_used == 1
