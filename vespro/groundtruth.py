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

from .errors import InputError
from .se3 import pq_from_transform, transform_from_pq

__all__ = ["GroundTruthWriter", "GroundTruthError", "read_groundtruth", "truth_per_frame", "gap_rows", "HEADER",
           "DistractorWriter", "read_distractors", "DISTRACTOR_HEADER"]

HEADER = ["index", "t", "x", "y", "z", "qw", "qx", "qy", "qz"]
DISTRACTOR_HEADER = ["index", "t", "name", "kind", "x", "y", "z", "qw", "qx", "qy", "qz", "cx", "cy", "cz"]


class GroundTruthError(InputError):
    """A malformed ``groundtruth.csv``; the message names the file, line and field."""


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


def read_groundtruth(recording_path: str | Path, allow_gaps: bool = False
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read ``groundtruth.csv``.

    Parameters
    ----------
    recording_path : path
    allow_gaps : bool
        Rows whose pose is not finite (``nan``: a motion-capture dropout) come
        back as all-NaN matrices instead of raising; the caller skips them
        (:func:`gap_rows`).

    Returns
    -------
    index : ndarray (N,), int
    t : ndarray (N,), s
    T_world_object : ndarray (N, 4, 4)

    Raises
    ------
    FileNotFoundError
        The recording has no ground truth.
    GroundTruthError
        Malformed header or row (the message names the file, line and field).
    """
    p = Path(recording_path) / "groundtruth.csv"
    if not p.is_file():
        raise FileNotFoundError(f"{p}: this recording has no ground truth")
    with open(p, newline="") as f:
        rows = [r for r in csv.reader(f) if r]
    if not rows or [h.strip() for h in rows[0][:9]] != HEADER:
        got = ",".join(rows[0][:9]) if rows else "an empty file"
        raise GroundTruthError(f"{p}: header must be {','.join(HEADER)}, got {got!r}")
    n = len(rows) - 1
    index = np.empty(n, dtype=np.int64)
    t = np.empty(n)
    T = np.empty((n, 4, 4))
    for k, r in enumerate(rows[1:]):
        line = k + 2
        if len(r) < 9:
            raise GroundTruthError(f"{p}: line {line}: expected 9 fields {','.join(HEADER)}, got {len(r)}")
        vals = []
        for name, x in zip(HEADER, r[:9]):
            try:
                vals.append(float(x))
            except ValueError:
                raise GroundTruthError(f"{p}: line {line}: field '{name}' is not a number: {x!r}") from None
        if vals[0] != k:
            raise GroundTruthError(f"{p}: line {line}: field 'index' is {r[0].strip()} where {k} was due "
                                   "(one row per frame index, from 0, in order)")
        if not np.isfinite(vals[1]):
            raise GroundTruthError(f"{p}: line {line}: field 't' is not finite: {r[1]!r}")
        index[k], t[k] = k, vals[1]
        pq = np.array(vals[2:9])
        if not np.all(np.isfinite(pq)):
            if not allow_gaps:
                bad = ", ".join(f for f, v in zip(HEADER[2:], pq) if not np.isfinite(v))
                raise GroundTruthError(f"{p}: line {line}: field(s) {bad} not finite; a frame without ground "
                                       "truth cannot be scored: remove its pose or give a finite one")
            T[k] = np.nan
            continue
        if np.linalg.norm(pq[3:]) < 1e-9:
            raise GroundTruthError(f"{p}: line {line}: quaternion qw,qx,qy,qz is zero")
        T[k] = transform_from_pq(pq)
    return index, t, T


def gap_rows(T_world_object: np.ndarray) -> np.ndarray:
    """Row positions whose ground truth is missing (not finite), as read with ``allow_gaps``."""
    T = np.asarray(T_world_object)
    return np.flatnonzero(~np.all(np.isfinite(T.reshape(len(T), -1)), axis=1))


def truth_per_frame(recording_path: str | Path, n_frames: int, warn=None, need_first: str | None = None) -> np.ndarray:
    """The true pose of each of a recording's ``n_frames`` frames, NaN where the file has none.

    Rows past ``n_frames`` (a frames.csv cut short) are dropped; each frame
    without a finite pose is left for the caller to skip. Both are said through
    ``warn(line)``.

    Parameters
    ----------
    need_first : str, optional
        The option that starts from frame 0's true pose (e.g. ``--gt-init``):
        frame 0 must then have one.

    Raises
    ------
    FileNotFoundError
        No ``groundtruth.csv``.
    GroundTruthError
        Malformed, fewer rows than frames, or no pose at frame 0 when ``need_first``.
    """
    p = Path(recording_path) / "groundtruth.csv"
    _, _, T = read_groundtruth(recording_path, allow_gaps=True)
    warn = warn or (lambda line: None)
    if len(T) < n_frames:
        raise GroundTruthError(f"{p}: {len(T)} rows for the {n_frames} frames of frames.csv; give one row per "
                               "frame (nan pose fields where a frame has no ground truth)")
    if len(T) > n_frames:
        warn(f"{p}: {len(T)} rows for the {n_frames} frames of frames.csv: rows past index {n_frames - 1} "
             "are not used")
        T = T[:n_frames]
    gaps = gap_rows(T)
    if need_first and gaps.size and gaps[0] == 0:
        raise GroundTruthError(f"{p}: line 2: no finite pose at index 0, which {need_first} starts from; give "
                               "--init-pose x,y,z,qw,qx,qy,qz instead")
    if gaps.size:
        shown = ", ".join(f"{i} (line {i + 2})" for i in gaps[:5]) + (f" and {gaps.size - 5} more" if gaps.size > 5 else "")
        warn(f"{p}: no finite pose at index {shown}: {gaps.size} of {n_frames} frames have no ground truth and are skipped")
    return T


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
