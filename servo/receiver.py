"""Control side of the link: receive poses from the vision PC without blocking.

Imports only pyserial and ``vespro.wire`` (the servo side's one dependency on
the vision code). The 500 Hz loop calls :meth:`PoseReceiver.poll` once per
tick (cheap when nothing arrived) and :meth:`PoseReceiver.latest` whenever it
needs the pose::

    rx = PoseReceiver("socket://192.168.10.2:5555")   # or "/dev/ttyUSB0", a pty path, "loop://"
    while running:
        rx.poll(now_ns)
        pose, age_ns = rx.latest(now_ns)
        ...

Neither call raises or blocks: a missing peer is a state
(``LinkState.DISCONNECTED``), and the receiver reconnects by itself with
exponential backoff after the peer goes away (a killed and restarted server,
an unplugged adapter).

``socket://host:port`` URLs (pyserial's syntax) are handled here with a
non-blocking connect, because pyserial's socket handler connects with a
blocking call (up to 5 s on an unreachable host), which would stall the loop.
Every other URL or device path is opened with ``serial.serial_for_url`` and
read with ``timeout=0``.

Age of a pose
-------------
The vision and control PCs have different monotonic clocks, so the capture
stamp cannot be compared with ``now_ns`` directly. ``latest`` estimates the
age since capture as ``(now_ns - t_receive_ns) + (t_send_ns - t_capture_ns)``:
time since arrival on this clock plus the vision-side latency on that one. The
transport delay (about 17 ms for a POSE frame at 115200 baud, well under 1 ms
on TCP loopback or a LAN) is not included.

Which poses are used
--------------------
A decoded POSE becomes the latest pose only if it passes these checks, else
it is counted in ``ReceiverStats.pose_rejected`` under its reason
(``POSE_REJECT_REASONS``) and dropped:

- ``no_hello``: no HELLO yet on this connection (the objects are unknown);
- ``unknown_object``: ``object_id`` beyond the objects the HELLO announced;
- ``future_stamp``: ``t_capture_ns`` after ``t_send_ns`` (both on the
  sender's clock) by more than ``future_tolerance_s``;
- ``duplicate``: the same ``seq`` as the last pose used;
- ``out_of_order``: a ``seq`` behind the last pose used (modulo 2**32).

A POSE carries the sender's probability that its pose is the object's
(``PoseMsg.probability``, NaN when the sender states none); the status alone
decides whether a pose is used.

A server that restarts sends a HELLO first and starts its ``seq`` over: after
a HELLO the next pose may have any ``seq`` but the last one (counted in
``ReceiverStats.seq_restarts`` when it goes back). A new connection starts a
new stream too.

A TCP server that serves no more clients sends one line of text instead of
the stream (``vespro.wire.REFUSAL_PREFIX`` and its reason) and closes the
connection: the receiver counts it (``ReceiverStats.refusals``), keeps the
reason (``ReceiverStats.refusal``, until a server sends its HELLO) and tries
again with its backoff.
"""

from __future__ import annotations

import enum
import errno
import select
import socket
import time
from dataclasses import dataclass
from typing import Callable
from urllib.parse import urlsplit

from vespro.wire import REFUSAL_PREFIX, Decoder, HelloMsg, PoseMsg

__all__ = ["PoseReceiver", "LinkState", "ReceiverStats", "NO_POSE_AGE_NS", "POSE_REJECT_REASONS"]

# Age reported when there is no pose at all: larger than any staleness limit.
NO_POSE_AGE_NS = 2**63 - 1

#: Why a well-formed POSE was not used (see the module docstring).
POSE_REJECT_REASONS = ("no_hello", "unknown_object", "future_stamp", "duplicate", "out_of_order")

_U32 = 2**32


class LinkState(enum.IntEnum):
    DISCONNECTED = 0   # waiting for the next (re)connect attempt
    CONNECTING = 1     # TCP connect in progress
    CONNECTED = 2


