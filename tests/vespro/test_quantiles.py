"""Running quantiles in fixed memory against numpy's exact ones."""

import math

import numpy as np
import pytest

from vespro.quantiles import LogHistogram
from vespro.throttle import LogThrottle


@pytest.mark.parametrize("scale", [0.05, 3.0, 400.0])
def test_quantiles_are_within_half_a_bin_of_the_exact_ones(scale):
    x = np.random.default_rng(0).lognormal(np.log(scale), 0.8, 20_000)
    h = LogHistogram(rel=0.01)
    for v in x:
        h.add(v)
    assert h.count == len(h) == x.size and h.mean == pytest.approx(x.mean())
    for q in (0.01, 0.5, 0.9, 0.99, 0.999):
        exact = np.quantile(x, q, method="inverted_cdf")  # nearest rank, as the histogram
        assert abs(h.quantile(q) / exact - 1) <= 0.005 + 1e-12, q  # half the 1 % bin width
    assert h.quantile(0.0) == x.min() and h.quantile(1.0) == x.max()  # the ends are exact


def test_memory_is_fixed_and_odd_values_are_kept_apart():
    h = LogHistogram()
    n_bins = h.counts.size
    for v in (0.0, -3.0, 1e9, math.nan, math.inf):
        h.add(v)
    assert h.counts.size == n_bins and h.counts.sum() == 3 and h.nonfinite == 2
    assert h.quantile(0.0) == -3.0 and h.quantile(1.0) == 1e9  # clamped to the values seen
    assert math.isnan(LogHistogram().quantile(0.5))


def test_log_throttle_lets_one_line_per_kind_and_period_through_and_counts_the_rest():
    t = [0]
    lines = []
    note = LogThrottle(lines.append, lambda: t[0], period_s=1.0)
    for k in range(100):  # 100 identical lines in 0.99 s, one of another kind
        t[0] = k * 10_000_000
        note("no pose", "no pose (no images)")
    note("a pose", "a pose")
    t[0] = 2_000_000_000
    note("no pose", "no pose (no images)")
    assert lines == ["no pose (no images)", "a pose", "no pose (no images) (and 99 more like it in the last 2 s)"]
    assert note.held == 99
