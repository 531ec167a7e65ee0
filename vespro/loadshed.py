"""A live loop that misses its capture deadlines says so and lowers its own load.

The pose server's live loop must take every capture instant (a frame set it
skips is a pose the servo never gets). On a machine too slow for all it was
asked to do, :class:`LoadShedder` counts the instants missed over a sliding
window and, once they pass ``max_missed_frac`` of the window's instants, takes the
next step of a fixed ladder, announces it (one log line) and records it:

1. record images at half the capture rate, then a quarter, then not at all
   (the recording keeps every frame set's row; the images skipped are missing,
   as the recording format allows);
2. drop one camera at a time (fixed cameras, last in the rig first, while another
   fixed one stays; then the eye-in-hand ones; never the last camera): it is no
   longer captured (rendered), tracked or recorded.

The window is long enough to tell a rate of misses from a single one: at 1% over
8 s (208 instants at 26 Hz) the third miss steps down. Over 2 s the allowance is
half a miss, so any one miss, however rare (a stall of the machine), took a
step, and the demo shed its recording and a camera for misses that stayed under
1% of its instants. Misses count against the whole window's allowance from the
start, so a loop missing a third of its instants steps down within a fraction
of a second. After a step the count starts again, so a step is taken only when
the load it left still misses. Misses while the loop's own work (``busy_ms``: capture, tracking,
publishing, recording) stays well inside the period come from outside the loop
(other work stalling it): shedding would not help, so they are reported (a
"stall" step that changes nothing) and nothing is shed. A step is taken back,
last first, once ``recover_s`` have passed without a miss and the loop's work,
scaled up by what the step took away, would still fit in ``recover_frac`` of the
period (the load a busy start, such as the initialiser's search, forced down
comes back when it is over).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

__all__ = ["LoadShedder", "LoadStep"]


@dataclass(frozen=True)
class LoadStep:
    """One step down: when (capture stamp, ns), what, and the misses that caused it."""

    t_ns: int
    what: str
    missed: int
    instants: int
    kind: str = "down"  # "down", "up" (a step taken back) or "stall" (nothing changed)


@dataclass
class LoadShedder:
    """Missed-deadline watch and load ladder of a live loop.

    Parameters
    ----------
    rate_hz : float
        Capture rate.
    cameras : sequence of (name, fixed)
        The rig's cameras in order.
    window_s : float
        Sliding window over which misses are counted, s.
    max_missed_frac : float
        Step down when the misses in the window pass this fraction of its capture
        instants (``window_s`` times the rate).
    record_steps : tuple of int
        Image recording periods to go through (1: every frame set; 0: none).
    stall_frac : float
        Misses while the window's 90th percentile of the loop's work is under this
        fraction of the period are stalls from outside: reported, nothing shed.
    recover_s, recover_frac : float
        Take the last step back after ``recover_s`` without a miss, when the loop's
        work (90th percentile, scaled by the cameras it would take back) stays under
        ``recover_frac`` of the period.
    """

    rate_hz: float
    cameras: tuple
    window_s: float = 8.0
    max_missed_frac: float = 0.01
    record_steps: tuple = (1, 2, 4, 0)
    stall_frac: float = 0.6
    recover_s: float = 6.0
    recover_frac: float = 0.6
    record_every: int = 1
    dropped: list = field(default_factory=list)
    steps: list = field(default_factory=list)

    def __post_init__(self):
        self.cameras = tuple((str(n), bool(f)) for n, f in self.cameras)
        self.record_every = self.record_steps[0]
        self._hist: deque = deque()  # (t_ns, missed total) per processed frame set
        self._window_ns = int(self.window_s * 1e9)

    def observe(self, t_ns: int, missed_total: int, busy_ms: float | None = None) -> LoadStep | None:
        """One processed frame set at capture stamp ``t_ns``, with the source's count of
        instants missed so far and the loop's work on it (ms; None: not known); the step
        taken now (or the stall reported), if any."""
        h = self._hist
        h.append((t_ns, missed_total, busy_ms))
        period_ns = 1e9 / self.rate_hz
        horizon = max(self._window_ns, int(self.recover_s * 1e9))
        while h and t_ns - h[0][0] > horizon:
            h.popleft()
        win = [e for e in h if t_ns - e[0] <= self._window_ns]
        missed = missed_total - win[0][1]
        instants = len(win) - 1 + missed
        busy = [e[2] for e in win if e[2] is not None]
        busy90 = float(np.percentile(busy, 90)) if busy else None
        if missed > self.max_missed_frac * self.window_s * self.rate_hz:
            if busy90 is not None and busy90 < self.stall_frac * period_ns * 1e-6:
                what = (f"stalled from outside (the loop's work {busy90:.0f} ms of the "
                        f"{period_ns * 1e-6:.0f} ms period): nothing shed")
                return self._record(LoadStep(int(t_ns), what, int(missed), int(instants), "stall"), h, missed_total)
            what = self._step_down()
            if what is None:
                return None
            return self._record(LoadStep(int(t_ns), what, int(missed), int(instants)), h, missed_total)
        if self.level and missed_total == h[0][1] and t_ns - h[0][0] >= 0.9 * self.recover_s * 1e9 and busy:
            kept = len(self.cameras) - len(self.dropped)
            scale = (kept + 1) / kept if self.dropped else 1.0
            if float(np.percentile([e[2] for e in h if e[2] is not None], 90)) * scale < \
                    self.recover_frac * period_ns * 1e-6:
                return self._record(LoadStep(int(t_ns), self._step_up(), 0, len(h) - 1, "up"), h, missed_total)
        return None

    def _record(self, step: LoadStep, h: deque, missed_total: int) -> LoadStep:
        self.steps.append(step)
        h.clear()
        h.append((step.t_ns, missed_total, None))
        return step

    def _step_up(self) -> str:
        if self.dropped:
            name = self.dropped.pop()
            return f"camera {name} back"
        k = self.record_steps.index(self.record_every)
        self.record_every = self.record_steps[k - 1]
        return f"recording images of one frame set in {self.record_every}"

    def _step_down(self) -> str | None:
        k = self.record_steps.index(self.record_every)
        if k + 1 < len(self.record_steps):
            self.record_every = self.record_steps[k + 1]
            return ("recording no images" if self.record_every == 0 else
                    f"recording images of one frame set in {self.record_every}")
        kept = [c for c in self.cameras if c[0] not in self.dropped]
        if len(kept) <= 1:
            return None
        fixed = [n for n, f in kept if f]
        # Fixed cameras, last in rig order first, while another fixed one stays (it sees the
        # part arrive); then the eye-in-hand ones.
        name = fixed[-1] if len(fixed) > 1 else [n for n, f in kept if not f][-1]
        self.dropped.append(name)
        return f"camera {name} dropped"

    def record_images(self, index: int) -> bool:
        """Whether frame set ``index``'s images are recorded."""
        return self.record_every > 0 and index % self.record_every == 0

    @property
    def level(self) -> int:
        """Steps down in force (0: the full load)."""
        return self.record_steps.index(self.record_every) + len(self.dropped)
