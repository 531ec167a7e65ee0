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


def _judge(tr, fs, obs, n_found, n_acc):
    """The tracker's status step on given observations (mean NIS 2), the blind cameras
    left out as ``Tracker._track`` leaves them."""
    return tr._status(fs, obs, n_found, n_acc, 2.0, {"visibility": 0.0}, tr._seeing(obs))


def _started(rec, T0, hidden=(), **cfg):
    """A tracker started confidently at ``T0`` (the initialiser having found the part hidden
    from the cameras ``hidden``), with an initialiser that finds nothing."""
    from vespro.tracker import InitResult

    tr = make_tracker(rec, TrackerConfig(**cfg))
    tr.initializer = lambda fs: None
    tr.start(InitResult(T0, cov6=np.diag([1e-6] * 6), hidden=hidden), rec.frameset(0).t_ns)
    return tr


def _judged_with(rec, T0, obs, n, per_frame, **cfg):
    """A tracker started at ``T0`` whose status step is fed the same observations ``obs``
    (``n`` corners found and accepted) on each frame, after the tracker attributes of that
    frame's dict in ``per_frame`` are set; stops where the filter is dropped. Returns
    (tracker, published statuses)."""
    tr = _started(rec, T0, **cfg)
    out = []
    for i, attrs in enumerate(per_frame):
        for k, v in attrs.items():
            setattr(tr, k, v)
        out.append(_judge(tr, rec.frameset(i), obs, n, n).status)
        if tr.ekf is None:
            break
    return tr, out


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


def test_textured_parts_are_told_on_the_command_line(recs):
    """``--textured`` (``vespro track``, ``serve``, ``eval``) turns off the plain-face rules of
    the initialiser (``InitOptions.plain_faces``): with one camera a pose whose faces cover
    image edges is otherwise refused, and a part with markings would never start. With
    ``--decision bank`` they are off too (the bank's likelihood takes texture as clutter)."""
    import argparse

    from vespro.options import add_tracker_options, init_options, initializer_for, tracker_config
    from vespro.model import load_model
    from vespro.recording import Recording

    p = argparse.ArgumentParser()
    add_tracker_options(p)
    rec = Recording(recs["box_conveyor"])
    model = load_model(rec.model_path, name=rec.object_name)
    for argv, plain in (([], True), (["--textured"], False), (["--decision", "bank"], False)):
        args = p.parse_args(argv)
        assert init_options(args) == {"plain_faces": plain, "workspace": None}
        ini = initializer_for(args, rec, model)
        assert ini is not None and ini.setup.options.plain_faces is plain
    ini = initializer_for(p.parse_args(["--workspace", "0,-1,0,2,1,1.5"]), rec, model)
    assert ini.setup.options.workspace == (0.0, -1.0, 0.0, 2.0, 1.0, 1.5)
    assert tracker_config(p.parse_args(["--decision", "bank"])).decision == "bank"
    # the working volume reaches the bank too (the prior over the poses it holds)
    from vespro.options import workspace_of
    from vespro.track import make_tracker

    args = p.parse_args(["--decision", "bank", "--workspace", "0,-1,0,2,1,1.5"])
    tr = make_tracker(rec, tracker_config(args), workspace=workspace_of(args))
    assert tr.bank.workspace == (0.0, -1.0, 0.0, 2.0, 1.0, 1.5)
    assert make_tracker(rec, tracker_config(p.parse_args(["--decision", "bank"]))).bank.workspace is None


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


def test_with_the_bank_a_fast_start_from_rest_is_found_again_on_the_edges(tmp_path):
    """Decision "bank", the bracket moving up to ~20 mm and ~10 deg a frame, the filter started
    at the true pose at rest: the first prediction misses, the windows find under half of the
    corners, and the pose refined on the image edges about the prediction joins the bank
    (``vespro.redetect``) and takes over. Published on at least 18 of the 20 frames (measured:
    19 from frame 0), none 5% of the diameter off."""
    from vespro.metrics import add
    from vespro.suite import ensure_recording, expand_suite

    _, (sc,) = expand_suite({"scenarios": [{"name": "f", "object": "bracket", "rig": "fixed2", "motion": "random",
                                            "speed": 3.0, "amplitude": 0.05, "rot_amplitude_deg": 22, "seed": 0,
                                            "rate_hz": 26, "frames": 20, "noise_px": 0.3}]})
    path = ensure_recording(sc, tmp_path, log=lambda *a: None)
    rec, tr, outs, T, s = _run(path, TrackerConfig(decision="bank"))
    pub = [i for i, o in enumerate(outs) if o.status == "tracking"]
    assert len(pub) >= 18, [o.status for o in outs]
    worst = max(add(outs[i].T_world_object, T[i], tr.model.vertices) for i in pub) / tr.model.diameter
    assert worst < 0.05, worst
    assert tr.redetector.calls >= 1


