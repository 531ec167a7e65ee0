"""ROS 2 messages of the project's data: definitions, construction, CDR bytes.

The message types are ROS 2 Jazzy's own (``rosbags``' type store, an optional
dependency: ``pip install vespro[interop]``), so ROS 2 tools, Foxglove and Rerun
read what this module writes without any package of ours.

Covariance convention
---------------------
The project's 6x6 pose covariance (``vespro.ekf``, ``poses.csv``, the wire
POSE) is that of ``[dp, dtheta]``: position error in metres, world frame, then
the orientation error as a rotation vector in radians applied on the left,
``R_true = exp(dtheta) @ R_est``, i.e. a small rotation about the *world*
axes. ``geometry_msgs/PoseWithCovariance`` orders its covariance
``(x, y, z, rotation about X, rotation about Y, rotation about Z)`` with the
orientation "in a fixed-axis representation": small rotations about the axes
of the header's frame, here the world. Both orders and both frames agree, so
the conversion is the identity and :func:`ros_covariance` copies the 36
numbers row-major, bit for bit. (A consumer that reads the orientation block in
the body's own axes, as RViz does with its covariance display set to "Local",
must rotate it: ``R.T @ P_rot @ R``.)

Frames: ``world`` for the cell, the camera's name for its OpenCV optical frame
(x right, y down, z forward, as ROS's ``*_optical`` frames), the object's name
for the part.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .errors import InputError
from .se3 import quat_from_matrix

__all__ = ["WORLD", "typestore", "msgdef", "type_hash", "serialize", "deserialize", "time_msg", "header",
           "ros_covariance", "cov6_from_ros", "pose_with_covariance_stamped", "pose_stamped", "transform_stamped",
           "tf_message", "image_msg", "camera_info", "twist_stamped", "vector3_stamped", "joint_state",
           "scalar_msg", "string_msg", "MissingInteropError"]

WORLD = "world"


class MissingInteropError(InputError, ImportError):
    """A ROS 2 / MCAP / Zenoh feature was asked for without its optional packages (the command line
    prints the one line saying what to install)."""


@lru_cache(maxsize=1)
def typestore():
    """ROS 2 Jazzy's message types (``rosbags.typesys``)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise MissingInteropError("ROS 2 messages need the 'rosbags' package: pip install 'vespro[interop]'") from None
    return get_typestore(Stores.ROS2_JAZZY)


def _T(name: str):
    return typestore().types[name]


def msgdef(typename: str) -> str:
    """The ``ros2msg`` definition text of ``typename`` with its dependencies (as rosbag2 writes it)."""
    text, _ = typestore().generate_msgdef(typename, ros_version=2)
    return text


def type_hash(typename: str) -> str:
    """The ROS 2 type hash (``RIHS01_<sha256>``) that rmw_zenoh puts in its key expressions."""
    return typestore().hash_rihs01(typename)


def serialize(msg) -> bytes:
    """CDR bytes (little endian, with the 4-byte encapsulation header) of a message."""
    return bytes(typestore().serialize_cdr(msg, msg.__msgtype__))


def deserialize(data: bytes, typename: str):
    return typestore().deserialize_cdr(data, typename)


