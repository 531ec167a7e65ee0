"""Tracker output, ``poses.csv`` (shared/spec/recording.md, "Tracker output").

``index,t,x,y,z,qw,qx,qy,qz,status`` then extra columns readers may ignore:
``time_ms`` (the frame's processing time, image decoding excluded), the
velocity ``vx,vy,vz,wx,wy,wz`` (world frame, m/s and rad/s) and the 6x6 pose
covariance as its 21 upper-triangle entries ``P00,P01,...,P55`` in the order
[position (m), orientation error (rad)], the orientation error being the
rotation vector ``log(R_true @ R_est.T)`` (a left, world-frame perturbation),
then ``probability``: the probability that the row's pose is the part's
(:attr:`vespro.tracker.TrackerOutput.probability`; empty where the tracker
does not state one).
Rows whose status is not ``tracking`` may leave the pose fields empty.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .se3 import pq_from_transform, transform_from_pq

__all__ = ["PoseRow", "STATUSES", "write_poses", "read_poses", "COV_COLUMNS"]

STATUSES = ("tracking", "initializing", "lost")
BASE = ["index", "t", "x", "y", "z", "qw", "qx", "qy", "qz", "status"]
VEL = ["vx", "vy", "vz", "wx", "wy", "wz"]
_IU = np.triu_indices(6)
COV_COLUMNS = [f"P{i}{j}" for i, j in zip(*_IU)]


@dataclass(frozen=True)
class PoseRow:
    """One frame of tracker output.

    Attributes
    ----------
    index : int
    t : float
        Capture time, s.
    status : str
        ``tracking``, ``initializing`` or ``lost``.
    T_world_object : ndarray (4, 4) or None
    time_ms : float or None
    velocity : ndarray (6,) or None
        ``[v (m/s), w (rad/s)]``, world frame.
    cov : ndarray (6, 6) or None
    probability : float or None
        That the pose is the part's (None: not stated).
    """

    index: int
    t: float
    status: str
    T_world_object: np.ndarray | None = None
    time_ms: float | None = None
    velocity: np.ndarray | None = None
    cov: np.ndarray | None = None
    probability: float | None = None

    def __post_init__(self):
        if self.status not in STATUSES:
            raise ValueError(f"status must be one of {STATUSES}, got {self.status!r}")


def _f(x: float) -> str:
    return f"{x:.9g}"


def write_poses(path: str | Path, rows) -> None:
    """Write rows (``PoseRow``) to ``poses.csv``."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(BASE + ["time_ms"] + VEL + COV_COLUMNS + ["probability"])
        for r in rows:
            pose = [""] * 7 if r.T_world_object is None else [_f(v) for v in pq_from_transform(r.T_world_object)]
            tm = "" if r.time_ms is None else f"{r.time_ms:.3f}"
            vel = [""] * 6 if r.velocity is None else [_f(v) for v in r.velocity]
            cov = [""] * 21 if r.cov is None else [_f(v) for v in np.asarray(r.cov)[_IU]]
            prob = "" if r.probability is None or not np.isfinite(r.probability) else f"{r.probability:.6g}"
            w.writerow([str(r.index), f"{r.t:.9f}"] + pose + [r.status, tm] + vel + cov + [prob])


def read_poses(path: str | Path) -> list[PoseRow]:
    """Read a ``poses.csv`` (ours or another tool's: unknown columns are ignored).

    Raises
    ------
    ValueError
        Missing columns or malformed values (the message names file and line).
    """
    p = Path(path)
    with open(p, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in BASE if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{p}: missing column(s) {', '.join(missing)}")
        out = []
        for line, d in enumerate(reader, start=2):
            try:
                status = d["status"].strip()
                T = None
                if all(d[c].strip() for c in BASE[2:9]):
                    T = transform_from_pq(np.array([float(d[c]) for c in BASE[2:9]]))
                tm = float(d["time_ms"]) if d.get("time_ms", "").strip() else None
                vel = np.array([float(d[c]) for c in VEL]) if all((d.get(c) or "").strip() for c in VEL) else None
                cov = None
                if all((d.get(c) or "").strip() for c in COV_COLUMNS):
                    cov = np.zeros((6, 6))
                    cov[_IU] = [float(d[c]) for c in COV_COLUMNS]
                    cov = cov + np.triu(cov, 1).T
                prob = float(d["probability"]) if (d.get("probability") or "").strip() else None
                out.append(PoseRow(int(d["index"]), float(d["t"]), status, T, tm, vel, cov, prob))
            except (ValueError, TypeError, AttributeError) as e:
                raise ValueError(f"{p}: line {line}: {e}") from None
            if status == "tracking" and T is None:
                raise ValueError(f"{p}: line {line}: status 'tracking' needs a pose")
    return out