def test_confirmation_needs_every_camera_to_agree(recs):
    """A pose one camera supports and another rejects is not confirmed, whatever the totals.

    Seen in the real-time demo after a 0.6 s gap: right camera 8 of 8 accepted, left 2 of 8,
    10 of 16 in all (above the 60% total), the pose 15 mm off along the right camera's ray.
    """
    from vespro.tracker import CameraObservation, InitResult

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    fs = rec.frameset(0)

    def frames(accepted_left, n=6, found_left=8):
        tr = make_tracker(rec)
        tr.start(InitResult(T[0], cov6=np.diag([1e-6] * 3 + [1e-6] * 3)), fs.t_ns)
        ids = np.arange(8)

        def ob(name, n_acc, n_found=8):
            acc = np.zeros(8, bool)
            acc[:n_acc] = True
            uv = np.zeros((8, 2))
            uv[n_found:] = np.nan
            return CameraObservation(name, True, 12, ids, np.zeros((8, 2)), np.full(8, 3.0), uv, acc)

        obs = [ob("cam_left", accepted_left, found_left), ob("cam_right", 8)]
        n_acc = accepted_left + 8
        # 12 corners found of 16 selected: totals pass the inlier (10/12) and selected (10/16) fractions.
        return [_judge(tr, fs, obs, 12, n_acc).status for _ in range(n)]

    assert "tracking" not in frames(accepted_left=2)  # 10 of 16 accepted, one camera rejecting
    assert frames(accepted_left=6)[-1] == "tracking"  # both cameras agree: confirmed
    # A camera finding only 3 of its 8 corners and accepting them all does not disagree
    # (confirm_camera_min_agreeing); with 2 of them, or 3 of 6 found, it does.
    assert frames(accepted_left=3, found_left=3)[-1] == "tracking"
    assert "tracking" not in frames(accepted_left=2, found_left=2)
    assert "tracking" not in frames(accepted_left=3, found_left=6)


def test_cameras_disagreeing_on_a_confirmed_track_reopen_the_windows(recs):
    """One camera rejecting most of its corners while the other accepts, three frames running:
    the pose covariance is widened (the windows open, the corners are associated again)."""
    from vespro.tracker import CameraObservation, InitResult

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    fs = rec.frameset(0)
    ids = np.arange(8)

    def ob(name, n_acc):
        acc = np.zeros(8, bool)
        acc[:n_acc] = True
        return CameraObservation(name, True, 12, ids, np.zeros((8, 2)), np.full(8, 3.0), np.zeros((8, 2)), acc)

    def run(accepted_left):
        tr = make_tracker(rec)
        tr.start(InitResult(T[0], cov6=np.diag([1e-6] * 6)), fs.t_ns)
        both = [ob("cam_left", 8), ob("cam_right", 8)]
        for _ in range(3):
            _judge(tr, fs, both, 16, 16)
        assert tr.confirmed
        P0 = tr.ekf.pose_covariance
        obs = [ob("cam_left", accepted_left), ob("cam_right", 8)]
        outs = [_judge(tr, fs, obs, 16, accepted_left + 8) for _ in range(3)]
        return tr, P0, outs

    tr, P0, outs = run(accepted_left=2)
    assert tr.reassociations == 1
    c = tr.config
    assert np.allclose(np.diag(tr.ekf.pose_covariance) - np.diag(P0),
                       [c.init_sigma_pos**2] * 3 + [c.init_sigma_rot**2] * 3)
    tr, P0, _ = run(accepted_left=6)  # both cameras agree: nothing changes
    assert tr.reassociations == 0 and np.allclose(tr.ekf.pose_covariance, P0)


