"""Real-time placement of a live process: a pinned core, niceness, SCHED_FIFO, and back.

Used by the pose server's live loop (``vespro serve --cpu --fifo --nice``) and by the
demo's plant. Each step is best effort: what the system refuses is returned as a
message and the process runs on, less isolated.
"""

from __future__ import annotations

import os

__all__ = ["enter_realtime", "leave_realtime", "background_thread"]


def enter_realtime(cpu: int | None, nice: int, fifo: int = 0) -> list[str]:
    """Pin this process to ``cpu``, set its niceness and SCHED_FIFO priority; returns what could not be done.

    Threads started afterwards (the renderer's, the recording writer's) inherit all three.
    """
    msgs = []
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})
        except (OSError, AttributeError, ValueError) as e:
            msgs.append(f"could not pin to CPU {cpu}: {e}")
    if nice:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        except (OSError, AttributeError) as e:
            msgs.append(f"could not set niceness {nice}: {e}")
    if fifo:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo))
        except (OSError, AttributeError, ValueError) as e:
            msgs.append(f"SCHED_FIFO {fifo} refused ({e}); normal scheduling")
    return msgs


def leave_realtime() -> None:
    """Back to normal scheduling on every core (this thread, and the threads it starts later)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.sched_setaffinity(0, range(os.cpu_count() or 1))
    except (OSError, AttributeError):
        pass


def background_thread(avoid_cpu: int | None, nice: int = 10) -> None:
    """Make the calling thread background work of a live process: off core ``avoid_cpu``
    (the live loop's; unless it is the only core) and below the loop.

    A thread started by a pinned SCHED_FIFO loop inherits its core and priority: the
    recording writer's then ran on the vision core at the loop's priority, and the loop
    waited for it. Below the loop means: under SCHED_FIFO, its lowest priority (1), not
    normal scheduling, because the thread shares the loop's interpreter lock, and a
    normal thread preempted by other work while it holds the lock would stall the loop
    for as long (a priority inversion); otherwise niced by ``nice``. Best effort: what
    the system refuses is left as it was.
    """
    import threading

    try:
        cpus = set(range(os.cpu_count() or 1))
        os.sched_setaffinity(0, (cpus - {avoid_cpu}) or cpus)
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        elif nice:
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + nice)
    except (OSError, AttributeError):
        pass


def freeze_set_up() -> None:
    """Leave what the set-up made (models, compiled kernels, the renderer's tables) out of
    the cyclic garbage collector's passes: collect once now and freeze the survivors.

    A full collection walks every object the process holds: after the set-up of a pose
    server (three cameras, the initialiser's worker) about 100 ms, three capture instants
    of a live loop. Frozen objects are not walked, so a full collection during the run sees
    only what the loop itself makes and stays short.
    """
    import gc

    gc.collect()
    gc.freeze()

