"""Receive the pose stream from Zenoh: the transport behind ``servo run --connect zenoh/KEY``.

URL: ``zenoh/KEY[?connect=ENDPOINT[,ENDPOINT...]][&listen=ENDPOINT...][&mode=peer|client][&config=FILE]``,
e.g. ``zenoh/vespro/pose`` (a peer connecting to ``tcp/127.0.0.1:7447``, the
pose server on this machine) or
``zenoh/vespro/pose?connect=tcp/192.168.10.1:7447&mode=client`` (a router on
another machine). A key expression cannot hold ``?``, so the URL parses
unambiguously.

:class:`ZenohTransport` has the interface of the receiver's transports
(``start``, ``finish``, ``read``, ``fileno``, ``close``, see
:mod:`servo.receiver`): Zenoh's own thread hands each sample's payload (one wire
frame) to a queue and writes a byte to a socket pair so ``fileno()`` can be
waited on; ``read`` returns what is queued, never blocking. Opening a Zenoh peer
takes about half a second, so it happens in a thread: ``start`` begins it and
``finish`` reports when it is up; the 500 Hz loop never waits for it.
"""

from __future__ import annotations

import socket
import threading
from collections import deque
from urllib.parse import parse_qs

from vespro.wire import ZENOH_ENDPOINT, zenoh_config_json5

__all__ = ["ZenohTransport", "parse_zenoh_url", "SCHEME"]

SCHEME = "zenoh/"


def parse_zenoh_url(url: str) -> dict:
    """``zenoh/KEY?...`` -> ``dict(key, mode, connect, listen, config)``; ValueError if malformed."""
    if not url.startswith(SCHEME):
        raise ValueError(f"expected zenoh/KEY, got {url!r}")
    key, _, query = url[len(SCHEME):].partition("?")
    if not key:
        raise ValueError(f"expected zenoh/KEY (a key expression after 'zenoh/'), got {url!r}")
    q = parse_qs(query, keep_blank_values=True)
    unknown = set(q) - {"connect", "listen", "mode", "config"}
    if unknown:
        raise ValueError(f"{url!r}: unknown option(s) {', '.join(sorted(unknown))} (connect, listen, mode, config)")
    split = lambda name: [e for v in q.get(name, []) for e in v.split(",") if e]  # noqa: E731
    mode = q.get("mode", ["peer"])[-1]
    if mode not in ("peer", "client"):
        raise ValueError(f"{url!r}: mode must be peer or client, got {mode!r}")
    return {"key": key, "mode": mode, "connect": split("connect") or [ZENOH_ENDPOINT], "listen": split("listen"),
            "config": q.get("config", [None])[-1]}


class ZenohTransport:
    """A Zenoh subscriber as a non-blocking byte source for :class:`servo.receiver.PoseReceiver`."""

    def __init__(self, url: str):
        self.options = parse_zenoh_url(url)
        try:
            import zenoh  # noqa: F401  (checked here: the peer is opened in a thread)
        except ImportError:
            raise ValueError(f"{url}: Zenoh needs the 'eclipse-zenoh' package: pip install 'vespro[interop]'") from None
        self._frames: deque[bytes] = deque()
        self._wake_r = self._wake_w = None
        self._lock = threading.Lock()
        self._attempt: dict | None = None  # the peer being opened or open

    @classmethod
    def from_url(cls, url: str) -> "ZenohTransport":
        return cls(url)

    def _open(self, attempt: dict) -> None:
        peer = None
        try:
            import zenoh

            o = self.options
            conf = zenoh.Config.from_file(o["config"]) if o["config"] else \
                zenoh.Config.from_json5(zenoh_config_json5(o["mode"], o["listen"], o["connect"]))
            peer = zenoh.open(conf)
            wake, frames = attempt["wake"], self._frames

            def on_sample(sample):
                frames.append(sample.payload.to_bytes())
                try:
                    wake.send(b"x")
                except OSError:
                    pass  # buffer full (a wake-up is pending anyway), or closed

            peer.declare_subscriber(o["key"], on_sample)
        except Exception as e:  # reported by finish(), in the loop's thread
            attempt["error"] = e
        with self._lock:
            attempt["peer"] = peer
            cancelled = attempt["cancelled"]
            attempt["ready"] = True
        if cancelled and peer is not None:  # closed while opening: nobody else will close it
            peer.close()

    def start(self) -> bool:
        """Begin opening the peer (in a thread); True when already open."""
        r, w = socket.socketpair()
        r.setblocking(False)
        w.setblocking(False)
        self._wake_r, self._wake_w = r, w
        self._attempt = {"wake": w, "peer": None, "error": None, "ready": False, "cancelled": False}
        threading.Thread(target=self._open, args=(self._attempt,), name="servo-zenoh-open", daemon=True).start()
        return False

    def finish(self) -> bool:
        """True once the peer is open and subscribed; raises what opening it raised."""
        a = self._attempt
        if a is None or not a["ready"]:
            return False
        if a["error"] is not None:
            raise OSError(f"zenoh: {a['error']}")
        return True

    def read(self, n: int) -> bytes:
        """Queued frames (about ``n`` bytes at most, whole frames), b"" when none."""
        try:
            while self._wake_r.recv(4096):
                pass
        except (BlockingIOError, InterruptedError):
            pass
        out, size, frames = [], 0, self._frames
        while frames and size < n:
            f = frames.popleft()
            out.append(f)
            size += len(f)
        if frames:  # more than n bytes waited: keep the descriptor readable
            try:
                self._wake_w.send(b"x")
            except OSError:
                pass
        return b"".join(out)

    def fileno(self) -> int | None:
        return None if self._wake_r is None else self._wake_r.fileno()

    def close(self) -> None:
        """Close the peer (or have it closed when its opening ends); never waits for it."""
        a, self._attempt = self._attempt, None
        if a is not None:
            with self._lock:
                a["cancelled"] = True
                peer = a["peer"]
            if peer is not None:
                try:
                    peer.close()
                except Exception:
                    pass
        for s in (self._wake_r, self._wake_w):
            if s is not None:
                s.close()
        self._wake_r = self._wake_w = None
        self._frames.clear()
