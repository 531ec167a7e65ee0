"""Freed image buffers go back to the system (vespro.memory), in a process of their own."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

CHURN = textwrap.dedent("""
    import json, sys
    import numpy as np
    if sys.argv[1] == "fixed":
        from vespro.memory import return_freed_images
        assert return_freed_images() is None
    def rss_mb():
        for line in open("/proc/self/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    before = rss_mb()
    big = np.ones(2**20, np.uint8)
    del big  # one large block freed: glibc's default raises its mmap threshold past an image's size
    imgs = [np.full((480, 640), k % 251 + 1, np.uint8) for k in range(100)]  # 100 frames' images
    last = imgs[-1]  # the newest kept (a backlog's last frame), the others dropped
    del imgs
    live = last.nbytes
    print(json.dumps({"growth_mb": rss_mb() - before, "live_mb": live / 2**20}))
""")


def _growth(mode: str) -> dict:
    r = subprocess.run([sys.executable, "-c", CHURN, mode], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_freed_images_leave_the_process_and_only_live_ones_stay():
    """A hundred frames' images made, the newest kept and the others dropped: with the
    thresholds fixed the resident size keeps what is live; with glibc's default (the
    premise) the dropped images stay in the heap under the kept one (30 MB)."""
    fixed = _growth("fixed")
    assert fixed["growth_mb"] < fixed["live_mb"] + 2.0, fixed
    default = _growth("default")
    assert default["growth_mb"] > 20.0, default


def test_scratch_images_are_kept_by_name_and_grow_to_the_largest_asked():
    import numpy as np

    from vespro.memory import ScratchImages

    s = ScratchImages()
    a = s.get("crop", (2, 40, 50), np.float64)
    assert a.shape == (2, 40, 50) and a.dtype == np.float64 and a.flags.c_contiguous
    b = s.get("crop", (2, 30, 20), np.float64)  # a smaller crop: the same block
    assert np.shares_memory(a, b) and b.flags.c_contiguous
    c = s.get("crop", (2, 60, 60), np.float64)  # a larger one: a larger block
    assert c.shape == (2, 60, 60) and not np.shares_memory(a, c)
    assert np.shares_memory(s.get("crop", (2, 60, 60), np.float64), c)
    assert not np.shares_memory(s.get("other", (60, 60), np.float64), c)  # names apart
    assert s.get("crop", (60, 60), np.uint8).dtype == np.uint8  # and dtypes
