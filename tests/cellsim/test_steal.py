"""The host's share of the CPUs (steal), as the demo reports it beside the servo's overruns."""

import os

from cellsim.steal import read_steal_ms, steal_since

STAT = """cpu  7986453 98016 531278 4241397 18986 0 3318 19080 0 0
cpu0 3959732 51727 280724 2232684 5107 0 1299 9392 0 0
cpu1 4026720 46289 250554 2008713 13878 0 2018 9688 0 0
intr 123 4 5
ctxt 99
"""


def test_steal_is_read_per_cpu_in_milliseconds_and_differenced():
    hz = os.sysconf("SC_CLK_TCK")
    before = read_steal_ms(STAT)
    assert set(before) == {"cpu0", "cpu1"}  # the total line and other lines left out
    assert before["cpu0"] == 9392 * 1000.0 / hz
    after = read_steal_ms(STAT.replace(" 9688 ", " 9691 "))
    assert steal_since(before, after) == {"cpu0": 0.0, "cpu1": round(3 * 1000.0 / hz, 1)}


def test_a_kernel_without_the_field_gives_nothing_to_report():
    assert read_steal_ms("cpu0 1 2 3 4\ncpu1 1 2 3 4\n") == {}
    assert steal_since({}, {"cpu0": 5.0}) == {}
