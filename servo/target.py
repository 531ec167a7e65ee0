"""The object pose sample the servo consumes (vision side -> control side).

An adapter from the ``vespro.wire`` message is written later; the loop only
sees :class:`TargetSample`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

__all__ = ["SampleStatus", "TargetSample", "target_sample_from_transform"]


class SampleStatus(enum.IntEnum):
    """Tracker status carried with each pose."""

    OK = 0
    COASTING = 1  # predicted without a fresh measurement; usable, flagged
    LOST = 2  # no valid pose: treated as "no sample" by the servo


def _ro(a, shape, name) -> np.ndarray:
    a = np.array(a, dtype=float)  # copy: the sample owns its arrays
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class TargetSample:
    """One object pose estimate, stamped at image capture.

    Attributes
    ----------
    t_capture_ns : int
        Capture time of the image the pose comes from, ns, on the shared
        monotonic clock.
    p_world_object : ndarray, shape (3,)
        Object origin in the world frame, m.
    q_world_object : ndarray, shape (4,)
        Object orientation in the world frame, unit quaternion (w, x, y, z).
    v_world_object : ndarray, shape (3,)
        Linear velocity of the object origin, world frame, m/s.
    w_world_object : ndarray, shape (3,)
        Angular velocity, world frame, rad/s.
    cov : ndarray, shape (6, 6)
        Pose covariance, [position (m^2); rotation vector (rad^2)], world frame.
    status : SampleStatus
    seq : int
        Sequence number from the sender (diagnostics only).

    Non-finite values are allowed here (a corrupt message is a normal input);
    the servo checks finiteness per tick and treats such a sample as invalid.
    """

    t_capture_ns: int
    p_world_object: np.ndarray
    q_world_object: np.ndarray
    v_world_object: np.ndarray
    w_world_object: np.ndarray
    cov: np.ndarray
    status: SampleStatus = SampleStatus.OK
    seq: int = 0

    def __post_init__(self):
        object.__setattr__(self, "t_capture_ns", int(self.t_capture_ns))
        object.__setattr__(self, "p_world_object", _ro(self.p_world_object, (3,), "p_world_object"))
        object.__setattr__(self, "q_world_object", _ro(self.q_world_object, (4,), "q_world_object"))
        object.__setattr__(self, "v_world_object", _ro(self.v_world_object, (3,), "v_world_object"))
        object.__setattr__(self, "w_world_object", _ro(self.w_world_object, (3,), "w_world_object"))
        object.__setattr__(self, "cov", _ro(self.cov, (6, 6), "cov"))
        object.__setattr__(self, "status", SampleStatus(self.status))

    @property
    def T_world_object(self) -> np.ndarray:
        """Pose as a (4, 4) transform (allocates; not for the 500 Hz path)."""
        from .rotation import matrix_from_quat

        T = np.eye(4)
        T[:3, :3] = matrix_from_quat(self.q_world_object)
        T[:3, 3] = self.p_world_object
        return T


def target_sample_from_transform(
    t_capture_ns: int,
    T_world_object: np.ndarray,
    v_world_object=(0.0, 0.0, 0.0),
    w_world_object=(0.0, 0.0, 0.0),
    cov=None,
    status: SampleStatus = SampleStatus.OK,
    seq: int = 0,
) -> TargetSample:
    """Build a :class:`TargetSample` from a (4, 4) ``T_world_object``."""
    from .rotation import quat_from_matrix

    T = np.asarray(T_world_object, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"T_world_object: expected shape (4, 4), got {T.shape}")
    return TargetSample(
        t_capture_ns,
        T[:3, 3],
        quat_from_matrix(np.ascontiguousarray(T[:3, :3])),
        v_world_object,
        w_world_object,
        np.eye(6) * 1e-8 if cov is None else cov,
        status,
        seq,
    )
