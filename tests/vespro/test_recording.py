"""Recordings: round trip, the example made outside the project, malformed input."""

import ast
import shutil
from pathlib import Path

import numpy as np
import pytest

from vespro.camera import CameraIntrinsics
from vespro.frames import FrameSet
from vespro.recording import Recording, RecordingError, RecordingWriter
from vespro.rig import Rig, RigCamera
from vespro.se3 import exp_so3, transform_from_rt

ROOT = Path(__file__).resolve().parents[2]
BOX = ROOT / "models" / "objects" / "box.stl"


def _rig():
    K = [[500, 0, 159.5], [0, 500, 119.5], [0, 0, 1]]
    return Rig((
        RigCamera("a", CameraIntrinsics(320, 240, K), "fixed", T_world_camera=transform_from_rt(exp_so3([0.1, 0.2, 0.3]), [1, 2, 3])),
        RigCamera("h", CameraIntrinsics(320, 240, K, [0.1, -0.01, 0.001, 0.002, 0.0]), "eye_in_hand", link="flange",
                  T_link_camera=transform_from_rt(exp_so3([3.0, 0, 0]), [0, 0, 0.1])),
    ))


def _write(path, n=5, seed=0, drop=((2, "a"),)):
    rng = np.random.default_rng(seed)
    rig = _rig()
    sets = []
    with RecordingWriter(path, rig, BOX, 26.0, "box") as w:
        for k in range(n):
            images = {
                "a": rng.integers(0, 256, (240, 320, 3), dtype=np.uint8),
                "h": rng.integers(0, 256, (240, 320), dtype=np.uint8),
            }
            for i, cam in drop:
                if i == k:
                    images[cam] = None
            T = transform_from_rt(exp_so3(rng.normal(size=3)), rng.normal(size=3))
            fs = FrameSet(k, 1_000_000_000 + k * 38_461_538, images, {"h": T})
            w.write(fs)
            sets.append(fs)
    return rig, sets


def test_roundtrip_identical_arrays(tmp_path):
    rig, sets = _write(tmp_path / "rec")
    rec = Recording(tmp_path / "rec")
    assert len(rec) == len(sets) and rec.rate_hz == 26.0 and rec.object_name == "box"
    assert rec.model_path.name == "model.stl"
    for fs, back in zip(sets, rec):
        assert back.index == fs.index
        assert back.t_ns - rec.frameset(0).t_ns == pytest.approx(fs.t_ns - sets[0].t_ns, abs=1)
        for name in ("a", "h"):
            if fs.images[name] is None:
                assert back.images[name] is None
            else:
                np.testing.assert_array_equal(back.images[name], fs.images[name])
        # 9 decimals in frames.csv: 1e-9 m and ~1e-9 rad.
        np.testing.assert_allclose(back.T_world_camera["h"], fs.T_world_camera["h"], atol=5e-9)
    assert rec.missing == {"a": 1, "h": 0}
    np.testing.assert_allclose(rec.rig["h"].intrinsics.dist, rig["h"].intrinsics.dist)


def test_writer_refuses_to_clobber_and_out_of_order(tmp_path):
    _write(tmp_path / "rec")
    with pytest.raises(FileExistsError):
        RecordingWriter(tmp_path / "rec", _rig(), BOX, 26.0, "box")
    with RecordingWriter(tmp_path / "r2", _rig(), BOX, 26.0, "box") as w:
        with pytest.raises(ValueError, match="out of order"):
            w.write(FrameSet(3, 0, {}, {}))


def test_reads_the_example_recording_made_outside(example_box2):
    rec = Recording(example_box2)
    assert len(rec) == 60 and rec.rig.names == ["cam0", "cam1"]
    fs = rec.frameset(10)
    assert all(img is not None and img.shape[:2] == (480, 640) for img in fs.images.values())
    assert rec.t[1] == pytest.approx(1 / 26, abs=1e-5)


