"""Publish the pose stream on Zenoh: any number of subscribers, on this machine or others.

The serial/TCP link (:mod:`vespro.link`) stays the hard real-time path to one
controller; Zenoh serves monitors, loggers, fleets and ROS 2 (``rmw_zenoh``)::

    pub = ZenohPublisher("vespro/pose", HelloMsg(26.0, ("box",)))   # peer, listening on 127.0.0.1:7447
    pub.publish(PoseMsg(...))                                      # never blocks
    pub.close()

Every sample on ``key`` is one wire frame (:mod:`vespro.wire`, "Zenoh"): the
POSE frames, a HELLO every ``hello_period_s`` and a HEARTBEAT when idle for
``heartbeat_period_s``. Subscribers: ``servo run --connect zenoh/KEY`` or any
Zenoh session feeding the payloads to ``vespro.wire.Decoder``.

Samples are sent with congestion control "drop": a subscriber that cannot keep
up loses samples (latest value wins) and the tracker is never held back; the
wire's sequence numbers show the gaps.

ROS 2: with ``ros2_key`` each POSE is also published there as a CDR
``geometry_msgs/PoseWithCovarianceStamped`` (:mod:`vespro.ros2`) with the
attachment ``rmw_zenoh`` (ROS 2 Jazzy) puts on its samples; :func:`ros2_key`
gives the key expression ``rmw_zenoh`` uses for a topic. Only POSE messages
whose status is TRACKING are published there (ROS has no status field). Its
header stamp is the capture stamp moved to the system clock (ROS time).
"""

from __future__ import annotations

import os
import threading
import time
from typing import Callable

from .errors import InputError
from .link import LinkStats, PublishStatus
from .ros2 import MissingInteropError
from .wire import ZENOH_ENDPOINT, HeartbeatMsg, HelloMsg, PoseMsg, PoseStatus, encode, zenoh_config_json5

__all__ = ["ZenohPublisher", "ZenohSetupError", "ros2_key", "open_session", "POSE_TYPE"]

POSE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
_U32 = 2**32


class ZenohSetupError(InputError):
    """A Zenoh session or key expression the options ask for cannot be set up."""


def _zenoh():
    try:
        import zenoh
    except ImportError:
        raise MissingInteropError("Zenoh needs the 'eclipse-zenoh' package: pip install 'vespro[interop]'") from None
    return zenoh


def open_session(mode: str = "peer", listen=(), connect=(), config_file: str | None = None):
    """A Zenoh session: from ``config_file`` (a Zenoh JSON5 file) if given, else
    :func:`vespro.wire.zenoh_config_json5` of the endpoints."""
    zenoh = _zenoh()
    conf = zenoh.Config.from_file(config_file) if config_file else \
        zenoh.Config.from_json5(zenoh_config_json5(mode, listen, connect))
    return zenoh.open(conf)


def ros2_key(topic: str, typename: str = POSE_TYPE, domain_id: int = 0) -> str:
    """``rmw_zenoh``'s key expression for a ROS 2 topic:
    ``<domain>/<topic>/<pkg>::msg::dds_::<Type>_/<type hash>``."""
    from .ros2 import type_hash

    pkg, _, name = typename.split("/")
    return f"{int(domain_id)}/{topic.strip('/')}/{pkg}::msg::dds_::{name}_/{type_hash(typename)}"