def test_a_start_not_confirmed_in_time_is_dropped_for_a_fresh_initialisation(recs):
    """A started filter whose frames never confirm it (here 4 of 8 corners accepted per
    camera: not bad, not strong) is dropped once ``confirm_within_s`` has passed since its
    start, and the initialiser runs again. Seen on a one-camera bracket trial: after a good
    start the filter slid with 3-4 of 8 corners accepted and, 38 frames on, confirmed a pose
    28% of the diameter off."""
    from vespro.tracker import CameraObservation, InitResult

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    ids = np.arange(8)

    def ob(name, n_acc):
        acc = np.zeros(8, bool)
        acc[:n_acc] = True
        return CameraObservation(name, True, 12, ids, np.zeros((8, 2)), np.full(8, 3.0), np.zeros((8, 2)), acc)

    calls = []
    tr = make_tracker(rec)
    tr.initializer = lambda fs: calls.append(fs.index)  # finds nothing
    t0 = rec.frameset(0).t_ns
    tr.start(InitResult(T[0], cov6=np.diag([1e-6] * 6)), t0)
    weak = [ob("cam_left", 4), ob("cam_right", 4)]
    deadline = t0 + tr.config.confirm_within_s * 1e9
    i = 0
    while tr.ekf is not None:
        fs = rec.frameset(i)
        out = _judge(tr, fs, weak, 8, 8)
        assert out.status == "initializing"
        assert (fs.t_ns >= deadline) == (tr.ekf is None)
        i += 1
    assert tr.unconfirmed_drops == 1 and not calls
    out = tr.process(rec.frameset(i))  # no filter: the initialiser is asked again
    assert calls == [i] and out.status == "initializing"

    # Strong frames confirm well before the deadline: nothing is dropped.
    tr = make_tracker(rec)
    tr.start(InitResult(T[0], cov6=np.diag([1e-6] * 6)), t0)
    strong = [ob("cam_left", 8), ob("cam_right", 8)]
    outs = [_judge(tr, rec.frameset(i), strong, 16, 16).status for i in range(30)]
    assert outs[-1] == "tracking" and tr.unconfirmed_drops == 0


def test_a_frame_that_jumped_neither_confirms_nor_is_published(recs):
    """The step gates (``confirm_max_step_frac``, ``max_step_frac``): a frame whose
    measurements moved the pose more than 5% of the diameter from its prediction
    (``Tracker._step``, set by ``_track``) is not strong and breaks the run of strong frames
    that confirms a filter, however many corners agree, and a
    confirmed frame that moved it more than 10% counts as bad: published ``lost`` while the
    track coasts, and after ``lost_after`` of them in a row the filter is dropped."""
    from vespro.tracker import CameraObservation

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    ids = np.arange(8)
    strong = [CameraObservation(n, True, 12, ids, np.zeros((8, 2)), np.full(8, 3.0), np.zeros((8, 2)),
                                np.ones(8, bool)) for n in ("cam_left", "cam_right")]

    def statuses(steps, **cfg):
        tr, out = _judged_with(rec, T[0], strong, 16, [{"_step": s} for s in steps], **cfg)
        return out, tr

    out, _ = statuses([0.0, 0.0, 0.0])
    assert out == ["initializing", "tracking", "tracking"]
    out, _ = statuses([0.0, 0.06, 0.04, 0.0])  # a frame moved over 5%: it breaks the run
    assert out == ["initializing"] * 3 + ["tracking"]
    out, _ = statuses([0.0, 0.06, 0.06], confirm_max_step_frac=math.inf)
    assert out == ["initializing", "tracking", "tracking"]
    out, tr = statuses([0.0, 0.0, 0.12, 0.02, 0.02])  # one jump of a confirmed track: one frame lost
    assert out == ["initializing", "tracking", "lost", "tracking", "tracking"]
    out, tr = statuses([0.0, 0.0] + [0.12] * tr.config.lost_after)
    assert out == ["initializing", "tracking"] + ["lost"] * tr.config.lost_after and tr.ekf is None
    out, _ = statuses([0.0, 0.0, 0.12], max_step_frac=math.inf)
    assert out == ["initializing", "tracking", "tracking"]
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="step_frac"):
            TrackerConfig(max_step_frac=bad)


