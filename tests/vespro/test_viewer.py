"""The Rerun view: a short track saved with --view-save, read back with Rerun's own reader."""

from collections import defaultdict

import numpy as np
import pytest

rr = pytest.importorskip("rerun", reason="the live view needs the view extra (pip install 'vespro[view]')")

from rerun.chunk import RrdReader  # noqa: E402

from vespro.cli import main  # noqa: E402
from vespro.groundtruth import read_groundtruth  # noqa: E402
from vespro.rig import load_rig  # noqa: E402
from vespro.se3 import pq_from_transform  # noqa: E402
from vespro.sim.cell import CellConfig  # noqa: E402
from vespro.sim.motion import Conveyor  # noqa: E402
from vespro.sim.record import record  # noqa: E402
from vespro.sim.rigs import CAMERAS_DIR  # noqa: E402
from vespro.sim.scene import MODELS_DIR  # noqa: E402

N = 8


def rrd_rows(path) -> dict:
    """entity path -> {frame index (None: static): {column: value}}, the columns logged at that frame."""
    rows = defaultdict(dict)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        cols = [c for c in batch.schema.names if c not in ("capture_time", "log_time")]
        data = {c: batch.column(c).to_pylist() for c in cols}
        frames = data.pop("frame", None) or [None] * batch.num_rows
        for k, f in enumerate(frames):
            rows[chunk.entity_path].setdefault(f, {}).update({c: v[k] for c, v in data.items() if v[k] is not None})
    return rows


def rrd_column(path, entity: str, suffix: str) -> list:
    """Every value logged to ``entity``'s column ending in ``suffix``, in log order."""
    out = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path == entity:
            batch = chunk.to_record_batch()
            for c in [c for c in batch.schema.names if c.endswith(suffix)]:  # none in a static chunk of names
                out += [v for v in batch.column(c).to_pylist() if v is not None]
    return out


def _col(row: dict, suffix: str):
    (value,) = [v for c, v in row.items() if c.endswith(suffix)]
    return value


@pytest.fixture(scope="module")
def rec_path(tmp_path_factory):
    cfg = CellConfig(MODELS_DIR / "objects" / "box.stl", load_rig(CAMERAS_DIR / "fixed2.yaml"))
    return record(tmp_path_factory.mktemp("view") / "rec", cfg, Conveyor(speed=0.1, y0=-0.2), N, "box")


#: A recording other processes may join (the servo's view, below).
JOIN = ["--view-recording-id", "cell-run-1", "--view-app-id", "vespro cell"]


@pytest.fixture(scope="module")
def tracked(rec_path, tmp_path_factory):
    """``vespro track --view-save`` of the recording: (the .rrd, the poses file)."""
    _, _, T = read_groundtruth(rec_path)
    pose = ",".join(f"{v:.9f}" for v in pq_from_transform(T[0]))
    tmp = tmp_path_factory.mktemp("tracked")
    rrd, out = tmp / "run.rrd", tmp / "poses.csv"
    assert main(["track", str(rec_path), "--init-pose", pose, "-o", str(out), "--no-progress",
                 "--view-save", str(rrd), *JOIN]) == 0
    return rrd, out


def test_view_save_of_a_track_holds_images_pose_and_series_for_every_frame(tracked):
    rrd, out = tracked
    rows = rrd_rows(rrd)
    frames = set(range(N))
    for cam in ("cam_left", "cam_right"):
        images = rows[f"/world/cameras/{cam}/image"]
        assert set(images) >= frames  # an image of every camera at every frame
        assert all(_col(images[f], "EncodedImage:blob") for f in frames)
        assert set(rows[f"/world/cameras/{cam}/image/corners"]) >= frames
        assert None in rows[f"/world/cameras/{cam}"]  # the fixed camera's pose, once (static)
    from vespro.poses import read_poses
    from vespro.viewer import STATUS_CODE

    poses = read_poses(out)
    est = rows["/world/estimate"]
    assert sum(r.status == "tracking" for r in poses) >= N - 2
    for r in poses:  # the 3D pose logged is the tracker's, at every frame it tracked
        if r.status == "tracking":
            t = np.asarray(_col(est[r.index], "Transform3D:translation"), dtype=float).ravel()
            np.testing.assert_allclose(t, r.T_world_object[:3, 3], atol=1e-6)  # float32 in Rerun: 1 um at 1 m
            assert _col(rows["/world/estimate_cov"][r.index], "Ellipsoids3D:half_sizes")
            assert _col(rows["/world/cameras/cam_left/image/model"][r.index], "LineStrips2D:strips")
        else:
            assert _col(est[r.index], "Clear:is_recursive")
        assert _col(rows["/series/status"][r.index], "Scalars:scalars") == [STATUS_CODE[r.status]]
    for name in ("features_used", "tracker_ms"):
        assert set(rows[f"/series/{name}"]) >= frames
    assert "/world/truth" not in rows  # tracking never shows ground truth


