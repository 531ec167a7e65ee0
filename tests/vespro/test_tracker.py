"""The multi-camera tracker on simulator recordings and on the example made outside.

Recordings are short (about 1.5-2 s at 26 Hz) and made once per module. The
tracker starts from the ground-truth pose of frame 0 (passed explicitly, as
``--init-pose`` would be): these tests measure tracking; initialisation has its
own tests. Bounds are set from measured values with margin; each says why.
"""

import math

import numpy as np
import pytest

from vespro.evaluate import pnp_baseline, score
from vespro.groundtruth import read_groundtruth
from vespro.recording import Recording
from vespro.rig import load_rig
from vespro.se3 import transform_from_rt
from vespro.sim.cell import CameraDropout, CellConfig
from vespro.sim.imaging import ImageEffects
from vespro.sim.motion import Conveyor, Sinusoid
from vespro.sim.record import record
from vespro.sim.rigs import CAMERAS_DIR
from vespro.sim.scene import MODELS_DIR
from vespro.track import make_tracker, track_recording
from vespro.tracker import TrackerConfig

NOISE = ImageEffects(noise_px=0.5)


def _rec(path, obj, rig, motion, n, **kw):
    cfg = CellConfig(MODELS_DIR / "objects" / f"{obj}.stl", load_rig(CAMERAS_DIR / f"{rig}.yaml"), effects=NOISE, **kw)
    return record(path, cfg, motion, n, obj)


@pytest.fixture(scope="module")
def recs(tmp_path_factory):
    d = tmp_path_factory.mktemp("tracker_recs")
    return {
        "box_conveyor": _rec(d / "box_conveyor", "box", "fixed2", Conveyor(speed=0.1, y0=-0.2), 40),
        "lblock_free": _rec(d / "lblock_free", "lblock", "fixed2", Sinusoid(), 40),
        "box_dropout": _rec(d / "box_dropout", "box", "fixed2", Sinusoid(), 52,
                            dropouts=(CameraDropout("cam_right", 0.5, 1.5),)),
        "hybrid": _rec(d / "hybrid", "lblock", "hybrid", Conveyor(speed=0.1, y0=-0.15), 40, arm="watch"),
    }


def _run(path, config=TrackerConfig(), init=None):
    rec = Recording(path)
    _, _, T = read_groundtruth(path)
    tr = make_tracker(rec, config)
    outs = track_recording(rec, tr, T[0] if init is None else init)
    s = score([o.T_world_object for o in outs], [o.status for o in outs], T, rec.t, tr.model,
              [o.time_ms for o in outs], [o.cov6 for o in outs])
    return rec, tr, outs, T, s


def test_two_fixed_cameras_submillimetre_and_beats_per_frame_pnp(recs):
    rec, tr, outs, T, s = _run(recs["box_conveyor"])
    base = pnp_baseline(rec, outs, tr.model)
    b = score(base, ["tracking" if x is not None else "lost" for x in base], T, rec.t, tr.model)
    # Measured 0.50 mm / 0.37 deg (filter) against 3.6 mm (solvePnP on the same detections).
    assert s["tracked_fraction"] >= 0.95  # the first frames confirm the start (status initializing)
    assert s["position_rmse_mm"] < 1.0 and s["orientation_rmse_deg"] < 0.8
    assert s["position_rmse_mm"] < 0.5 * b["position_rmse_mm"]
    assert s["wrong_lock_frames"] == 0


def test_free_motion_nonconvex_part_and_honest_covariance(recs):
    rec, tr, outs, T, s = _run(recs["lblock_free"])
    # Measured 0.7 mm and NEES in the 95% band on ~90% of frames (adaptive noise);
    # 0.75 allows for the short run (40 frames: one frame is 2.5%).
    assert s["position_rmse_mm"] < 1.5 and s["tracked_fraction"] >= 0.95
    assert s["nees_in_band"] >= 0.75


