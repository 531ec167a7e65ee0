"""Timing by thread CPU time instead of wall time, for benches on a busy machine.

On a machine whose cores other work shares, a stage's wall time includes every
preemption that fell inside it (tens of ms at a time), so the longest stage
collects most of them. Its thread's CPU time does not: on a quiet machine the two
agree for single-threaded work (the tracker's, and ViSP's with one OpenMP thread).
"""

from __future__ import annotations

import time
import types
from contextlib import contextmanager

import vespro.tracker


@contextmanager
def tracker_clock(kind: str = "cpu"):
    """The tracker's stage and frame times (``TrackerOutput.time_ms``, ``stage_ms``) in this
    thread's CPU time (``kind="cpu"``) or wall time (``"wall"``, unchanged) meanwhile."""
    if kind == "wall":
        yield time.perf_counter
        return
    saved = vespro.tracker.time
    vespro.tracker.time = types.SimpleNamespace(perf_counter=time.thread_time)
    try:
        yield time.thread_time
    finally:
        vespro.tracker.time = saved
