"""Benchmark the pose link: frame size, latency and throughput over TCP loopback and a pty.

Run from the repository root::

    python3 bench/link.py [--frames 2000] [--burst 20000]

Rows:

- ``stack``: ``PosePublisher.publish`` -> ``PoseReceiver.poll`` (encode,
  non-blocking send, I/O, decode). The send stamp is ``t_send_ns`` taken by
  the publisher before encoding; the receive stamp is taken when ``poll``
  returns.
- ``zenoh peers``: the same through :class:`vespro.zenoh_link.ZenohPublisher`
  and ``PoseReceiver("zenoh/KEY?connect=...")`` (two peers on loopback, the
  receiver waiting in ``select`` on its wake-up descriptor); its ``raw`` row is
  Zenoh's own ``put`` of the pre-encoded frame to a bare subscriber callback.
  Latency only (see the note printed with the table).
- ``raw``: the baseline, in the same process: the same pre-encoded bytes
  written with a plain ``sendall`` / ``os.write`` and read with ``recv`` /
  ``os.read``, frames counted by their 0x00 delimiters, no decoding.

Receivers run in a child process (a different PC in reality). Latency is
measured with frames paced every ``--period-us`` and a receiver that waits in
``select`` on ``PoseReceiver.fileno()`` and then calls ``poll`` (the real servo loop polls every 2 ms, which adds up to
2 ms). Throughput is a burst of ``--burst`` frames sent as fast as possible
(no drops: the publisher queue is made large enough), divided by the time from
the first send to the last receive.

The pty runs at its default speed: a pseudo-terminal ignores the baud rate,
so it measures the tty layer, not a 115200-baud line. The line budget is
printed separately from the frame size.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import pty
import select
import socket
import sys
import time
import tty
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from servo.receiver import PoseReceiver  # noqa: E402
from vespro import wire  # noqa: E402
from vespro.link import PosePublisher  # noqa: E402
from vespro.wire import HelloMsg, PoseMsg, PoseStatus  # noqa: E402

HELLO = HelloMsg(26.0, ("box",))


def make_pose(seq: int) -> PoseMsg:
    return PoseMsg(seq, time.monotonic_ns(), 0, 0, PoseStatus.TRACKING, [0.4, 0.1, 0.3],
                   [0.9, 0.1, 0.2, 0.3], [0.1, 0, 0], [0, 0, 0.2], np.eye(6) * 1e-6)


def wait_until(t_ns: int) -> None:
    """Sleep (releasing the GIL for the publisher's I/O thread), spin the last 100 us."""
    dt = t_ns - time.monotonic_ns() - 100_000
    if dt > 0:
        time.sleep(dt / 1e9)
    while time.monotonic_ns() < t_ns:
        pass


class _FdPort:
    """The pty master as a serial-like object for PosePublisher.serial."""

    def __init__(self, fd: int):
        self.fd = fd

    def fileno(self) -> int:
        return self.fd

    def write(self, data: bytes) -> int:
        return os.write(self.fd, data)


# The receivers run in a child process, as on the real control PC: in one
# process the sender's and receiver's threads would share the GIL and its 5 ms
# switch interval would dominate the latency. CLOCK_MONOTONIC is system-wide,
# so stamps compare across the two processes.


def _stack_child(url: str, n: int, conn) -> None:
    rx = PoseReceiver(url, idle_timeout_s=0)
    t_end = time.monotonic() + 10
    while rx.hello is None and time.monotonic() < t_end:
        rx.poll()
        time.sleep(0.001)
    conn.send("ready")
    lat = np.zeros(n, dtype=np.int64)
    k = 0
    buf: list = []
    t_end = time.monotonic() + 60
    while k < n and time.monotonic() < t_end:
        # Block until readable, as the raw reader does in recv/read: a process
        # spinning on poll() is deprioritised by the scheduler on a busy machine.
        fd = rx.fileno()
        if fd is not None:
            select.select([fd], [], [], 0.01)
        rx.poll(out=buf)
        if buf:
            now = time.monotonic_ns()
            for m in buf:
                if isinstance(m, PoseMsg) and k < n:
                    lat[k] = now - m.t_send_ns
                    k += 1
            buf.clear()
    conn.send((lat[:k], time.monotonic_ns(), rx.stats().rejected_total))


def _raw_child(read, n: int, conn) -> None:
    conn.send("ready")
    t_recv = np.zeros(n, dtype=np.int64)
    k = 0
    while k < n:
        data = read()
        now = time.monotonic_ns()
        for _ in range(data.count(0)):
            if k < n:
                t_recv[k] = now
                k += 1
    conn.send(t_recv)


def _spawn(target, *args, start="fork"):
    # "spawn" once this process has a Zenoh peer open: a forked child inherits its runtime without its threads.
    parent, child = mp.Pipe()
    p = mp.get_context(start).Process(target=target, args=(*args, child), daemon=True)
    p.start()
    if parent.poll(15):
        assert parent.recv() == "ready"
    return p, parent


def _stack_run(pub, rx_url, n: int, period_ns: int, start="fork"):
    """Returns (latencies_ns, frames/s)."""
    poses = [make_pose(i) for i in range(n)]   # built beforehand, like the raw row's bytes
    proc, conn = _spawn(_stack_child, rx_url, n, start=start)
    t0 = time.monotonic_ns()
    for i in range(n):
        if period_ns:
            wait_until(t0 + i * period_ns)
        pub.publish(poses[i])
    lat, t_done, rejected = conn.recv()
    proc.join(5)
    drops = pub.stats().drops
    pub.close()
    if len(lat) < n or rejected:
        raise RuntimeError(f"received {len(lat)} of {n} frames (drops {drops}, rejected {rejected})")
    return lat, n / ((t_done - t0) / 1e9)


def _raw_run(write, read, n: int, period_ns: int):
    frame = wire.encode(make_pose(0))
    t_send = np.zeros(n, dtype=np.int64)
    proc, conn = _spawn(_raw_child, read, n)
    t0 = time.monotonic_ns()
    for i in range(n):
        if period_ns:
            wait_until(t0 + i * period_ns)
        t_send[i] = time.monotonic_ns()
        write(frame)
    t_recv = conn.recv()
    proc.join(5)
    return t_recv - t_send, n / ((t_recv[-1] - t0) / 1e9)


def tcp_stack(n, period_ns):
    pub = PosePublisher.tcp(HELLO, 0, max_pending_frames=n, heartbeat_period_s=0)
    return _stack_run(pub, f"socket://127.0.0.1:{pub.address[1]}", n, period_ns)


def tcp_raw(n, period_ns):
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    cli = socket.create_connection(srv.getsockname())
    conn, _ = srv.accept()
    for s in (cli, conn):
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    try:
        return _raw_run(conn.sendall, lambda: cli.recv(65536), n, period_ns)
    finally:
        for s in (cli, conn, srv):
            s.close()


def _pty():
    master, slave = pty.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    return master, slave


def pty_stack(n, period_ns):
    master, slave = _pty()
    try:
        pub = PosePublisher.serial(HELLO, _FdPort(master), max_pending_frames=n, heartbeat_period_s=0,
                                   hello_period_s=0.2)
        return _stack_run(pub, os.ttyname(slave), n, period_ns)
    finally:
        os.close(master)
        os.close(slave)


def pty_raw(n, period_ns):
    master, slave = _pty()

    def write(b):
        mv = memoryview(b)
        while mv:
            mv = mv[os.write(master, mv):]

    try:
        return _raw_run(write, lambda: os.read(slave, 65536), n, period_ns)
    finally:
        os.close(master)
        os.close(slave)


ZENOH_KEY = "bench/vespro/pose"


def _zenoh_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def zenoh_stack(n, period_ns):
    """ZenohPublisher -> PoseReceiver("zenoh/..."): two peers on loopback."""
    from vespro.zenoh_link import ZenohPublisher

    ep = _zenoh_endpoint()
    pub = ZenohPublisher(ZENOH_KEY, HELLO, listen=[ep], hello_period_s=0.1, heartbeat_period_s=0)
    return _stack_run(pub, f"zenoh/{ZENOH_KEY}?connect={ep}", n, period_ns, start="spawn")


def _zenoh_raw_child(ep: str, n: int, conn) -> None:
    import threading

    import zenoh

    t_recv = np.zeros(n, dtype=np.int64)
    k = [0]
    done = threading.Event()

    def on_sample(sample):
        now = time.monotonic_ns()
        if k[0] < n:
            t_recv[k[0]] = now
            k[0] += 1
            if k[0] == n:
                done.set()

    peer = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config_json5("peer", [], [ep])))
    peer.declare_subscriber(ZENOH_KEY, on_sample)
    conn.send("ready")
    done.wait(60)
    conn.send(t_recv[: k[0]])
    peer.close()


