import subprocess
import sys

import pytest

from vespro.cli import main
from vespro.recording import Recording


def test_help_lists_record_and_explains_it():
    out = subprocess.run([sys.executable, "-m", "vespro", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "record" in out.stdout
    out = subprocess.run([sys.executable, "-m", "vespro", "record", "--help"], capture_output=True, text=True)
    assert "--noise" in out.stdout and "--occluder" in out.stdout and "--distortion" in out.stdout


def test_record_command_writes_a_readable_recording(tmp_path):
    rc = main(["record", str(tmp_path / "r"), "--object", "lblock", "--rig", "hybrid", "--motion", "random",
               "--frames", "4", "--noise", "0.5", "--distortion", "--resolution", "320x240", "--no-progress",
               "--drop", "cam_right:0.05:0.1"])
    assert rc == 0
    rec = Recording(tmp_path / "r")
    assert len(rec) == 4 and rec.rig.names == ["cam_left", "cam_right", "hand"]
    assert rec.rig["cam_left"].intrinsics.width == 320 and rec.rig["hand"].intrinsics.has_distortion
    assert rec.image("cam_right", 2) is None and rec.image("cam_right", 0) is not None
    assert (tmp_path / "r" / "groundtruth.csv").is_file()


@pytest.mark.parametrize("argv, match", [
    (["--object", "teapot"], "no object 'teapot'"),
    (["--rig", "nowhere"], "no rig 'nowhere'"),
])
def test_record_command_clear_errors(tmp_path, capsys, argv, match):
    assert main(["record", str(tmp_path / "r"), "--frames", "1", "--no-progress", *argv]) == 2
    assert match in capsys.readouterr().err
