"""Hand-eye calibration against the simulator's truth.

The eye-in-hand camera ("hand" rig, plumb_bob distortion) on the flange views a
ChArUco board lying on the belt from 15 arm poses reached by IK; the flange
poses come from the measured joints. Truth: the rig's T_link_camera.
"""

import numpy as np
import pytest

from vespro.calib import CalibrationError
from vespro.calib.board import BoardSpec, detect_board
from vespro.calib.handeye import calibrate_hand_eye
from vespro.calib.io import list_images, load_images, lookup_pose, read_pose_csv
from vespro.camera import CameraIntrinsics
from vespro.cli import main
from vespro.rig import Rig, RigCamera, load_rig, save_rig
from vespro.se3 import pose_error
from vespro.sim.rigs import CAMERAS_DIR

DIST = (-0.22, 0.09, 0.0006, -0.0004, -0.015)
SPEC = BoardSpec("charuco", 11, 8, 0.028, 0.021)


def _true_rig():
    h = load_rig(CAMERAS_DIR / "hand.yaml")["hand"]
    return Rig((RigCamera("hand", CameraIntrinsics(640, 480, h.intrinsics.K, DIST), "eye_in_hand",
                          link=h.link, T_link_camera=h.T_link_camera),))


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    from vespro.sim.board import capture_handeye

    folder = tmp_path_factory.mktemp("he")
    _, T_world_board = capture_handeye(_true_rig(), "hand", SPEC, folder, n_views=15, seed=0)
    images = load_images(list_images(folder))
    poses = read_pose_csv(folder / "flange_poses.csv", "index")
    dets = {n: detect_board(img, SPEC) for n, img in images.items()}
    return folder, dets, {n: lookup_pose(poses, n) for n in images}, T_world_board


def test_hand_eye_matches_simulator(captured):
    _, dets, links, T_world_board = captured
    cam = _true_rig()["hand"]
    res = calibrate_hand_eye(links, dets, cam.intrinsics, SPEC)
    dp, da = pose_error(res.best.T_link_camera, cam.T_link_camera)
    assert dp < 1e-3 and np.rad2deg(da) < 0.1, (dp, np.rad2deg(da))
    dp, da = pose_error(res.best.T_base_board, T_world_board)
    assert dp < 1e-3 and np.rad2deg(da) < 0.1
    # The closed forms that work here are within the brief's tolerance on their own.
    for m in ("park", "daniilidis"):
        dp, da = pose_error(res.candidates[m].T_link_camera, cam.T_link_camera)
        assert dp < 1e-3 and np.rad2deg(da) < 0.1, (m, dp, np.rad2deg(da))
    # The choice is by consistency: nothing scores better than the chosen one.
    assert all(res.best.rms_px <= c.rms_px for c in res.candidates.values())
    assert res.best.rms_px < 0.2


def test_consistency_exposes_a_wrong_solution(captured):
    """A solution 2 mm off scores visibly worse than the true one."""
    from vespro.calib.handeye import consistency
    from vespro.calib.pose import board_pose

    _, dets, links, _ = captured
    cam = _true_rig()["hand"]
    names = [n for n, d in dets.items() if d is not None]
    Tl = [links[n] for n in names]
    Tc = [board_pose(cam.intrinsics, dets[n], SPEC) for n in names]
    good = consistency("true", cam.T_link_camera, Tl, Tc, [dets[n] for n in names], cam.intrinsics, SPEC)
    X = cam.T_link_camera.copy()
    X[:3, 3] += [0.002, 0.0, 0.0]
    bad = consistency("off", X, Tl, Tc, [dets[n] for n in names], cam.intrinsics, SPEC)
    assert bad.spread_m > 1e-3 > good.spread_m
    assert bad.rms_px > 2 * good.rms_px


def test_missing_pose_row_is_named(captured):
    _, dets, links, _ = captured
    cam = _true_rig()["hand"]
    some = dict(links)
    del some["000004"]
    with pytest.raises(CalibrationError, match="000004"):
        calibrate_hand_eye(some, dets, cam.intrinsics, SPEC)


def test_cli_writes_eye_in_hand_mount(captured, tmp_path):
    folder, _, _, _ = captured
    cam = _true_rig()["hand"]
    # Intrinsics known, mounting not: written as a fixed camera by the intrinsics step.
    save_rig(Rig((RigCamera("hand", cam.intrinsics, "fixed", T_world_camera=np.eye(4)),)), tmp_path / "cameras.yaml")
    assert main(["calibrate", "hand-eye", str(folder), "--rig", str(tmp_path / "cameras.yaml"),
                 "--camera", "hand"]) == 0
    out = load_rig(tmp_path / "cameras.yaml")["hand"]
    assert out.mount == "eye_in_hand" and out.link == "flange"
    dp, da = pose_error(out.T_link_camera, cam.T_link_camera)
    assert dp < 1e-3 and np.rad2deg(da) < 0.1


def test_cli_sim_end_to_end(tmp_path, capsys):
    """--sim: capture, then the same image-folder path; the rig file gains the
    simulated camera (intrinsics seeded from the simulator) and its mounting."""
    rig_file = tmp_path / "cameras.yaml"
    argv = ["calibrate", "hand-eye", str(tmp_path / "he"), "--sim", "--sim-views", "8", "--camera", "hand",
            "--rig", str(rig_file)]
    assert main(argv) == 0
    out = load_rig(rig_file)["hand"]
    cam = _true_rig()["hand"]
    dp, da = pose_error(out.T_link_camera, cam.T_link_camera)
    assert dp < 1e-3 and np.rad2deg(da) < 0.1
    assert "chosen: refined" in capsys.readouterr().out
    assert main(argv) == 1  # the folder now holds images: a second capture would mix with them
    assert "new or empty folder" in capsys.readouterr().err
