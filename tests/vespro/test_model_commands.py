"""Every command that takes a model checks it at the door: one line, exit 2, no traceback.

Bad models (millimetres read as metres, an open surface, an empty file, an STL
with zero triangles, a malformed .cao) against every entry point: record,
track, eval, serve (sim, replay, camera), demo, bop export and import visp.
An inside-out mesh is turned right way out with a note instead.
"""

import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vespro.cli import build_parser, main
from vespro.frames import FrameSet
from vespro.groundtruth import GroundTruthWriter
from vespro.model import load_model
from vespro.recording import RecordingWriter
from vespro.rig import Rig, RigCamera
from vespro.camera import CameraIntrinsics

BOX = trimesh.creation.box(extents=[0.12, 0.08, 0.06])

# (kind, file name, writer, what the one line must say)
BAD = {
    "mm": ("box_mm.stl", lambda p: trimesh.Trimesh(BOX.vertices * 1000, BOX.faces).export(p),
           r"box_mm.stl: largest extent 120 m exceeds 5 m .*--model-unit mm"),
    "open": ("open.stl", lambda p: trimesh.Trimesh(BOX.vertices, BOX.faces[2:], process=False).export(p),
             r"open.stl: not watertight: 4 boundary edge.*closed solid"),
    "empty": ("empty.stl", lambda p: p.write_bytes(b""), r"empty.stl: file is empty"),
    "zero": ("zero.stl", lambda p: p.write_bytes(b"\0" * 80 + struct.pack("<I", 0)),
             r"zero.stl: no triangles found"),
    "cao": ("bad.cao", lambda p: p.write_text("V1\n3\n0 0 0\n1 0 0\n"), r"bad.cao:4: file ends where 3D point 2"),
}