class ZenohPublisher:
    """Wire frames (and optionally ROS 2 CDR poses) on Zenoh; the interface of
    :class:`vespro.link.PosePublisher` (``publish``, ``heartbeat``, ``stats``, ``close``).

    Parameters
    ----------
    key : str
        Key expression of the wire frames.
    hello : HelloMsg
    listen, connect : sequence of str
        Zenoh endpoints of the session (peer mode). By default it listens on
        ``tcp/127.0.0.1:7447`` only: reachable from this machine alone.
    config_file : str, optional
        A Zenoh configuration file instead (several machines: see the README).
    ros2_key : str, optional
        Also publish each tracked pose as ROS 2 CDR on this key (:func:`ros2_key`).
    frame_id : str
        ROS 2 header frame.
    hello_period_s, heartbeat_period_s : float
        HELLO repeat period; HEARTBEAT after this long without a publish (0: never).
    stamp_send_time : bool
        Replace ``t_send_ns`` of each message with ``clock_ns()`` at publish.
    clock_ns : callable
        The clock of the capture stamps (``SimClock.now_ns`` in simulation).
    """

    def __init__(self, key: str, hello: HelloMsg, *, listen=(ZENOH_ENDPOINT,), connect=(),
                 config_file: str | None = None, ros2_key: str | None = None, frame_id: str = "world",
                 hello_period_s: float = 1.0, heartbeat_period_s: float = 1.0, stamp_send_time: bool = True,
                 clock_ns: Callable[[], int] = time.monotonic_ns):
        if not isinstance(hello, HelloMsg):
            raise ValueError(f"hello: expected a HelloMsg, got {type(hello).__name__}")
        zenoh = _zenoh()
        self.key = key
        self.hello = hello
        self._hello_frame = encode(hello)
        self._clock_ns = clock_ns
        self._stamp = stamp_send_time
        self._frame_id = frame_id
        # ROS time is the system clock: capture stamps are moved onto it by this offset.
        self._ros_offset_ns = time.time_ns() - clock_ns()
        try:
            self._session = open_session("peer", listen, connect, config_file)
        except Exception as e:
            where = f"configuration {config_file}" if config_file else f"listen {list(listen)} connect {list(connect)}"
            raise ZenohSetupError(f"cannot open a Zenoh session ({where}): {e} (an endpoint in use, "
                                  "or a malformed one?)") from None
        opts = dict(congestion_control=zenoh.CongestionControl.DROP, express=True)
        try:
            self._pub = self._session.declare_publisher(key, **opts)
            self._ros = self._session.declare_publisher(ros2_key, **opts) if ros2_key else None
        except Exception as e:
            self._session.close()
            raise ZenohSetupError(f"Zenoh key expression {key!r}: {e}") from None
        self._gid = os.urandom(16)   # rmw_zenoh's publisher id in the attachment
        self._lock = threading.Lock()
        self._closed = False
        self._published = self._sent = self._bytes = self._errors = self._ros_seq = 0
        self._hb_seq = 0
        self._last_publish_ns = clock_ns()
        self._put(self._hello_frame)
        self._stop = threading.Event()
        self._hello_s, self._hb_ns = float(hello_period_s), int(heartbeat_period_s * 1e9)
        self._thread = threading.Thread(target=self._run, name="vespro-zenoh", daemon=True)
        self._thread.start()

    def _put(self, frame: bytes) -> bool:
        try:
            self._pub.put(frame)
        except Exception:
            self._errors += 1
            return False
        self._sent += 1
        self._bytes += len(frame)
        return True

    def _put_ros2(self, msg: PoseMsg) -> None:
        from zenoh.ext import Int64, z_serialize

        from . import ros2

        t = msg.t_capture_ns + self._ros_offset_ns
        ros = ros2.pose_with_covariance_stamped(t, msg.p_world_object, msg.q_world_object, msg.cov, self._frame_id)
        self._ros_seq += 1
        att = z_serialize(("sequence_number", Int64(self._ros_seq), "source_timestamp", Int64(time.time_ns()),
                           "source_gid", self._gid))
        self._ros.put(ros2.serialize(ros), attachment=att)

    def publish(self, msg) -> PublishStatus:
        """Send one message to every subscriber; never blocks or raises."""
        if self._closed:
            return PublishStatus.CLOSED
        try:
            frame = encode(msg, self._clock_ns() if self._stamp else None)
        except Exception:
            with self._lock:
                self._errors += 1
            return PublishStatus.INVALID
        with self._lock:
            self._published += 1
            self._last_publish_ns = self._clock_ns()
            ok = self._put(frame)
            if ok and self._ros is not None and isinstance(msg, PoseMsg) and msg.status == PoseStatus.TRACKING:
                try:
                    self._put_ros2(msg)
                except Exception:
                    self._errors += 1
        return PublishStatus.OK if ok else PublishStatus.NO_SINK

    def heartbeat(self) -> PublishStatus:
        with self._lock:
            seq = self._hb_seq
            self._hb_seq = (seq + 1) % _U32
        return self.publish(HeartbeatMsg(seq, self._clock_ns()))

    def subscribers_matched(self) -> bool:
        """True when at least one subscriber matches the key."""
        try:
            return bool(self._pub.matching_status.matching)
        except Exception:
            return False

    def stats(self) -> LinkStats:
        with self._lock:
            return LinkStats(frames_published=self._published, frames_sent=self._sent, bytes_sent=self._bytes,
                             drops=0, clients_connected=int(self.subscribers_matched()), clients_accepted=0,
                             clients_refused=0, errors=self._errors, sinks=())

    def _run(self) -> None:
        next_hello = time.monotonic() + self._hello_s
        while not self._stop.wait(0.1):
            with self._lock:
                if self._hello_s > 0 and time.monotonic() >= next_hello:
                    self._put(self._hello_frame)
                    next_hello = time.monotonic() + self._hello_s
                idle = self._hb_ns > 0 and self._clock_ns() - self._last_publish_ns >= self._hb_ns
            if idle:
                self.heartbeat()

    def close(self) -> None:
        """Stop the thread and close the session. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._thread.join(timeout=5.0)
        try:
            self._session.close()
        except Exception:
            pass

    def __enter__(self) -> "ZenohPublisher":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