def test_a_frame_whose_edge_fit_lies_far_from_the_corners_pose_does_not_confirm(recs):
    """``confirm_max_fit_gap``: a frame of an unconfirmed start whose edge fit landed over
    6% of the diameter from the pose the corners gave the filter (``Tracker._fit_gap``, set
    by the edge update) does not count towards confirmation, however many corners agree,
    nor does it break a run of strong frames. A one-camera box's corners, biased on its
    dark faces, took a start 10.8% off while its edges stayed 1-4% from the truth, and it
    was confirmed. A confirmed track is not judged by it (its fits keep their own gate,
    ``edge_aid_max_move``)."""
    from vespro.tracker import CameraObservation

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    ids = np.arange(8)
    strong = [CameraObservation("cam_left", True, 12, ids, np.zeros((8, 2)), np.full(8, 3.0), np.zeros((8, 2)),
                                np.ones(8, bool))]

    def statuses(gaps, **cfg):
        return _judged_with(rec, T[0], strong, 8, [{"_fit_gap": g} for g in gaps], **cfg)[1]

    assert statuses([0.0, 0.05, 0.0]) == ["initializing", "tracking", "tracking"]
    assert statuses([0.0, 0.08, 0.0]) == ["initializing", "initializing", "tracking"]  # neutral: the run holds
    assert statuses([0.08] * 6) == ["initializing"] * 6
    assert statuses([0.08] * 3, confirm_max_fit_gap=math.inf)[1] == "tracking"
    assert statuses([0.0, 0.0, 0.2, 0.2]) == ["initializing"] + ["tracking"] * 3  # confirmed: not judged
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="confirm_max_fit_gap"):
            TrackerConfig(confirm_max_fit_gap=bad)


def test_an_agreeing_edge_fit_lets_fewer_corners_confirm(recs):
    """Five of six corners accepted (fewer than confirm_min_accepted = 6) confirm a start only
    on frames whose edge fit agreed with the filter (``Tracker._edge_ok``, set by the edge
    update): a lone camera often finds 5 of a box's corners while its edges hold the pose.
    Four do in two frames only when the fit found edge points for 90% of the visible samples
    (``confirm_outline_*``), otherwise in four (``confirm_slow_*``); three never."""
    from vespro.tracker import CameraObservation, InitResult, TrackerConfig

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    fs = rec.frameset(0)
    ids = np.arange(6)
    acc = np.array([True] * 5 + [False])
    ob = CameraObservation("cam_left", True, 6, ids, np.zeros((6, 2)), np.full(6, 3.0), np.zeros((6, 2)), acc)

    def statuses(edge_ok, found=0.7, config=TrackerConfig(confirm_slow_frames=0)):
        tr = make_tracker(rec, config)
        tr.start(InitResult(T[0], cov6=np.diag([1e-6] * 6)), fs.t_ns)
        out = []
        for _ in range(4):
            tr._edge_ok = edge_ok
            tr._edge_found = found if edge_ok else 0.0
            n = int(acc.sum())
            out.append(_judge(tr, fs, [ob], n, n).status)
        return out

    assert "tracking" not in statuses(edge_ok=False)
    assert statuses(edge_ok=True)[-1] == "tracking"
    acc[4] = False  # four corners: in two frames when the edge fit found the whole outline
    assert "tracking" not in statuses(edge_ok=True, found=0.86)
    assert statuses(edge_ok=True, found=0.93)[1] == "tracking"
    # ... and in four on any agreeing fit (the slower confirmation, on by default), never without one
    assert statuses(edge_ok=True, found=0.86, config=TrackerConfig()) == ["initializing"] * 3 + ["tracking"]
    assert "tracking" not in statuses(edge_ok=False, config=TrackerConfig())
    acc[3] = False  # three: never
    assert "tracking" not in statuses(edge_ok=True, found=1.0, config=TrackerConfig())


