"""PoseReceiver: pty, loop:// and TCP loopback links, reconnects, backoff, ages."""

from __future__ import annotations

import os
import pty
import socket
import time
import tty

import numpy as np
import pytest

from servo.receiver import NO_POSE_AGE_NS, LinkState, PoseReceiver
from vespro import wire
from vespro.link import PosePublisher
from vespro.wire import HeartbeatMsg, HelloMsg, PoseMsg, PoseStatus

HELLO = HelloMsg(26.0, ("box",))
WAIT_S = 10.0  # hang guard for "eventually", not a speed requirement


def make_poses(n: int, seed: int = 0, seq0: int = 0) -> list[PoseMsg]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        A = rng.normal(size=(6, 6))
        t_cap = int(rng.integers(0, 2**60))
        out.append(PoseMsg(seq0 + i, t_cap, t_cap + int(rng.integers(0, 10**8)), 0, PoseStatus.TRACKING,
                           rng.normal(size=3), rng.normal(size=4), rng.normal(size=3), rng.normal(size=3),
                           A @ A.T * 1e-6, probability=np.nan if i % 3 == 0 else rng.uniform()))
    return out


def poll_until(rx: PoseReceiver, pred, out: list | None = None, timeout_s: float = WAIT_S) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        rx.poll(out=out)
        if pred():
            return True
        time.sleep(0.0005)
    return pred()


def free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.fixture
def pty_pair():
    master, slave = pty.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


def test_pty_every_pose_arrives_bit_exact(pty_pair):
    master, name = pty_pair
    rx = PoseReceiver(name, idle_timeout_s=0)
    assert rx.poll() is None and rx.state == LinkState.CONNECTED
    poses = make_poses(500, seed=1)
    stream = b"\x00" + wire.encode(HELLO) + b"".join(wire.encode(p) for p in poses)
    got: list = []
    # Written in pieces while polling, so frames straddle reads.
    for k in range(0, len(stream), 777):
        os.write(master, stream[k : k + 777])
        rx.poll(out=got)
    assert poll_until(rx, lambda: len(got) >= 501, got)
    assert got[0] == HELLO and got[1:] == poses
    assert rx.hello == HELLO
    st = rx.stats()
    assert st.poses == 500 and st.rejected_total == 0 and st.seq_gaps == 0
    pose, _ = rx.latest()
    assert pose == poses[-1]
    rx.close()


def test_pty_garbage_and_corruption_are_counted(pty_pair):
    master, name = pty_pair
    rx = PoseReceiver(name)
    rx.poll()
    poses = make_poses(4, seed=2)
    bad = bytearray(wire.encode(poses[1]))
    bad[50] ^= 0x10
    os.write(master, b"\x13\x37garbage" + wire.encode(poses[0])[5:] + bytes(bad)
             + wire.encode(poses[2]) + wire.encode(poses[3]))
    got: list = []
    assert poll_until(rx, lambda: len(got) >= 2, got)
    assert got == poses[2:]   # the joined-mid-frame garbage and the flipped frame are dropped
    st = rx.stats()
    assert st.rejected["crc"] + st.rejected["cobs"] + st.rejected["length"] == 2 and st.rejected_total == 2
    rx.close()


def test_loop_url():
    rx = PoseReceiver("loop://")
    rx.poll()
    assert rx.state == LinkState.CONNECTED
    poses = make_poses(20, seed=3)
    rx._transport.port.write(b"".join(wire.encode(p) for p in poses))
    got: list = []
    assert poll_until(rx, lambda: len(got) >= 20, got)
    assert got == poses  # the probability too (NaN: not stated)
    assert np.isnan(got[0].probability) and 0.0 <= got[1].probability <= 1.0
    rx.close()


def test_tcp_every_pose_arrives_bit_exact_in_order():
    pub = PosePublisher.tcp(HELLO, 0, max_pending_frames=1000, stamp_send_time=False, heartbeat_period_s=0)
    rx = PoseReceiver("socket://127.0.0.1:%d" % pub.address[1])
    try:
        got: list = []
        assert poll_until(rx, lambda: got == [HELLO], got)
        poses = make_poses(500, seed=4)
        for p in poses:
            pub.publish(p)
        assert poll_until(rx, lambda: len(got) >= 501, got)
        assert got[1:] == poses
        assert rx.stats().seq_gaps == 0 and rx.stats().rejected_total == 0 and rx.stats().connects == 1
    finally:
        rx.close()
        pub.close()