@dataclass(frozen=True)
class ReceiverStats:
    """Counters of a :class:`PoseReceiver` (cumulative over reconnects)."""

    state: LinkState
    connects: int        # successful opens / connects
    disconnects: int     # links lost (EOF, error, idle timeout)
    open_failures: int   # failed open / connect attempts
    bytes_in: int
    frames_ok: int
    poses: int
    rejected: dict       # by reason, see vespro.wire.REJECT_REASONS
    seq_gaps: int
    seq_duplicates: int
    seq_resets: int
    pose_rejected: dict  # well-formed poses not used, by reason (POSE_REJECT_REASONS)
    hellos: int          # HELLO messages received
    seq_restarts: int    # sequences started over after a HELLO (a restarted server)
    refusals: int = 0    # connections the server refused (it serves no more clients)
    refusal: str | None = None  # the server's last refusal line, without its prefix

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    @property
    def pose_rejected_total(self) -> int:
        return sum(self.pose_rejected.values())


_HEAD_BYTES = 512  # a refusal line is shorter


class _TcpTransport:
    """Non-blocking TCP client for ``socket://host:port``."""

    def __init__(self, host: str, port: int):
        # Resolving a name may block, so it happens once, at set-up.
        self._addrs = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        self.sock: socket.socket | None = None

    def start(self) -> bool:
        """Begin connecting; True when already connected."""
        family, stype, proto, _, addr = self._addrs[0]
        s = socket.socket(family, stype, proto)
        s.setblocking(False)
        err = s.connect_ex(addr)
        self.sock = s
        if err == 0:
            return True
        if err in (errno.EINPROGRESS, errno.EWOULDBLOCK, errno.EALREADY, errno.EINTR):
            return False
        raise OSError(err, errno.errorcode.get(err, "connect failed"))

    def finish(self) -> bool:
        """True once connected; raises OSError when the connect failed."""
        _, w, _ = select.select([], [self.sock], [], 0)
        if not w:
            return False
        err = self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        if err:
            raise OSError(err, errno.errorcode.get(err, "connect failed"))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return True

    def read(self, n: int) -> bytes:
        """Up to ``n`` bytes, b"" when none; raises ConnectionError on EOF."""
        try:
            data = self.sock.recv(n)
        except (BlockingIOError, InterruptedError):
            return b""
        if not data:
            raise ConnectionError("peer closed the connection")
        return data

    def fileno(self) -> int | None:
        return None if self.sock is None else self.sock.fileno()

    def close(self) -> None:
        if self.sock is not None:
            try:
                self.sock.close()
            except OSError:
                pass
            self.sock = None


class _SerialTransport:
    """Any pyserial URL or device path, read with ``timeout=0``."""

    def __init__(self, url: str, baudrate: int):
        self._url = url
        self._baudrate = baudrate
        self.port = None

    def start(self) -> bool:
        import serial

        self.port = serial.serial_for_url(self._url, baudrate=self._baudrate, timeout=0)
        return True

    def finish(self) -> bool:
        return True

    def read(self, n: int) -> bytes:
        return self.port.read(n)

    def fileno(self) -> int | None:
        return None if self.port is None else self.port.fileno()

    def close(self) -> None:
        if self.port is not None:
            try:
                self.port.close()
            except Exception:
                pass
            self.port = None


