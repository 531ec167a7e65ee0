"""Calibration files: pose CSVs and rig-file updates."""

import numpy as np
import pytest

from vespro.calib import CalibrationError
from vespro.calib.io import lookup_pose, parse_pose, read_pose_csv, update_rig_camera, write_pose_csv
from vespro.camera import CameraIntrinsics
from vespro.rig import load_rig
from vespro.se3 import exp_so3, transform_from_rt

INTR = CameraIntrinsics(640, 480, [[600.0, 0, 320.0], [0, 600.0, 240.0], [0, 0, 1]], (-0.1, 0.01, 0, 0, 0))


def test_pose_csv_round_trip_and_lookup(tmp_path):
    T = {i: transform_from_rt(exp_so3([0.1 * i, -0.2, 0.3]), [i, 2.0, 3.0]) for i in range(3)}
    write_pose_csv(tmp_path / "p.csv", T, key="index")
    back = read_pose_csv(tmp_path / "p.csv", "index")
    for i in range(3):
        np.testing.assert_allclose(lookup_pose(back, f"{i:06d}"), T[i], atol=1e-8)
    assert lookup_pose(back, "000009") is None and lookup_pose(back, "left") is None


@pytest.mark.parametrize("body, match", [
    ("index,x,y,z,qw,qx,qy\n0,1,2,3,1,0,0\n", r"missing column.*qz"),
    ("index,x,y,z,qw,qx,qy,qz\n0,1,2,3,1,0,0,zero\n", r"line 2: malformed"),
    ("index,x,y,z,qw,qx,qy,qz\n0,1,2,3,1,1,0,0\n", r"line 2: quaternion.*1.414"),
    ("index,x,y,z,qw,qx,qy,qz\n0,1,2,3,1,0,0,0\n0,1,2,3,1,0,0,0\n", r"line 3: duplicate index '0'"),
    ("index,x,y,z,qw,qx,qy,qz\n", r"no poses"),
])
def test_pose_csv_errors_name_file_and_line(tmp_path, body, match):
    (tmp_path / "p.csv").write_text(body)
    with pytest.raises(CalibrationError, match=match) as e:
        read_pose_csv(tmp_path / "p.csv", "index")
    assert "p.csv" in str(e.value)


def test_parse_pose():
    np.testing.assert_allclose(parse_pose("1,2,3,1,0,0,0")[:3, 3], [1, 2, 3])
    with pytest.raises(CalibrationError, match="7"):
        parse_pose("1,2,3")


def test_update_rig_keeps_other_cameras_and_mounts(tmp_path):
    path = tmp_path / "cameras.yaml"
    update_rig_camera(path, "a", intrinsics=INTR)  # new: fixed at identity until extrinsics
    T = transform_from_rt(exp_so3([0.0, 0.2, 0.0]), [1.0, 0.0, 1.0])
    update_rig_camera(path, "b", intrinsics=INTR)
    update_rig_camera(path, "b", link="flange", T_link_camera=T)
    update_rig_camera(path, "a", T_world_camera=T)
    new_intr = CameraIntrinsics(640, 480, [[610.0, 0, 321.0], [0, 611.0, 239.0], [0, 0, 1]])
    update_rig_camera(path, "b", intrinsics=new_intr)  # intrinsics only: mounting stays
    rig = load_rig(path)
    assert rig.names == ["a", "b"]
    np.testing.assert_allclose(rig["a"].T_world_camera, T, atol=1e-8)
    assert rig["b"].mount == "eye_in_hand" and rig["b"].link == "flange"
    np.testing.assert_allclose(rig["b"].T_link_camera, T, atol=1e-8)
    assert rig["b"].intrinsics.fx == 610.0
    with pytest.raises(CalibrationError, match="'c' is not in the rig file"):
        update_rig_camera(path, "c", T_world_camera=T)
