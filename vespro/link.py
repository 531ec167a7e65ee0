"""Vision side of the link: publish wire frames to a serial line or TCP clients.

A server loop does::

    pub = PosePublisher.tcp(HelloMsg(26.0, ("box",)), port=5555)   # or PosePublisher.serial(...)
    while running:
        ...
        pub.publish(PoseMsg(...))        # every frame; returns a PublishStatus, never blocks
        if once_a_second:
            log(pub.stats())
    pub.close()

Design
------
- ``publish`` encodes once and hands the frame to every sink (the serial
  port, or each connected TCP client) with a non-blocking write. What the OS
  does not take waits in a per-sink queue of at most ``max_pending_frames``
  whole frames; when a new frame would exceed it the *oldest* waiting frame is
  dropped and counted (latest value wins). A frame already partly written is
  always finished so the byte stream stays intact. A stalled client therefore
  costs the publisher one failed ``send`` per frame, nothing more.
- One background thread owns the sockets: it accepts clients (each gets a
  ``0x00`` and a HELLO first), flushes queued bytes when a socket becomes
  writable, notices disconnects, sends a HEARTBEAT when nothing was published
  for ``heartbeat_period_s``, repeats HELLO on a serial line every
  ``hello_period_s`` (a serial receiver can join at any time and has no
  connect event) and reopens a serial port that failed.
- A TCP client beyond ``max_clients`` is not served: it receives one line of
  text starting ``vespro refused: `` (:data:`vespro.wire.REFUSAL_PREFIX`) and
  the connection is closed; the refusal is counted (``clients_refused``).
- The kernel send buffer of each client is set small (``sndbuf_bytes``) so
  stale poses do not pile up in the kernel either.
- A serial port opened by URL that has a file descriptor (a tty, a pty) is
  written with ``os.write`` on its non-blocking descriptor: pyserial's own
  ``write`` busy-waits on a full buffer. A port without one (``loop://``,
  ``rfc2217://``) is written with its blocking ``write()``.
"""

from __future__ import annotations

import enum
import os
import selectors
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

from vespro.throttle import LogThrottle
from vespro.wire import REFUSAL_PREFIX, HeartbeatMsg, HelloMsg, encode

__all__ = ["PosePublisher", "PublisherGroup", "PublishStatus", "LinkStats", "SinkStats"]

_U32 = 2**32


class PublishStatus(enum.IntEnum):
    """Outcome of :meth:`PosePublisher.publish`."""

    OK = 0          # handed to every sink (written, or queued without dropping)
    DROPPED = 1     # at least one sink dropped a waiting frame to make room
    NO_SINK = 2     # nobody to send to (no TCP client, serial port down)
    INVALID = 3     # not a wire message; nothing sent
    CLOSED = 4      # publisher closed


@dataclass(frozen=True)
class SinkStats:
    """Counters of one destination (the serial port or one TCP client)."""

    name: str
    frames_sent: int     # frames completely handed to the OS
    bytes_sent: int
    drops: int           # frames dropped because the sink could not keep up
    pending_frames: int  # frames waiting now


@dataclass(frozen=True)
class LinkStats:
    """Snapshot of a publisher's counters; totals include closed clients."""

    frames_published: int
    frames_sent: int
    bytes_sent: int
    drops: int
    clients_connected: int
    clients_accepted: int
    clients_refused: int
    errors: int
    sinks: tuple[SinkStats, ...]


class _Sink:
    """One destination: a write function plus a bounded queue of frames."""

    def __init__(self, name: str, write: Callable[[memoryview], int], max_pending: int):
        self.name = name
        self._write = write
        self.max_pending = max_pending
        self.pending: deque[bytes] = deque()
        self.head = 0          # bytes of pending[0] already written
        self.frames_sent = 0
        self.bytes_sent = 0
        self.drops = 0
        self.dead = False

    def offer(self, frame: bytes) -> bool:
        """Queue ``frame`` and write what the OS takes; False if something was dropped."""
        dropped = False
        self.pending.append(frame)
        started = 1 if self.head > 0 else 0
        while len(self.pending) - started > self.max_pending:
            del self.pending[started]
            self.drops += 1
            dropped = True
        self.flush()
        return not dropped

    def flush(self) -> None:
        """Write queued bytes until the OS refuses; marks the sink dead on error."""
        if self.dead:
            return
        try:
            while self.pending:
                buf = self.pending[0]
                n = self._write(memoryview(buf)[self.head :])
                if not n:
                    return
                self.head += n
                self.bytes_sent += n
                if self.head >= len(buf):
                    self.pending.popleft()
                    self.head = 0
                    self.frames_sent += 1
        except Exception:
            self.dead = True

    def stats(self) -> SinkStats:
        return SinkStats(self.name, self.frames_sent, self.bytes_sent, self.drops, len(self.pending))


