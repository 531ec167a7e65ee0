"""Scene options of the simulator: clutter, distractors, textured parts; their recording files and suite fields."""

from pathlib import Path

import numpy as np
import pytest

from vespro.camera import project_points
from vespro.cli import main
from vespro.groundtruth import read_distractors, read_groundtruth
from vespro.recording import Recording
from vespro.se3 import invert_transform
from vespro.suite import expand_suite, scenario_key

ROOT = Path(__file__).resolve().parents[2]
SMALL = ["--rig", "fixed1", "--resolution", "160x120", "--frames", "1", "--motion", "conveyor",
         "--render-samples", "0", "--no-progress", "--object", "lblock"]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    d = tmp_path_factory.mktemp("scenes")
    assert main(["record", str(d / "plain"), *SMALL]) == 0
    assert main(["record", str(d / "busy"), *SMALL, "--clutter", "6", "--distractor", "near"]) == 0
    assert main(["record", str(d / "textured"), *SMALL, "--textured-part"]) == 0
    return d


def _grey(rec_dir, cam="cam_left"):
    return Recording(rec_dir).image(cam, 0).astype(float).mean(axis=2)


def _pixel(rec_dir, p_world, cam="cam_left"):
    c = Recording(rec_dir).rig[cam]
    uv, z = project_points(c.intrinsics, invert_transform(c.T_world_camera), np.asarray(p_world)[None])
    assert z[0] > 0
    return int(round(uv[0, 1])), int(round(uv[0, 0]))


def _part_centre(rec_dir):
    _, _, T = read_groundtruth(rec_dir)
    return T[0][:3, :3] @ [0.0, 0.0, 0.03] + T[0][:3, 3]  # inside the L-block's base


def test_distractor_and_clutter_are_in_the_images_and_the_part_is_unchanged(recordings):
    plain, busy = _grey(recordings / "plain"), _grey(recordings / "busy")
    dist = read_distractors(recordings / "busy")
    assert list(dist) == ["distractor_0"] and dist["distractor_0"]["kind"] == "near"
    assert read_distractors(recordings / "plain") == {}
    # the distractor stands where its file says: its centre's pixels are the part's grey, not the dark belt
    r, c = _pixel(recordings / "busy", dist["distractor_0"]["center"][0])
    assert busy[r - 1:r + 2, c - 1:c + 2].mean() - plain[r - 1:r + 2, c - 1:c + 2].mean() > 40
    # the part is drawn as before, in front of everything
    r, c = _pixel(recordings / "plain", _part_centre(recordings / "plain"))
    assert np.abs(busy[r - 1:r + 2, c - 1:c + 2] - plain[r - 1:r + 2, c - 1:c + 2]).max() < 3
    # the background changed over a good part of the image (patterned belt, panels, boxes)
    assert np.mean(np.abs(busy - plain) > 10) > 0.10


def test_textured_part_shows_a_pattern_on_its_faces(recordings):
    plain, tex = _grey(recordings / "plain"), _grey(recordings / "textured")
    r, c = _pixel(recordings / "plain", _part_centre(recordings / "plain"))
    assert np.abs(tex - plain)[r - 4:r + 5, c - 4:c + 5].max() > 15
    far = np.ones_like(plain, bool)
    far[max(r - 30, 0):r + 30, max(c - 40, 0):c + 40] = False
    assert np.abs(tex - plain)[far].max() < 3  # only the part differs


def test_near_distractor_has_the_part_footprint_and_keeps_clear_in_view():
    from vespro.rig import load_rig
    from vespro.sim.distractors import CLEARANCE, NEAR_HEIGHT_SCALE, place_distractors
    from vespro.sim.motion import Conveyor

    mesh = ROOT / "models/objects/bracket.stl"
    rig = load_rig(ROOT / "cameras/fixed2.yaml")
    t = np.arange(52) / 26.0
    path = np.array([Conveyor().pose(x) for x in t])
    (d,) = place_distractors(["near"], mesh, rig, t, path, 0.13, "belt", Conveyor(), seed=3)
    assert d.scale == (1.0, 1.0, NEAR_HEIGHT_SCALE)
    np.testing.assert_allclose(d.lo[:2], [-0.07, -0.05], atol=1e-6)
    np.testing.assert_allclose(d.hi, [0.07, 0.05, 0.1 * NEAR_HEIGHT_SCALE], atol=1e-6)
    track = np.array([d.pose(x)[:3, 3] for x in t])
    gap = np.hypot(*(track[:, :2] - path[:, :2, 3]).T)
    assert gap.min() >= 0.13 + d.radius + CLEARANCE - 1e-9  # carried along beside the part, never on it
    for cam in rig:
        for T in (d.pose(t[0]), d.pose(t[-1])):
            uv, z = project_points(cam.intrinsics, invert_transform(cam.T_world_camera) @ T, d.corners())
            assert np.all(z > 0) and np.all((uv >= 0) & (uv < [cam.intrinsics.width, cam.intrinsics.height]))