def zenoh_raw(n, period_ns):
    """The baseline: zenoh's own put of the pre-encoded bytes to a bare subscriber callback."""
    import zenoh

    ep = _zenoh_endpoint()
    peer = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config_json5("peer", [ep], [])))
    try:
        pub = peer.declare_publisher(ZENOH_KEY, congestion_control=zenoh.CongestionControl.DROP, express=True)
        proc, conn = _spawn(_zenoh_raw_child, ep, n, start="spawn")
        t_end = time.monotonic() + 15
        while not pub.matching_status.matching and time.monotonic() < t_end:
            time.sleep(0.01)
        frame = wire.encode(make_pose(0))
        t_send = np.zeros(n, dtype=np.int64)
        t0 = time.monotonic_ns()
        for i in range(n):
            if period_ns:
                wait_until(t0 + i * period_ns)
            t_send[i] = time.monotonic_ns()
            pub.put(frame)
        t_recv = conn.recv()
        proc.join(5)
    finally:
        peer.close()
    if len(t_recv) < n:
        raise RuntimeError(f"zenoh raw: received {len(t_recv)} of {n} frames")
    return t_recv - t_send, n / ((t_recv[-1] - t0) / 1e9)


def codec_us(n: int = 5000) -> tuple[float, float]:
    m = make_pose(1)
    f = wire.encode(m)
    t = time.perf_counter()
    for _ in range(n):
        wire.encode(m)
    enc = (time.perf_counter() - t) / n * 1e6
    d = wire.Decoder()
    t = time.perf_counter()
    for _ in range(n):
        d.feed(f)
    dec = (time.perf_counter() - t) / n * 1e6
    return enc, dec


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=1000, help="paced frames per latency run")
    ap.add_argument("--period-us", type=int, default=2000, help="pacing of the latency runs (500 Hz; the tracker sends 26 Hz)")
    ap.add_argument("--burst", type=int, default=20000, help="frames per throughput run")
    ap.add_argument("--no-zenoh", action="store_true", help="skip the Zenoh rows")
    args = ap.parse_args(argv)
    period = args.period_us * 1000

    size = wire.POSE_FRAME_BYTES
    line = wire.LINE_BYTES_PER_S_115200
    enc, dec = codec_us()
    print(f"POSE frame: {size} bytes on the wire (196-byte packet + 1 COBS byte + 0x00); "
          f"HEARTBEAT {wire.HEARTBEAT_FRAME_BYTES} bytes")
    print(f"encode {enc:.1f} us, decode {dec:.1f} us per POSE frame (this CPU)")
    print(f"115200 baud 8N1 = {line} B/s: max {line / size:.1f} POSE frames/s; 26 Hz uses "
          f"{26 * size} B/s = {100 * 26 * size / line:.0f} % of the line; {1e3 * size / line:.1f} ms per frame")
    print()
    rows = []
    for link, stack, raw in (("tcp loopback", tcp_stack, tcp_raw), ("pty pair", pty_stack, pty_raw)):
        lat_s, _ = stack(args.frames, period)
        lat_r, _ = raw(args.frames, period)
        _, thr_s = stack(args.burst, 0)
        _, thr_r = raw(args.burst, 0)
        rows.append((link, "stack", lat_s, thr_s))
        rows.append((link, "raw", lat_r, thr_r))
        rows.append((link, "ratio", (lat_s, lat_r), thr_s / thr_r))
    if not args.no_zenoh:
        try:
            import zenoh  # noqa: F401
        except ImportError:
            print("zenoh rows skipped: eclipse-zenoh is not installed (pip install 'vespro[interop]')")
        else:
            # Latency only: the publisher drops samples a subscriber cannot take (latest value wins),
            # so a burst measures its drops, not a throughput.
            lat_s, _ = zenoh_stack(args.frames, period)
            lat_r, _ = zenoh_raw(args.frames, period)
            rows += [("zenoh peers", "stack", lat_s, None), ("zenoh peers", "raw", lat_r, None),
                     ("zenoh peers", "ratio", (lat_s, lat_r), None)]

    hdr = f"{'link':<13} {'path':<6} {'frame B':>7} {'lat med us':>10} {'lat p99 us':>10} {'frames/s':>10}"
    print(hdr)
    print("-" * len(hdr))
    for link, path, lat, thr in rows:
        if path == "ratio":
            s, r = lat
            med = np.median(s) / np.median(r)
            p99 = np.percentile(s, 99) / np.percentile(r, 99)
            thr = f"{thr:>9.2f}x" if thr is not None else f"{'-':>10}"
            print(f"{link:<13} {'ratio':<6} {'':>7} {med:>9.1f}x {p99:>9.1f}x {thr}")
        else:
            thr = f"{thr:>10.0f}" if thr is not None else f"{'-':>10}"
            print(f"{link:<13} {path:<6} {size:>7} {np.median(lat) / 1e3:>10.1f} "
                  f"{np.percentile(lat, 99) / 1e3:>10.1f} {thr}")
    print()
    print(f"latency: {args.frames} frames paced every {args.period_us} us, receiver waiting in select; "
          f"throughput: burst of {args.burst} frames")
    if any(r[0] == "zenoh peers" for r in rows):
        print("zenoh: no throughput row: its publisher drops what a subscriber cannot take (latest value wins)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
