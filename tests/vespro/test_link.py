"""PosePublisher over TCP loopback and a real pseudo-terminal pair.

Received bytes are decoded here with ``wire.Decoder`` on a plain socket / the
pty master, independently of the servo-side receiver.
"""

from __future__ import annotations

import os
import pty
import select
import socket
import threading
import time
import tty

import numpy as np
import pytest

from vespro import wire
from vespro.link import PosePublisher, PublishStatus
from vespro.wire import REFUSAL_PREFIX, Decoder, HeartbeatMsg, HelloMsg, PoseMsg, PoseStatus

HELLO = HelloMsg(26.0, ("box", "bracket"))
WAIT_S = 10.0  # upper bound for "eventually" (a hang guard, not a speed requirement)


def make_poses(n: int, seed: int = 0) -> list[PoseMsg]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        A = rng.normal(size=(6, 6))
        out.append(PoseMsg(i, int(rng.integers(0, 2**62)), int(rng.integers(0, 2**62)), i % 2,
                           PoseStatus.TRACKING, rng.normal(size=3), rng.normal(size=4),
                           rng.normal(size=3), rng.normal(size=3), A @ A.T * 1e-6))
    return out


def wait_for(pred, timeout_s: float = WAIT_S) -> bool:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.001)
    return pred()


class Reader:
    """Reads a file descriptor / socket in a thread and decodes what arrives."""

    def __init__(self, read):
        self._read = read
        self.dec = wire.Decoder()
        self.msgs: list = []
        self.raw = bytearray()
        self.eof = False
        self._stop = False
        self._cond = threading.Condition()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self):
        while not self._stop:
            try:
                data = self._read()
            except OSError:
                data = b""
            if data is None:
                continue
            if not data:
                self.eof = True
                return
            with self._cond:
                self.raw += data
                self.msgs += self.dec.feed(data)
                self._cond.notify_all()

    def wait(self, pred, timeout_s: float = WAIT_S) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: pred(self.msgs), timeout_s)

    def poses(self):
        with self._cond:
            return [m for m in self.msgs if isinstance(m, PoseMsg)]

    def stop(self):
        self._stop = True
        self._t.join(timeout=2.0)


def socket_reader(sock: socket.socket) -> Reader:
    def read():
        r, _, _ = select.select([sock], [], [], 0.05)
        return sock.recv(65536) if r else None

    return Reader(read)


def connect(pub: PosePublisher, rcvbuf: int | None = None) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf is not None:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.connect(pub.address)
    return s


@pytest.fixture
def tcp_pub():
    pubs = []

    def make(**kw):
        kw.setdefault("stamp_send_time", False)
        kw.setdefault("heartbeat_period_s", 0)
        p = PosePublisher.tcp(HELLO, 0, **kw)
        pubs.append(p)
        return p

    yield make
    for p in pubs:
        p.close()


def test_tcp_every_pose_arrives_bit_exact_in_order(tcp_pub):
    pub = tcp_pub(max_pending_frames=1000)  # the test checks delivery, so nothing may be dropped
    assert pub.address[0] == "127.0.0.1"
    sock = connect(pub)
    reader = socket_reader(sock)
    assert reader.wait(lambda m: len(m) >= 1)
    poses = make_poses(500)
    for p in poses:
        assert pub.publish(p) == PublishStatus.OK
    assert reader.wait(lambda m: len(m) >= 501)
    reader.stop()
    assert reader.msgs[0] == HELLO
    assert reader.msgs[1:] == poses
    expected = b"\x00" + wire.encode(HELLO) + b"".join(wire.encode(p) for p in poses)
    assert bytes(reader.raw) == expected
    st = pub.stats()
    assert (st.frames_published, st.frames_sent, st.bytes_sent, st.drops) == (500, 501, len(expected), 0)
    assert st.clients_connected == 1 and st.clients_accepted == 1
    assert reader.dec.stats().rejected_total == 0 and reader.dec.seq_gaps == 0
    sock.close()


