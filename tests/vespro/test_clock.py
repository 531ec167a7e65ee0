import threading
import time

import pytest

from vespro.clock import SimClock, WallClock


def test_simclock_lockstep():
    c = SimClock()
    assert c.now_ns() == 0
    assert c.sleep_until(2_000_000) == 2_000_000  # time jumps to the deadline
    c.advance(500)
    assert c.now_ns() == 2_000_500
    with pytest.raises(ValueError):
        c.advance(-1)


def test_simclock_blocking_waits_for_simulation():
    c = SimClock(blocking=True)
    woke = []
    th = threading.Thread(target=lambda: woke.append(c.sleep_until(10)))
    th.start()
    time.sleep(0.05)
    assert not woke  # nobody advanced the clock yet
    c.advance(10)
    th.join(2)
    assert woke == [10]


def test_wallclock_reaches_deadline():
    c = WallClock()
    t0 = c.now_ns()
    t = c.sleep_until(t0 + 3_000_000)
    assert t >= t0 + 3_000_000
