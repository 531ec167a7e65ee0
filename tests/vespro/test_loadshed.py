"""The live loop's missed-deadline watch and its load ladder."""

from vespro.loadshed import LoadShedder

RATE = 26.0
PERIOD = int(1e9 / RATE)
HYBRID = [("cam_left", True), ("cam_right", True), ("hand", False)]


def _run(sh, n, miss_every=0, t0=0, missed0=0):
    """Feed ``n`` capture instants, one in ``miss_every`` missed (0: none); the steps taken,
    the next instant's stamp and the misses counted."""
    steps, missed, t = [], missed0, t0
    for k in range(n):
        t += PERIOD
        if miss_every and k % miss_every == 0:
            missed += 1
            continue
        st = sh.observe(t, missed)
        if st is not None:
            steps.append(st)
    return steps, t, missed


def test_no_step_while_deadlines_are_kept():
    sh = LoadShedder(RATE, HYBRID)
    steps, _, _ = _run(sh, 400)
    assert steps == [] and sh.record_every == 1 and sh.dropped == []
    assert all(sh.record_images(i) for i in range(10))


def test_a_rare_miss_is_tolerated():
    sh = LoadShedder(RATE, HYBRID, max_missed_frac=0.04)
    steps, _, _ = _run(sh, 400, miss_every=100)  # 1%
    assert steps == []


def test_isolated_misses_under_the_rate_shed_nothing():
    """One miss every 150 instants (0.7%, a machine's stall now and then): never more than two
    in an 8 s window, under its allowance of 1% (2.1 misses). Over a 2 s window (52 instants,
    half a miss allowed) every one of them took a step."""
    sh = LoadShedder(RATE, HYBRID)
    steps, _, missed = _run(sh, 26 * 60, miss_every=150)
    assert missed >= 10 and steps == [] and sh.level == 0


def test_missing_a_third_walks_down_the_ladder_a_step_each_third_miss():
    sh = LoadShedder(RATE, HYBRID)
    steps, _, _ = _run(sh, 26 * 3)  # the first 3 s kept
    assert steps == []
    # Three misses in nine instants pass the window's allowance at once (no need to wait for
    # 8 s of them): one step.
    steps, t, missed = _run(sh, 9, miss_every=3, t0=26 * 3 * PERIOD)
    assert [s.what for s in steps] == ["recording images of one frame set in 2"]
    assert steps[0].missed == 3 > sh.max_missed_frac * sh.window_s * RATE
    assert sh.record_images(4) and not sh.record_images(5)
    more, _, _ = _run(sh, 26 * 12, miss_every=3, t0=t, missed0=missed)
    whats = [s.what for s in more]
    assert whats == ["recording images of one frame set in 4", "recording no images",
                     "camera cam_right dropped", "camera hand dropped"]
    assert sh.dropped == ["cam_right", "hand"] and not sh.record_images(0)
    # Each step counted its own misses after the last (the load it left still missing); never
    # the last camera.
    assert all(s.missed == 3 for s in more)
    assert sh.level == 5


def test_eye_in_hand_rig_keeps_its_last_camera():
    sh = LoadShedder(RATE, [("hand", False)], record_steps=(1, 0))
    steps, _, _ = _run(sh, 26 * 10, miss_every=2)
    assert [s.what for s in steps] == ["recording no images"] and sh.dropped == []


def _feed(sh, n, busy_ms, miss_every=0, t0=0, missed0=0, until_steps=None):
    steps, missed, t = [], missed0, t0
    for k in range(n):
        if until_steps is not None and len(steps) == until_steps:
            break
        t += PERIOD
        if miss_every and k % miss_every == 0:
            missed += 1
            continue
        st = sh.observe(t, missed, busy_ms)
        if st is not None:
            steps.append(st)
    return steps, t, missed


def test_misses_with_a_light_loop_are_stalls_and_shed_nothing():
    sh = LoadShedder(RATE, HYBRID)
    steps, _, _ = _feed(sh, 26 * 8, busy_ms=8.0, miss_every=4)
    assert steps and all(s.kind == "stall" and "nothing shed" in s.what for s in steps)
    assert sh.level == 0 and sh.record_every == 1 and sh.dropped == []


def test_a_step_is_taken_back_once_the_loop_has_room_again():
    sh = LoadShedder(RATE, HYBRID, record_steps=(1, 0))
    steps, t, missed = _feed(sh, 26 * 10, busy_ms=36.0, miss_every=3, until_steps=2)  # too slow: down twice
    assert [s.what for s in steps] == ["recording no images", "camera cam_right dropped"]
    # Light again (an initialiser's search over): 6 s without a miss, then one step back at a time.
    up, t, _ = _feed(sh, 26 * 5, busy_ms=10.0, t0=t, missed0=missed)
    assert up == []  # not yet 6 s
    up, _, _ = _feed(sh, 26 * 9, busy_ms=10.0, t0=t, missed0=missed)
    assert [(s.kind, s.what) for s in up] == [("up", "camera cam_right back"),
                                             ("up", "recording images of one frame set in 1")]
    assert sh.level == 0 and sh.dropped == []


def test_no_step_back_while_the_load_would_not_fit():
    sh = LoadShedder(RATE, HYBRID, record_steps=(1, 0))
    _, t, missed = _feed(sh, 26 * 10, busy_ms=36.0, miss_every=3, until_steps=2)
    up, _, _ = _feed(sh, 26 * 15, busy_ms=20.0, t0=t, missed0=missed)  # 20 * 3/2 = 30 ms > 0.6 period
    assert up == [] and sh.dropped == ["cam_right"]