@pytest.mark.parametrize(
    "damage, match",
    [
        (lambda p: (p / "meta.yaml").unlink(), r"meta\.yaml: missing"),
        (lambda p: (p / "frames.csv").unlink(), r"frames\.csv: missing"),
        (lambda p: (p / "cameras.yaml").unlink(), r"cameras\.yaml: rig file not found"),
        (lambda p: (p / "model.stl").unlink(), r"model\.stl: model file named by meta\.yaml field 'model'"),
        (lambda p: _edit(p / "meta.yaml", "version: 1", "version: 7"), r"meta\.yaml: field 'version'"),
        (lambda p: _edit(p / "meta.yaml", "format: vespro-recording", "format: other"), r"meta\.yaml: field 'format'"),
        (lambda p: _edit(p / "meta.yaml", "rate_hz: 26.0", "rate_hz: fast"), r"meta\.yaml: field 'rate_hz'"),
        (lambda p: _edit(p / "meta.yaml", "model: model.stl", "model: ../x.stl"), r"meta\.yaml: field 'model'"),
        (lambda p: _edit(p / "meta.yaml", "rate_hz", "  rate_hz: [\n"), r"meta\.yaml: not valid YAML"),
        (lambda p: _edit(p / "frames.csv", "index,t", "idx,t"), r"frames\.csv: header must start"),
        (lambda p: _edit(p / "frames.csv", "h.qz", "h.qq"), r"frames\.csv: eye_in_hand camera 'h' needs column\(s\) h\.qz"),
        (lambda p: _edit(p / "frames.csv", "\n2,", "\n7,"), r"frames\.csv: line 4: field 'index' is 7 where 2 was due: the rows of indices 2-6 are missing"),
        (lambda p: _edit_line(p / "frames.csv", 3, 1, "soon"), r"frames\.csv: line 3: field 't' is not a number"),
        (lambda p: _edit_line(p / "frames.csv", 3, 5, "nan"), r"frames\.csv: line 3: field\(s\) h\.qw not finite: the eye_in_hand camera 'h'"),
        (lambda p: _edit(p / "cameras.yaml", "image_width: 320", "image_width: wide"), r"cameras\.yaml: camera 'a': image_width"),
    ],
)
def test_malformed_recordings_name_file_and_field(tmp_path, damage, match):
    _write(tmp_path / "rec")
    damage(tmp_path / "rec")
    with pytest.raises(RecordingError, match=match):
        Recording(tmp_path / "rec")


def _edit(path, old, new):
    s = path.read_text()
    assert old in s, (old, s[:200])
    path.write_text(s.replace(old, new, 1))


def _edit_line(path, line, field, value):
    lines = path.read_text().splitlines()
    parts = lines[line - 1].split(",")
    parts[field] = value
    lines[line - 1] = ",".join(parts)
    path.write_text("\n".join(lines) + "\n")


def test_bad_images_are_counted_not_fatal(tmp_path):
    _write(tmp_path / "rec", drop=())
    p = tmp_path / "rec" / "frames" / "a"
    (p / "000001.png").write_bytes(b"\x89PNG garbage")  # corrupt
    import cv2

    cv2.imwrite(str(p / "000003.png"), np.zeros((10, 10), np.uint8))  # wrong size
    shutil.rmtree(tmp_path / "rec" / "frames" / "h")  # a whole camera missing
    rec = Recording(tmp_path / "rec")
    sets = list(rec)
    assert sets[1].images["a"] is None and sets[3].images["a"] is None and sets[0].images["a"] is not None
    assert all(s.images["h"] is None for s in sets)
    assert rec.missing == {"a": 2, "h": 5}


def test_reader_never_opens_groundtruth(tmp_path, opened_files):
    from vespro.sim.cell import CellConfig
    from vespro.sim.motion import Conveyor
    from vespro.sim.record import record
    from vespro.rig import load_rig

    out = record(tmp_path / "rec", CellConfig(BOX, load_rig(ROOT / "cameras" / "fixed1.yaml")), Conveyor(), 3, "box")
    assert (out / "groundtruth.csv").is_file()
    opened_files.clear()  # from here on: what the reader opens
    rec = Recording(out)
    for _ in rec:
        pass
    assert opened_files and not any("groundtruth" in f for f in opened_files)
    # Nothing the tracker reads holds the object's true pose.
    gt_row = (out / "groundtruth.csv").read_text().splitlines()[1].split(",")
    for name in ("meta.yaml", "cameras.yaml", "frames.csv"):
        text = (out / name).read_text()
        assert gt_row[2] not in text and gt_row[5] not in text, name


