"""Ground truth (``groundtruth.csv``): for the simulator's writer and evaluators only.

No tracker, initialiser or server code may import this module (a test checks
the import graph). ``index,t,x,y,z,qw,qx,qy,qz`` is the object's true
``T_world_object`` at each capture instant.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from .se3 import pq_from_transform, transform_from_pq

__all__ = ["GroundTruthWriter", "read_groundtruth", "HEADER"]

HEADER = ["index", "t", "x", "y", "z", "qw", "qx", "qy", "qz"]


class GroundTruthWriter:
    """Append true object poses to ``<recording>/groundtruth.csv``."""

    def __init__(self, recording_path: str | Path):
        self._f = open(Path(recording_path) / "groundtruth.csv", "w", newline="")
        self._w = csv.writer(self._f, lineterminator="\n")
        self._w.writerow(HEADER)

    def write(self, index: int, t: float, T_world_object: np.ndarray) -> None:
        self._w.writerow([str(index), f"{t:.9f}"] + [f"{v:.9f}" for v in pq_from_transform(T_world_object)])

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_groundtruth(recording_path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read ``groundtruth.csv``.

    Returns
    -------
    index : ndarray (N,), int
    t : ndarray (N,), s
    T_world_object : ndarray (N, 4, 4)

    Raises
    ------
    FileNotFoundError
        The recording has no ground truth.
    ValueError
        Malformed header or row (the message names the file, line and field).
    """
    p = Path(recording_path) / "groundtruth.csv"
    if not p.is_file():
        raise FileNotFoundError(f"{p}: this recording has no ground truth")
    with open(p, newline="") as f:
        rows = [r for r in csv.reader(f) if r]
    if not rows or [h.strip() for h in rows[0][:9]] != HEADER:
        raise ValueError(f"{p}: header must be {','.join(HEADER)}")
    n = len(rows) - 1
    index = np.empty(n, dtype=np.int64)
    t = np.empty(n)
    T = np.empty((n, 4, 4))
    for k, r in enumerate(rows[1:]):
        try:
            vals = [float(x) for x in r[:9]]
            if len(vals) < 9:
                raise ValueError
            T[k] = transform_from_pq(np.array(vals[2:9]))
        except ValueError:
            raise ValueError(f"{p}: line {k + 2}: expected 9 numbers with a non-zero quaternion") from None
        index[k], t[k] = int(vals[0]), vals[1]
    return index, t, T