def test_losing_one_camera_for_a_second_keeps_tracking(recs):
    rec, tr, outs, T, s = _run(recs["box_dropout"])
    during = [o for o in outs if 0.5 <= rec.t[o.index] < 1.5]
    assert during and all(o.status == "tracking" for o in during)
    # Only cam_left measures during the dropout (its observation list says so).
    assert all(not ob.has_image for o in during for ob in o.observations if ob.name == "cam_right")
    # Measured 1.6 mm RMSE, 7.5 mm max (depth from one camera for a second); 10% of the
    # diameter (14.4 mm) is the wrong-lock line.
    assert s["position_max_mm"] < 12.0 and s["wrong_lock_frames"] == 0


def test_hybrid_rig_eye_in_hand_and_fixed_in_one_filter(recs):
    rec, tr, outs, T, s = _run(recs["hybrid"])
    assert s["position_rmse_mm"] < 1.5 and s["tracked_fraction"] >= 0.95  # measured 0.48 mm
    hand_used = sum(int(ob.accepted.sum()) for o in outs for ob in o.observations if ob.name == "hand")
    assert hand_used > len(outs)  # the eye-in-hand camera contributes measurements


def test_a_wrong_start_is_never_published_as_tracking(recs):
    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    # 30 cm away and turned by 120 degrees: nothing in the windows supports it. (From
    # 7 cm off the filter still locks onto the right pose within a frame.)
    from vespro.se3 import exp_so3

    wrong = transform_from_rt(exp_so3([0, 0, 2.1]) @ T[0][:3, :3], T[0][:3, 3] + [0.2, -0.2, 0.1])
    tr = make_tracker(rec)
    outs = track_recording(rec, tr, wrong)
    diam = tr.model.diameter
    for o in outs:
        if o.status == "tracking":
            assert np.linalg.norm(o.T_world_object[:3, 3] - T[o.index][:3, 3]) < 0.1 * diam
    assert any(o.status == "lost" for o in outs)


def test_both_selection_methods_track(recs):
    for sel in ("quality", "information"):
        _, _, _, _, s = _run(recs["box_conveyor"], TrackerConfig(selection=sel))
        assert s["position_rmse_mm"] < 1.5, (sel, s["position_rmse_mm"])


def test_example_recording_made_outside(example_box2):
    rec, tr, outs, T, s = _run(example_box2)
    base = pnp_baseline(rec, outs, tr.model)
    b = score(base, ["tracking" if x is not None else "lost" for x in base], T, rec.t, tr.model)
    # Measured 0.23 mm / 0.25 deg against 2.2 mm for per-frame solvePnP.
    assert s["position_rmse_mm"] < 0.6 and s["tracked_fraction"] >= 0.95
    assert s["position_rmse_mm"] < 0.5 * b["position_rmse_mm"]


def test_start_pose_validation_and_track_command(tmp_path, recs):
    from vespro.cli import main
    from vespro.poses import read_poses

    _, _, T = read_groundtruth(recs["box_conveyor"])
    from vespro.se3 import pq_from_transform

    pose = ",".join(f"{v:.9f}" for v in pq_from_transform(T[0]))
    out = tmp_path / "poses.csv"
    assert main(["track", str(recs["box_conveyor"]), "-o", str(out), "--init-pose", pose, "--no-progress"]) == 0
    rows = read_poses(out)
    assert len(rows) == 40 and all(r.time_ms is not None for r in rows)
    assert sum(r.status == "tracking" for r in rows) >= 38
    header = out.read_text().splitlines()[0].split(",")
    assert header[:10] == ["index", "t", "x", "y", "z", "qw", "qx", "qy", "qz", "status"] and header[10] == "time_ms"
    assert main(["track", str(recs["box_conveyor"]), "-o", str(out), "--init-pose", "1,2,3"]) == 2