def time_msg(t_ns: int):
    """``builtin_interfaces/Time`` of a stamp in ns (sec rounded down, 0 <= nanosec < 1e9)."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return _T("builtin_interfaces/msg/Time")(sec=sec, nanosec=nsec)


def header(t_ns: int, frame_id: str):
    return _T("std_msgs/msg/Header")(stamp=time_msg(t_ns), frame_id=frame_id)


def ros_covariance(cov6: np.ndarray) -> np.ndarray:
    """The project's pose covariance as ``PoseWithCovariance.covariance`` (36,), row-major.

    Parameters
    ----------
    cov6 : ndarray (6, 6)
        Covariance of ``[dp (m, world), dtheta (rad, world axes, left)]``.

    Returns
    -------
    ndarray (36,), float64
        ROS order ``(x, y, z, rot X, rot Y, rot Z)`` about the fixed (world)
        axes: the same matrix (see the module docstring), flattened.
    """
    c = np.asarray(cov6, dtype=np.float64)
    if c.shape != (6, 6):
        raise ValueError(f"cov6: expected shape (6, 6), got {c.shape}")
    return c.reshape(36).copy()


def cov6_from_ros(covariance) -> np.ndarray:
    """Inverse of :func:`ros_covariance`: (36,) -> (6, 6)."""
    c = np.asarray(covariance, dtype=np.float64)
    if c.shape != (36,):
        raise ValueError(f"covariance: expected 36 numbers, got shape {c.shape}")
    return c.reshape(6, 6).copy()


def _pose(p: np.ndarray, q_wxyz: np.ndarray):
    g = "geometry_msgs/msg/"
    return _T(g + "Pose")(position=_T(g + "Point")(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                          orientation=_T(g + "Quaternion")(x=float(q_wxyz[1]), y=float(q_wxyz[2]),
                                                           z=float(q_wxyz[3]), w=float(q_wxyz[0])))


def _pq(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(T, dtype=float)[:3, 3], quat_from_matrix(np.asarray(T, dtype=float)[:3, :3])


def pose_with_covariance_stamped(t_ns: int, p: np.ndarray, q_wxyz: np.ndarray, cov6: np.ndarray,
                                 frame_id: str = WORLD):
    """``geometry_msgs/PoseWithCovarianceStamped`` of a position, a quaternion (w, x, y, z) and the project's
    covariance (converted by :func:`ros_covariance`)."""
    g = "geometry_msgs/msg/"
    return _T(g + "PoseWithCovarianceStamped")(
        header=header(t_ns, frame_id),
        pose=_T(g + "PoseWithCovariance")(pose=_pose(p, q_wxyz), covariance=ros_covariance(cov6)))


def pose_stamped(t_ns: int, p: np.ndarray, q_wxyz: np.ndarray, frame_id: str = WORLD):
    return _T("geometry_msgs/msg/PoseStamped")(header=header(t_ns, frame_id), pose=_pose(p, q_wxyz))


def transform_stamped(t_ns: int, T_parent_child: np.ndarray, parent: str, child: str):
    """``geometry_msgs/TransformStamped``: the pose of ``child`` in ``parent`` (ROS's tf convention is ours)."""
    g = "geometry_msgs/msg/"
    p, q = _pq(T_parent_child)
    return _T(g + "TransformStamped")(
        header=header(t_ns, parent), child_frame_id=child,
        transform=_T(g + "Transform")(translation=_T(g + "Vector3")(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                                      rotation=_T(g + "Quaternion")(x=float(q[1]), y=float(q[2]), z=float(q[3]),
                                                                    w=float(q[0]))))


def tf_message(transforms: list):
    return _T("tf2_msgs/msg/TFMessage")(transforms=list(transforms))


def image_msg(t_ns: int, frame_id: str, img: np.ndarray):
    """``sensor_msgs/Image`` of an 8-bit grey (``mono8``) or BGR (``bgr8``) image."""
    img = np.ascontiguousarray(img)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise ValueError(f"image: expected 8-bit grey (H, W) or BGR (H, W, 3), got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    ch = 1 if img.ndim == 2 else 3
    return _T("sensor_msgs/msg/Image")(header=header(t_ns, frame_id), height=h, width=w,
                                       encoding="mono8" if ch == 1 else "bgr8", is_bigendian=0, step=w * ch,
                                       data=img.reshape(-1))


def camera_info(t_ns: int, frame_id: str, intrinsics):
    """``sensor_msgs/CameraInfo`` of a :class:`vespro.camera.CameraIntrinsics`.

    ``plumb_bob`` with OpenCV's ``k1 k2 p1 p2 k3``; no rectification
    (``R = I``) and ``P = [K | 0]``, a monocular camera's projection of the
    images as they are.
    """
    K = np.asarray(intrinsics.K, dtype=np.float64)
    P = np.zeros((3, 4))
    P[:, :3] = K
    s = "sensor_msgs/msg/"
    return _T(s + "CameraInfo")(
        header=header(t_ns, frame_id), height=intrinsics.height, width=intrinsics.width,
        distortion_model="plumb_bob", d=np.asarray(intrinsics.dist, dtype=np.float64).copy(), k=K.reshape(9).copy(),
        r=np.eye(3).reshape(9), p=P.reshape(12), binning_x=0, binning_y=0,
        roi=_T(s + "RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def _vec3(v):
    return _T("geometry_msgs/msg/Vector3")(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def twist_stamped(t_ns: int, v: np.ndarray, w: np.ndarray, frame_id: str = WORLD):
    g = "geometry_msgs/msg/"
    return _T(g + "TwistStamped")(header=header(t_ns, frame_id), twist=_T(g + "Twist")(linear=_vec3(v), angular=_vec3(w)))


def vector3_stamped(t_ns: int, v: np.ndarray, frame_id: str = WORLD):
    return _T("geometry_msgs/msg/Vector3Stamped")(header=header(t_ns, frame_id), vector=_vec3(v))


def joint_state(t_ns: int, names, position=None, velocity=None):
    empty = np.zeros(0)
    f = lambda a: empty if a is None else np.asarray(a, dtype=np.float64).copy()  # noqa: E731
    return _T("sensor_msgs/msg/JointState")(header=header(t_ns, ""), name=list(names), position=f(position),
                                            velocity=f(velocity), effort=empty)


def scalar_msg(typename: str, value):
    """A ``std_msgs`` scalar (``std_msgs/msg/Int8``, ``Int32``, ``Float64``...)."""
    return _T(typename)(data=value)


def string_msg(text: str):
    return _T("std_msgs/msg/String")(data=text)