def test_reconnects_after_server_restart():
    port = free_port()
    pub = PosePublisher.tcp(HELLO, port, heartbeat_period_s=0, stamp_send_time=False)
    rx = PoseReceiver(f"socket://127.0.0.1:{port}", backoff_min_s=0.005, backoff_max_s=0.02)
    try:
        first = make_poses(10, seed=5)
        got: list = []
        assert poll_until(rx, lambda: got == [HELLO], got)
        for p in first:
            pub.publish(p)
        assert poll_until(rx, lambda: got[-1:] == [first[-1]], got)
        pub.close()                                  # the server goes away
        assert poll_until(rx, lambda: rx.state != LinkState.CONNECTED)
        assert rx.stats().disconnects == 1
        # Nobody listening for a while: polls keep failing quietly.
        for _ in range(20):
            assert rx.poll() is None
            time.sleep(0.001)
        pub = PosePublisher.tcp(HELLO, port, heartbeat_period_s=0, stamp_send_time=False)
        got.clear()
        assert poll_until(rx, lambda: got == [HELLO], got)
        second = make_poses(10, seed=6)            # the new server restarts seq at 0
        for p in second:
            pub.publish(p)
        assert poll_until(rx, lambda: got[-1:] == [second[-1]], got)
        assert got == [HELLO] + second
        st = rx.stats()
        assert st.connects == 2 and st.disconnects == 1 and st.rejected_total == 0
        # HELLO starts a new stream, so the seq restart is neither a gap nor a reset.
        assert st.seq_gaps == 0 and st.seq_resets == 0
        assert rx.latest()[0] == second[-1]
    finally:
        rx.close()
        pub.close()


def test_a_refusing_server_s_reason_is_kept_and_shown_and_a_later_seat_is_taken():
    """A server that serves no more clients says why and closes: the receiver counts the
    refusal, keeps the reason for the servo's status line, retries, and is served once a
    seat is free (the reason then goes)."""
    from servo.report import status_line
    from servo.loop import LoopConfig, LoopState

    pub = PosePublisher.tcp(HELLO, 0, max_clients=1, heartbeat_period_s=0, stamp_send_time=False)
    port = pub.address[1]
    first = PoseReceiver(f"socket://127.0.0.1:{port}")
    rx = PoseReceiver(f"socket://127.0.0.1:{port}", backoff_min_s=0.005, backoff_max_s=0.02)
    try:
        assert poll_until(first, lambda: first.hello is not None)
        assert poll_until(rx, lambda: rx.stats().refusals >= 2)
        st = rx.stats()
        assert rx.hello is None and st.poses == 0 and st.rejected_total == 0
        assert "at most 1 clients" in st.refusal and "--max-clients" in st.refusal
        line = status_line(LoopState(LoopConfig()), rx, time.monotonic_ns())
        assert "(refused: this pose server takes at most 1 clients" in line, line
        first.close()                                # a seat frees up
        got: list = []
        assert poll_until(rx, lambda: got[-1:] == [HELLO], got)
        pose = make_poses(1, seed=3)[0]
        pub.publish(pose)
        assert poll_until(rx, lambda: rx.latest()[0] == pose)
        assert rx.stats().refusal is None and "refused" not in status_line(
            LoopState(LoopConfig()), rx, time.monotonic_ns())
    finally:
        first.close()
        rx.close()
        pub.close()


def test_partial_frame_from_a_dead_connection_does_not_spoil_the_next():
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    rx = PoseReceiver("socket://127.0.0.1:%d" % srv.getsockname()[1], backoff_min_s=0.001)
    poses = make_poses(2, seed=7)
    try:
        assert poll_until(rx, lambda: rx.state == LinkState.CONNECTED)
        conn, _ = srv.accept()
        conn.sendall(wire.encode(poses[0])[:100])    # dies mid-frame
        assert poll_until(rx, lambda: rx.stats().bytes_in == 100)
        conn.close()
        assert poll_until(rx, lambda: rx.stats().disconnects == 1)
        assert poll_until(rx, lambda: rx.state == LinkState.CONNECTED)
        conn, _ = srv.accept()
        conn.sendall(wire.encode(poses[1]))          # no leading 0x00 from this peer
        got: list = []
        assert poll_until(rx, lambda: got == [poses[1]], got)
        st = rx.stats()
        assert st.rejected["length"] == 1 and st.rejected_total == 1   # the truncated frame
        conn.close()
    finally:
        rx.close()
        srv.close()


def test_backoff_schedule_with_no_server():
    port = free_port()
    rx = PoseReceiver(f"socket://127.0.0.1:{port}", backoff_min_s=0.05, backoff_max_s=0.2)
    ms = 1_000_000

    def poll_at(t_ms):
        # A refused loopback connect may complete on a later poll: repeat at the same time.
        for _ in range(1000):
            assert rx.poll(now_ns=t_ms * ms) is None
            if rx.state == LinkState.DISCONNECTED:
                return
        pytest.fail("connect neither failed nor succeeded")

    # Attempts at 0, then after 50, 100, 200, 200 ms (doubling, capped).
    expected_attempts = {0: 1, 10: 1, 49: 1, 50: 2, 149: 2, 150: 3, 349: 3, 350: 4, 550: 5}
    for t_ms, n in expected_attempts.items():
        poll_at(t_ms)
        assert rx.stats().open_failures == n, t_ms
    assert rx.stats().connects == 0
    rx.close()