def test_textured_is_accepted_and_said_to_be_unneeded(recs, capsys):
    """``--textured`` (``vespro track``, ``serve``, ``eval``) is no longer needed: texture
    inside a face is clutter to the image likelihood. It is accepted, with one line saying so,
    and changes nothing."""
    import argparse

    from vespro.cmd_track import add_tracker_options, tracker_config

    p = argparse.ArgumentParser()
    add_tracker_options(p)
    assert tracker_config(p.parse_args(["--textured"])) == tracker_config(p.parse_args([]))
    err = capsys.readouterr().err
    assert err.count("--textured is no longer needed") == 1 and "ignored" in err


def test_single_camera_does_not_drift_in_depth(tmp_path):
    # One camera sees depth only through the part's image size: the error along the
    # optical axis is larger than across it, but the motion model and the filter keep
    # it zero-mean, bounded and matched by the filter's own uncertainty (no drift).
    path = _rec(tmp_path / "single", "box", "fixed1", Conveyor(speed=0.1, y0=-0.3), 104)
    rec, tr, outs, T, s = _run(path)
    z = rec.rig["cam_left"].T_world_camera[:3, 2]
    d = np.array([(o.T_world_object[:3, 3] - T[o.index][:3, 3]) @ z for o in outs if o.status == "tracking"])
    sd = np.array([np.sqrt(z @ o.cov6[:3, :3] @ z) for o in outs if o.status == "tracking"])
    assert len(d) >= 100
    # Measured on 156 frames: mean +0.06 mm, RMS 2-4 mm, filter std 3.2 mm.
    assert abs(d.mean()) < 2e-3
    half = len(d) // 2
    assert np.sqrt(np.mean(d[half:] ** 2)) < 8e-3  # the second half no worse than a bound: no drift
    ratio = np.sqrt(np.mean(d**2)) / np.median(sd)
    assert 0.3 < ratio < 2.0, ratio  # the covariance is honest about the weak axis


def test_single_camera_confirms_on_the_complex_part(tmp_path):
    # A lone camera sees depth 4-5 mm worse than lateral position on the bracket: the
    # confirmation must still be reached (it once required 3 mm absolute and never was).
    path = _rec(tmp_path / "single_bracket", "bracket", "fixed1", Conveyor(speed=0.1, y0=-0.2), 40)
    rec, tr, outs, T, s = _run(path)
    first = next(i for i, o in enumerate(outs) if o.status == "tracking")
    assert first <= 8, first  # measured: frame 4
    assert s["tracked_fraction"] >= 0.85, s["tracked_fraction"]
    assert s["position_rmse_mm"] < 8.0, s  # measured 4.3 mm (depth-dominated)


def test_symmetric_part_starts_from_the_upright_equivalent_pose():
    from vespro.model import box_model
    from vespro.rig import Rig
    from vespro.se3 import exp_so3
    from vespro.tracker import Tracker

    tr = Tracker(Rig(()), box_model([0.12, 0.08, 0.06]))
    assert len(tr.symmetries) == 4  # identity and three half turns
    T = transform_from_rt(exp_so3([np.pi, 0, 0.2]), [0.9, 0.0, 0.6])  # upside down
    C = tr.canonical_pose(T)
    assert C[2, 2] > 0.99  # z up
    # Same shape: the vertices coincide as sets.
    from vespro.se3 import transform_points

    a = np.round(transform_points(T, tr.model.vertices), 9)
    b = np.round(transform_points(C, tr.model.vertices), 9)
    assert sorted(map(tuple, a)) == sorted(map(tuple, b))


def test_track_command_initialises_the_example_by_itself(example_box2, tmp_path):
    from vespro.cli import main
    from vespro.poses import read_poses

    out = tmp_path / "poses.csv"
    assert main(["track", str(example_box2), "-o", str(out), "--no-progress"]) == 0  # no --init-pose
    rows = read_poses(out)
    _, _, T = read_groundtruth(example_box2)
    track = [r for r in rows if r.status == "tracking"]
    # Measured: tracking from frame 1 (0.04 s) to the end, median error 0.21 mm, max 0.5 mm.
    assert track and track[0].t < 1.0 and all(r.status == "tracking" for r in rows if r.t >= 1.0)
    assert max(np.linalg.norm(r.T_world_object[:3, 3] - T[r.index][:3, 3]) for r in track) < 2e-3


