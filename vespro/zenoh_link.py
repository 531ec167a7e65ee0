"""Publish the pose stream on Zenoh: any number of subscribers, on this machine or others.

The serial/TCP link (:mod:`vespro.link`) stays the hard real-time path to one
controller; Zenoh serves monitors, loggers, fleets and ROS 2 (``rmw_zenoh``)::

    pub = ZenohPublisher("vespro/pose", HelloMsg(26.0, ("box",)))   # peer, listening on 127.0.0.1:7447
    pub.publish(PoseMsg(...))                                      # never blocks
    pub.close()

Every sample on ``key`` is one wire frame (:mod:`vespro.wire`, "Zenoh"): the
POSE frames, a HELLO every ``hello_period_s`` and a HEARTBEAT when idle for
``heartbeat_period_s``. Subscribers: ``servo run --connect zenoh/KEY`` or any
Zenoh peer feeding the payloads to ``vespro.wire.Decoder``.

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
import time
from dataclasses import replace
from typing import Callable

from .errors import InputError
from .link import LinkStats, PosePublisher, PublishStatus
from .ros2 import MissingInteropError
from .wire import ZENOH_ENDPOINT, HelloMsg, PoseMsg, PoseStatus, zenoh_config_json5

__all__ = ["ZenohPublisher", "ZenohSetupError", "ros2_key", "open_peer", "POSE_TYPE"]

POSE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"


class ZenohSetupError(InputError):
    """A Zenoh peer or key expression the options ask for cannot be set up."""


def _zenoh():
    try:
        import zenoh
    except ImportError:
        raise MissingInteropError("Zenoh needs the 'eclipse-zenoh' package: pip install 'vespro[interop]'") from None
    return zenoh


def open_peer(mode: str = "peer", listen=(), connect=(), config_file: str | None = None):
    """A Zenoh peer: from ``config_file`` (a Zenoh JSON5 file) if given, else
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


class _ZenohPort:
    """A Zenoh publisher as the port of :meth:`vespro.link.PosePublisher.serial` (``write(bytes)``)."""

    def __init__(self, pub, key: str):
        self._pub = pub
        self._key = key

    def __str__(self) -> str:
        return f"zenoh {self._key}"

    def write(self, data: bytes) -> int:
        self._pub.put(bytes(data))
        return len(data)


class ZenohPublisher:
    """Wire frames (and optionally ROS 2 CDR poses) on Zenoh; the interface of
    :class:`vespro.link.PosePublisher` (``publish``, ``heartbeat``, ``stats``, ``close``).

    The link's own publisher does the work (encoding, send stamps, HELLO
    repeats, heartbeats, counters), writing each frame as one sample as it
    writes a serial line; the very first sample opens with a lone delimiter,
    as a serial stream does.

    Parameters
    ----------
    key : str
        Key expression of the wire frames.
    hello : HelloMsg
    listen, connect : sequence of str
        Zenoh endpoints of the peer (peer mode). By default it listens on
        ``tcp/127.0.0.1:7447`` only: reachable from this machine alone.
    config_file : str, optional
        A Zenoh configuration file instead (several machines: see the README).
    ros2_key : str, optional
        Also publish each tracked pose as ROS 2 CDR on this key (:func:`ros2_key`).
    frame_id : str
        ROS 2 header frame.
    hello_period_s, heartbeat_period_s, stamp_send_time, clock_ns
        As for :class:`vespro.link.PosePublisher`.
    """

    def __init__(self, key: str, hello: HelloMsg, *, listen=(ZENOH_ENDPOINT,), connect=(),
                 config_file: str | None = None, ros2_key: str | None = None, frame_id: str = "world",
                 hello_period_s: float = 1.0, heartbeat_period_s: float = 1.0, stamp_send_time: bool = True,
                 clock_ns: Callable[[], int] = time.monotonic_ns):
        zenoh = _zenoh()
        self.key = key
        self.hello = hello
        self._frame_id = frame_id
        # ROS time is the system clock: capture stamps are moved onto it by this offset.
        self._ros_offset_ns = time.time_ns() - clock_ns()
        try:
            self._peer = open_peer("peer", listen, connect, config_file)
        except Exception as e:
            where = f"configuration {config_file}" if config_file else f"listen {list(listen)} connect {list(connect)}"
            raise ZenohSetupError(f"cannot open a Zenoh peer ({where}): {e} (an endpoint in use, "
                                  "or a malformed one?)") from None
        opts = dict(congestion_control=zenoh.CongestionControl.DROP, express=True)
        try:
            self._pub = self._peer.declare_publisher(key, **opts)
            self._ros = self._peer.declare_publisher(ros2_key, **opts) if ros2_key else None
        except Exception as e:
            self._peer.close()
            raise ZenohSetupError(f"Zenoh key expression {key!r}: {e}") from None
        self._gid = os.urandom(16)   # rmw_zenoh's publisher id in the attachment
        self._ros_seq = 0
        self._ros_errors = 0
        self._link = PosePublisher.serial(hello, _ZenohPort(self._pub, key), hello_period_s=hello_period_s,
                                          heartbeat_period_s=heartbeat_period_s, stamp_send_time=stamp_send_time,
                                          clock_ns=clock_ns)

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
        status = self._link.publish(msg)
        if status == PublishStatus.OK and self._ros is not None and isinstance(msg, PoseMsg) \
                and msg.status == PoseStatus.TRACKING:
            try:
                self._put_ros2(msg)
            except Exception:
                self._ros_errors += 1
        return status

    def heartbeat(self) -> PublishStatus:
        return self._link.heartbeat()

    def subscribers_matched(self) -> bool:
        """True when at least one subscriber matches the key."""
        try:
            return bool(self._pub.matching_status.matching)
        except Exception:
            return False

    def stats(self) -> LinkStats:
        """The link's counters; ``clients_connected`` is 1 while a subscriber matches the key."""
        st = self._link.stats()
        return replace(st, clients_connected=int(self.subscribers_matched()), errors=st.errors + self._ros_errors)

    def close(self) -> None:
        """Stop sending and close the peer. Idempotent."""
        self._link.close()
        try:
            self._peer.close()
        except Exception:
            pass

    def __enter__(self) -> "ZenohPublisher":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