class PoseReceiver:
    """Non-blocking pose receiver with automatic reconnect.

    Parameters
    ----------
    url : str
        ``socket://HOST:PORT``, a device path (``/dev/ttyUSB0``, a pty slave),
        any other pyserial URL (``loop://``, ``rfc2217://...``), or
        ``zenoh/KEY`` (:mod:`servo.zenoh_source`).
    baudrate : int
        Serial lines only.
    backoff_min_s, backoff_max_s : float
        Delay before a reconnect attempt starts at ``backoff_min_s`` and
        doubles after each failure up to ``backoff_max_s``; a valid frame
        resets it.
    idle_timeout_s : float
        TCP only: drop and reconnect when no byte arrived for this long (the
        publisher sends at least a HEARTBEAT per second, so silence means a
        dead peer or a half-open connection). 0 disables.
    connect_timeout_s : float
        TCP only: give up a connect attempt after this long.
    max_read_bytes : int
        Upper bound on bytes consumed per ``poll`` (bounds its run time).
    clock_ns : callable
        Monotonic clock, ns, used when ``poll``/``latest`` get no ``now_ns``.
    future_tolerance_s : float
        A pose captured after it was sent (sender's clock) by more than this
        is rejected (``future_stamp``).

    Raises
    ------
    ValueError
        Malformed ``socket://`` URL (at construction only).
    """

    def __init__(self, url: str, *, baudrate: int = 115200, backoff_min_s: float = 0.05,
                 backoff_max_s: float = 1.0, idle_timeout_s: float = 3.0, connect_timeout_s: float = 2.0,
                 max_read_bytes: int = 65536, clock_ns: Callable[[], int] = time.monotonic_ns,
                 future_tolerance_s: float = 0.005):
        self.url = url
        if url.startswith("socket://"):
            parts = urlsplit(url)
            if parts.hostname is None or parts.port is None:
                raise ValueError(f"expected socket://HOST:PORT, got {url!r}")
            self._transport = _TcpTransport(parts.hostname, parts.port)
            self._idle_ns = int(idle_timeout_s * 1e9)
        elif url.startswith("zenoh/"):
            from .zenoh_source import ZenohTransport  # Zenoh: servo.zenoh_source (URL options there)

            self._transport = ZenohTransport(url)
            self._idle_ns = 0
            connect_timeout_s = max(connect_timeout_s, 10.0)  # opening a Zenoh peer takes ~0.5 s, more under load
        else:
            self._transport = _SerialTransport(url, baudrate)
            self._idle_ns = 0
        self._connect_timeout_ns = int(connect_timeout_s * 1e9)
        self._backoff_min_ns = int(backoff_min_s * 1e9)
        self._backoff_max_ns = int(backoff_max_s * 1e9)
        self._backoff_ns = self._backoff_min_ns
        self._max_read = int(max_read_bytes)
        self._clock_ns = clock_ns
        self._decoder = Decoder()
        self.state = LinkState.DISCONNECTED
        self._next_attempt_ns = 0
        self._connect_started_ns = 0
        self._last_rx_ns = 0
        self.hello: HelloMsg | None = None
        self._latest: PoseMsg | None = None
        self._latest_rx_ns = 0
        self._by_object: dict[int, tuple[PoseMsg, int]] = {}
        self._connects = 0
        self._disconnects = 0
        self._open_failures = 0
        self._poses = 0
        self._future_ns = int(round(future_tolerance_s * 1e9))
        self._pose_rejected = {r: 0 for r in POSE_REJECT_REASONS}
        self._hellos = 0
        self._seq_restarts = 0
        self._last_seq: int | None = None
        self._seq_open = True  # the next pose may start a new sequence
        self._head = bytearray()  # a connection's first bytes while they may be a refusal line
        self._head_open = False
        self._refusals = 0
        self.refusal: str | None = None

    # --- the loop's API -----------------------------------------------------------

    def poll(self, now_ns: int | None = None, out: list | None = None) -> PoseMsg | None:
        """Read what has arrived; return the newest POSE among it, or None.

        Never blocks, never raises: a lost link is closed and reopened later.

        Parameters
        ----------
        now_ns : int, optional
            Current time, ns (this PC's monotonic clock); ``clock_ns()`` if None.
        out : list, optional
            If given, every message decoded in this call (HELLO, POSE,
            HEARTBEAT) is appended to it, in arrival order, rejected poses
            included.
        """
        now = self._clock_ns() if now_ns is None else int(now_ns)
        newest = None
        try:
            if self.state == LinkState.DISCONNECTED and now >= self._next_attempt_ns:
                self._connect_started_ns = now
                self.state = LinkState.CONNECTED if self._transport.start() else LinkState.CONNECTING
                if self.state == LinkState.CONNECTED:
                    self._on_connected(now)
            if self.state == LinkState.CONNECTING:
                if self._transport.finish():
                    self.state = LinkState.CONNECTED
                    self._on_connected(now)
                elif now - self._connect_started_ns > self._connect_timeout_ns:
                    raise TimeoutError("connect timed out")
            if self.state == LinkState.CONNECTED:
                newest = self._read(now, out)
        except Exception:
            self._lost(now, connected=self.state == LinkState.CONNECTED)
        return newest

    def latest(self, now_ns: int | None = None, object_id: int | None = None) -> tuple[PoseMsg | None, int]:
        """Newest pose received (of ``object_id``, or of any object) and its age.

        Returns
        -------
        pose : PoseMsg or None
        age_ns : int
            Estimated time since capture, ns (see module docstring);
            ``NO_POSE_AGE_NS`` when there is no pose.
        """
        now = self._clock_ns() if now_ns is None else int(now_ns)
        if object_id is None:
            pose, t_rx = self._latest, self._latest_rx_ns
        else:
            pose, t_rx = self._by_object.get(object_id, (None, 0))
        if pose is None:
            return None, NO_POSE_AGE_NS
        return pose, (now - t_rx) + (pose.t_send_ns - pose.t_capture_ns)

    def fileno(self) -> int | None:
        """Descriptor of the open link (for ``select``), or None when there is none."""
        try:
            return self._transport.fileno()
        except Exception:
            return None

    def stats(self) -> ReceiverStats:
        d = self._decoder.stats()
        return ReceiverStats(self.state, self._connects, self._disconnects, self._open_failures,
                             d.bytes_in, d.frames_ok, self._poses, d.rejected, d.seq_gaps,
                             d.seq_duplicates, d.seq_resets, dict(self._pose_rejected), self._hellos,
                             self._seq_restarts, self._refusals, self.refusal)

    def close(self) -> None:
        self._transport.close()
        self.state = LinkState.DISCONNECTED
        self._next_attempt_ns = NO_POSE_AGE_NS  # never reopen

    def __enter__(self) -> "PoseReceiver":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- internals ----------------------------------------------------------------

    def _on_connected(self, now: int) -> None:
        self._connects += 1
        self._last_rx_ns = now
        self._decoder.reset_stream()
        self.hello = None  # the peer announces its objects again
        self._last_seq = None
        self._seq_open = True
        self._head.clear()
        self._head_open = True

    def _lost(self, now: int, connected: bool) -> None:
        self._transport.close()
        if connected:
            self._disconnects += 1
            if self._head.startswith(REFUSAL_PREFIX):
                self._refusals += 1
                line = bytes(self._head[len(REFUSAL_PREFIX):]).split(b"\n", 1)[0]
                self.refusal = line.decode("utf-8", "replace").strip()[:200]
        else:
            self._open_failures += 1
        self.state = LinkState.DISCONNECTED
        self._next_attempt_ns = now + self._backoff_ns
        self._backoff_ns = min(2 * self._backoff_ns, self._backoff_max_ns)

    def _read(self, now: int, out: list | None) -> PoseMsg | None:
        newest = None
        total = 0
        while total < self._max_read:
            data = self._transport.read(min(65536, self._max_read - total))
            if not data:
                break
            total += len(data)
            if self._head_open:
                data = self._hold_refusal(data)
                if not data:
                    continue
            msgs = self._decoder.feed(data)
            if out is not None:
                out.extend(msgs)
            for msg in msgs:
                if isinstance(msg, PoseMsg):
                    why = self._reject_reason(msg)
                    if why is not None:
                        self._pose_rejected[why] += 1
                        continue
                    newest = msg
                    self._poses += 1
                    self._by_object[msg.object_id] = (msg, now)
                    self._latest, self._latest_rx_ns = msg, now
                elif isinstance(msg, HelloMsg):
                    self.hello = msg
                    self._hellos += 1
                    self.refusal = None  # served now
                    self._seq_open = True
                self._backoff_ns = self._backoff_min_ns
        if total:
            self._last_rx_ns = now
        elif self._idle_ns and now - self._last_rx_ns > self._idle_ns:
            raise TimeoutError("link idle")
        return newest

    def _hold_refusal(self, data: bytes) -> bytes:
        """A connection's first bytes are held back while they may be a refusal line (not
        garbage for the decoder); what to decode now (b"" while held)."""
        self._head += data
        n = min(len(self._head), len(REFUSAL_PREFIX))
        if self._head[:n] == REFUSAL_PREFIX[:n] and len(self._head) <= _HEAD_BYTES:
            return b""
        self._head_open = False
        data = bytes(self._head)
        self._head.clear()
        return data

    def _reject_reason(self, msg: PoseMsg) -> str | None:
        """Why a decoded pose is not used (``POSE_REJECT_REASONS``), None if it is; updates the sequence."""
        if self.hello is None:
            return "no_hello"
        if msg.object_id >= len(self.hello.object_names):
            return "unknown_object"
        if msg.t_capture_ns - msg.t_send_ns > self._future_ns:
            return "future_stamp"
        last = self._last_seq
        if last is not None:
            d = (msg.seq - last) % _U32
            if d == 0:
                return "duplicate"
            if d >= _U32 // 2:
                if not self._seq_open:
                    return "out_of_order"
                self._seq_restarts += 1
        self._last_seq = msg.seq
        self._seq_open = False
        return None