def test_a_weak_frame_that_agrees_does_not_break_a_confirmation(recs):
    """Strong frames confirm a start when only frames with nothing against the pose lie
    between them: a frame whose corners all agree but are too few to confirm (3 of 6 found
    and accepted: the dark faces of a small box) neither counts nor breaks the run
    (``confirm_hold_neutral``). A frame whose corners disagree (3 of 6 found accepted)
    or whose edge fit vetoes breaks it. One-camera box, rig seed 400: an accurate start
    (2% of the diameter) was published 17 frames after the initialiser found it (frame 32),
    strong frames alternating with such weak ones; now 9 (frame 24)."""
    from vespro.tracker import CameraObservation, InitResult

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    fs = rec.frameset(0)
    ids = np.arange(6)

    def ob(n_found, n_acc):
        uv = np.zeros((6, 2))
        uv[n_found:] = np.nan
        acc = np.arange(6) < n_acc
        return CameraObservation("cam_left", True, 6, ids, uv, np.full(6, 3.0), np.zeros((6, 2)), acc)

    def statuses(frames, **kw):
        tr = make_tracker(rec, TrackerConfig(edge_aid="off", **kw))
        tr.start(InitResult(T[0], cov6=np.diag([1e-6] * 6)), fs.t_ns)
        out = []
        for n_found, n_acc, veto in frames:
            tr._edge_veto = veto
            out.append(_judge(tr, fs, [ob(n_found, n_acc)], n_found, n_acc).status)
        return out

    strong, weak, disagreeing = (6, 6, False), (3, 3, False), (6, 3, False)
    assert statuses([strong, weak, strong]) == ["initializing", "initializing", "tracking"]
    assert statuses([strong, weak, strong], confirm_hold_neutral=False)[-1] == "initializing"
    assert statuses([strong, disagreeing, strong])[-1] == "initializing"
    assert statuses([strong, (6, 6, True), strong])[-1] == "initializing"  # the edges vetoed the middle frame
    assert statuses([strong, weak, disagreeing, strong, strong])[-1] == "tracking"


def test_a_provisional_start_is_published_only_once_the_initialiser_confirms_it(recs):
    """A start the initialiser gave provisionally (``InitResult.provisional``) is tracked but
    not published, however strong its frames, until an initialiser answer gives the same
    pose as confirmed (``Tracker.offer``: its strong frames so far count, its deadline runs
    from the confirmation); the same pose still provisional changes nothing; another pose
    starts the filter again from it."""
    from vespro.tracker import CameraObservation, InitResult

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    fs = rec.frameset(0)
    ids = np.arange(6)
    ob = CameraObservation("cam_left", True, 6, ids, np.zeros((6, 2)), np.full(6, 3.0), np.zeros((6, 2)),
                           np.ones(6, bool))
    tr = make_tracker(rec, TrackerConfig(edge_aid="off"))
    cov = np.diag([1e-6] * 6)
    tr.start(InitResult(T[0], cov6=cov, provisional=True), fs.t_ns)
    assert tr.provisional and tr.provisional_pose()[1] == fs.t_ns
    assert [_judge(tr, fs, [ob], 6, 6).status for _ in range(3)] == ["initializing"] * 3
    moved = T[0].copy()
    moved[:3, 3] += [0.004, 0.0, 0.0]  # 4 mm: the same pose
    assert not tr.offer(InitResult(moved, cov6=cov, provisional=True), fs.t_ns) and tr.provisional
    assert _judge(tr, fs, [ob], 6, 6).status == "initializing"
    assert not tr.offer(InitResult(moved, cov6=cov), fs.t_ns) and not tr.provisional and tr.starts_replaced == 0
    assert _judge(tr, fs, [ob], 6, 6).status == "tracking"  # its strong frames counted all along

    # Confirmed half a second in: the deadline for its strong frames (confirm_within_s) runs
    # from the confirmation, as for a start made then.
    tr.start(InitResult(T[0], cov6=cov, provisional=True), fs.t_ns)
    assert not tr.offer(InitResult(moved, cov6=cov), fs.t_ns + 500_000_000) and not tr.provisional
    later = type(fs)(fs.index, fs.t_ns + 900_000_000, fs.images, fs.T_world_camera)
    assert _judge(tr, later, [ob], 3, 3).status == "initializing" and tr.ekf is not None

    tr.start(InitResult(T[0], cov6=cov, provisional=True), fs.t_ns)
    far = T[0].copy()
    far[:3, 3] += [0.0, 0.0, 0.05]  # 5 cm: another pose, the initialiser's best now
    assert tr.offer(InitResult(far, cov6=cov, provisional=True), fs.t_ns)
    assert tr.provisional and np.allclose(tr.ekf.pose[:3, 3], far[:3, 3])
    assert not tr.offer(None, fs.t_ns) and tr.provisional


