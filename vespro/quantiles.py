"""Running quantiles in fixed memory: a histogram of log-spaced bins.

A loop that runs for hours (the pose server) reports the median and the 99th
percentile of per-frame figures since it started. Keeping every value grows
without end (74 bytes a frame: 7 MB an hour at 26 Hz). Bins a fixed relative
width apart, as HdrHistogram and DDSketch use, answer any quantile within half
that width from an array of counts allocated once: 1851 bins (15 KB) cover
1 us to 100 s at 1 % relative width, whatever the run's length.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["LogHistogram"]


class LogHistogram:
    """Counts of values in log-spaced bins; quantiles to within ``rel / 2`` (relative).

    Parameters
    ----------
    lo, hi : float
        Range resolved (in the caller's unit, e.g. ms). Values below ``lo``
        (including 0 and negatives) count in the first bin, above ``hi`` in the
        last; the exact minimum and maximum are kept, so quantiles there are
        clamped to the values seen.
    rel : float
        Relative bin width.
    """

    def __init__(self, lo: float = 1e-3, hi: float = 1e5, rel: float = 0.01):
        if not (0 < lo < hi and 0 < rel < 1):
            raise ValueError(f"LogHistogram needs 0 < lo < hi and 0 < rel < 1, got lo={lo} hi={hi} rel={rel}")
        self.lo, self.hi, self.rel = float(lo), float(hi), float(rel)
        self._log_lo = math.log(lo)
        self._log_step = math.log1p(rel)
        n = int(math.ceil((math.log(hi) - self._log_lo) / self._log_step)) + 1
        self.counts = np.zeros(n, np.int64)
        self.count = 0
        self.nonfinite = 0  # values that were NaN or infinite: counted apart, not binned
        self.total = 0.0
        self.min = math.inf
        self.max = -math.inf

    def __len__(self) -> int:
        return self.count

    def add(self, x: float) -> None:
        """Count one value."""
        x = float(x)
        if not math.isfinite(x):
            self.nonfinite += 1
            return
        i = 0 if x <= self.lo else min(int((math.log(x) - self._log_lo) / self._log_step) + 1, len(self.counts) - 1)
        self.counts[i] += 1
        self.count += 1
        self.total += x
        self.min = min(self.min, x)
        self.max = max(self.max, x)

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (0..1) of the values counted (nearest rank); NaN if none."""
        if self.count == 0:
            return math.nan
        rank = min(max(int(math.ceil(q * self.count)), 1), self.count)
        if rank == 1 or rank == self.count:
            return self.min if rank == 1 else self.max  # the ends are kept exactly
        i = int(np.searchsorted(np.cumsum(self.counts), rank))
        # Bin i > 0 holds (lo * (1+rel)^(i-1), lo * (1+rel)^i]: its geometric middle.
        mid = self.lo if i == 0 else math.exp(self._log_lo + (i - 0.5) * self._log_step)
        return min(max(mid, self.min), self.max)

    @property
    def mean(self) -> float:
        return self.total / self.count if self.count else math.nan