def test_only_evaluators_and_the_simulator_import_groundtruth():
    allowed = {"vespro/groundtruth.py", "vespro/sim/record.py", "vespro/evaluate.py", "vespro/cmd_eval.py",
               "vespro/accuracy.py", "vespro/suite.py", "vespro/bop.py", "cellsim/demo.py"}
    offenders = []
    for path in sorted([*(ROOT / "vespro").rglob("*.py"), *(ROOT / "cellsim").rglob("*.py")]):
        rel = path.relative_to(ROOT).as_posix()
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""] + [a.name for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            if any("groundtruth" in n for n in names) and rel not in allowed:
                offenders.append(rel)
    assert not offenders, f"ground truth imported outside evaluators: {offenders}"


def test_async_writer_fills_gaps_and_never_blocks(tmp_path):
    from vespro.recording import AsyncRecordingWriter

    rig = _rig()
    rng = np.random.default_rng(3)
    T = transform_from_rt(exp_so3([0.1, 0, 0]), [0, 0, 1])
    with AsyncRecordingWriter(tmp_path / "rec", rig, BOX, 26.0, "box") as w:
        for k in (0, 1, 4, 5):  # the source skipped indices 2 and 3
            imgs = {"a": rng.integers(0, 256, (240, 320, 3), dtype=np.uint8), "h": None}
            w.write(FrameSet(k, k * 1000, imgs, {"h": T}))
    rec = Recording(tmp_path / "rec")
    assert len(rec) == 6
    assert [rec.image("a", i) is None for i in range(6)] == [False, False, True, True, False, False]
    np.testing.assert_allclose(rec.t * 1e9, [0, 1000, 2000, 3000, 4000, 5000], atol=1e-3)


def test_deferred_png_writer_gives_the_same_recording(tmp_path):
    # Raw frames spooled while recording, PNG-encoded on close: the same files as direct writing.
    from vespro.recording import AsyncRecordingWriter

    rig = _rig()
    rng = np.random.default_rng(5)
    T = transform_from_rt(exp_so3([0.1, 0, 0]), [0, 0, 1])
    frames = [FrameSet(k, k * 1000, {"a": rng.integers(0, 256, (240, 320, 3), dtype=np.uint8),
                                     "h": rng.integers(0, 256, (240, 320), dtype=np.uint8)}, {"h": T})
              for k in range(4)]
    for name, defer in (("direct", False), ("deferred", True)):
        with AsyncRecordingWriter(tmp_path / name, rig, BOX, 26.0, "box", defer_png=defer) as w:
            for fs in frames:
                w.write(fs)
        assert not (tmp_path / name / ".spool").exists()
    a, b = Recording(tmp_path / "direct"), Recording(tmp_path / "deferred")
    assert len(a) == len(b) == 4
    for i in range(4):
        for cam in ("a", "h"):
            np.testing.assert_array_equal(b.frameset(i).images[cam], frames[i].images[cam])
            np.testing.assert_array_equal(a.frameset(i).images[cam], b.frameset(i).images[cam])


def test_replaying_frames_adds_no_interned_names(tmp_path, monkeypatch):
    """A server replays for hours: reading a frame must not intern a new string.

    CPython keeps interned strings in one table that is rebuilt larger, never
    smaller, as short-lived names fill it; pathlib interns every part of every
    path it builds, so a path object per frame grew the server's memory by a
    step of megabytes every few minutes.
    """
    import sys

    _write(tmp_path / "rec", n=6, drop=())
    rec = Recording(tmp_path / "rec")
    interned = []
    real = sys.intern
    monkeypatch.setattr(sys, "intern", lambda s: interned.append(s) or real(s))
    rec.image_path("a", 3)  # premise: a path object interns its parts (the patch sees it)
    assert "000003.png" in interned
    interned.clear()
    for k in range(len(rec)):
        fs = rec.frameset(k)
        assert fs.images["a"] is not None and fs.images["h"] is not None
        assert rec.check_image("a", k).reason is None
    assert interned == []
