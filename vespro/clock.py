"""Time as a parameter: one interface for simulated and wall-clock time.

Every loop in the project (capture, tracker, pose server, servo) takes a
:class:`Clock`. ``SimClock`` advances only when the simulation steps it
(lockstep with MuJoCo), ``WallClock`` follows ``time.monotonic_ns``. The loop
code is the same for both, so a virtual-mode demo runs the real-mode code path.

Times are integer nanoseconds (``t_ns``), as ``time.monotonic_ns`` gives them.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "SimClock", "WallClock", "NS_PER_S", "seconds", "ns_from_s"]

NS_PER_S = 1_000_000_000


def seconds(t_ns: int) -> float:
    """Nanoseconds to seconds (float)."""
    return t_ns / NS_PER_S


def ns_from_s(t_s: float) -> int:
    """Seconds to integer nanoseconds, rounded to the nearest."""
    return int(round(t_s * NS_PER_S))


@runtime_checkable
class Clock(Protocol):
    """What a loop needs from time."""

    def now_ns(self) -> int:
        """Current time, ns."""
        ...

    def sleep_until(self, t_ns: int) -> int:
        """Block until ``t_ns`` (no-op if past); returns the time on waking, ns."""
        ...


class SimClock:
    """Simulated time, advanced explicitly by the simulation.

    ``sleep_until`` in a single-threaded lockstep loop simply advances the clock
    to the deadline (time jumps, nobody waits). With ``blocking=True`` a waiting
    thread instead blocks until another thread advances the clock past the
    deadline, which lets threaded code run in lockstep with a simulator.
    """

    def __init__(self, t0_ns: int = 0, blocking: bool = False):
        self._t_ns = int(t0_ns)
        self._blocking = blocking
        self._cond = threading.Condition()

    def now_ns(self) -> int:
        return self._t_ns

    def advance(self, dt_ns: int) -> int:
        """Move time forward by ``dt_ns`` (>= 0); returns the new time."""
        if dt_ns < 0:
            raise ValueError(f"simulated time cannot go backwards (dt_ns={dt_ns})")
        with self._cond:
            self._t_ns += int(dt_ns)
            self._cond.notify_all()
        return self._t_ns

    def set(self, t_ns: int) -> None:
        """Jump to ``t_ns`` (must not be earlier than now)."""
        self.advance(int(t_ns) - self._t_ns)

    def sleep_until(self, t_ns: int) -> int:
        if self._blocking:
            with self._cond:
                while self._t_ns < t_ns:
                    self._cond.wait(timeout=1.0)
            return self._t_ns
        if t_ns > self._t_ns:
            self.advance(t_ns - self._t_ns)
        return self._t_ns


class WallClock:
    """The monotonic wall clock.

    ``sleep_until`` sleeps to ``spin_ns`` before the deadline, then spins, which
    keeps period jitter in the microseconds on a pinned core (OS sleeps
    overshoot by 50-100 us).
    """

    def __init__(self, spin_ns: int = 200_000):
        self.spin_ns = int(spin_ns)

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until(self, t_ns: int) -> int:
        now = time.monotonic_ns()
        remaining = t_ns - now - self.spin_ns
        if remaining > 0:
            time.sleep(remaining / NS_PER_S)
        now = time.monotonic_ns()
        while now < t_ns:
            now = time.monotonic_ns()
        return now
