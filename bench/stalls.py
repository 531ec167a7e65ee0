"""How long the machine itself stops a pinned real-time loop: the floor under the servo's overruns.

A thread pinned to each core in turn runs a servo-like duty cycle (sleep 0.5 ms,
then read the monotonic clock in a tight loop for 1.5 ms) and records every
gap between two consecutive readings longer than ``--min-us`` (200 us): time
in which the thread did not run although nothing in the guest could take its
core from it (SCHED_FIFO at priority 90, above the servo's 80). Beside it, the
kernel's count of steal time for that core over the same seconds
(:mod:`cellsim.steal`: time the virtual machine's host ran something else).
The baseline is the same loop under normal scheduling in the same process,
where the machine's other work also takes the core.

Per core and policy: seconds spun, gaps over ``--min-us`` and over 1 ms,
median, p99 and largest gap, time lost in gaps, the kernel's steal, and the
time lost relative to the baseline's. A servo tick that starts late by more
than its period less its computation (2 ms less ~0.3 ms in ``vespro demo``)
is an overrun: every gap over 1.7 ms that falls in a tick's spin or
computation is one, whatever the servo's code.

Usage: ``python3 bench/stalls.py [--seconds 20] [--cores 0,1] [--min-us 200]`` (as root for
SCHED_FIFO; without it the FIFO rows are left out).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _table import print_table  # noqa: E402

from cellsim.steal import read_steal_ms, steal_since  # noqa: E402

SLEEP_S = 0.0005
SPIN_NS = 1_500_000


def _spin(seconds: float, min_ns: int) -> tuple[float, np.ndarray]:
    """The duty cycle for ``seconds``: (seconds spun, gaps over ``min_ns`` in ms)."""
    mono = time.monotonic_ns
    gaps = []
    spun = 0
    t_end = mono() + int(seconds * 1e9)
    while True:
        time.sleep(SLEEP_S)
        t0 = now = mono()
        if now > t_end:
            break
        while now - t0 < SPIN_NS:
            prev, now = now, mono()
            if now - prev > min_ns:
                gaps.append(now - prev)
        spun += now - t0
    return spun * 1e-9, np.asarray(gaps, float) * 1e-6


def _measure(core: int, fifo: bool, seconds: float, min_ns: int) -> dict | None:
    saved_aff = os.sched_getaffinity(0)
    saved_pol = (os.sched_getscheduler(0), os.sched_getparam(0))
    try:
        os.sched_setaffinity(0, {core})
        if fifo:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(90))
            except PermissionError:
                return None
        s0 = read_steal_ms()
        spun, gaps = _spin(seconds, min_ns)
        steal = steal_since(s0).get(f"cpu{core}", float("nan"))
    finally:
        os.sched_setscheduler(0, saved_pol[0], saved_pol[1])
        os.sched_setaffinity(0, saved_aff)
    return {"spun": spun, "gaps": gaps, "steal": steal}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="per core and policy")
    ap.add_argument("--cores", default=None, help="comma list (default: every core this process may use)")
    ap.add_argument("--min-us", type=float, default=200.0, help="gaps counted from this long, us")
    a = ap.parse_args(argv)
    if a.seconds <= 0 or a.min_us <= 0:
        print("stalls: --seconds and --min-us must be > 0", file=sys.stderr)
        return 2
    try:
        cores = sorted(os.sched_getaffinity(0)) if a.cores is None else [int(c) for c in a.cores.split(",")]
    except ValueError:
        print(f"stalls: --cores must be a comma list of core numbers, got {a.cores!r}", file=sys.stderr)
        return 2
    rows = []
    for core in cores:
        base = None
        for fifo in (False, True):
            try:
                m = _measure(core, fifo, a.seconds, int(a.min_us * 1e3))
            except OSError as e:
                print(f"stalls: core {core}: {e}", file=sys.stderr)
                return 2
            if m is None:
                continue
            g = m["gaps"]
            lost = float(g.sum())
            if not fifo:
                base = lost
            rows.append([core, "SCHED_FIFO 90" if fifo else "normal", m["spun"], int(g.size), int((g > 1.0).sum()),
                         float(np.median(g)) if g.size else 0.0, float(np.percentile(g, 99)) if g.size else 0.0,
                         float(g.max()) if g.size else 0.0, lost, m["steal"],
                         lost / base if base else float("nan")])
    print_table(["core", "policy", "spun s", "gaps", "> 1 ms", "median ms", "p99 ms", "max ms", "lost ms",
                 "steal ms", "lost / normal"], rows,
                title=f"A pinned loop's gaps over {a.min_us:.0f} us (sleep 0.5 ms, spin 1.5 ms; {a.seconds:.0f} s "
                      f"per row); steal: the kernel's count for that core over the same seconds")
    return 0


if __name__ == "__main__":
    sys.exit(main())
