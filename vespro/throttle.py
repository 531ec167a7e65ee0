"""Log lines of a long-running loop, at most one per kind and period.

A loop that meets the same condition every frame (a camera gone, an initialiser
finding nothing) must not write a line every frame: 23,093 identical lines in a
minute hide the one line that says what happened. :class:`LogThrottle` lets the
first line of each kind through, holds back the repeats for ``period_s`` and
says how many it held with the next line of that kind.
"""

from __future__ import annotations

from typing import Callable

__all__ = ["LogThrottle"]


class LogThrottle:
    """At most one line per key every ``period_s`` on ``clock_ns``'s time.

    Parameters
    ----------
    log : callable or None
        Receives the lines let through (None: nothing is written).
    clock_ns : callable
        Time, ns (a :class:`~vespro.clock.Clock`'s ``now_ns``).
    period_s : float
    """

    MAX_KEYS = 256  # the keys are kinds of line, a handful; forgotten past this many

    def __init__(self, log: Callable[[str], None] | None, clock_ns: Callable[[], int], period_s: float = 1.0):
        self.log = log
        self.clock_ns = clock_ns
        self.period_ns = int(period_s * 1e9)
        self._seen: dict = {}  # key -> [time of the last line let through, repeats held since]
        self.held = 0  # lines held back in all

    def __call__(self, key, line: str) -> bool:
        """Write ``line`` unless a line of ``key`` went out less than ``period_s`` ago; True if written."""
        now = self.clock_ns()
        seen = self._seen.get(key)
        if seen is not None and now - seen[0] < self.period_ns:
            seen[1] += 1
            self.held += 1
            return False
        if seen is not None and seen[1]:
            line += f" (and {seen[1]} more like it in the last {(now - seen[0]) * 1e-9:.0f} s)"
        if len(self._seen) >= self.MAX_KEYS:
            self._seen.clear()
        self._seen[key] = [now, 0]
        if self.log is not None:
            self.log(line)
        return True