def test_reading_a_recording_never_opens_distractors_csv(recordings, opened_files):
    opened_files.clear()
    rec = Recording(recordings / "busy")
    for _ in rec:
        pass
    assert opened_files and not any("distractors" in f or "groundtruth" in f for f in opened_files)


def test_record_refuses_bad_scene_options_in_one_line(tmp_path, capsys):
    assert main(["record", str(tmp_path / "r"), *SMALL, "--distractor", "teapot"]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown distractor 'teapot'" in err and "\n" not in err
    assert not (tmp_path / "r").exists()
    with pytest.raises(SystemExit):
        main(["record", str(tmp_path / "r"), *SMALL, "--clutter", "-1"])
    assert main(["record", str(tmp_path / "r"), *SMALL, "--motion", "random", "--distractor", "near",
                 "--distractor-motion", "belt"]) == 2
    assert "needs --motion conveyor" in capsys.readouterr().err


@pytest.mark.parametrize("field, value, match", [
    ("clutter", -2, "clutter must be a count"),
    ("clutter", "lots", "clutter must be a count"),
    ("distractors", ["near", "teapot"], "distractors must be a list of near"),
    ("distractor_motion", "fly", "distractor_motion must be one of static, belt"),
    ("textured_part", "yes", "textured_part must be true or false"),
])
def test_suite_scene_fields_are_validated(field, value, match):
    with pytest.raises(ValueError, match=match) as e:
        expand_suite({"scenarios": [{"name": "a", field: value}]}, "s.yaml")
    assert "s.yaml: scenario a" in str(e.value) and "\n" not in str(e.value)


def test_suite_scene_fields_parse_and_key_the_cache_only_when_set():
    _, (a, b, c) = expand_suite({"scenarios": [
        {"name": "a"}, {"name": "b", "clutter": 0, "distractors": [], "textured_part": False},
        {"name": "c", "clutter": 4, "distractors": "near", "distractor_motion": "belt"}]})
    assert c["distractors"] == ["near"] and c["clutter"] == 4
    assert scenario_key(a) == scenario_key(b)  # the defaults leave existing recordings' keys alone
    assert scenario_key(c) != scenario_key(a)
    _, crossed = expand_suite({"cross": [{"object": ["box", "lblock"], "distractors": ["near", "block"]}]})
    assert [s["distractors"] for s in crossed] == [["near", "block"]] * 2  # a list of kinds, not an axis


def test_score_published_counts_errors_and_a_pose_on_the_distractor():
    from vespro.model import load_model
    from vespro.se3 import transform_from_rt
    from vespro.suite import score_published
    from vespro.tracker import TrackerOutput

    model = load_model(ROOT / "models/objects/lblock.stl")
    D = model.diameter
    T_true = np.array([transform_from_rt(np.eye(3), [0.9, -0.2 + 0.01 * i, 0.5]) for i in range(5)])
    off = lambda i, dx: transform_from_rt(np.eye(3), T_true[i][:3, 3] + [dx, 0, 0])  # noqa: E731
    T_d = np.array([off(i, 0.25) for i in range(5)])
    dist = {"distractor_0": {"kind": "near", "index": np.arange(5), "T": T_d,
                             "center": T_d[:, :3, 3] + [0.0, 0.0, 0.028]}}
    outs = [TrackerOutput(0, 0, "searching"),
            TrackerOutput(1, 1, "tracking", off(1, 0.0)),
            TrackerOutput(2, 2, "tracking", off(2, 0.06 * D)),  # 6% off
            TrackerOutput(3, 3, "tracking", off(3, 0.24)),  # on the distractor
            TrackerOutput(4, 4, "lost")]
    f = score_published(outs, T_true, model, dist)
    assert (f["frames"], f["published"], f["first"], f["ge5"], f["ge10"], f["on_distractor"]) == (5, 3, 1, 2, 1, 1)
    assert f["max_err"] == pytest.approx(0.24 / D)
    assert score_published(outs[:1], T_true, model)["first"] is None
