"""A robot on the other side of a shared-memory "fieldbus".

The simulated cell runs its physics in its own process (as a real arm runs in
its own controller); the servo reaches it through a small shared-memory block,
as it would reach real drives through a fieldbus: the plant writes measured
joint positions and velocities, the servo writes commanded positions and
velocities and the drives-on flag. Each side's block is guarded by a seqlock
(the writer makes the counter odd while writing; a reader retries until it sees
the same even counter before and after copying), so neither side ever waits
for the other.

Layout (float64 words; ``n`` joints)::

    0               plant seqlock counter
    1               plant time t_ns (as float64: exact to 2**53 ns, 104 days)
    2 .. 2+n        q_measured, rad
    2+n .. 2+2n     qd_measured, rad/s
    2+2n            servo seqlock counter
    3+2n            command time t_ns
    4+2n .. 4+3n    q_command, rad
    4+3n .. 4+4n    qd_command, rad/s
    4+4n            drives on (1.0) / off (0.0)
    5+4n            plant alive flag (1.0 while the plant runs; 0.0 when it stops)
"""

from __future__ import annotations

import time

import numpy as np

from rtkit.shm import SharedBlock  # one lifecycle for shared-memory blocks

__all__ = ["RobotShm", "ShmArm"]


class RobotShm(SharedBlock):
    """The robot's shared block, from either side.

    Parameters
    ----------
    name : str or None
        Attach to an existing block; None creates a new one (see :attr:`name`).
    n : int
        Number of joints.
    """

    def __init__(self, name: str | None = None, n: int = 6):
        self.n = n
        super().__init__(name, 6 + 4 * n)
        self._i_cmd = 2 + 2 * n

    # -- generic seqlock ------------------------------------------------------
    def _write(self, seq_index: int, values: np.ndarray) -> None:
        a = self.a
        a[seq_index] += 1.0
        a[seq_index + 1: seq_index + 1 + values.size] = values
        a[seq_index] += 1.0

    def _read(self, seq_index: int, size: int, out: np.ndarray, tries: int = 1000) -> bool:
        a = self.a
        for _ in range(tries):
            s1 = a[seq_index]
            if s1 == 0.0:
                return False  # never written: no data yet (not all zeros)
            if int(s1) % 2:
                continue
            out[:] = a[seq_index + 1: seq_index + 1 + size]
            if a[seq_index] == s1:
                return True
        return False

    # -- plant side ------------------------------------------------------------
    def write_state(self, t_ns: int, q: np.ndarray, qd: np.ndarray) -> None:
        self._write(0, np.concatenate([[float(t_ns)], q, qd]))

    def read_command(self, out: np.ndarray) -> bool:
        """``out`` (2 + 2n,): t_ns, q, qd, drives_on. False if never written or torn."""
        return self._read(self._i_cmd, 2 + 2 * self.n, out)

    def set_alive(self, alive: bool) -> None:
        self.a[-1] = 1.0 if alive else 0.0

    # -- servo side --------------------------------------------------------------
    def read_state(self, out: np.ndarray) -> bool:
        """``out`` (1 + 2n,): t_ns, q, qd."""
        return self._read(0, 1 + 2 * self.n, out)

    def write_command(self, t_ns: int, q: np.ndarray, qd: np.ndarray, drives_on: bool) -> None:
        self._write(self._i_cmd, np.concatenate([[float(t_ns)], q, qd, [1.0 if drives_on else 0.0]]))

    @property
    def plant_alive(self) -> bool:
        return bool(self.a[-1] > 0.5)


class ShmArm:
    """:class:`servo.robot.Robot` on a shared-memory fieldbus to a plant process.

    ``plant_step`` does nothing: the plant runs on its own, in real time.
    """

    def __init__(self, name: str, n: int = 6):
        self.shm = RobotShm(name, n)
        self.n = n
        self._state = np.zeros(1 + 2 * n)
        self._q = np.zeros(n)
        self._qd = np.zeros(n)
        self._drives = True
        self._t = 0
        self.came_up = None  # whether the plant was running when the loop started (wait_alive)

    def read(self, q_out: np.ndarray) -> None:
        if self.shm.read_state(self._state):
            q_out[:] = self._state[1:1 + self.n]
        # else: the plant has not published yet; q_out keeps its last value

    def command(self, q: np.ndarray, qd: np.ndarray) -> None:
        self._t += 1
        self._drives = True
        self.shm.write_command(self._t, q, qd, True)

    def stop(self) -> None:
        self._drives = False
        self.shm.read_state(self._state)
        self.shm.write_command(self._t, self._state[1:1 + self.n], np.zeros(self.n), False)

    def enable(self) -> None:
        self._drives = True

    def plant_step(self) -> None:
        pass

    @property
    def plant_alive(self) -> bool:
        return self.shm.plant_alive

    def wait_alive(self, timeout_s: float, poll_s: float = 0.001) -> bool:
        """Wait until the plant runs (its alive flag), at most ``timeout_s``; whether it does.

        A drive's controller comes up on its own time: the loop set up and locked in memory
        first, then waiting for it, starts ticking with nothing left to do but tick."""
        t_end = time.monotonic() + timeout_s
        while not self.shm.plant_alive and time.monotonic() < t_end:
            time.sleep(poll_s)
        self.came_up = self.shm.plant_alive
        return self.came_up

    def close(self) -> None:
        self.shm.close()