def test_an_edge_fit_that_disagrees_vetoes_confirmation_and_drops_a_slid_start(recs):
    """Six of six corners accepted confirm a start, unless the frame's edge fit found far
    less of the outline than the filter's first fit did (``Tracker._edge_veto``): a
    one-camera bracket start slid to 38% of the diameter on wrong corners that kept
    agreeing, while its edges went from 71% of the outline found to 35-40%.
    ``veto_drop_frames`` vetoed frames since the start drop it for a fresh
    initialisation; a frame without a veto between them does not reset the count (a
    slid bracket escaped between vetoes when they were counted in a row)."""
    from vespro.tracker import CameraObservation

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    ids = np.arange(6)
    ob = CameraObservation("cam_left", True, 6, ids, np.zeros((6, 2)), np.full(6, 3.0), np.zeros((6, 2)),
                           np.ones(6, bool))

    def run(vetoes, **cfg):
        return _judged_with(rec, T[0], [ob], 6, [{"_edge_veto": v} for v in vetoes], **cfg)

    tr, out = run([False, False])
    assert out[-1] == "tracking"
    n = TrackerConfig().veto_drop_frames
    tr, out = run([True] * (n - 1) + [False])  # one short: kept, never confirmed
    assert "tracking" not in out and tr.ekf is not None and tr.unconfirmed_drops == 0
    tr, out = run([True] * (n - 1) + [False, True])  # interrupted: still the n-th veto drops it
    assert "tracking" not in out and tr.ekf is None and tr.unconfirmed_drops == 1
    tr, out = run([True] * n)
    assert "tracking" not in out and tr.ekf is None and tr.unconfirmed_drops == 1
    tr, out = run([True] * n, confirm_edge_veto=False)  # off: the corners confirm
    assert out[1] == "tracking"


def _statuses(rec, T0, frames, hidden=(), **cfg):
    """A tracker started confidently at ``T0`` (the initialiser having found the part
    hidden from the cameras ``hidden``) whose status logic is fed the given per-frame
    observation lists (no edge fits; found = finite measurements); stops where the
    filter is dropped. Returns (tracker, published statuses)."""
    tr = _started(rec, T0, hidden, **cfg)
    out = []
    for i, obs in enumerate(frames):
        tr._edge_ok = tr._edge_veto = False
        tr._edge_found = 0.0
        n_found = sum(int(np.isfinite(o.uv_meas[:, 0]).sum()) for o in obs)
        n_acc = sum(int(o.accepted.sum()) for o in obs)
        out.append(_judge(tr, rec.frameset(i), obs, n_found, n_acc).status)
        if tr.ekf is None:
            break
    return tr, out


def test_after_a_coast_a_track_is_published_again_only_when_strong(recs):
    """A confirmed track that had a bad frame (published ``lost``, coasting) is
    published as ``tracking`` again only after ``recover_frames`` strong frames:
    frames that are merely not bad (4 corners, no edge support) stay ``lost``
    (a one-camera box track came back from a coast on 4 corners and slid to 11-21%
    of the diameter), and with none strong within ``confirm_within_s`` the filter is
    dropped for a fresh initialisation. ``recover_frames = 0`` publishes the first
    frame that is not bad."""
    from vespro.tracker import CameraObservation

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    ids = np.arange(6)

    def ob(n_acc):  # n_acc corners found, all accepted
        acc = np.zeros(6, bool)
        acc[:n_acc] = True
        uv = np.where(acc[:, None], 0.0, np.nan)
        return CameraObservation("cam_left", True, 6, ids, np.zeros((6, 2)), np.full(6, 3.0), uv, acc)

    def run(accepted, **cfg):
        return _statuses(rec, T[0], [[ob(n)] for n in accepted], **cfg)

    # Confirmed on 6 corners, one bad frame (2 corners), then 4 corners a frame: not strong.
    tr, out = run([6, 6, 6, 2, 4, 4, 4])
    assert out == ["initializing", "tracking", "tracking", "lost", "lost", "lost", "lost"]
    tr, out = run([6, 6, 6, 2, 4, 6, 4])  # a strong frame: published again
    assert out[-3:] == ["lost", "tracking", "tracking"]
    tr, out = run([6, 6, 6, 2, 4, 4, 4], recover_frames=0)  # off: the first frame not bad
    assert out[-3:] == ["tracking"] * 3
    n_deadline = int(np.ceil(TrackerConfig().confirm_within_s * 26)) + 2
    tr, out = run([6, 6, 6, 2] + [4] * (n_deadline + 5))
    assert "tracking" not in out[3:] and tr.ekf is None and tr.lost_events == 1


