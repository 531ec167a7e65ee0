"""The loop's timing policy: how many late ticks, how late, lead to what.

Industrial controllers tolerate a bounded number of missed cycles and stop in
a controlled way before they cut the drives. The servo loop does the same,
from the interval ``dt`` between two ticks (its own clock):

- ``dt`` up to ``late_tick_ticks`` periods (1.5, i.e. 3 ms): on time;
- longer: a *late tick*, counted and integrated with its real ``dt`` (the
  planner and the CLIK take the longer step; the joint velocity check is on
  ``dq / dt``, so it stays exact);
- more than ``max_late_ticks`` late ticks (10) within ``late_window_s`` (1 s),
  or one ``dt`` longer than ``stop_dt_ticks`` periods (10, i.e. 20 ms): a
  controlled stop, cause TIMING, drives on; tracking resumes by itself once
  ``late_window_s`` has passed without another such trip;
- one ``dt`` longer than ``max_dt_ticks`` periods (50, i.e. 100 ms), or a
  clock that does not advance: a FAULT, drives off, latched until reset.

The thresholds are fields of :class:`servo.loop.LoopConfig`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["TimingPolicy"]


class TimingPolicy:
    """Late-tick bookkeeping on preallocated memory.

    Parameters
    ----------
    period_ns : int
    late_tick_ticks, max_late_ticks, late_window_s, stop_dt_ticks, max_dt_ticks :
        see the module docstring.
    """

    def __init__(self, period_ns: int, late_tick_ticks: float, max_late_ticks: int, late_window_s: float,
                 stop_dt_ticks: int, max_dt_ticks: int):
        self.late_ns = int(late_tick_ticks * period_ns)
        self.stop_dt_ns = int(stop_dt_ticks * period_ns)
        self.max_dt_ns = int(max_dt_ticks * period_ns)
        self.window_ns = int(round(late_window_s * 1e9))
        self.max_late = int(max_late_ticks)
        self._ring = np.zeros(self.max_late + 1, np.int64)  # times of the last late ticks
        self.reset()

    def reset(self) -> None:
        self.n_late = 0
        self.hold_until_ns = 0  # no resume before this time after a timing stop

    def broken(self, dt_ns: int) -> bool:
        """A FAULT: the clock did not advance, or the interval is over ``max_dt_ticks`` periods."""
        return dt_ns <= 0 or dt_ns > self.max_dt_ns

    def late(self, dt_ns: int) -> bool:
        return dt_ns > self.late_ns

    def observe_late(self, t_ns: int, dt_ns: int) -> tuple[bool, float, float]:
        """Count a late tick at ``t_ns``; returns (stop, value, limit).

        value / limit: the tick's dt and ``stop_dt`` (s) for a single long
        tick; the number of late ticks in the window and ``max_late_ticks``
        for too many of them.
        """
        ring = self._ring
        ring[self.n_late % len(ring)] = t_ns
        self.n_late += 1
        if dt_ns > self.stop_dt_ns:
            trip, value, limit = True, dt_ns * 1e-9, self.stop_dt_ns * 1e-9
        elif self.n_late >= len(ring) and t_ns - ring[self.n_late % len(ring)] <= self.window_ns:
            trip, value, limit = True, float(len(ring)), float(self.max_late)
        else:
            return False, 0.0, 0.0
        self.hold_until_ns = t_ns + self.window_ns
        return trip, value, limit

    def resume_ok(self, t_ns: int) -> bool:
        """No timing stop within the last window."""
        return t_ns >= self.hold_until_ns