def test_complex_part_free_motion_from_a_given_start(tmp_path):
    # The nominal bracket recording that once failed from its (exact) start pose: the
    # start covariance (1 cm, 3 deg) makes 24 px windows, and windows holding a
    # neighbouring corner of the part measured the neighbour (7 mm off after one frame,
    # lost after 11). Selection now prefers corners with no predicted neighbour inside
    # their window, and biased corners learn a larger noise.
    from vespro.suite import ensure_recording, expand_suite

    _, (sc,) = expand_suite({"scenarios": [{"name": "b", "object": "bracket", "rig": "fixed2", "motion": "random",
                                            "frames": 52, "noise_px": 0.5}]})
    path = ensure_recording(sc, tmp_path, log=lambda *a: None)
    rec, tr, outs, T, s = _run(path)
    # Measured (130 frames): all tracked after the first, 0.74 mm RMSE, NEES in band 88%.
    assert s["tracked_fraction"] >= 0.95, s["tracked_fraction"]
    assert s["position_rmse_mm"] < 1.5, s
    assert s["wrong_lock_frames"] == 0
    assert s["nees_in_band"] >= 0.75  # short run: one frame is 2%


def test_fast_start_is_measured_twice_and_a_wrong_track_never_published(tmp_path):
    # The bracket moving at 0.2 m/s from the first frame while the filter starts at rest:
    # 24 px windows at the start. Once this confirmed a pose 17 mm off after 3 frames (7 of 16
    # corners accepted) and published it while it drifted to 0.3 m. Now large windows get a
    # second, small-window pass after the first update, confirmation needs 60% of the selected
    # corners, and a frame with under half of them accepted counts as bad.
    from vespro.suite import ensure_recording, expand_suite

    _, (sc,) = expand_suite({"scenarios": [{"name": "f", "object": "bracket", "rig": "fixed2",
                                            "motion": "sinusoid_fast", "seed": 2, "frames": 26,
                                            "noise_px": 0.5}]})
    path = ensure_recording(sc, tmp_path, log=lambda *a: None)
    rec, tr, outs, T, s = _run(path)
    assert s["wrong_lock_frames"] == 0
    # Measured (130 frames): every frame after the first tracked, 0.91 mm RMSE.
    assert s["tracked_fraction"] >= 0.9, s["tracked_fraction"]
    assert s["position_rmse_mm"] < 2.0, s


def test_fast_free_motion_from_rest_is_held(tmp_path):
    # The bracket moving up to ~20 mm and ~10 deg a frame at 26 Hz (the fast suite's
    # motion, bench/suites/fast.yaml), the filter started at the true pose at rest: the
    # first prediction misses by ~20 mm, the windows find under half of the corners, and
    # the constant-velocity process noise is several times too small for this motion.
    # With the fixed densities and no second search the start was never confirmed.
    from vespro.metrics import add
    from vespro.suite import ensure_recording, expand_suite

    _, (sc,) = expand_suite({"scenarios": [{"name": "f", "object": "bracket", "rig": "fixed2", "motion": "random",
                                            "speed": 3.0, "amplitude": 0.05, "rot_amplitude_deg": 22, "seed": 0,
                                            "rate_hz": 26, "frames": 20, "noise_px": 0.3}]})
    path = ensure_recording(sc, tmp_path, log=lambda *a: None)
    rec, tr, outs, T, s = _run(path)
    pub = [i for i, o in enumerate(outs) if o.status == "tracking"]
    # Measured: published from frame 6 on (14 of 20), at most 0.8% of the diameter off.
    assert len(pub) >= 12, [o.status for o in outs]
    worst = max(add(outs[i].T_world_object, T[i], tr.model.vertices) for i in pub) / tr.model.diameter
    assert worst < 0.05, worst
    assert tr.motion_scale.max() > 1.5, tr.motion_scale  # the process noise followed the motion


