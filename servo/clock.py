"""Time as a parameter for the servo loop: simulated or wall-clock.

Same idea as ``vespro.clock`` (the servo package must not import ``vespro``
beyond ``vespro.wire``): ``SimClock`` advances only when the simulation steps
it (lockstep with MuJoCo), ``WallClock`` follows ``time.monotonic_ns``. The
scheduler is the same code for both.

Times are integer nanoseconds (``t_ns``).
"""

from __future__ import annotations

import time
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "SimClock", "WallClock", "NS_PER_S"]

NS_PER_S = 1_000_000_000


@runtime_checkable
class Clock(Protocol):
    """What the scheduler needs from time."""

    def now_ns(self) -> int:
        """Current time, ns."""
        ...

    def sleep_until(self, t_ns: int) -> int:
        """Block until ``t_ns`` (no-op if past); returns the time on waking, ns."""
        ...


class SimClock:
    """Simulated time: ``sleep_until`` jumps to the deadline (lockstep, nobody waits)."""

    realtime = False

    def __init__(self, t0_ns: int = 0):
        self._t_ns = int(t0_ns)

    def now_ns(self) -> int:
        return self._t_ns

    def advance(self, dt_ns: int) -> int:
        """Move time forward by ``dt_ns`` (>= 0); returns the new time, ns."""
        if dt_ns < 0:
            raise ValueError(f"simulated time cannot go backwards (dt_ns={dt_ns})")
        self._t_ns += int(dt_ns)
        return self._t_ns

    def sleep_until(self, t_ns: int) -> int:
        if t_ns > self._t_ns:
            self._t_ns = int(t_ns)
        return self._t_ns


class WallClock:
    """The monotonic wall clock; sleeps to ``spin_ns`` before the deadline, then spins.

    OS sleeps overshoot by 50-100 us (more under load); the final spin keeps the
    wake-up error in the microseconds on a pinned core.
    """

    realtime = True

    def __init__(self, spin_ns: int = 300_000):
        self.spin_ns = int(spin_ns)

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until(self, t_ns: int) -> int:
        remaining = t_ns - time.monotonic_ns() - self.spin_ns
        if remaining > 0:
            time.sleep(remaining / NS_PER_S)
        now = time.monotonic_ns()
        while now < t_ns:
            now = time.monotonic_ns()
        return now
