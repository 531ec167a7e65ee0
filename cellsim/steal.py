"""What the machine took from the cell: CPU time a hypervisor ran something else ("steal").

On a virtual machine the host may deschedule a virtual CPU whatever runs on it,
and the guest kernel's own interrupt work runs above every task: a SCHED_FIFO
loop at the highest priority, pinned to its own core, then stops. On the
2-core virtual machines the project is measured on, a pinned SCHED_FIFO
thread at priority 90 spinning 1.5 ms of every 2 ms lost its core 2.9-9.8 ms
at a time, five times in 40 s, while the kernel counted 60 ms of steal on that
core (``bench/stalls.py``). The servo's late ticks in a ``vespro demo`` run
are such stalls: ``perf sched`` shows the servo itself "running" for 2-4.6 ms
around each (its computation 0.2 ms), and a priority-90 canary waking every
millisecond on the servo's core was late by 1.2-3.5 ms at three of a run's
five late ticks. No placement or priority inside the guest avoids them; the
demo reports the steal of its run beside the servo's overruns (steal counts
the host's share only, in 10 ms ticks: a run can show overruns and none).

Linux counts steal per CPU in ``/proc/stat`` (the eighth value of each ``cpuN``
line, in ``USER_HZ`` ticks, 10 ms); elsewhere there is nothing to read.
"""

from __future__ import annotations

import os

__all__ = ["read_steal_ms", "steal_since"]

_PROC_STAT = "/proc/stat"


def read_steal_ms(text: str | None = None) -> dict[str, float]:
    """Steal time per CPU so far, ms: ``{"cpu0": ..., "cpu1": ...}`` from ``/proc/stat`` (or
    ``text`` in its format); empty where the file or the field is absent."""
    if text is None:
        try:
            with open(_PROC_STAT) as f:
                text = f.read()
        except OSError:
            return {}
    try:
        hz = os.sysconf("SC_CLK_TCK")
    except (ValueError, OSError, AttributeError):
        hz = 100
    out = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) > 8 and parts[0].startswith("cpu") and parts[0] != "cpu":
            try:
                out[parts[0]] = int(parts[8]) * 1000.0 / hz
            except ValueError:
                continue
    return out


def steal_since(before: dict[str, float], after: dict[str, float] | None = None) -> dict[str, float]:
    """Steal per CPU between two :func:`read_steal_ms` readings (``after``: now), ms."""
    after = read_steal_ms() if after is None else after
    return {cpu: round(after[cpu] - before[cpu], 1) for cpu in before if cpu in after}
