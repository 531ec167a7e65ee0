"""Recorder: preallocated rows, NPZ + CSV round trip, overflow, scheduler channels."""

import csv

import numpy as np

from servo.clock import SimClock
from servo.loop import LoopConfig, Scheduler
from servo.planner import FollowTask
from servo.recorder import LOOP_CHANNELS, Recorder
from servo.robot import MujocoArm

from servo_helpers import T_DOWN, q_above


def test_rows_and_round_trip(tmp_path):
    rec = Recorder(5, {"t_ns": ((), np.int64), "q": ((3,), np.float64), "s": ((), np.int8)})
    before = {k: v.__array_interface__["data"][0] for k, v in rec.data.items()}
    for i in range(7):
        row = rec.next_row()
        if row >= 0:
            rec.data["t_ns"][row] = 1_000_000_000 * i + 1  # beyond float precision on purpose
            rec.data["q"][row] = [i, 0.1 * i, -1e-17 * i]
            rec.data["s"][row] = i
    # no reallocation during the run, overflow counted not raised
    assert {k: v.__array_interface__["data"][0] for k, v in rec.data.items()} == before
    assert rec.n == 5 and rec.dropped == 2
    npz, csv_path = rec.save(tmp_path / "run")
    z = np.load(npz)
    np.testing.assert_array_equal(z["t_ns"], [1_000_000_000 * i + 1 for i in range(5)])
    np.testing.assert_array_equal(z["q"][:, 1], 0.1 * np.arange(5))
    with open(csv_path) as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["t_ns", "q_0", "q_1", "q_2", "s"]
    assert len(rows) == 6
    assert int(rows[5][0]) == 4_000_000_001  # integers written exactly
    assert float(rows[4][2]) == 0.1 * 3  # repr round-trips floats exactly
    assert float(rows[5][3]) == -4e-17


def test_scheduler_fills_loop_channels(tmp_path):
    rec = Recorder(300, LOOP_CHANNELS)
    arm = MujocoArm(q0=q_above())
    sch = Scheduler.from_config(LoopConfig(task=FollowTask(T_DOWN)), SimClock(), arm, None, recorder=rec)
    sch.run(250)
    a = rec.arrays()
    assert rec.n == 250
    np.testing.assert_array_equal(np.diff(a["t_ns"]), 2_000_000)
    np.testing.assert_allclose(np.linalg.norm(a["quat_ref"], axis=1), 1.0)
    assert np.all(a["compute_ns"] > 0)
    np.testing.assert_allclose(a["q_cmd"][-1], q_above(), atol=1e-6)  # no target: holds
    npz, csv_path = rec.save(tmp_path / "loop")
    assert npz.exists() and csv_path.exists()