def test_a_start_that_goes_bad_before_it_is_confirmed_leaves_the_status_initializing(recs):
    """A started filter whose frames go bad (``lost_after`` in a row) before it was ever
    confirmed is dropped for a fresh initialisation, as one not confirmed in time: the
    part was never reported found, so the status stays ``initializing`` (not ``lost``),
    no loss is counted and no recovery seed is offered. A confirmed track that goes bad
    the same way is lost."""
    from vespro.tracker import CameraObservation

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    ids = np.arange(6)

    def ob(n_acc):
        acc = np.zeros(6, bool)
        acc[:n_acc] = True
        uv = np.where(acc[:, None], 0.0, np.nan)
        return CameraObservation("cam_left", True, 6, ids, np.zeros((6, 2)), np.full(6, 3.0), uv, acc)

    n_bad = TrackerConfig().lost_after
    tr, out = _statuses(rec, T[0], [[ob(2)]] * (n_bad + 2))
    assert out == ["initializing"] * n_bad and tr.ekf is None
    assert tr.unconfirmed_drops == 1 and tr.lost_events == 0 and tr.status == "initializing"
    assert tr.recovery_seed() is None
    tr, out = _statuses(rec, T[0], [[ob(6)]] * 3 + [[ob(2)]] * (n_bad + 2))
    assert out[:3] == ["initializing", "tracking", "tracking"] and out[-1] == "lost"
    assert tr.ekf is None and tr.lost_events == 1 and tr.unconfirmed_drops == 0 and tr.status == "lost"


def test_a_camera_that_finds_nothing_does_not_count_against_a_confirmed_track(recs):
    """A camera whose windows find (almost) nothing is blind (the arm in front of the part,
    unknown to the model): with another camera seeing the part (two for a start), its
    corners count neither against the frame nor against a strong frame, so the track is
    still published (and a start is confirmed). Corners found and gated out are a
    disagreement, not blindness."""
    from vespro.tracker import CameraObservation

    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    ids = np.arange(8)

    def ob(name, n_found, n_acc):
        uv = np.full((8, 2), np.nan)
        uv[:n_found] = 100.0
        acc = np.zeros(8, bool)
        acc[:n_acc] = True
        return CameraObservation(name, True, 8, ids, np.zeros((8, 2)), np.full(8, 3.0), uv, acc)

    seeing = [ob("cam_left", 8, 7), ob("cam_right", 8, 8)]

    def run(frames, **cfg):
        return _statuses(rec, T[0], frames, **cfg)

    full = seeing + [ob("cam_top", 8, 8)]
    # The top camera finds 1 of 8 (11 of 24 accepted in all: under half, a bad frame without the rule).
    hidden = [ob("cam_left", 8, 5), ob("cam_right", 8, 5), ob("cam_top", 1, 1)]
    tr, out = run([full] * 3 + [hidden] * 10)
    assert out == ["initializing"] + ["tracking"] * 12 and tr.blind_frames == 10
    assert tr.reassociations == 0  # not a disagreement between cameras either
    tr, out = run([full] * 3 + [hidden] * 10, blind_found_fraction=0.0)  # off: bad frames, dropped after 4
    assert out[3:] == ["lost"] * 4 and tr.ekf is None
    # Found and gated out: the top camera disagrees with the pose (windows widened after 3 frames).
    tr, out = run([full] * 3 + [seeing + [ob("cam_top", 8, 1)]] * 3)
    assert tr.blind_frames == 0 and tr.reassociations == 1
    # Two cameras, one of them blind: a confirmed track goes on with the other (as through a
    # dropout: 7 of 16 accepted would be a bad frame) ...
    one_blind = [ob("cam_left", 8, 6), ob("cam_right", 1, 1)]
    tr, out = run([seeing] * 3 + [one_blind] * 3)
    assert out[3:] == ["tracking"] * 3 and tr.blind_frames == 3
    tr, out = run([seeing] * 3 + [one_blind] * 3, blind_found_fraction=0.0)
    assert out[3:] == ["lost"] * 3
    # ... but a start is not confirmed by one camera while the other finds nothing, unless
    # the initialiser found the part hidden from that camera ...
    tr, out = run([[ob("cam_left", 8, 8), ob("cam_right", 1, 1)]] * 3)
    assert "tracking" not in out and tr.blind_frames == 0
    tr, out = _statuses(rec, T[0], [[ob("cam_left", 8, 8), ob("cam_right", 1, 1)]] * 3, hidden=("cam_right",))
    assert out == ["initializing", "tracking", "tracking"] and tr.blind_frames == 3
    tr, out = _statuses(rec, T[0], [[ob("cam_left", 8, 8), ob("cam_right", 1, 1)]] * 3, hidden=("cam_top",))
    assert "tracking" not in out
    # ... and a seeing camera must see: none with min_accepted corners, no allowance.
    tr, out = run([seeing] * 3 + [[ob("cam_left", 8, 3), ob("cam_right", 1, 1)]] * 3)
    assert "tracking" not in out[3:] and tr.blind_frames == 0
    # A start: confirmed by the two seeing cameras (not with the rule off).
    start = [[ob("cam_left", 8, 8), ob("cam_right", 8, 7), ob("cam_top", 1, 1)]] * 3
    tr, out = run(start)
    assert out == ["initializing", "tracking", "tracking"] and tr.blind_frames == 3
    tr, out = run(start, blind_found_fraction=0.0)
    assert out == ["initializing"] * 3 and not tr.confirmed
    # ...but not when a seeing camera rejects half its corners.
    tr, out = run([[ob("cam_left", 8, 8), ob("cam_right", 8, 3), ob("cam_top", 1, 1)]] * 3)
    assert "tracking" not in out and not tr.confirmed


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