def _socket_writer(sock: socket.socket) -> Callable[[memoryview], int]:
    def write(mv: memoryview) -> int:
        try:
            return sock.send(mv)
        except (BlockingIOError, InterruptedError):
            return 0

    return write


def _serial_writer(port) -> tuple[Callable[[memoryview], int], int | None]:
    """A non-blocking write function for ``port`` and its file descriptor (or None)."""
    fd = None
    try:
        fd = port.fileno()
    except Exception:
        fd = None
    if fd is not None:
        os.set_blocking(fd, False)

        def write_fd(mv: memoryview) -> int:
            try:
                return os.write(fd, mv)
            except (BlockingIOError, InterruptedError):
                return 0

        return write_fd, fd

    def write_port(mv: memoryview) -> int:
        n = port.write(bytes(mv))
        return len(mv) if n is None else int(n)

    return write_port, None


class PosePublisher:
    """Sends wire frames to a serial port or to any number of TCP clients.

    Build it with :meth:`tcp` or :meth:`serial`. ``publish``, ``heartbeat``,
    ``stats`` and ``close`` are thread-safe; ``publish`` never blocks on a
    slow peer and never raises.

    Parameters
    ----------
    hello : HelloMsg
        Sent to each new client (and periodically on a serial line).
    max_pending_frames : int
        Frames that may wait per sink beyond the one being written (>= 1).
    heartbeat_period_s : float
        Send a HEARTBEAT when nothing was published for this long; 0 disables.
    hello_period_s : float
        Serial only: repeat HELLO this often; 0 disables.
    stamp_send_time : bool
        Replace ``t_send_ns`` of each message with ``clock_ns()`` at publish.
    clock_ns : callable
        Monotonic clock in ns (``time.monotonic_ns``; pass ``SimClock.now_ns``
        in simulation).
    """

    def __init__(self, hello: HelloMsg, *, max_pending_frames: int = 2, heartbeat_period_s: float = 1.0,
                 hello_period_s: float = 1.0, stamp_send_time: bool = True,
                 clock_ns: Callable[[], int] = time.monotonic_ns):
        if not isinstance(hello, HelloMsg):
            raise ValueError(f"hello: expected a HelloMsg, got {type(hello).__name__}")
        if max_pending_frames < 1:
            raise ValueError(f"max_pending_frames must be >= 1, got {max_pending_frames}")
        self.hello = hello
        self._hello_frame = encode(hello)
        self._max_pending = int(max_pending_frames)
        self._heartbeat_ns = int(heartbeat_period_s * 1e9)
        self._hello_ns = int(hello_period_s * 1e9)
        self._stamp = stamp_send_time
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._closed = False
        self._thread: threading.Thread | None = None
        # TCP
        self._listener: socket.socket | None = None
        self._clients: dict[socket.socket, _Sink] = {}
        self._masks: dict[socket.socket, int] = {}
        self._max_clients = 0
        self._sndbuf = 0
        # serial
        self._serial_url: str | None = None
        self._serial_kwargs: dict = {}
        self._port = None
        self._serial_sink: _Sink | None = None
        self._reopen_at_ns = 0
        self._reopen_ns = 1_000_000_000
        self._serial_fd: int | None = None
        self._serial_fd_watched = False
        self._last_hello_ns = 0
        # counters
        self._frames_published = 0
        self._heartbeat_seq = 0
        self._last_publish_ns = clock_ns()
        self._closed_totals = [0, 0, 0]  # frames_sent, bytes_sent, drops of gone sinks
        self._accepted = 0
        self._refused = 0
        self._refusal_log = LogThrottle(None, clock_ns)
        self._errors = 0

    # --- construction -------------------------------------------------------------

    @classmethod
    def tcp(cls, hello: HelloMsg, port: int = 0, host: str = "127.0.0.1", *, max_clients: int = 8,
            sndbuf_bytes: int = 8192, log: Callable[[str], None] | None = None, **kwargs) -> "PosePublisher":
        """Listen on ``host:port`` (``port=0``: any free port, see :attr:`address`).

        A client beyond ``max_clients`` is sent one line of text,
        ``vespro refused: ...`` (:data:`vespro.wire.REFUSAL_PREFIX`), and closed;
        ``log`` hears of it (the first refusal, then at most one line a minute).
        """
        if max_clients < 1:
            raise ValueError(f"max_clients must be >= 1, got {max_clients}")
        pub = cls(hello, **kwargs)
        pub._refusal_log = LogThrottle(log, pub._clock_ns, period_s=60.0)
        lst = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
        try:
            # A restarted server must be able to bind while old connections sit in TIME_WAIT.
            lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            lst.bind((host, port))
            lst.listen(8)
            lst.setblocking(False)
        except OSError:
            lst.close()
            pub._close_wake()
            raise
        pub._listener = lst
        pub._max_clients = int(max_clients)
        pub._sndbuf = int(sndbuf_bytes)
        pub._sel.register(lst, selectors.EVENT_READ, "listen")
        pub._start()
        return pub

    @classmethod
    def serial(cls, hello: HelloMsg, port, baudrate: int = 115200, *, reopen_period_s: float = 1.0,
               **kwargs) -> "PosePublisher":
        """Publish on a serial line.

        Parameters
        ----------
        port : str or serial-like
            A pyserial URL or device path (``/dev/ttyUSB0``, ``/dev/pts/3``,
            ``loop://``), opened with ``serial.serial_for_url`` and reopened
            after an error; or an already open object with ``write(bytes)``
            (and optionally ``fileno()``), used as is.
        """
        pub = cls(hello, **kwargs)
        pub._reopen_ns = int(reopen_period_s * 1e9)
        if isinstance(port, str):
            pub._serial_url = port
            pub._serial_kwargs = dict(baudrate=baudrate)
            pub._port = pub._open_serial()      # raises on a bad URL: a set-up error
        else:
            pub._port = port
        pub._attach_serial()
        pub._start()
        return pub

    def _open_serial(self):
        import serial  # pyserial; imported here so TCP-only users need not have it

        return serial.serial_for_url(self._serial_url, timeout=0, write_timeout=None, **self._serial_kwargs)

    def _attach_serial(self) -> None:
        write, self._serial_fd = _serial_writer(self._port)
        self._serial_sink = _Sink(str(self._serial_url or self._port), write, self._max_pending)
        self._serial_sink.offer(b"\x00" + self._hello_frame)
        self._last_hello_ns = self._clock_ns()

    def _start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="vespro-link", daemon=True)
        self._thread.start()

    @property
    def address(self) -> tuple[str, int] | None:
        """``(host, port)`` the TCP listener is bound to, else None."""
        return None if self._listener is None else self._listener.getsockname()[:2]

    # --- the loop's API -----------------------------------------------------------

    def publish(self, msg) -> PublishStatus:
        """Send one message (usually a :class:`PoseMsg`) to every sink; never blocks or raises."""
        if self._closed:
            return PublishStatus.CLOSED
        try:
            frame = encode(msg, self._clock_ns() if self._stamp else None)
        except Exception:
            with self._lock:
                self._errors += 1
            return PublishStatus.INVALID
        with self._lock:
            self._frames_published += 1
            self._last_publish_ns = self._clock_ns()
            return self._broadcast(frame)

    def heartbeat(self) -> PublishStatus:
        """Send a HEARTBEAT now (the publisher also sends them on its own when idle)."""
        with self._lock:
            seq = self._heartbeat_seq
            self._heartbeat_seq = (seq + 1) % _U32
        return self.publish(HeartbeatMsg(seq, self._clock_ns()))

    def stats(self) -> LinkStats:
        with self._lock:
            sinks = list(self._clients.values())
            if self._serial_sink is not None:
                sinks.append(self._serial_sink)
            per = tuple(s.stats() for s in sinks)
            return LinkStats(
                frames_published=self._frames_published,
                frames_sent=self._closed_totals[0] + sum(s.frames_sent for s in per),
                bytes_sent=self._closed_totals[1] + sum(s.bytes_sent for s in per),
                drops=self._closed_totals[2] + sum(s.drops for s in per),
                clients_connected=len(self._clients),
                clients_accepted=self._accepted,
                clients_refused=self._refused,
                errors=self._errors,
                sinks=per,
            )

    def close(self) -> None:
        """Stop the thread and close every socket / the port. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._wake()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        with self._lock:
            for sock in list(self._clients):
                self._drop_client(sock)
            if self._listener is not None:
                try:
                    self._sel.unregister(self._listener)
                except Exception:
                    pass
                self._listener.close()
            self._serial_fd_watched = False
            self._sel.close()
            if self._port is not None and self._serial_url is not None:
                try:
                    self._port.close()
                except Exception:
                    pass
            self._close_wake()

    def __enter__(self) -> "PosePublisher":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- internals (lock held) ----------------------------------------------------

    def _broadcast(self, frame: bytes) -> PublishStatus:
        sinks = list(self._clients.values())
        if self._serial_sink is not None and not self._serial_sink.dead:
            sinks.append(self._serial_sink)
        sinks = [s for s in sinks if not s.dead]
        if not sinks:
            return PublishStatus.NO_SINK
        ok = True
        need_io = False
        for s in sinks:
            ok &= s.offer(frame)
            need_io |= bool(s.pending) or s.dead
        if need_io:
            self._wake()
        return PublishStatus.OK if ok else PublishStatus.DROPPED

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass  # buffer full (a wake-up is pending anyway) or closed

    def _close_wake(self) -> None:
        for s in (self._wake_r, self._wake_w):
            try:
                s.close()
            except OSError:
                pass

    def _drop_client(self, sock: socket.socket) -> None:
        sink = self._clients.pop(sock, None)
        self._masks.pop(sock, None)
        if sink is not None:
            self._closed_totals[0] += sink.frames_sent
            self._closed_totals[1] += sink.bytes_sent
            self._closed_totals[2] += sink.drops
        try:
            self._sel.unregister(sock)
        except Exception:
            pass
        try:
            sock.close()
        except OSError:
            pass

    def _accept(self) -> None:
        while True:
            try:
                sock, addr = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self._errors += 1
                return
            if len(self._clients) >= self._max_clients:
                self._refuse(sock, addr)
                continue
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self._sndbuf > 0:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self._sndbuf)
            sink = _Sink(f"tcp {addr[0]}:{addr[1]}", _socket_writer(sock), self._max_pending)
            self._clients[sock] = sink
            self._accepted += 1
            self._sel.register(sock, selectors.EVENT_READ, sink)
            self._masks[sock] = selectors.EVENT_READ
            sink.offer(b"\x00" + self._hello_frame)

    def _refuse(self, sock: socket.socket, addr) -> None:
        """Tell a client over the limit why, in one line it can read, and close it."""
        self._refused += 1
        why = f"this pose server takes at most {self._max_clients} clients at once (vespro serve --max-clients)"
        try:
            sock.setblocking(False)
            sock.send(REFUSAL_PREFIX + why.encode() + b"\n")  # a few bytes: the socket buffer takes them
            sock.shutdown(socket.SHUT_WR)
        except OSError:
            pass
        sock.close()
        self._refusal_log("refused", f"link: refused a client from {addr[0]}:{addr[1]}: {why}; "
                                     f"{self._refused} refused so far")

    def _service_client(self, sock: socket.socket, mask: int) -> None:
        sink = self._clients.get(sock)
        if sink is None:
            return
        if mask & selectors.EVENT_READ:
            # Receivers send nothing; read only to notice EOF / reset.
            try:
                data = sock.recv(4096)
                if not data:
                    sink.dead = True
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                sink.dead = True
        if mask & selectors.EVENT_WRITE and not sink.dead:
            sink.flush()

    def _update_masks(self) -> None:
        for sock, sink in list(self._clients.items()):
            if sink.dead:
                self._drop_client(sock)
                continue
            want = selectors.EVENT_READ | (selectors.EVENT_WRITE if sink.pending else 0)
            if self._masks.get(sock) != want:
                self._sel.modify(sock, want, sink)
                self._masks[sock] = want

    def _watch_serial_fd(self) -> None:
        """Have select() report the port writable while bytes wait for it."""
        sink = self._serial_sink
        want = sink is not None and self._serial_fd is not None and bool(sink.pending) and not sink.dead
        if want and not self._serial_fd_watched:
            self._sel.register(self._serial_fd, selectors.EVENT_WRITE, "serial")
            self._serial_fd_watched = True
        elif not want and self._serial_fd_watched:
            try:
                self._sel.unregister(self._serial_fd)
            except Exception:
                pass
            self._serial_fd_watched = False

    def _service_serial(self, now_ns: int) -> None:
        sink = self._serial_sink
        if sink is None:
            if self._serial_url is not None and now_ns >= self._reopen_at_ns:
                try:
                    self._port = self._open_serial()
                    self._attach_serial()
                except Exception:
                    self._errors += 1
                    self._reopen_at_ns = now_ns + self._reopen_ns
            return
        sink.flush()
        if sink.dead:
            self._errors += 1
            self._closed_totals[0] += sink.frames_sent
            self._closed_totals[1] += sink.bytes_sent
            self._closed_totals[2] += sink.drops
            self._watch_serial_fd()
            self._serial_sink = None
            if self._serial_url is not None:   # ours: close and reopen later
                try:
                    self._port.close()
                except Exception:
                    pass
                self._reopen_at_ns = now_ns + self._reopen_ns
            return
        if self._hello_ns > 0 and now_ns - self._last_hello_ns >= self._hello_ns:
            sink.offer(self._hello_frame)
            self._last_hello_ns = now_ns

    def _run(self) -> None:
        while not self._closed:
            try:
                self._run_once()
            except Exception:
                # The I/O thread must outlive any surprise (a socket closed
                # under it, a selector error): count it and carry on.
                with self._lock:
                    self._errors += 1
                time.sleep(0.01)

    def _run_once(self) -> None:
        with self._lock:
            self._update_masks()
            self._watch_serial_fd()
            # A port without a descriptor cannot be watched: poll it.
            serial_busy = (self._serial_sink is not None and bool(self._serial_sink.pending)
                           and not self._serial_fd_watched)
        timeout = 0.005 if serial_busy else 0.1
        try:
            events = self._sel.select(timeout)
        except OSError:
            events = []
        if self._closed:
            return
        with self._lock:
            for key, mask in events:
                if key.data == "wake":
                    try:
                        while self._wake_r.recv(4096):
                            pass
                    except OSError:
                        pass
                elif key.data == "listen":
                    self._accept()
                elif key.data == "serial":
                    pass  # flushed by _service_serial below
                else:
                    self._service_client(key.fileobj, mask)
            now = self._clock_ns()
            if self._serial_url is not None or self._serial_sink is not None:
                self._service_serial(now)
            hb_due = self._heartbeat_ns > 0 and now - self._last_publish_ns >= self._heartbeat_ns
        if hb_due:
            self.heartbeat()


class PublisherGroup:
    """Several publishers behind one ``publish`` (the TCP or serial link and Zenoh, say).

    ``publish`` hands the message to each in turn and returns the worst status;
    ``stats`` adds up their counters.
    """

    def __init__(self, *publishers):
        self.publishers = tuple(publishers)
        self.hello = self.publishers[0].hello

    def publish(self, msg) -> PublishStatus:
        return max(p.publish(msg) for p in self.publishers)

    def heartbeat(self) -> PublishStatus:
        return max(p.heartbeat() for p in self.publishers)

    def stats(self) -> LinkStats:
        st = [p.stats() for p in self.publishers]
        total = {f: sum(getattr(s, f) for s in st) for f in LinkStats.__dataclass_fields__ if f != "sinks"}
        return LinkStats(**total, sinks=tuple(k for s in st for k in s.sinks))

    @property
    def address(self):
        return self.publishers[0].address

    def close(self) -> None:
        for p in self.publishers:
            p.close()

    def __enter__(self) -> "PublisherGroup":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
