"""The simulated world's state in shared memory: what the plant writes and the cameras render from.

The plant process (``python -m cellsim.plant``) writes the arm's joints and the
object's pose at every physics step; the pose server's world source
(:class:`vespro.sources.WorldSource`) reads them at each capture instant and
renders its camera images from them. A seqlock guards the block (the writer
makes the counter odd while writing; a reader retries until it sees the same
even counter before and after copying), so neither side waits for the other.
"""

from __future__ import annotations

import numpy as np

from rtkit.shm import SharedBlock  # one lifecycle for shared-memory blocks

__all__ = ["WorldShm"]


class WorldShm(SharedBlock):
    """World state for the cameras: seqlock, t_ns, q (6), object pose (7), t0_ns, running.

    Layout (float64 words): ``0`` seqlock, ``1`` t_ns, ``2:8`` q, ``8:15`` object
    ``x y z qw qx qy qz``, ``15`` the plant's start time t0_ns, ``16`` running
    (1.0 while stepping, 0.0 before start and after the end), ``17`` the step index.
    """

    SIZE = 18

    def __init__(self, name: str | None = None):
        super().__init__(name, self.SIZE)

    def write(self, t_ns: int, q: np.ndarray, pq_object: np.ndarray, step: int) -> None:
        a = self.a
        a[0] += 1.0
        a[1] = float(t_ns)
        a[2:8] = q
        a[8:15] = pq_object
        a[17] = float(step)
        a[0] += 1.0

    def read(self) -> tuple[int, np.ndarray, np.ndarray, int] | None:
        """``(t_ns, q, pq_object, step)``, or None if never written."""
        a = self.a
        for _ in range(1000):
            s1 = a[0]
            if s1 == 0.0:
                return None
            if int(s1) % 2:
                continue
            v = a[1:18].copy()
            if a[0] == s1:
                return int(v[0]), v[1:7], v[7:14], int(v[16])
        return None

    @property
    def t0_ns(self) -> int:
        return int(self.a[15])

    @property
    def running(self) -> bool:
        return bool(self.a[16] > 0.5)

    @property
    def finished(self) -> bool:
        """The plant ran and has stopped."""
        return self.a[15] > 0 and not self.running