def test_pty_every_pose_arrives_bit_exact_in_order():
    master, slave = pty.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    name = os.ttyname(slave)
    pub = PosePublisher.serial(HELLO, name, max_pending_frames=1000, stamp_send_time=False,
                               heartbeat_period_s=0, hello_period_s=0)
    try:
        def read():
            r, _, _ = select.select([master], [], [], 0.05)
            return os.read(master, 65536) if r else None

        reader = Reader(read)
        poses = make_poses(500, seed=1)
        statuses = [pub.publish(p) for p in poses]
        assert set(statuses) == {PublishStatus.OK}
        assert reader.wait(lambda m: len(m) >= 501)
        reader.stop()
        assert reader.msgs[0] == HELLO and reader.msgs[1:] == poses
        # Raw mode: not a byte translated (no CR/LF mapping, no echo).
        assert bytes(reader.raw) == b"\x00" + wire.encode(HELLO) + b"".join(wire.encode(p) for p in poses)
        st = pub.stats()
        assert st.frames_sent == 501 and st.drops == 0
    finally:
        pub.close()
        os.close(master)
        os.close(slave)


def test_serial_hello_is_repeated_for_late_joiners():
    master, slave = pty.openpty()
    tty.setraw(slave)
    pub = PosePublisher.serial(HELLO, os.ttyname(slave), hello_period_s=0.02, heartbeat_period_s=0.02)
    try:
        def read():
            r, _, _ = select.select([master], [], [], 0.05)
            return os.read(master, 65536) if r else None

        reader = Reader(read)
        hb = lambda m: [x for x in m if isinstance(x, HeartbeatMsg)]
        assert reader.wait(lambda m: m.count(HELLO) >= 3 and len(hb(m)) >= 2)
        reader.stop()
        seqs = [x.seq for x in hb(reader.msgs)]
        assert seqs == list(range(len(seqs)))
    finally:
        pub.close()
        os.close(master)
        os.close(slave)


def test_clients_connect_disconnect_reconnect(tcp_pub):
    pub = tcp_pub()
    assert pub.publish(make_poses(1)[0]) == PublishStatus.NO_SINK
    a = connect(pub)
    ra = socket_reader(a)
    assert ra.wait(lambda m: m == [HELLO])
    poses = make_poses(30, seed=2)
    for p in poses[:10]:
        pub.publish(p)
        assert ra.wait(lambda m, p=p: m[-1] == p)
    b = connect(pub)
    rb = socket_reader(b)
    assert rb.wait(lambda m: m == [HELLO])  # a new client gets HELLO first
    for p in poses[10:20]:
        pub.publish(p)
        assert ra.wait(lambda m, p=p: m[-1] == p) and rb.wait(lambda m, p=p: m[-1] == p)
    ra.stop()
    a.close()
    assert wait_for(lambda: pub.stats().clients_connected == 1)
    a2 = connect(pub)
    ra2 = socket_reader(a2)
    assert ra2.wait(lambda m: m == [HELLO])
    for p in poses[20:]:
        pub.publish(p)
        assert ra2.wait(lambda m, p=p: m[-1] == p) and rb.wait(lambda m, p=p: m[-1] == p)
    rb.stop()
    ra2.stop()
    assert rb.msgs == [HELLO] + poses[10:]
    assert ra2.msgs == [HELLO] + poses[20:]
    st = pub.stats()
    assert st.clients_accepted == 3 and st.clients_connected == 2 and st.drops == 0
    b.close()
    a2.close()


def test_stalled_client_does_not_hold_up_others_and_drops_are_counted(tcp_pub):
    pub = tcp_pub(max_pending_frames=2)
    stalled = connect(pub, rcvbuf=4096)            # connected, never reads
    good = connect(pub)
    rg = socket_reader(good)
    assert rg.wait(lambda m: m == [HELLO]) and wait_for(lambda: pub.stats().clients_connected == 2)
    poses = make_poses(3000, seed=3)
    statuses = []

    def run():
        for p in poses:
            statuses.append(pub.publish(p))
            if not rg.wait(lambda m, p=p: m[-1] == p):   # the healthy client gets every pose
                return

    # In a thread so that a publisher blocking on the stalled client fails the
    # test instead of hanging it.
    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    worker.join(timeout=60.0)
    assert not worker.is_alive(), "publish() blocked on a stalled client"
    rg.stop()
    assert rg.msgs == [HELLO] + poses
    st = pub.stats()
    by_name = {s.name: s for s in st.sinks}
    stalled_name = "tcp %s:%d" % stalled.getsockname()[:2]
    good_name = "tcp %s:%d" % good.getsockname()[:2]
    s_st, g_st = by_name[stalled_name], by_name[good_name]
    assert s_st.drops > 0 and g_st.drops == 0
    assert PublishStatus.DROPPED in statuses
    assert statuses.count(PublishStatus.DROPPED) == s_st.drops   # one drop per DROPPED publish
    # Every frame offered (HELLO + poses) is sent, dropped, or waiting: nothing lost silently.
    assert s_st.frames_sent + s_st.drops + s_st.pending_frames == 1 + len(poses)
    assert s_st.pending_frames <= 2 + 1                         # bounded: max_pending + the partial one
    # Latest value wins: what the stalled client eventually reads ends with the newest poses.
    rs = socket_reader(stalled)
    assert rs.wait(lambda m: len(m) > 0 and m[-1] == poses[-1])
    rs.stop()
    got = [m.seq for m in rs.msgs if isinstance(m, PoseMsg)]
    assert got == sorted(got) and len(got) < len(poses)
    assert rs.dec.stats().rejected_total == 0                  # drops are whole frames: stream stays intact
    assert rs.dec.seq_gaps == s_st.drops
    stalled.close()
    good.close()