def test_a_given_pose_of_a_symmetric_part_is_tracked_in_the_given_frame(recs, capsys):
    """``--init-pose`` with the box turned half a turn about its x axis (z down: an
    equivalent pose the rule ``up`` would never choose): every frame is reported in that
    frame, not flipped, and the command says that the part is symmetric and the pose is kept."""
    from vespro.cli import main
    from vespro.metrics import discrete_symmetries
    from vespro.model import load_model
    from vespro.poses import read_poses
    from vespro.se3 import pq_from_transform, rotation_angle

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    syms = discrete_symmetries(load_model(rec.model_path).vertices)
    S = next(S for S in syms if S[2, 2] < -0.5 and S[0, 0] > 0.5)  # half turn about x
    given = T[0] @ S
    assert given[2, 2] < 0  # z down
    out = rec.path.parent / "given_flipped.csv"
    pose = ",".join(f"{v:.9f}" for v in pq_from_transform(given))
    assert main(["track", str(rec.path), "-o", str(out), "--init-pose", pose, "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "box is symmetric: 4 poses look alike; the start pose given is kept as given" in err
    rows = [r for r in read_poses(out) if r.status == "tracking"]
    assert len(rows) >= 30
    for r in rows:
        Tt = T[r.index] @ S
        assert np.linalg.norm(r.T_world_object[:3, 3] - Tt[:3, 3]) < 2e-3
        assert rotation_angle(r.T_world_object[:3, :3].T @ Tt[:3, :3]) < math.radians(2)


def test_the_tracker_chooses_among_equivalent_poses_by_the_symmetry_option():
    from vespro.model import box_model
    from vespro.rig import Rig
    from vespro.se3 import exp_so3
    from vespro.tracker import InitResult, Tracker

    flip = transform_from_rt(exp_so3([np.pi, 0, 0]), np.zeros(3))
    T = transform_from_rt(exp_so3([0, 0, 0.3]), [0.9, 0.0, 0.6])  # upright, yaw 0.3
    last = T @ flip  # the last good track had the box's z down
    for rule, restart_z_up in (("continuity", False), ("up", True)):
        tr = Tracker(Rig(()), box_model([0.12, 0.08, 0.06]), TrackerConfig(symmetry=rule))
        tr.start(InitResult(last), 0)  # the initialiser's start: upright under either rule
        assert np.allclose(tr.ekf.pose, T)
        tr.last_good = (last, np.zeros(6), 0)  # then lost; found again as the flipped pose
        tr.start(InitResult(T @ flip), 1)
        assert bool(tr.ekf.pose[2, 2] > 0.99) is restart_z_up, rule
        tr.start(InitResult(last, given=True), 2)  # a pose the user gives: as given
        assert np.allclose(tr.ekf.pose, last)
    with pytest.raises(ValueError, match="symmetry"):
        TrackerConfig(symmetry="nearest")


def test_up_picks_one_frame_among_a_cubes_quarter_turns():
    from vespro.se3 import exp_so3
    from vespro.symmetry import choose, describe
    from vespro.metrics import discrete_symmetries
    from vespro.model import box_model

    syms = discrete_symmetries(box_model([0.1, 0.1, 0.1]).vertices)
    assert len(syms) == 24
    T = transform_from_rt(exp_so3([0, 0, 0.3]), [0.5, 0.1, 0.2])
    for S in syms:  # whichever equivalent pose comes in, the same one comes out
        assert np.allclose(choose(T @ S, syms, "up"), T)
    assert describe("cube", 24, "up", False, True) == \
        "cube is symmetric: 24 poses look alike; the tracker reports the one with z most nearly up in the world " \
        "(--symmetry up)"
    assert describe("bracket", 1, "up", False, True) is None