def test_idle_tcp_link_is_dropped_and_reopened():
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    rx = PoseReceiver("socket://127.0.0.1:%d" % srv.getsockname()[1], idle_timeout_s=1.0, backoff_min_s=0.1)
    s = 1_000_000_000
    try:
        for _ in range(1000):
            rx.poll(now_ns=0)
            if rx.state == LinkState.CONNECTED:
                break
        assert rx.state == LinkState.CONNECTED
        conn, _ = srv.accept()
        rx.poll(now_ns=s)                     # silent for exactly 1 s: still fine
        assert rx.state == LinkState.CONNECTED
        conn.sendall(wire.encode(HeartbeatMsg(0, 0)))
        for _ in range(1000):                  # bytes arrive at t = 1.5 s: idle clock restarts
            rx.poll(now_ns=s + s // 2)
            if rx.stats().frames_ok:
                break
        assert rx.stats().frames_ok == 1
        rx.poll(now_ns=2 * s + s // 2)        # 1.0 s after the heartbeat: still fine
        assert rx.state == LinkState.CONNECTED
        rx.poll(now_ns=2 * s + s // 2 + 1)    # silent for more than 1 s: dropped
        assert rx.state == LinkState.DISCONNECTED and rx.stats().disconnects == 1
        rx.poll(now_ns=2 * s + s // 2 + 1 + s // 10)   # after the 0.1 s backoff: reconnects
        assert rx.state in (LinkState.CONNECTING, LinkState.CONNECTED)
        conn.close()
    finally:
        rx.close()
        srv.close()


def test_latest_age_combines_local_and_remote_clocks(pty_pair):
    master, name = pty_pair
    rx = PoseReceiver(name)
    assert rx.latest(now_ns=5) == (None, NO_POSE_AGE_NS)
    rx.poll(now_ns=0)
    a = PoseMsg(0, 1_000, 1_500, 0, PoseStatus.TRACKING, np.zeros(3), [1, 0, 0, 0])
    b = PoseMsg(1, 2_000, 2_800, 1, PoseStatus.LOST, np.ones(3), [1, 0, 0, 0])
    os.write(master, wire.encode(HelloMsg(26.0, ("box", "lid"))) + wire.encode(a) + wire.encode(b))
    newest = None
    for _ in range(10000):
        newest = rx.poll(now_ns=10_000) or newest
        if rx.stats().poses == 2:
            break
    assert newest == b
    # Received at 10_000 (local clock); asked at 12_000: 2_000 since arrival + sender latency.
    assert rx.latest(now_ns=12_000) == (b, 2_000 + 800)
    assert rx.latest(now_ns=12_000, object_id=0) == (a, 2_000 + 500)
    assert rx.latest(now_ns=12_000, object_id=7) == (None, NO_POSE_AGE_NS)
    rx.close()


def test_serial_device_that_vanishes_is_reopened_quietly():
    master, slave = pty.openpty()
    tty.setraw(slave)
    name = os.ttyname(slave)
    rx = PoseReceiver(name, backoff_min_s=0.001, backoff_max_s=0.004)
    rx.poll()
    assert rx.state == LinkState.CONNECTED
    os.close(master)                           # the adapter is unplugged
    os.close(slave)
    assert poll_until(rx, lambda: rx.stats().disconnects == 1)
    for _ in range(50):
        assert rx.poll() is None
        time.sleep(0.001)
    assert rx.stats().open_failures >= 1
    rx.close()


def test_bad_socket_url_is_a_setup_error():
    with pytest.raises(ValueError):
        PoseReceiver("socket://127.0.0.1")


def test_fileno_follows_the_link(pty_pair):
    _, name = pty_pair
    rx = PoseReceiver(name)
    assert rx.fileno() is None                 # not opened before the first poll
    rx.poll()
    assert isinstance(rx.fileno(), int)
    rx.close()
    assert rx.fileno() is None


def test_receiver_loads_only_the_wire_protocol():
    """Importing the receiver loads vespro.wire alone of vespro, and no SciPy, OpenCV or MuJoCo
    (what each package may import at all: tests/test_layers.py)."""
    import subprocess
    import sys
    from pathlib import Path

    code = ("import sys, servo.receiver; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('vespro', 'scipy', 'cv2', 'mujoco')))")
    root = Path(__file__).resolve().parents[2]
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "['vespro', 'vespro.wire']"
