"""Work handed to a process of its own through a bounded queue (the Rerun views of both sides).

A live loop (the 500 Hz servo loop, the pose server's tracking loop) must not
wait for logging: logging in a thread would hold the interpreter lock the loop
needs, so it runs in a child process (started with "spawn": the caller may run
threads) that takes items from a bounded queue. What the caller pays per item
is handing its references to the queue's feeder thread. A full queue either
drops the item (counted: ``block=False``, live) or waits (``block=True``:
offline, every item logged).

The child builds its worker with ``factory(*args)``; an item
``(method, *args)`` calls ``worker.method(*args)`` (an exception is counted,
the logging goes on); at the end ``worker.close()``. ``close()`` on this side sends the end, waits for the worker to
finish what is queued, and returns a line on what was not logged.
"""

from __future__ import annotations

import queue

__all__ = ["QueuedProcess"]


class QueuedProcess:
    """A worker in a child process fed by a bounded queue.

    Parameters
    ----------
    factory : callable
        Builds the worker in the child (importable: the child is spawned).
    args : tuple
        The factory's arguments (picklable).
    name : str
        The process's name, and the prefix of the line :meth:`close` returns.
    block : bool
        A full queue: wait (True) or drop the item (False, counted in ``dropped``).
    max_queue : int
    wait_ready : float
        Seconds to wait for the worker to be built (0: do not wait; the queue holds
        the first items meanwhile, and a failure is reported by :meth:`close`).
        Raises RuntimeError when it is not ready by then.
    """

    def __init__(self, factory, args: tuple, *, name: str, block: bool = False, max_queue: int = 16,
                 wait_ready: float = 0.0):
        import multiprocessing as mp

        self.name = name
        self.block = block
        self.dropped = 0
        self.errors = 0
        self.last_error = ""
        self._closed = False
        ctx = mp.get_context("spawn")
        self._q = ctx.Queue(maxsize=max_queue)
        self._result, child = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_child, args=(factory, args, self._q, child), daemon=True, name=name)
        self._proc.start()
        child.close()
        self._q.put(("ready?",))  # starts the feeder thread now (before a caller's loop goes real-time)
        if wait_ready:
            try:
                ready = self._result.poll(wait_ready) and self._result.recv() == "ready"
            except EOFError:  # the process died on start
                ready = False
            if not ready:
                self._proc.terminate()
                raise RuntimeError(f"{name}: the process did not start")

    def put(self, item) -> None:
        """Queue one call ``(method name, *args)`` of the worker."""
        if self._closed:
            return
        try:
            if self.block:
                self._q.put(item)
            else:
                self._q.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def close(self, what: str = "items") -> str:
        """Let the worker finish what is queued and close; returns a line on what was not logged, or ""."""
        if self._closed:
            return ""
        self._closed = True
        try:
            self._q.put(None, timeout=60)
        except queue.Full:
            pass
        try:
            while self._result.poll(120):
                msg = self._result.recv()
                if msg != "ready":
                    self.errors, self.last_error = msg
                    break
            else:
                self.errors, self.last_error = -1, "the process did not finish"
        except EOFError:
            self.errors, self.last_error = -1, "the process ended early"
        self._proc.join(timeout=10)
        if self._proc.is_alive():
            self._proc.terminate()
        lost = []
        if self.dropped:
            lost.append(f"{self.dropped} {what} not logged (it fell behind)")
        if self.errors < 0:
            lost.append(self.last_error)
        elif self.errors:
            lost.append(f"{self.errors} {what} failed to log (last: {self.last_error})")
        return f"{self.name}: " + "; ".join(lost) if lost else ""


def _child(factory, args, q, result) -> None:
    """The process: build the worker, hand it what arrives until None, then report (errors, last error)."""
    import signal

    for s in (signal.SIGINT, signal.SIGTERM):  # the caller handles these, then closes us
        signal.signal(s, signal.SIG_IGN)
    try:
        worker = factory(*args)
    except Exception as e:  # reported to the caller as one line
        result.send((-1, f"did not start: {e!r}"))
        return
    result.send("ready")
    errors, last = 0, ""
    while True:
        item = q.get()
        if item is None:
            break
        if item[0] == "ready?":
            continue
        try:
            getattr(worker, item[0])(*item[1:])
        except Exception as e:  # a viewer problem must never stop the logging
            errors += 1
            last = repr(e)
    try:
        worker.close()
    except Exception as e:
        errors, last = errors + 1, repr(e)
    result.send((errors, last))
