"""Shared helpers for the benchmark scripts: timing statistics and a plain table."""

from __future__ import annotations

import numpy as np


def stats_ms(samples_s) -> tuple[float, float]:
    """Median and p99 of durations in seconds, as milliseconds."""
    a = np.asarray(samples_s) * 1e3
    return float(np.median(a)), float(np.percentile(a, 99))


def print_table(headers: list[str], rows: list[list], title: str | None = None) -> None:
    """Print a fixed-width table (numbers to 3 significant decimals)."""
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.3f}" if abs(v) < 1000 else f"{v:.0f}"
        return str(v)

    cells = [[fmt(v) for v in r] for r in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) for i, h in enumerate(headers)]
    if title:
        print(title)
    print("  ".join(h.rjust(w) for h, w in zip(headers, widths)))
    print("  ".join("-" * w for w in widths))
    for r in cells:
        print("  ".join(c.rjust(w) for c, w in zip(r, widths)))
