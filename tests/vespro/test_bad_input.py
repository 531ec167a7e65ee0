"""Bad input against every command that reads it: one line naming the file, or a counted report.

Each row damages a tiny recording (two cameras, three frames of 64x48 pixels)
in one way and runs one command through ``vespro.cli.main``: a malformed file
gives exit status 2 and a line naming it; images that cannot be used are
counted per camera and reason at the end, and a camera without any usable
image is named in a warning. Nothing prints a traceback or a libpng line.
"""

import re
import shutil
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from vespro.camera import CameraIntrinsics
from vespro.cli import main
from vespro.frames import FrameSet
from vespro.groundtruth import GroundTruthWriter
from vespro.imagecheck import ImageTally, read_image
from vespro.recording import RecordingWriter
from vespro.rig import Rig, RigCamera
from vespro.se3 import exp_so3, transform_from_rt

ROOT = Path(__file__).resolve().parents[2]
BOX = ROOT / "models" / "objects" / "box.stl"
W, H, N = 64, 48, 3
POSE = "0,0,0,1,0,0,0"


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A recording: fixed camera 'a' and eye-in-hand camera 'h' above the box, ground truth."""
    out = tmp_path_factory.mktemp("bad_input") / "rec"
    K = [[60, 0, 31.5], [0, 60, 23.5], [0, 0, 1]]
    T_wc = transform_from_rt(exp_so3([np.pi, 0, 0]), [0, 0, 1.0])
    rig = Rig((RigCamera("a", CameraIntrinsics(W, H, K), "fixed", T_world_camera=T_wc),
               RigCamera("h", CameraIntrinsics(W, H, K), "eye_in_hand", link="flange",
                         T_link_camera=transform_from_rt(np.eye(3), [0, 0, 0.1]))))
    rng = np.random.default_rng(0)
    with RecordingWriter(out, rig, BOX, 26.0, "box") as w, GroundTruthWriter(out) as gt:
        for k in range(N):
            images = {c: rng.integers(0, 256, (H, W), dtype=np.uint8) for c in ("a", "h")}
            w.write(FrameSet(k, k * 38_461_538, images, {"h": T_wc}))
            gt.write(k, k / 26.0, np.eye(4))
    return out


# -- damage -------------------------------------------------------------------------
def _sub(name, old, new, regex=False):
    def damage(rec):
        p = rec / name
        s = p.read_text()
        s2 = re.sub(old, new, s, count=1) if regex else s.replace(old, new, 1)
        assert s2 != s, (name, old)
        p.write_text(s2)
    return damage


def _field(name, line, col, value):
    def damage(rec):
        p = rec / name
        lines = p.read_text().splitlines()
        parts = lines[line - 1].split(",")
        parts[col] = value
        lines[line - 1] = ",".join(parts)
        p.write_text("\n".join(lines) + "\n")
    return damage


def _drop_lines(name, *lines):
    def damage(rec):
        p = rec / name
        rows = [r for i, r in enumerate(p.read_text().splitlines(), 1) if i not in lines]
        p.write_text("\n".join(rows) + "\n")
    return damage


def _truncate(p):
    b = p.read_bytes()
    p.write_bytes(b[: len(b) // 2])


IMAGE_FAULTS = {
    "truncated": _truncate,
    "wrong size": lambda p: cv2.imwrite(str(p), np.zeros((H // 2, W // 2), np.uint8)),
    "wrong depth": lambda p: cv2.imwrite(str(p), np.zeros((H, W), np.uint16)),
    "unreadable": lambda p: p.write_bytes(b"this is not an image"),
    "missing": lambda p: p.unlink(),
}


def _images(fault, whole):
    def damage(rec):
        files = sorted((rec / "frames" / "a").glob("*.png")) if whole else [rec / "frames" / "a" / "000001.png"]
        for f in files:
            IMAGE_FAULTS[fault](f)
    return damage


# (name, damage, file named in the message, expected text)
RIG = [
    ("negative focal", _sub("cameras.yaml", "[60.0,", "[-60.0,"), "cameras.yaml", "fx=-60"),
    ("zero focal", _sub("cameras.yaml", "[60.0,", "[0.0,"), "cameras.yaml", "fx=0"),
    ("NaN in pose", _sub("cameras.yaml", r"T_world_camera: \[[^,]+,", "T_world_camera: [.nan,", True),
     "cameras.yaml", "T_world_camera: element 0 is nan"),
    ("inf in intrinsics", _sub("cameras.yaml", "[60.0,", "[.inf,"), "cameras.yaml", "camera_matrix: element 0 is inf"),
    ("non-unit quaternion", _sub("cameras.yaml", r"(T_world_camera: \[[^,]+, [^,]+, [^,]+, )[^,]+,", r"\g<1>2.0,", True),
     "cameras.yaml", "must have unit norm"),
    ("missing field", _sub("cameras.yaml", "  image_width: 64\n", ""), "cameras.yaml", "missing field 'image_width'"),
    ("unknown mount", _sub("cameras.yaml", "mount: fixed", "mount: ceiling"), "cameras.yaml", "got 'ceiling'"),
    ("not YAML", lambda r: (r / "cameras.yaml").write_text("cameras: [ {name: a\n"), "cameras.yaml",
     "not valid YAML"),
]
RECORDING = [
    ("meta.yaml malformed", lambda r: (r / "meta.yaml").write_text("format: vespro-recording\nversion: [1\n"),
     "meta.yaml", "not valid YAML"),
    ("frames.csv missing row", _drop_lines("frames.csv", 3), "frames.csv", "line 3: field 'index' is 2 where 1 was due"),
    ("frames.csv NaN eye-in-hand pose", _field("frames.csv", 2, 2, "nan"), "frames.csv", "line 2: field(s) h.x not finite"),
    ("frames.csv t not monotonic", _field("frames.csv", 4, 1, "0.0"), "frames.csv", "line 4: field 't'"),
]
COMMANDS = {
    "track": lambda r: ["track", str(r), "-o", str(r / "poses.csv"), "--init-pose", POSE, "--no-progress"],
    "eval": lambda r: ["eval", str(r), "-o", str(r / "eval"), "--gt-init", "--no-progress", "--no-video"],
    "bop export": lambda r: ["bop", "export", str(r), str(r / "bop")],
    "serve": lambda r: ["serve", "--source", "replay", "--recording", str(r), "--lockstep", "--init-pose", POSE,
                        "--tcp", "0", "--quiet"],
}
RIG_COMMANDS = dict(COMMANDS, calibrate=lambda r: ["calibrate", "extrinsics", str(r / "frames"),
                                                    "--rig", str(r / "cameras.yaml")])


@pytest.fixture(autouse=True)
def no_plots(monkeypatch):
    """eval's error plot is not what these tests look at (and is most of eval's time on three frames)."""
    import vespro.evaluate

    monkeypatch.setattr(vespro.evaluate, "plot_errors", lambda *a, **k: None)


def _run(base, tmp_path, damage, argv, capfd):
    rec = tmp_path / "rec"
    shutil.copytree(base, rec)
    damage(rec)
    rc = main(argv(rec))
    out, err = capfd.readouterr()
    assert "Traceback" not in err and "libpng" not in err, err
    return rc, out, err


def _one_line(err, command):
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"vespro {command.split()[0]}"), lines[0]
    return lines[0]


MALFORMED = [(case, command) for case in RIG for command in RIG_COMMANDS] + \
            [(case, command) for case in RECORDING for command in COMMANDS]


@pytest.mark.parametrize("case, command", MALFORMED, ids=[f"{c[0]}-{cmd}" for c, cmd in MALFORMED])
def test_malformed_file_is_one_line_and_exit_2(base, tmp_path, capfd, case, command):
    _, damage, file, text = case
    rc, _, err = _run(base, tmp_path, damage, RIG_COMMANDS[command], capfd)
    line = _one_line(err, command)
    assert rc == 2 and file in line and text in line, line


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("whole", [False, True], ids=["one frame", "whole camera"])
@pytest.mark.parametrize("fault", IMAGE_FAULTS)
def test_bad_images_are_counted_and_reported(base, tmp_path, capfd, command, fault, whole):
    rc, out, err = _run(base, tmp_path, _images(fault, whole), COMMANDS[command], capfd)
    assert rc == 0, err
    n = N if whole else 1
    first = "000000.png" if whole else "000001.png"
    lines = [x for x in err.splitlines() if x.strip()]
    report = [x for x in lines if "camera 'a':" in x]
    assert len(report) == 1, lines
    assert f"camera 'a': {n} of {N} images not used ({fault} {n}); first: " in report[0], report[0]
    assert str(tmp_path / "rec" / "frames" / "a" / first) in report[0], report[0]
    dead = [x for x in lines if "gave no usable image in the whole run" in x]
    assert len(dead) == (1 if whole else 0), lines
    if whole:
        assert dead[0].startswith(f"vespro {command}: warning: camera 'a'"), dead[0]
    assert not any("camera 'h'" in x for x in lines), lines  # the other camera is fine


def test_no_usable_image_at_all_is_an_error(base, tmp_path, capfd):
    def damage(rec):
        for f in (rec / "frames").glob("*/*.png"):
            _truncate(f)
    rc, _, err = _run(base, tmp_path, damage, COMMANDS["track"], capfd)
    assert rc == 2 and "no camera gave a usable image" in err.splitlines()[-1], err
    assert "camera 'a': 3 of 3" in err and "camera 'h': 3 of 3" in err


@pytest.mark.parametrize("command", COMMANDS)
def test_frames_csv_cut_short_is_reported(base, tmp_path, capfd, command):
    rc, out, err = _run(base, tmp_path, _drop_lines("frames.csv", 4), COMMANDS[command], capfd)
    assert rc == 0, err
    warning = [x for x in err.splitlines() if "frames.csv: lists 2 frames" in x]
    assert len(warning) == 1 and "frames/a 1 (up to index 2)" in warning[0], err
    if command == "track":
        assert "0/2 frames" in out or "/2 frames tracking" in out, out


@pytest.mark.parametrize("command", ["eval", "bop export"])
def test_groundtruth_nan_rows_are_named_and_skipped(base, tmp_path, capfd, command):
    rc, out, err = _run(base, tmp_path, _field("groundtruth.csv", 3, 4, "nan"), COMMANDS[command], capfd)
    assert rc == 0, err
    assert "groundtruth.csv: no finite pose at index 1 (line 3)" in err, err
    if command == "eval":
        assert not re.search(r"\bnan\b", out.lower()), out


@pytest.mark.parametrize("name, damage, text", [
    ("NaN at frame 0 with --gt-init", _field("groundtruth.csv", 2, 2, "nan"), "line 2: no finite pose at index 0"),
    ("too few rows", _drop_lines("groundtruth.csv", 4), "2 rows for the 3 frames"),
    ("not a number", _field("groundtruth.csv", 3, 5, "abc"), "line 3: field 'qw' is not a number"),
])
def test_malformed_groundtruth(base, tmp_path, capfd, name, damage, text):
    rc, _, err = _run(base, tmp_path, damage, COMMANDS["eval"], capfd)
    line = _one_line(err, "eval")
    assert rc == 2 and "groundtruth.csv" in line and text in line, line


def test_scores_skip_frames_without_truth():
    from vespro.evaluate import score
    from vespro.model import load_model

    T = [transform_from_rt(np.eye(3), [0.001 * k, 0, 0]) for k in range(4)]
    T_true = np.array([np.eye(4)] * 4)
    T_true[2] = np.nan
    s = score(T, ["tracking"] * 4, T_true, np.arange(4) / 26.0, load_model(BOX))
    assert s["frames_without_truth"] == 1 and s["tracked_fraction"] == 1.0
    assert s["position_rmse_mm"] == pytest.approx(np.sqrt((0 + 1 + 9) / 3))


def test_replay_status_line_counts_rejected_images(base, tmp_path):
    from vespro.clock import SimClock
    from vespro.model import load_model
    from vespro.recording import Recording
    from vespro.server import PoseServer
    from vespro.sources import ReplaySource
    from vespro.tracker import Tracker

    rec_path = tmp_path / "rec"
    shutil.copytree(base, rec_path)
    _images("truncated", True)(rec_path)
    rec = Recording(rec_path)
    lines = []
    clock = SimClock()
    server = PoseServer(ReplaySource(rec, clock, loop=True), Tracker(rec.rig, load_model(rec.model_path)), None,
                        clock, None, background_init=False, log=lines.append)
    server.run(max_frames=30)  # 30 frames at 26 Hz: one status line
    m = re.search(r"\| images not used: a (\d+) \(truncated (\d+)\)$", lines[-1]) if lines else None
    assert m and m.group(1) == m.group(2) and int(m.group(1)) >= 26, lines  # every image of 'a' so far


# -- the image reader itself ------------------------------------------------------------
def _png(img) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


def _chunks(data: bytes):
    o, out = 8, []
    while o < len(data):
        n, t = struct.unpack_from(">I4s", data, o)
        out.append((t, o, n))
        o += 12 + n
    return out


@pytest.mark.parametrize("cut", [4, 20, 40, -13, -1])
def test_reader_names_truncation_at_any_point(tmp_path, capfd, cut):
    data = _png(np.random.default_rng(1).integers(0, 256, (H, W), dtype=np.uint8))
    p = tmp_path / "x.png"
    p.write_bytes(data[:cut])
    res = read_image(p, W, H)
    assert res.image is None and res.reason == "truncated", res
    assert res.describe().startswith(f"{p}: truncated")
    assert capfd.readouterr().err == ""


def test_reader_catches_damage_without_libpng_noise(tmp_path, capfd):
    data = bytearray(_png(np.random.default_rng(2).integers(0, 256, (H, W), dtype=np.uint8)))
    _, o, n = next(c for c in _chunks(bytes(data)) if c[0] == b"IDAT")
    data[o + 8 + n // 2] ^= 0xFF  # a flipped byte: the chunk's CRC no longer matches
    p = tmp_path / "x.png"
    p.write_bytes(bytes(data))
    res = read_image(p, W, H)
    assert res.reason == "unreadable" and "CRC mismatch in chunk IDAT" in res.detail, res
    assert capfd.readouterr().err == ""


def test_reader_accepts_grey_colour_and_alpha(tmp_path):
    rng = np.random.default_rng(3)
    for img, shape in [(rng.integers(0, 256, (H, W), dtype=np.uint8), (H, W)),
                       (rng.integers(0, 256, (H, W, 3), dtype=np.uint8), (H, W, 3)),
                       (rng.integers(0, 256, (H, W, 4), dtype=np.uint8), (H, W, 3))]:
        p = tmp_path / "x.png"
        p.write_bytes(_png(img))
        res = read_image(p, W, H)
        assert res.reason is None and res.image.shape == shape and res.image.dtype == np.uint8
        np.testing.assert_array_equal(res.image, img[..., :3] if img.ndim == 3 else img)


def test_tally_counts_and_names_dead_cameras(tmp_path):
    tally = ImageTally(["a", "b"])
    good = tmp_path / "g.png"
    good.write_bytes(_png(np.zeros((H, W), np.uint8)))
    for _ in range(3):
        tally.note("a", read_image(good, W, H))
        tally.note("b", read_image(tmp_path / "none.png", W, H))
    tally.note("a", read_image(good, W + 1, H))
    assert tally.dead() == ["b"] and tally.as_dict() == {"a": {"usable": 3, "wrong size": 1},
                                                         "b": {"usable": 0, "missing": 3}}
    assert tally.status() == "images not used: a 1 (wrong size 1); b 3 (missing 3)"
    rep = tally.report()
    assert len(rep) == 3 and rep[2].startswith("warning: camera 'b' gave no usable image"), rep


def test_help_states_the_policy(capsys):
    for cmd in ("track", "eval"):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "no usable image in the whole run" in text and "exit status stays 0" in text, cmd


@pytest.mark.parametrize("extra, text", [
    (["--workspace", "0,0,0,1,1"], "six numbers"),
    (["--workspace", "0,0,1,1,1,0.5"], "z1 > z0"),
], ids=["five numbers", "empty"])
def test_a_bad_working_volume_is_one_line_and_exit_2(base, tmp_path, capfd, extra, text):
    rc, _, err = _run(base, tmp_path, lambda r: None, lambda r: COMMANDS["track"](r) + extra, capfd)
    line = _one_line(err, "track")
    assert rc == 2 and "--workspace" in line and text in line, line