@pytest.fixture
def model_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("VESPRO_MODEL_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def _bad(tmp_path: Path, kind: str) -> tuple[Path, str]:
    name, write, match = BAD[kind]
    p = tmp_path / name
    write(p)
    return p, match


def _recording(tmp_path: Path, model: Path) -> Path:
    """A two-frame, one-camera recording (with ground truth) carrying ``model`` as is."""
    K = np.array([[300.0, 0, 80], [0, 300.0, 60], [0, 0, 1]])
    rig = Rig((RigCamera("cam0", CameraIntrinsics(160, 120, K), "fixed", T_world_camera=np.eye(4)),))
    path = tmp_path / "rec"
    with RecordingWriter(path, rig, model, 10.0, "part") as w:
        for i in range(2):
            w.write(FrameSet(i, i * 100_000_000, {"cam0": np.zeros((120, 160), np.uint8)}))
    with GroundTruthWriter(path) as g:
        for i in range(2):
            T = np.eye(4)
            T[2, 3] = 0.5
            g.write(i, 0.1 * i, T)
    return path


def _argv(command: str, tmp_path: Path, model: Path) -> list[str]:
    out = str(tmp_path / "out")
    if command == "record":
        return ["record", out, "--object", str(model), "--frames", "1", "--no-progress"]
    if command == "serve-sim":
        return ["serve", "--source", "sim", "--object", str(model), "--frames", "1", "--quiet", "--lockstep"]
    if command == "serve-camera":
        return ["serve", "--source", "camera", "--model", str(model), "--rig", "fixed1", "--frames", "1", "--quiet"]
    if command == "demo":
        return ["demo", "--object", str(model), "--out", out, "--no-video", "--lockstep"]
    if command == "import":
        folder, name = tmp_path / "visp", model.stem
        (folder / name).mkdir(parents=True)
        import cv2

        cv2.imwrite(str(folder / name / "image0000.pgm"), np.zeros((120, 160), np.uint8))
        (folder / f"{name}.xml").write_text("<conf><camera><u0>80</u0><v0>60</v0><px>300</px><py>300</py>"
                                            "</camera></conf>")
        (folder / model.name).write_bytes(model.read_bytes())
        return ["import", "visp", str(folder), "-o", out, "--no-progress"]
    rec = str(_recording(tmp_path, model))
    return {
        "track": ["track", rec, "-o", out + ".csv", "--init-pose", "0,0,0.5,1,0,0,0", "--no-progress"],
        "eval": ["eval", rec, "-o", out, "--gt-init", "--no-video", "--no-progress"],
        "serve-replay": ["serve", "--source", "replay", "--recording", rec, "--frames", "1", "--quiet", "--lockstep"],
        "bop": ["bop", "export", rec, out],
    }[command]


FILE_COMMANDS = ["record", "serve-sim", "serve-camera", "demo", "import"]
RECORDING_COMMANDS = ["track", "eval", "serve-replay", "bop"]


# A recording's model is an STL, OBJ or PLY (the spec); the ViSP importer reads .cao models.
CASES = [(c, k) for c in FILE_COMMANDS + RECORDING_COMMANDS for k in BAD
         if not (c in RECORDING_COMMANDS and k == "cao") and not (c == "import" and k != "cao")]


@pytest.mark.parametrize("command, kind", CASES)
def test_bad_model_gives_one_line_and_exit_2(tmp_path, capsys, model_cache, command, kind):
    model, match = _bad(tmp_path, kind)
    if command in RECORDING_COMMANDS:  # the recording holds the file as model.stl
        match = match.replace(model.name, "rec/model.stl")
    assert main(_argv(command, tmp_path, model)) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    import re

    assert re.search(match, lines[0]), lines[0]
    assert not (tmp_path / "out").exists()  # bad input leaves nothing behind


def test_millimetre_model_is_taken_with_model_unit(tmp_path, model_cache):
    """The fix the message names works: record's scenario is built with the part in metres."""
    model, _ = _bad(tmp_path, "mm")
    from vespro.sim.scenario import build_config

    args = build_parser().parse_args(["record", str(tmp_path / "r"), "--object", str(model), "--model-unit", "mm"])
    config, _, name = build_config(args)
    m = load_model(config.object_mesh)
    assert name == "box_mm" and Path(config.object_mesh).suffix == ".stl"
    # float32 STL of 0.12 m: within 1e-8 m of the true size.
    np.testing.assert_allclose(m.bounds[1] - m.bounds[0], [0.12, 0.08, 0.06], atol=1e-8)
    # Track and eval take the same option for a recording's model file.
    rec = _recording(tmp_path, model)
    from vespro.recording import Recording
    from vespro.track import make_tracker

    with pytest.raises(Exception, match="--model-unit mm"):
        make_tracker(Recording(rec))
    assert abs(make_tracker(Recording(rec), unit="mm").model.volume - 0.12 * 0.08 * 0.06) < 1e-9


def test_inside_out_model_is_turned_once_with_a_note(tmp_path, capsys, model_cache):
    inv = tmp_path / "inv.stl"
    trimesh.Trimesh(BOX.vertices, BOX.faces[:, ::-1], process=False).export(inv)
    from vespro.sim.scenario import build_config

    args = build_parser().parse_args(["record", str(tmp_path / "r"), "--object", str(inv)])
    config, _, name = build_config(args)
    err = capsys.readouterr().err
    assert err.count("inv.stl: every face pointed inward") == 1 and err.count("\n") == 1
    # What the simulator and the recording get is the turned mesh, in the cache, under the same stem.
    assert Path(config.object_mesh).parent.parent == model_cache and name == "inv"
    m = load_model(config.object_mesh)
    assert m.volume > 0 and capsys.readouterr().err == ""


def test_a_good_metre_file_is_used_as_is(tmp_path, model_cache):
    from vespro.model import model_file_in_metres

    p = tmp_path / "good.stl"
    BOX.export(p)
    assert model_file_in_metres(p) == p and not model_cache.exists()


@pytest.mark.parametrize("text, match", [
    ("0,0", r"--init-pose needs 7 numbers"),
    ("nowhere.txt", r"--init-pose: 'nowhere.txt' is neither 7 numbers .* nor an existing file"),
    ("FILE", r"--init-pose file .*pose.txt needs 7 numbers x,y,z,qw,qx,qy,qz, got 3"),
    ("0,0,0.5,2,0,0,0", r"quaternion must be unit length"),
])
def test_init_pose_errors_are_one_line(tmp_path, capsys, model_cache, text, match):
    good = tmp_path / "good.stl"
    BOX.export(good)
    rec = _recording(tmp_path, good)
    if text == "FILE":
        text = str(tmp_path / "pose.txt")
        Path(text).write_text("# a comment\n1 2 3\n")
    for argv in (["track", str(rec), "-o", str(tmp_path / "p.csv"), "--no-progress"],
                 ["eval", str(rec), "-o", str(tmp_path / "e"), "--no-video", "--no-progress"]):
        assert main([*argv, "--init-pose", text]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and err.count("\n") == 1
        import re

        assert re.search(match, err), err


def test_init_pose_file_reads_as_the_numbers(tmp_path):
    from vespro.track import parse_pose

    p = tmp_path / "init_pose.txt"
    p.write_text("# T_world_object\n0.1, 0.2, 0.3,\n0.7071067811865476 0 0.7071067811865476 0  # about y\n")
    np.testing.assert_allclose(parse_pose(str(p)), parse_pose("0.1,0.2,0.3,0.7071067811865476,0,0.7071067811865476,0"))
    T = parse_pose(str(p))
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 0, -1], atol=1e-12)  # 90 deg about y