FIRST_FRAME = """
import json, sys
from vespro.groundtruth import read_groundtruth
from vespro.jit import KERNELS
from vespro.model import load_model
from vespro.recording import Recording
from vespro.rig import Rig
from vespro.tracker import InitResult, Tracker, TrackerConfig
rec = Recording(sys.argv[1])
_, _, T = read_groundtruth(sys.argv[1])
tr = Tracker(Rig((rec.rig.cameras[0],)), load_model(rec.model_path),  # one camera: the edge fit runs too
             TrackerConfig(decision=sys.argv[2]))
before = {id(k): set(k.signatures) for k in KERNELS}
fs = rec.frameset(0)
tr.start(InitResult(T[0]), fs.t_ns)
out = tr.process(fs)
late = [k.py_func.__qualname__ for k in KERNELS if set(k.signatures) - before.get(id(k), set())]
print(json.dumps({"late": late, "stages": sorted(out.stage_ms)}))
"""


@pytest.mark.parametrize("decision", ["rules", "bank"])
def test_the_first_frame_loads_no_compiled_kernel(recs, decision):
    """The tracker loads its compiled kernels when it is made, not on its first frame (in a
    fresh process: a one-camera tracker's first frame took 42 ms instead of 5, loading the
    edge fit's last kernels), with either decision (the bank's likelihood has its own)."""
    import json
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", FIRST_FRAME, str(recs["box_conveyor"]), decision], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout.strip().splitlines()[-1])
    assert "edges" in got["stages"]  # the edge fit ran on that frame
    assert got["late"] == []


@pytest.mark.parametrize("max_half, crowded, confirmed, widened, passes", [
    (24, False, True, False, 1),   # a confirmed track, large windows each holding one corner: once
    (24, False, False, False, 2),  # a start not confirmed yet: twice
    (24, True, True, False, 2),    # a chosen window held another predicted corner: twice
    (24, False, True, True, 2),    # windows widened for a search: twice
    (6, True, False, True, 1),     # small windows: once, whatever else
])
def test_a_frame_is_measured_again_only_where_the_first_pass_is_in_doubt(recs, max_half, crowded, confirmed,
                                                                         widened, passes):
    """Large windows alone do not call for a second pass: a camera that sees the part close up
    has large windows in pixels (and its corners far apart) on every frame."""
    rec = Recording(recs["box_conveyor"])
    _, _, T = read_groundtruth(recs["box_conveyor"])
    tr = _started(rec, T[0])
    tr.confirmed = confirmed
    calls = []

    def measure(fs, stage, assoc=None):
        calls.append(assoc)
        return [], 8, 8, 1.0, (max_half, crowded), True

    tr._measure = measure
    tr._measure_twice(rec.frameset(1), {}, widened=widened)
    assert len(calls) == passes
    assert calls[0] is None and all(a is not None for a in calls[1:])  # the second about the first's result
