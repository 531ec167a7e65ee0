"""Ground truth (``groundtruth.csv``, ``distractors.csv``): for the simulator's writer and evaluators only.

No tracker, initialiser or server code may import this module (a test checks
the import graph). ``groundtruth.csv``: ``index,t,x,y,z,qw,qx,qy,qz`` is the
object's true ``T_world_object`` at each capture instant. ``distractors.csv``
(only in recordings with distractors, :mod:`vespro.sim.distractors`):
``index,t,name,kind,x,y,z,qw,qx,qy,qz,cx,cy,cz``, one row per distractor and
capture instant: its true ``T_world_distractor`` (the frame its shape is drawn
in) and the world position of its shape's centre, m.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from .se3 import pq_from_transform, transform_from_pq

__all__ = ["GroundTruthWriter", "read_groundtruth", "HEADER", "DistractorWriter", "read_distractors",
           "DISTRACTOR_HEADER"]

HEADER = ["index", "t", "x", "y", "z", "qw", "qx", "qy", "qz"]
DISTRACTOR_HEADER = ["index", "t", "name", "kind", "x", "y", "z", "qw", "qx", "qy", "qz", "cx", "cy", "cz"]


class _CsvWriter:
    """A CSV file of a recording, its header written first; a context manager."""

    FILE = ""
    COLUMNS: list = []

    def __init__(self, recording_path: str | Path):
        self._f = open(Path(recording_path) / self.FILE, "w", newline="")
        self._w = csv.writer(self._f, lineterminator="\n")
        self._w.writerow(self.COLUMNS)

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class GroundTruthWriter(_CsvWriter):
    """Append true object poses to ``<recording>/groundtruth.csv``."""

    FILE, COLUMNS = "groundtruth.csv", HEADER

    def write(self, index: int, t: float, T_world_object: np.ndarray) -> None:
        self._w.writerow([str(index), f"{t:.9f}"] + [f"{v:.9f}" for v in pq_from_transform(T_world_object)])


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


class DistractorWriter(_CsvWriter):
    """Append true distractor poses to ``<recording>/distractors.csv``."""

    FILE, COLUMNS = "distractors.csv", DISTRACTOR_HEADER

    def write(self, index: int, t: float, name: str, kind: str, T_world_distractor: np.ndarray,
              center_world: np.ndarray) -> None:
        self._w.writerow([str(index), f"{t:.9f}", name, kind]
                         + [f"{v:.9f}" for v in pq_from_transform(T_world_distractor)]
                         + [f"{v:.9f}" for v in center_world])


def read_distractors(recording_path: str | Path) -> dict[str, dict]:
    """Read ``distractors.csv`` (an empty dict when the recording has none).

    Returns
    -------
    dict
        ``{name: {"kind": str, "index": (N,) int, "T": (N, 4, 4), "center": (N, 3)}}``.

    Raises
    ------
    ValueError
        Malformed header or row (the message names the file and line).
    """
    p = Path(recording_path) / "distractors.csv"
    if not p.is_file():
        return {}
    with open(p, newline="") as f:
        rows = [r for r in csv.reader(f) if r]
    if not rows or [h.strip() for h in rows[0]] != DISTRACTOR_HEADER:
        raise ValueError(f"{p}: header must be {','.join(DISTRACTOR_HEADER)}")
    acc: dict[str, dict] = {}
    for k, r in enumerate(rows[1:]):
        try:
            if len(r) != len(DISTRACTOR_HEADER):
                raise ValueError
            vals = [float(x) for x in r[4:]]
            T = transform_from_pq(np.array(vals[:7]))
            index = int(r[0])
        except ValueError:
            raise ValueError(f"{p}: line {k + 2}: expected index,t,name,kind and 10 numbers") from None
        d = acc.setdefault(r[2], {"kind": r[3], "index": [], "T": [], "center": []})
        d["index"].append(index)
        d["T"].append(T)
        d["center"].append(vals[7:])
    return {n: {"kind": d["kind"], "index": np.array(d["index"], dtype=np.int64), "T": np.array(d["T"]),
                "center": np.array(d["center"])} for n, d in acc.items()}
