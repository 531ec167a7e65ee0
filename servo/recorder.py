"""Time history of chosen loop variables in preallocated memory, saved at the end.

During the run a row is claimed with :meth:`Recorder.next_row` and written in
place (``rec.data[name][row] = value``): no allocation, no I/O. :meth:`save`
writes NPZ (exact, one array per channel) plus CSV (one column per scalar,
multi-dimensional channels flattened as ``name_0, name_1, ...``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["Recorder", "LOOP_CHANNELS"]

#: The channels the :class:`~servo.loop.Scheduler` fills when present.
LOOP_CHANNELS = {
    "t_ns": ((), np.int64),
    "q_cmd": ((6,), np.float64),
    "qd_cmd": ((6,), np.float64),
    "q_meas": ((6,), np.float64),
    "p_ref": ((3,), np.float64),
    "quat_ref": ((4,), np.float64),
    "v_ref": ((3,), np.float64),
    "status": ((), np.int8),
    "flags": ((), np.int32),  # servo.safety.Check bits fired this tick
    "reject": ((), np.int8),  # servo.safety.Reject code of a pose not used this tick (0: none)
    "trip_value": ((), np.float64),  # what tripped the first check in flags (NaN: nothing), SI
    "trip_limit": ((), np.float64),  # its limit
    "compute_ns": ((), np.int64),
}


class Recorder:
    """Fixed-capacity recorder.

    Parameters
    ----------
    capacity : int
        Maximum number of rows (ticks); further rows are dropped and counted.
    channels : dict name -> (shape, dtype)
        Per-row shape of each channel (``()`` for a scalar).
    """

    def __init__(self, capacity: int, channels: dict | None = None):
        channels = LOOP_CHANNELS if channels is None else channels
        self.capacity = int(capacity)
        self.channels = dict(channels)
        self.data = {
            name: np.zeros((self.capacity, *tuple(shape)), dtype=dtype) for name, (shape, dtype) in self.channels.items()
        }
        for a in self.data.values():
            a.fill(0)  # touch every page now: no page faults in the loop, flat resident memory
        self.n = 0
        self.dropped = 0

    def next_row(self) -> int:
        """Claim the next row; returns its index, or -1 when full (counted in ``dropped``)."""
        if self.n >= self.capacity:
            self.dropped += 1
            return -1
        self.n += 1
        return self.n - 1

    def append(self, **values) -> int:
        """Claim a row and write the given channels (convenience outside the hot path)."""
        row = self.next_row()
        if row >= 0:
            for k, v in values.items():
                self.data[k][row] = v
        return row

    def arrays(self) -> dict:
        """The recorded rows (views), name -> (n, *shape)."""
        return {k: v[: self.n] for k, v in self.data.items()}

    def save(self, path_stem) -> tuple[Path, Path]:
        """Write ``<stem>.npz`` and ``<stem>.csv``; returns both paths."""
        stem = Path(path_stem)
        stem.parent.mkdir(parents=True, exist_ok=True)
        npz = stem.with_suffix(".npz")
        csv = stem.with_suffix(".csv")
        arrays = self.arrays()
        np.savez(npz, **arrays)
        cols, names = [], []
        for k, v in arrays.items():
            flat = v.reshape(self.n, -1)
            if v.ndim == 1:
                names.append(k)
            else:
                names.extend(f"{k}_{i}" for i in range(flat.shape[1]))
            cols.append(flat)
        if cols:
            table = np.concatenate([c.astype(object) for c in cols], axis=1) if self.n else np.zeros((0, len(names)))
        with open(csv, "w") as f:
            f.write(",".join(names) + "\n")
            for r in range(self.n):
                f.write(",".join(_fmt(x) for x in table[r]) + "\n")
        return npz, csv


def _fmt(x) -> str:
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    return repr(float(x))
