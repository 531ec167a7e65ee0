"""A live loop that misses its capture deadlines says so and lowers its own load.

The pose server's live loop must take every capture instant (a frame set it
skips is a pose the servo never gets). On a machine too slow for all it was
asked to do, :class:`LoadShedder` watches the instants missed over a sliding
window and, past ``max_missed_frac`` of them, takes the next step of a fixed
ladder, announces it (one log line) and records it:

1. record images at half the capture rate, then a quarter, then not at all
   (the recording keeps every frame set's row; the images skipped are missing,
   as the recording format allows);
2. drop one camera at a time (fixed cameras, last in the rig first, while another
   fixed one stays; then the eye-in-hand ones; never the last camera): it is no
   longer captured (rendered), tracked or recorded.

After a step the window starts again, so the effect of one step is seen before
the next. Steps are not taken back within a run: a loop that had to shed load
once would miss deadlines again when it took it up.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

__all__ = ["LoadShedder", "LoadStep"]


@dataclass(frozen=True)
class LoadStep:
    """One step down: when (capture stamp, ns), what, and the misses that caused it."""

    t_ns: int
    what: str
    missed: int
    instants: int


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
        Sliding window over which misses are counted.
    max_missed_frac : float
        Step down when more than this fraction of the window's capture instants
        were missed.
    record_steps : tuple of int
        Image recording periods to go through (1: every frame set; 0: none).
    """

    rate_hz: float
    cameras: tuple
    window_s: float = 2.0
    max_missed_frac: float = 0.02
    record_steps: tuple = (1, 2, 4, 0)
    record_every: int = 1
    dropped: list = field(default_factory=list)
    steps: list = field(default_factory=list)

    def __post_init__(self):
        self.cameras = tuple((str(n), bool(f)) for n, f in self.cameras)
        self.record_every = self.record_steps[0]
        self._hist: deque = deque()  # (t_ns, missed total) per processed frame set
        self._window_ns = int(self.window_s * 1e9)

    def observe(self, t_ns: int, missed_total: int) -> LoadStep | None:
        """One processed frame set at capture stamp ``t_ns``, with the source's count of
        instants missed so far; the step taken now, if any."""
        h = self._hist
        h.append((t_ns, missed_total))
        while h and t_ns - h[0][0] > self._window_ns:
            h.popleft()
        period_ns = 1e9 / self.rate_hz
        if t_ns - h[0][0] < 0.9 * self._window_ns - period_ns:
            return None  # not a full window yet (since the start, or the last step)
        missed = missed_total - h[0][1]
        instants = len(h) - 1 + missed
        if instants <= 0 or missed <= self.max_missed_frac * instants:
            return None
        what = self._step_down()
        if what is None:
            return None
        step = LoadStep(int(t_ns), what, int(missed), int(instants))
        self.steps.append(step)
        h.clear()
        h.append((t_ns, missed_total))
        return step

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
        """Steps taken so far."""
        return len(self.steps)