def test_heartbeat_when_idle_and_status_codes(tcp_pub):
    pub = tcp_pub(heartbeat_period_s=0.02)
    s = connect(pub)
    r = socket_reader(s)
    assert r.wait(lambda m: sum(isinstance(x, HeartbeatMsg) for x in m) >= 3)
    r.stop()
    assert pub.publish("not a message") == PublishStatus.INVALID
    assert pub.stats().errors == 1
    pub.close()
    assert pub.publish(make_poses(1)[0]) == PublishStatus.CLOSED
    pub.close()  # idempotent
    s.close()


def test_send_time_is_stamped_from_the_clock(tcp_pub):
    t = [1000]
    pub = tcp_pub(stamp_send_time=True, clock_ns=lambda: t[0])
    s = connect(pub)
    r = socket_reader(s)
    assert r.wait(lambda m: m == [HELLO])
    p = make_poses(1)[0]
    t[0] = 123456789
    pub.publish(p)
    assert r.wait(lambda m: len(m) == 2)
    r.stop()
    got = r.msgs[1]
    assert got.t_send_ns == 123456789 and got.t_capture_ns == p.t_capture_ns
    assert got.p_world_object.tobytes() == p.p_world_object.tobytes()
    s.close()


def _read_to_eof(sock) -> bytes:
    sock.settimeout(WAIT_S)
    data = b""
    while True:
        chunk = sock.recv(4096)
        if not chunk:
            return data
        data += chunk


def test_max_clients_refuses_extra_connections_and_says_why(tcp_pub):
    """A client over the limit reads one line saying why, then the close; the server logs
    the first refusal (not every one) and counts them all; the served client is unharmed."""
    lines = []
    pub = tcp_pub(max_clients=1, log=lines.append)
    a = connect(pub)
    assert wait_for(lambda: pub.stats().clients_connected == 1)
    refused = []
    for _ in range(3):
        b = connect(pub)
        refused.append(_read_to_eof(b))  # the line, then closed by the server
        b.close()
    assert wait_for(lambda: pub.stats().clients_refused == 3)
    for text in refused:
        assert text.startswith(REFUSAL_PREFIX) and text.endswith(b"\n") and b"\x00" not in text, text
        assert b"at most 1 clients" in text and b"--max-clients" in text
    assert Decoder().feed(refused[0]) == []  # no 0x00: a receiver's decoder takes nothing from it
    assert len(lines) == 1 and "refused a client" in lines[0], lines
    assert pub.stats().clients_connected == 1
    r = socket_reader(a)
    assert r.wait(lambda m: m == [HELLO])
    r.stop()
    a.close()


def test_serial_port_that_fails_is_closed_and_retried_without_raising():
    master, slave = pty.openpty()
    tty.setraw(slave)
    pub = PosePublisher.serial(HELLO, os.ttyname(slave), reopen_period_s=0.01, heartbeat_period_s=0,
                               hello_period_s=0)
    try:
        poses = make_poses(50, seed=9)
        assert pub.publish(poses[0]) == PublishStatus.OK
        os.close(master)                    # the other end disappears: writes now fail (EIO)
        os.close(slave)
        statuses = []
        for p in poses[1:]:
            statuses.append(pub.publish(p))
            if statuses[-1] == PublishStatus.NO_SINK:
                break
        assert wait_for(lambda: pub.stats().errors >= 2)   # the write error, then failed reopens
        assert pub.publish(poses[-1]) == PublishStatus.NO_SINK
        assert pub.stats().sinks == ()
    finally:
        pub.close()