def test_view_save_of_a_lockstep_demo_shows_estimate_truth_and_servo(tmp_path):
    """The demo (an evaluator) adds the true pose, the arm and the servo's series to the view."""
    from cellsim.demo import DemoConfig, run_demo
    from vespro.poses import read_poses
    from vespro.recording import Recording

    rrd = tmp_path / "demo.rrd"
    run_demo(DemoConfig(out=tmp_path / "demo", object="box", cameras="fixed", duration=0.4, lockstep=True,
                        video=False, view_save=rrd), log=lambda m: None)
    rows = rrd_rows(rrd)
    rec = Recording(tmp_path / "demo" / "vision" / "recording")
    poses = read_poses(tmp_path / "demo" / "vision" / "poses.csv")
    frames = set(range(len(rec)))
    assert len(frames) >= 10 and len(poses) == len(frames)
    for cam in rec.rig.names:
        assert set(rows[f"/world/cameras/{cam}/image"]) >= frames
    assert set(rows["/world/truth"]) == frames and set(rows["/series/status"]) >= frames
    tracked = [r for r in poses if r.status == "tracking"]
    assert len(tracked) >= len(frames) - 2
    for r in tracked:
        t = np.asarray(_col(rows["/world/estimate"][r.index], "Transform3D:translation"), dtype=float).ravel()
        np.testing.assert_allclose(t, r.T_world_object[:3, 3], atol=1e-6)  # float32 in Rerun
        err = _col(rows["/series/error_mm"][r.index], "Scalars:scalars")[0]
        assert 0.0 < err < 5.0  # the estimate beside the truth, a millimetre or so apart
    # The servo's series and the arm, at 50 Hz of cell time (on the capture_time timeline only).
    assert len(_col(rows["/series/servo_status"][None], "Scalars:scalars")) >= 1
    assert "/world/arm/tcp" in rows and "/world/arm/target" in rows


def test_servo_process_logs_into_the_recording_of_the_pose_servers_view(tracked, tmp_path):
    """``servo run`` (a process of its own, real time) and ``vespro track`` log into one recording
    (same application and recording ids); their files, merged, hold both processes' entities."""
    import subprocess
    import sys

    from servo.kinematics import ArmKinematics
    from servo.robot import MujocoArm
    from vespro.viewer import merge_rrd

    import shutil

    servo_rrd, rrd = tmp_path / "run.servo.rrd", tmp_path / "run.rrd"
    # One second of the 500 Hz loop on the simulated arm; no pose server answers: it holds.
    r = subprocess.run([sys.executable, "-m", "servo", "run", "--robot", "mujoco", "--duration", "1",
                        "--connect", "socket://127.0.0.1:9", "--view-save", str(servo_rrd), *JOIN],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "not logged" not in r.stdout
    ticks = int(r.stdout.split(" ticks,")[0].rsplit(" ", 1)[-1])
    shutil.copy(tracked[0], rrd)  # the pose server's side: the tracker's view in the same recording
    merge_rrd([rrd, servo_rrd], rrd)

    (store,) = RrdReader(rrd).recordings()  # one recording
    assert (store.application_id, store.recording_id) == ("vespro cell", "cell-run-1")
    rows = rrd_rows(rrd)
    assert set(rows["/world/cameras/cam_left/image"]) >= set(range(N))  # the pose server's side
    # The servo's side, every 10th tick: its status (1: HOLD), timing, end effector, events.
    status = rrd_column(rrd, "/series/servo_status", "scalars")
    assert ticks // 10 - 1 <= len(status) <= ticks // 10 and {tuple(s) for s in status} == {(1.0,)}
    for name in ("servo_compute_us", "servo_period_error_us", "servo_overruns"):
        assert len(rrd_column(rrd, f"/series/{name}", "scalars")) == len(status)
    arm = MujocoArm()
    q = np.zeros(arm.n)
    arm.read(q)
    kin = ArmKinematics()
    kin.update(q, jacobian=False)
    tcp = np.array(rrd_column(rrd, "/world/arm/tcp", "positions"), dtype=float).reshape(-1, 3)
    assert len(tcp) == len(status)
    np.testing.assert_allclose(tcp, np.repeat(kin.p[None], len(tcp), 0), atol=2e-3)  # held at its start
    assert "/world/arm/target" not in rows  # no pose, no target
    assert any("status HOLD" in str(t) for t in rrd_column(rrd, "/servo/events", "text"))


def test_real_time_demo_gives_its_pose_server_and_servo_one_recording(tmp_path):
    """Both processes get the same ids and time zero; each saves its own file, the servo's beside the one asked for."""
    from cellsim.demo import DemoConfig, view_options
    from servo.cli import build_parser as servo_parser
    from vespro.cli import build_parser

    rrd = tmp_path / "run.rrd"
    vision, servo = view_options(DemoConfig(view_save=rrd, view=True), "rid", 123)
    a = build_parser().parse_args(["serve", *vision])
    b = servo_parser().parse_args(["run", *servo])
    for x in (a, b):
        assert (x.view_recording_id, x.view_app_id, x.view_t0_ns) == ("rid", "vespro demo", 123)
    assert a.view and a.view_save == rrd
    assert b.view_save == tmp_path / "run.servo.rrd" and b.view_connect.startswith("rerun+http://127.0.0.1:9876")
    assert view_options(DemoConfig(), "rid", 123) == ([], [])
