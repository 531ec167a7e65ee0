"""Named shared-memory blocks of float64 words (or bytes): created by one process, attached by others.

What both sides' processes share in memory (the robot's fieldbus, the simulated
world's state) is built on :class:`SharedBlock`: one lifecycle, in which the
creator alone unlinks the block.
"""

from __future__ import annotations

from multiprocessing import shared_memory

import numpy as np

__all__ = ["SharedBlock"]


_CREATED: set = set()


def _untrack(shm) -> None:
    """Only the creator may unlink a block: before Python 3.13 merely attaching
    registers it with this process's resource tracker, which unlinks it at exit."""
    if shm._name in _CREATED:  # attached in the creating process: keep its registration
        return
    try:
        from multiprocessing import resource_tracker

        resource_tracker.unregister(shm._name, "shared_memory")
    except Exception:
        pass


class SharedBlock:
    """A block of float64 words in shared memory: created by one process, attached by others.

    The creator zeroes it and alone unlinks it at :meth:`close`; attaching never
    registers it for unlinking (see :func:`_untrack`). ``a`` is the word array.
    """

    def __init__(self, name: str | None, n_words: int):
        if name is None:
            self._shm = shared_memory.SharedMemory(create=True, size=8 * n_words)
            self.owner = True
            _CREATED.add(self._shm._name)
        else:
            self._shm = shared_memory.SharedMemory(name=name)
            self.owner = False
            _untrack(self._shm)
        self.a = np.ndarray((n_words,), dtype=np.float64, buffer=self._shm.buf)
        if self.owner:
            self.a[:] = 0.0

    @property
    def name(self) -> str:
        return self._shm.name

    @property
    def bytes(self) -> np.ndarray:
        """The whole block as bytes (uint8), for data other than words (images)."""
        return np.ndarray((self.a.size * 8,), dtype=np.uint8, buffer=self._shm.buf)

    def close(self) -> None:
        self.a = None
        self._shm.close()
        if self.owner:
            try:
                self._shm.unlink()
            except FileNotFoundError:
                pass
