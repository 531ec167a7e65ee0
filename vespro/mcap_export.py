"""A recording (with its tracker output and servo time histories) as an MCAP file of ROS 2 messages.

Foxglove, Rerun, ``ros2 bag play`` and any MCAP reader open the result as is:
the ``ros2`` profile, ``cdr`` messages, ``ros2msg`` schemas (ROS 2 Jazzy's
definitions, :mod:`vespro.ros2`). Every stamp (message header and MCAP log
time) is the recording's capture time ``t`` (seconds from the first frame
set); servo ticks are put on the same time line (see :func:`export_mcap`).

Topics
------
=============================  ===================================  ========================================
topic                          type                                 one message per
=============================  ===================================  ========================================
``/<camera>/image_raw``        sensor_msgs/Image (mono8, bgr8)      frame set where the camera has an image
``/<camera>/camera_info``      sensor_msgs/CameraInfo               same
``/tf_static``                 tf2_msgs/TFMessage                   once: world -> every fixed camera
``/tf``                        tf2_msgs/TFMessage                   frame set with an eye-in-hand camera or
                                                                    a tracked pose: world -> those frames
``/vespro/pose``               geometry_msgs/PoseWithCovariance-    tracked frame set (status ``tracking``)
                               Stamped
``/vespro/velocity``           geometry_msgs/TwistStamped           tracked frame set with a velocity
``/vespro/status``             std_msgs/String                      row of poses.csv
``/vespro/probability``        std_msgs/Float64                     row of poses.csv stating a probability
``/servo/joint_states``        sensor_msgs/JointState (q_meas)      servo tick
``/servo/joint_command``       sensor_msgs/JointState (q, qd cmd)   servo tick
``/servo/reference``           geometry_msgs/PoseStamped            servo tick (TCP reference, world)
``/servo/reference_velocity``  geometry_msgs/Vector3Stamped         servo tick
``/servo/status``              std_msgs/Int8 (servo.safety.Status)  servo tick
``/servo/flags``               std_msgs/Int32 (check bits)          servo tick
``/servo/compute_time``        std_msgs/Float64, s                  servo tick
=============================  ===================================  ========================================
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from . import ros2
from .errors import InputError
from .se3 import pq_from_transform

__all__ = ["McapExportError", "Ros2McapWriter", "export_mcap", "JOINT_NAMES"]

#: The arm's joints (models/arm.xml), in the servo's order.
JOINT_NAMES = ("j1", "j2", "j3", "j4", "j5", "j6")
#: What ``servo run --record DIR`` writes (servo.recorder.Recorder.save).
SERVO_FILE = "servo.npz"


class McapExportError(InputError):
    """An input of the MCAP export is missing or inconsistent; the message says which and what to do."""


class Ros2McapWriter:
    """ROS 2 messages into an MCAP file, one channel per topic (schemas registered on first use)."""

    def __init__(self, path: str | Path):
        try:
            from mcap.writer import Writer
        except ImportError:
            raise ros2.MissingInteropError("MCAP export needs the 'mcap' package: pip install 'vespro[interop]'") from None
        self._f = open(path, "wb")
        self._w = Writer(self._f)
        self._w.start(profile="ros2", library="vespro")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}

    def write(self, topic: str, msg, t_ns: int) -> None:
        """Append ``msg`` on ``topic`` at log time ``t_ns`` (must be >= 0)."""
        ch = self._channels.get(topic)
        if ch is None:
            typename = msg.__msgtype__
            sid = self._schemas.get(typename)
            if sid is None:
                sid = self._w.register_schema(typename, "ros2msg", ros2.msgdef(typename).encode())
                self._schemas[typename] = sid
            ch = self._w.register_channel(topic, "cdr", sid)
            self._channels[topic] = ch
        n = self.counts.get(topic, 0)
        self._w.add_message(ch, log_time=int(t_ns), data=ros2.serialize(msg), publish_time=int(t_ns), sequence=n)
        self.counts[topic] = n + 1

    def metadata(self, name: str, data: dict) -> None:
        self._w.add_metadata(name, {k: str(v) for k, v in data.items()})

    def close(self) -> None:
        if not self._f.closed:
            self._w.finish()
            self._f.close()

    def __enter__(self) -> "Ros2McapWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _t_ns(t_s: float) -> int:
    return int(round(float(t_s) * 1e9))


def _servo_t0_ns(recording: Path, given: int | None) -> int:
    """The servo clock's stamp of the recording's time 0 (its first frame set's capture stamp)."""
    if given is not None:
        return int(given)
    info = recording.parent / "server.json"
    try:
        t0 = json.loads(info.read_text()).get("t0_ns")
    except (OSError, ValueError):
        t0 = None
    if t0 is None:
        raise McapExportError(f"--servo: the capture stamp of frame 0 is unknown ({info} has no t0_ns); "
                              "pass --servo-t0-ns NS (the vision clock's stamp of the recording's first frame set)")
    return int(t0)


def _write_servo(w: Ros2McapWriter, path: Path, t0_ns: int) -> None:
    try:
        d = np.load(path)
        h = {k: d[k] for k in d.files}
    except (OSError, ValueError) as e:
        raise McapExportError(f"{path}: not a servo recording ({e})") from None
    if "t_ns" not in h:
        raise McapExportError(f"{path}: no channel 't_ns' (expected what 'servo run --record DIR' writes)")
    t = h["t_ns"].astype(np.int64) - int(t0_ns)
    keep = np.flatnonzero(t >= 0)  # ticks before the first frame set have no place on the recording's time line
    g = h.get
    for i in keep:
        ti = int(t[i])
        if "q_meas" in h:
            w.write("/servo/joint_states", ros2.joint_state(ti, JOINT_NAMES, position=h["q_meas"][i]), ti)
        if "q_cmd" in h:
            qd = g("qd_cmd")
            w.write("/servo/joint_command",
                    ros2.joint_state(ti, JOINT_NAMES, position=h["q_cmd"][i], velocity=None if qd is None else qd[i]), ti)
        if "p_ref" in h and "quat_ref" in h:
            w.write("/servo/reference", ros2.pose_stamped(ti, h["p_ref"][i], h["quat_ref"][i]), ti)
        if "v_ref" in h:
            w.write("/servo/reference_velocity", ros2.vector3_stamped(ti, h["v_ref"][i]), ti)
        if "status" in h:
            w.write("/servo/status", ros2.scalar_msg("std_msgs/msg/Int8", int(h["status"][i])), ti)
        if "flags" in h:
            w.write("/servo/flags", ros2.scalar_msg("std_msgs/msg/Int32", int(h["flags"][i])), ti)
        if "compute_ns" in h:
            w.write("/servo/compute_time", ros2.scalar_msg("std_msgs/msg/Float64", float(h["compute_ns"][i]) * 1e-9), ti)


def export_mcap(recording: str | Path, out: str | Path, poses: str | Path | None = None,
                servo: str | Path | None = None, servo_t0_ns: int | None = None) -> dict[str, int]:
    """Write a recording (and optionally its poses and servo histories) as ROS 2 messages in MCAP.

    Parameters
    ----------
    recording : path
        The recording folder (shared/spec/recording.md).
    out : path
        The ``.mcap`` file to write.
    poses : path, optional
        A ``poses.csv`` of this recording (``vespro track`` or ``vespro serve --record``).
    servo : path, optional
        A folder holding ``servo.npz`` (``servo run --record DIR``).
    servo_t0_ns : int, optional
        The servo clock's stamp of the recording's time 0, ns. The servo and the
        vision side share one monotonic clock on one machine (and in the
        lockstep simulation), so this is the first frame set's capture stamp,
        which ``vespro serve --record`` keeps in ``server.json`` (``t0_ns``)
        beside the recording: read from there when not given.

    Returns
    -------
    dict
        Messages written per topic.

    Raises
    ------
    InputError
        A malformed recording, poses file or servo folder (one line naming it).
    """
    from .poses import read_poses
    from .recording import Recording

    rec = Recording(recording)
    rows = []
    if poses is not None:
        header = Path(poses).open().readline().strip().split(",")
        if "object" in header:
            raise McapExportError(f"{poses}: several objects (column 'object'): export one object's poses at a time")
        try:
            rows = read_poses(poses)
        except (OSError, ValueError) as e:
            raise McapExportError(str(e)) from None
        bad = [r.index for r in rows if not 0 <= r.index < len(rec)]
        if bad:
            raise McapExportError(f"{poses}: index {bad[0]} is not a frame of {rec.path} (0..{len(rec) - 1}): "
                                  "poses of another recording?")
    servo_npz = None
    if servo is not None:
        servo_npz = Path(servo) / SERVO_FILE
        if not servo_npz.is_file():
            raise McapExportError(f"{servo_npz}: missing (--servo takes the folder given to 'servo run --record')")
        servo_t0_ns = _servo_t0_ns(rec.path, servo_t0_ns)
    obj = rec.object_name
    by_index = {r.index: r for r in rows}
    with Ros2McapWriter(out) as w:
        w.metadata("vespro", {"recording": rec.path.name, "object": obj, "rate_hz": rec.rate_hz,
                              "covariance": "row-major 6x6 of (x, y, z, rotation about world X, Y, Z), m and rad"})
        t_first = _t_ns(rec.t[0])
        fixed = [ros2.transform_stamped(t_first, c.T_world_camera, ros2.WORLD, c.name) for c in rec.rig if c.is_fixed]
        if fixed:
            w.write("/tf_static", ros2.tf_message(fixed), t_first)
        for i in range(len(rec)):
            t = _t_ns(rec.t[i])
            for cam in rec.rig:
                img = rec.image(cam.name, i)
                if img is not None:
                    w.write(f"/{cam.name}/image_raw", ros2.image_msg(t, cam.name, img), t)
                    w.write(f"/{cam.name}/camera_info", ros2.camera_info(t, cam.name, cam.intrinsics), t)
            tfs = [ros2.transform_stamped(t, rec.T_world_camera(c.name, i), ros2.WORLD, c.name)
                   for c in rec.rig.eye_in_hand]
            r = by_index.get(i)
            if r is not None:
                w.write("/vespro/status", ros2.string_msg(r.status), t)
                if r.probability is not None and np.isfinite(r.probability):
                    w.write("/vespro/probability", ros2.scalar_msg("std_msgs/msg/Float64", float(r.probability)), t)
            if r is not None and r.status == "tracking":
                pq = pq_from_transform(r.T_world_object)
                cov = r.cov if r.cov is not None else np.zeros((6, 6))
                w.write("/vespro/pose", ros2.pose_with_covariance_stamped(t, pq[:3], pq[3:], cov), t)
                if r.velocity is not None:
                    w.write("/vespro/velocity", ros2.twist_stamped(t, r.velocity[:3], r.velocity[3:]), t)
                tfs.append(ros2.transform_stamped(t, r.T_world_object, ros2.WORLD, obj))
            if tfs:
                w.write("/tf", ros2.tf_message(tfs), t)
        if servo_npz is not None:
            _write_servo(w, servo_npz, servo_t0_ns)
        return dict(w.counts)
