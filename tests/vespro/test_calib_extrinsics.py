"""Fixed-camera extrinsics against the simulator's truth.

Three fixed cameras (fixed3) with plumb_bob distortion; a 9x6 ChArUco board of
45 mm squares at four known world placements (captured once per module). The
cameras' intrinsics are the true ones, so this checks the extrinsic stage alone.
"""

import numpy as np
import pytest

from vespro.calib import CalibrationError
from vespro.calib.board import BoardSpec, detect_board
from vespro.calib.extrinsics import calibrate_extrinsics
from vespro.calib.io import list_images, load_images, lookup_pose, read_pose_csv
from vespro.camera import CameraIntrinsics
from vespro.cli import main
from vespro.rig import Rig, RigCamera, load_rig, save_rig
from vespro.se3 import pose_error
from vespro.sim.rigs import CAMERAS_DIR

DIST = (-0.22, 0.09, 0.0006, -0.0004, -0.015)
SPEC = BoardSpec("charuco", 9, 6, 0.045, 0.034)


def _true_rig():
    rig = load_rig(CAMERAS_DIR / "fixed3.yaml")
    return Rig(tuple(RigCamera(c.name, CameraIntrinsics(640, 480, c.intrinsics.K, DIST), "fixed",
                               T_world_camera=c.T_world_camera) for c in rig))


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    from vespro.sim.board import capture_extrinsics

    folder = tmp_path_factory.mktemp("ext")
    rig = _true_rig()
    capture_extrinsics(rig, SPEC, folder, n_placements=4)
    dets = {}
    for c in rig.names:
        for p, img in load_images(list_images(folder / c)).items():
            dets[(c, p)] = detect_board(img, SPEC)
    known = read_pose_csv(folder / "board_poses.csv", "placement")
    return folder, dets, {p: lookup_pose(known, p) for p in {p for _, p in dets}}


def _check(res, rig):
    for c in rig:
        dp, da = pose_error(res.T_world_camera[c.name], c.T_world_camera)
        assert dp < 1e-3 and np.rad2deg(da) < 0.05, (c.name, dp, np.rad2deg(da))
        assert res.rms_px[c.name] < 0.3


def test_known_placements_give_true_camera_poses(captured):
    _, dets, known = captured
    rig = _true_rig()
    res = calibrate_extrinsics(dets, {c.name: c.intrinsics for c in rig}, known, SPEC)
    _check(res, rig)


def test_one_known_placement_and_free_ones(captured):
    """Only placement 0 is surveyed; the others are estimated jointly and still
    tie every camera down (and come out at their true poses)."""
    _, dets, known = captured
    rig = _true_rig()
    first = sorted(known)[0]
    res = calibrate_extrinsics(dets, {c.name: c.intrinsics for c in rig}, {first: known[first]}, SPEC)
    _check(res, rig)
    for p, T in known.items():
        if any(k[1] == p for k in res.view_rms_px):
            dp, da = pose_error(res.T_world_board[p], T)
            assert dp < 1e-3 and np.rad2deg(da) < 0.05


def test_camera_without_any_board_is_named(captured):
    _, dets, known = captured
    rig = _true_rig()
    blind = {k: (None if k[0] == "cam_top" else d) for k, d in dets.items()}
    with pytest.raises(CalibrationError, match=r"cam_top \(board found in no image; not found in"):
        calibrate_extrinsics(blind, {c.name: c.intrinsics for c in rig}, known, SPEC)


def test_cli_updates_rig(captured, tmp_path):
    folder, _, _ = captured
    rig = _true_rig()
    # Start from a rig with the right intrinsics and wrong poses.
    wrong = Rig(tuple(RigCamera(c.name, c.intrinsics, "fixed", T_world_camera=np.eye(4)) for c in rig))
    save_rig(wrong, tmp_path / "cameras.yaml")
    assert main(["calibrate", "extrinsics", str(folder), "--rig", str(tmp_path / "cameras.yaml")]) == 0
    out = load_rig(tmp_path / "cameras.yaml")
    for c in rig:
        dp, da = pose_error(out[c.name].T_world_camera, c.T_world_camera)
        assert dp < 1e-3 and np.rad2deg(da) < 0.05


def test_cli_refuses_eye_in_hand_camera(captured, tmp_path, capsys):
    folder, _, _ = captured
    cams = []
    for c in _true_rig():
        if c.name == "cam_top":
            c = RigCamera(c.name, c.intrinsics, "eye_in_hand", link="flange", T_link_camera=np.eye(4))
        cams.append(c)
    save_rig(Rig(tuple(cams)), tmp_path / "cameras.yaml")
    assert main(["calibrate", "extrinsics", str(folder), "--rig", str(tmp_path / "cameras.yaml")]) == 1
    assert "['cam_top'] ride on the robot" in capsys.readouterr().err
