"""The initialiser on simulated cells and on the external example recording.

Trials (``vespro.sim.trials``): random start pose in the common view, random
rig (a subset of the standard cameras with perturbed placements, 1 to 3
cameras, or hybrid), a few frames each, cached per module. Ground truth is
used here, for scoring only.
"""

import math
from dataclasses import replace

import numpy as np
import pytest
from strided import Strided
from trial_frames import trial_frames

from vespro.frames import FrameSet
from vespro.groundtruth import read_groundtruth
from vespro.init import InitOptions, make_initializer
from vespro.init.features import EdgeOptions
from vespro.library import object_mesh_path
from vespro.metrics import add
from vespro.model import load_model
from vespro.recording import Recording
from vespro.se3 import transform_from_rt
from vespro.sim.cell import SimCell
from vespro.sim.motion import Static
from vespro.sim.trials import model_symmetries, random_rig, trial_config

#: (object, rig kind, seed): one or more of each object, each rig size.
TRIALS = [("box", "1", 0), ("box", "3", 1), ("lblock", "2", 2), ("lblock", "hybrid", 3),
          ("bracket", "3", 4), ("bracket", "1", 5)]
#: Frames each trial may use (attempts on frames 0 and ATTEMPT_STRIDE).
N_FRAMES = 4
ATTEMPT_STRIDE = 3


def _rig(kind, seed):
    rng = np.random.default_rng(10_000 + seed)
    return random_rig(rng, 2, hand=True) if kind == "hybrid" else random_rig(rng, int(kind))


def _sym_add_frac(T_est, T_true, model, syms):
    return min(add(T_est, T_true @ S, model.vertices) for S in syms) / model.diameter


def _trial_frame(obj, kind, seed, frame, **config_changes):
    """A bench trial's frame ``frame`` (its cell config changed by ``config_changes``):
    (initialiser set-up, model, symmetries, frame set, true pose)."""
    rig = _rig(kind, seed)
    config, motion, mesh = trial_config(obj, rig, seed)
    model = load_model(mesh)
    setup = make_initializer(rig, model).setup
    with SimCell(replace(config, **config_changes), motion) as cell:
        cell.settle_arm()
        for _ in range(frame + 1):
            fs = cell.next_frameset()
        T_true = cell.true_object_pose()
    return setup, model, model_symmetries(model.vertices), fs, T_true


def _calls_until_pose(cell, ini, model, syms, before=None, frames=6, stride=5):
    """Call ``ini`` on frames 0, stride, ... of ``cell`` until it returns a pose
    (not a provisional one: that is for the tracker to confirm, and the next call).

    ``before(k, frameset)`` runs ahead of each call. A returned pose must be
    within 10% of the diameter (symmetry-aware ADD). Returns the last result
    and each call's (mode, plain, reason).
    """
    cell.settle_arm()
    res, modes = None, []
    for k in range(frames):
        fs = cell.next_frameset()
        if k % stride:
            continue
        if before is not None:
            before(k, fs)
        res = ini(fs)
        modes.append((ini.last_report.mode, ini.last_report.plain, ini.last_report.reason))
        if res is not None and not res.provisional:
            assert _sym_add_frac(res.T_world_object, cell.true_object_pose(), model, syms) < 0.1
            break
    return res, modes


@pytest.fixture(scope="module")
def trial_results():
    """Per trial: (ADD / diameter of the first pose returned or None, report)."""
    out = {}
    for obj, kind, seed in TRIALS:
        rig = _rig(kind, seed)
        config, motion, mesh = trial_config(obj, rig, seed)
        model = load_model(mesh)
        syms = model_symmetries(model.vertices)
        ini = make_initializer(rig, model)
        result = (None, None)
        with SimCell(config, motion) as cell:
            cell.settle_arm()
            for k in range(N_FRAMES):
                fs = cell.next_frameset()
                if k % ATTEMPT_STRIDE:
                    continue
                res = ini(fs)
                if res is not None:
                    result = (_sym_add_frac(res.T_world_object, cell.true_object_pose(), model, syms), ini.last_report)
                    break
                result = (None, ini.last_report)
        out[(obj, kind, seed)] = result
    return out


def test_returned_poses_are_right(trial_results):
    """Whenever a pose is returned, ADD < 10% of the diameter (no wrong lock)."""
    for key, (e, rep) in trial_results.items():
        if e is not None:
            assert e < 0.1, (key, e, rep)


def test_most_trials_initialise(trial_results):
    ok = sum(e is not None for e, _ in trial_results.values())
    # The bench (bench/init.py) measures the rate over many trials; these few
    # must mostly succeed: at most one of six may stay 'initializing'.
    assert ok >= len(TRIALS) - 1, {k: (e, r and r.reason) for k, (e, r) in trial_results.items()}


def test_multi_camera_poses_are_tracker_grade(trial_results):
    """Several cameras pin the pose well inside the EKF's initial uncertainty."""
    for (obj, kind, seed), (e, rep) in trial_results.items():
        if e is not None and kind != "1":
            assert e < 0.03, (obj, kind, seed, e)


def test_reports_carry_compute_time(trial_results):
    for e, rep in trial_results.values():
        assert rep is not None and rep.wall_s > 0 and rep.cpu_s > 0
        assert rep.accepted == (e is not None)


def test_no_object_in_view_never_locks():
    """The part parked far below the floor: nothing to find on any frame."""
    rig = _rig("3", 7)
    config, _, mesh = trial_config("lblock", rig, 7)
    model = load_model(mesh)
    ini = make_initializer(rig, model)
    with SimCell(config, Static(transform_from_rt(np.eye(3), [0.0, 0.0, -5.0]))) as cell:
        cell.settle_arm()
        for _ in range(3):
            assert ini(cell.next_frameset()) is None
            assert not ini.last_report.accepted


def test_single_camera_without_object_never_locks():
    rig = _rig("1", 8)
    config, _, mesh = trial_config("box", rig, 8)
    ini = make_initializer(rig, load_model(mesh))
    with SimCell(config, Static(transform_from_rt(np.eye(3), [0.0, 0.0, -5.0]))) as cell:
        cell.settle_arm()
        for _ in range(2):
            assert ini(cell.next_frameset()) is None


def test_reseed_finds_the_part_near_its_predicted_pose():
    rig = _rig("2", 9)
    config, motion, mesh = trial_config("bracket", rig, 9)
    model = load_model(mesh)
    ini = make_initializer(rig, model, seed_only=True)
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        fs = cell.next_frameset()
        T = cell.true_object_pose()
    # A prediction 1 cm and ~5 degrees off, as after a short loss.
    Tp = T @ transform_from_rt(np.eye(3), [0.006, -0.005, 0.005])
    c, s = np.cos(0.08), np.sin(0.08)
    Tp[:3, :3] = Tp[:3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    ini.reseed(Tp, velocity=np.zeros(6), t_ns=fs.t_ns)
    res = ini(fs)
    assert res is not None and ini.last_report.mode == "seed", ini.last_report.reason
    assert add(res.T_world_object, T, model.vertices) < 0.03 * model.diameter


def test_example_box2_initialises_within_one_second(example_box2):
    rec = Recording(example_box2)
    model = load_model(rec.model_path)
    syms = model_symmetries(model.vertices)
    _, _, T_true = read_groundtruth(example_box2)  # scoring only
    ini = make_initializer(rec.rig, model)
    for k in range(min(26, len(rec))):
        res = ini(rec.frameset(k))
        if res is not None:
            assert _sym_add_frac(res.T_world_object, T_true[k], model, syms) < 0.1
            return
    pytest.fail(f"no pose within 26 frames: {ini.last_report.reason}")


def test_example_box2_one_camera_missing(example_box2):
    """A frame set with one image missing still initialises from the other."""
    rec = Recording(example_box2)
    model = load_model(rec.model_path)
    syms = model_symmetries(model.vertices)
    _, _, T_true = read_groundtruth(example_box2)
    ini = make_initializer(rec.rig, model)
    name = rec.rig.names[0]
    for k in range(0, 26, 5):
        fs = rec.frameset(k)
        fs1 = FrameSet(fs.index, fs.t_ns, {n: (None if n == name else im) for n, im in fs.images.items()},
                       fs.T_world_camera)
        res = ini(fs1)
        if res is not None:
            assert _sym_add_frac(res.T_world_object, T_true[k], model, syms) < 0.1
            return
    pytest.skip("one camera alone did not initialise within 26 frames (allowed: a late lock, not a wrong one)")


#: Single-camera trials (rig seed as in bench/init.py) the plain-face limits
#: initialise: one face dark against the dark belt, so the strict single-camera
#: limits reject the true pose; found on frame 0, confirmed on frame 5. With
#: the edge thresholds that lose that face (the former fixed 40 / 100: the
#: present floors find most of its edges, and the strict limits then pass),
#: with culling alone in the ranking (``keep_occlusion_rank=0``) and with an
#: image edge point counted for both edges of a thin strip
#: (``shared_edge_px=0``). (L-block 16, once here, now passes the strict
#: limits on frame 0 even so: an edge end where another edge of the part runs
#: straight on in the image no longer counts as an overrun.)
SINGLE_PLAIN = [("box", 6), ("lblock", 6)]
LOSSY_EDGES = EdgeOptions(canny_low=40.0, canny_high=100.0)


@pytest.mark.parametrize("obj,seed", SINGLE_PLAIN)
def test_single_camera_plain_faces_initialise_without_wrong_lock(obj, seed):
    rig = _rig("1", seed)
    config, motion, mesh = trial_config(obj, rig, seed)
    model = load_model(mesh)
    syms = model_symmetries(model.vertices)
    ini = make_initializer(rig, model, edges=LOSSY_EDGES, keep_occlusion_rank=0, shared_edge_px=0.0)
    strict = make_initializer(rig, model, plain_faces=False, edges=LOSSY_EDGES, keep_occlusion_rank=0,
                              shared_edge_px=0.0)

    def strict_fails_on_frame_0(k, fs):
        if k == 0:
            assert strict(fs) is None  # the strict limits alone cannot

    with SimCell(config, motion) as cell:
        res, modes = _calls_until_pose(cell, ini, model, syms, before=strict_fails_on_frame_0)
    assert res is not None, modes
    # Provisional on frame 0 (plain limits), found again on frame 5.
    assert modes[0][:2] == ("provisional", True) and modes[-1][0] == "confirm", modes


#: Single-camera trials (rig seed as in bench/init.py) with one face seen
#: head-on: every check passes but the accidental-view test (one face seen
#: openly), so the pose is held back on frame 0 and confirmed on frame 5.
SINGLE_ACCIDENTAL = [("box", 18), ("lblock", 17)]


def _held_back_then_confirmed(obj, seed, **route_off):
    """One-camera trial: a provisional pose on frame 0, confirmed on frame 5; an
    initialiser with the provisional route turned off (``route_off``) returns
    nothing on either. Returns that initialiser (its last report says why)."""
    rig = _rig("1", seed)
    config, motion, mesh = trial_config(obj, rig, seed)
    model = load_model(mesh)
    syms = model_symmetries(model.vertices)
    ini = make_initializer(rig, model)
    without = make_initializer(rig, model, **route_off)
    res_without = []
    with SimCell(config, motion) as cell:
        res, modes = _calls_until_pose(cell, ini, model, syms, before=lambda k, fs: res_without.append(without(fs)))
    assert res is not None, modes
    assert modes[0][:2] == ("provisional", True) and modes[-1][0] == "confirm", modes
    assert res_without == [None, None]
    return without


@pytest.mark.parametrize("obj,seed", SINGLE_ACCIDENTAL)
def test_single_camera_accidental_view_is_confirmed_not_locked_at_once(obj, seed):
    _held_back_then_confirmed(obj, seed, min_open_faces_confirm=2)  # the accidental-view test alone rejects it


def test_edges_running_on_past_true_corners_are_confirmed_not_rejected():
    """L-block seed 201, one camera: its step seen edge-on lines two faces up,
    so image edges run on past 44% of the true pose's corners (the strict
    single-camera limit is 25%). Held back on frame 0, confirmed on frame 5;
    rejected on both with the provisional overrun turned off."""
    without = _held_back_then_confirmed("lblock", 201, max_overrun_frac_confirm=0.25)
    assert "run on past" in without.last_report.reason


def _bracket_frame_0_found_only_with(seed, without, max_add=0.1, **base):
    """One-camera bracket trial, frame 0: an initialiser with options ``base``
    plus ``without`` returns nothing; with ``base`` alone it returns a pose
    within ``max_add`` of the diameter (symmetry-aware ADD)."""
    rig = _rig("1", seed)
    config, motion, mesh = trial_config("bracket", rig, seed)
    model = load_model(mesh)
    ini = make_initializer(rig, model, **base)
    lacking = make_initializer(rig, model, **base, **without)
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        fs = cell.next_frameset()
        assert lacking(fs) is None
        res = ini(fs)
        assert res is not None, ini.last_report.reason
        assert _sym_add_frac(res.T_world_object, cell.true_object_pose(), model,
                             model_symmetries(model.vertices)) < max_add


def test_ranking_with_self_occlusion_lets_the_strict_limits_initialise():
    """Bracket, rig seed 16, one camera, strict limits: ranked with culling
    alone no refined candidate passes on frame 0 (the edges the bracket hides
    from itself count as unsupported and rank its true pose out); ranked
    without the samples the part hides from itself, the right pose is refined
    and passes at once."""
    _bracket_frame_0_found_only_with(16, dict(keep_occlusion_rank=0), plain_faces=False)


def test_a_brief_refinement_lifts_a_rough_true_hypothesis_above_clutter_fits():
    """Bracket, rig seed 610, one camera, frame 0: the P3P hypotheses near the
    true pose rank 38th and lower (three corners located to a pixel or two put
    the outline a few px off, below clutter fits), beyond the few the search
    refines, and no pose comes out. With none of those passing, the best 60 are
    refined briefly (``n_quick``), ranked on their refined poses, and the true
    one passes at once."""
    _bracket_frame_0_found_only_with(610, dict(n_quick=0), max_add=0.05)


def test_an_image_edge_serves_one_edge_of_a_thin_strip():
    """L-block, rig seed 38, one camera, frame 15: a face seen nearly edge-on
    makes a thin strip whose two edges both find the one image edge. Refined
    from the true pose with that image edge counted for both, the strip is
    pulled thinner and the pose slides along the line of sight, 19% of the
    diameter (this was a wrong lock, 12%, on frame 20); with the image edge
    point serving the nearer model edge only, the refinement stays on it."""
    from vespro.init.initializer import _views
    from vespro.edgefit import refine_pose, refine_subpixel

    setup, model, syms, fs, T_true = _trial_frame("lblock", "1", 38, 15)
    views = _views(setup, fs)
    T0 = refine_pose(T_true, views, setup.mf, setup.tree)
    err = {sh: _sym_add_frac(refine_subpixel(T0, views, setup.mf, setup.tree, shared_edge_px=sh), T_true, model, syms)
           for sh in (setup.options.shared_edge_px, 0.0)}
    assert err[setup.options.shared_edge_px] < 0.05 and err[0.0] > 0.1, err


def test_dark_face_edges_let_the_strict_limits_initialise():
    """Box, rig seed 6, one camera: the face 10-20 grey levels above the dark
    belt. The former thresholds lost its edges (the strict limits rejected the
    true pose, test above); the present floors keep them, and the strict
    limits accept the right pose on frame 0."""
    rig = _rig("1", 6)
    config, motion, mesh = trial_config("box", rig, 6)
    model = load_model(mesh)
    strict = make_initializer(rig, model, plain_faces=False)
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        res = strict(cell.next_frameset())
        assert res is not None, strict.last_report.reason
        assert _sym_add_frac(res.T_world_object, cell.true_object_pose(), model,
                             model_symmetries(model.vertices)) < 0.1


def test_only_a_plain_pose_that_passed_every_check_is_tried_again(monkeypatch):
    """The initialiser hands the next call a pose to confirm only when the
    report says it passed every check under the plain-face limits (a
    candidate rejected as ambiguous was once confirmed: a wrong lock)."""
    from vespro.init import initializer as mod

    T_a, T_b = np.eye(4), transform_from_rt(np.eye(3), [0.1, 0.0, 0.0])
    script = [(None, mod.InitReport(0.1, 0.1, "none", 5, False, reason="ambiguous", candidates=((T_a, None),))),
              (None, mod.InitReport(0.1, 0.1, "none", 5, False, reason="to be confirmed", candidates=((T_b, None),),
                                    plain=True)),
              (None, mod.InitReport(0.1, 0.1, "none", 5, False, reason="x"))]
    seen = []

    def fake(setup, frameset, seed, rng, pending, attempt, age_s, recall=()):
        assert recall == ()  # no call found an ambiguity between poses it returned as rivals
        seen.append((pending, attempt, age_s))
        return script[len(seen) - 1]

    monkeypatch.setattr(mod, "initialize", fake)
    ini = mod.Initializer(setup=None)
    for i in range(3):
        assert ini(FrameSet(i, i, {})) is None
    assert seen[0] == (None, 0, 0.0) and seen[1] == (None, 1, 0.0)
    assert seen[2][0] is T_b and seen[2][1] == 2 and seen[2][2] == 1e-9  # stamps 1 ns apart


def test_an_ambiguity_found_is_recalled_for_a_second_unless_a_pose_is_returned(monkeypatch):
    """A call that finds the view ambiguous hands its two poses (``InitReport.rivals``) to
    the calls of the next ``recall_rivals_s`` (a later call whose own search misses one
    of them still weighs it); a returned pose or an older ambiguity clears them."""
    from types import SimpleNamespace

    from vespro.init import initializer as mod
    from vespro.startpose import InitResult

    T_a, T_b = np.eye(4), transform_from_rt(np.eye(3), [0.1, 0.0, 0.0])
    amb = mod.InitReport(0.1, 0.1, "none", 5, False, reason="ambiguous", rivals=(T_a, T_b))
    none = mod.InitReport(0.1, 0.1, "none", 5, False, reason="x")
    found = mod.InitReport(0.1, 0.1, "search", 5, True)
    script = [(None, amb), (None, none), (InitResult(T_a), found), (None, amb), (None, none)]
    seen = []

    def fake(setup, frameset, seed, rng, pending, attempt, age_s, recall=()):
        seen.append(recall)
        return script[len(seen) - 1]

    monkeypatch.setattr(mod, "initialize", fake)
    ini = mod.Initializer(setup=SimpleNamespace(options=InitOptions()))
    s = int(1e9)
    for t_ns in (0, s // 2, 9 * s // 10, 2 * s, 3 * s + 1):
        ini(FrameSet(len(seen), t_ns, {}))
    assert seen[0] == ()
    assert seen[1] == (T_a, T_b) and seen[2] == (T_a, T_b)  # 0.5 and 0.9 s after it
    assert seen[3] == ()  # a pose was returned
    assert seen[4] == ()  # found at 2 s: over a second old at 3 s


def test_single_camera_turned_over_lblock_is_not_a_lock():
    """Rig seed 36, one camera: the L-block turned over fits the edges better
    (0.95 of the samples) than the true pose (0.89). Once locked wrong on
    frame 0 (the distinct-pose test used ADD-S, under which the two are
    close) and on frame 5 (margin 0.05); now ambiguous, or right."""
    rig = _rig("1", 36)
    config, motion, mesh = trial_config("lblock", rig, 36)
    model = load_model(mesh)
    syms = model_symmetries(model.vertices)
    ini = make_initializer(rig, model)
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        for k in range(6):
            fs = cell.next_frameset()
            if k % 5:
                continue
            res = ini(fs)
            if res is not None:
                assert _sym_add_frac(res.T_world_object, cell.true_object_pose(), model, syms) < 0.1


def test_one_camera_never_accepts_a_pose_whose_faces_cover_image_edges():
    """Rig seed 1617, one camera, a bracket seen from above on the belt: the search
    missed the true pose and put first one 90% of the diameter off whose faces lie over
    the real part's slot and step (3.6% of their interiors on image edges). It passed
    every strict single-camera check (inlier fraction 0.72, two open faces) and was
    returned, and the tracker published it. A part with plain faces shows no edges
    inside its faces at the true pose (at most 0.13% in 352 one-camera views), so with
    one judging camera every pose must keep them clear, not only the plain-face ones."""
    from vespro.init.initializer import _checked, _refined, _verdict, _views, initialize

    setup, model, syms, fs, T_true = _trial_frame("bracket", "1", 1617, 5)
    res, rep = initialize(setup, fs)
    assert res is None or _sym_add_frac(res.T_world_object, T_true, model, syms) < 0.1
    T_best, chk = rep.candidates[0]
    assert _sym_add_frac(T_best, T_true, model, syms) > 0.5
    assert chk.n_cameras == 1 and chk.interior_edge_frac > 0.02
    assert _verdict(replace(chk, interior_edge_frac=0.0), setup.options)[0]  # the premise: it passes otherwise
    assert "inside the faces" in rep.reason
    views = _views(setup, fs)
    chk_true = _checked(_refined(T_true, views, setup), views, setup)
    assert chk_true.interior_edge_frac <= setup.options.plain_max_interior_edge_frac

def test_paths_with_one_edge_running_on_find_a_part_against_an_aligned_background():
    """Bracket, rig seed 36, one camera, frame 0: the flange's long edge lies
    along a rail whose edge runs on past the part's corner, so no image corner
    path on the part's true corners has both edges ending there and no P3P
    pose comes within 14% of the diameter. A call after one without a pose
    also forms paths with one edge ending at the middle corner, and finds it
    (the first call does not: its cost is unchanged)."""
    from vespro.init.initializer import initialize, make_setup

    rig = _rig("1", 36)
    config, motion, mesh = trial_config("bracket", rig, 36)
    model = load_model(mesh)
    setup = make_setup(rig, model)
    both_ends = make_setup(rig, model, replace(InitOptions(), one_end_paths=False), tree=setup.tree)
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        fs = cell.next_frameset()
        T_true = cell.true_object_pose()
    assert initialize(setup, fs, attempt=0)[0] is None
    assert initialize(both_ends, fs, attempt=1)[0] is None
    res, rep = initialize(setup, fs, attempt=1)
    assert res is not None, rep.reason
    assert _sym_add_frac(res.T_world_object, T_true, model, model_symmetries(model.vertices)) < 0.1


def test_a_provisional_pose_is_confirmed_only_if_it_still_comes_first():
    """Bracket, rig seed 404, one camera, judged without the plain-face
    assumption (which now rejects that pose outright, test_init_plain): frame
    0 leaves a provisional pose fitted over clutter, 71% of the diameter off.
    Given it as the pending pose on frame 5, the call still searches: the
    part's true pose explains twice the edge length and comes first, so the
    fit to static clutter (found again on every frame) is not confirmed.
    The outline rule (``max_outer_parallel_confirm``) refuses
    that fit and frame 0 gives the true pose (3.6% off); the rule is off here to
    keep the premise."""
    from vespro.init.initializer import initialize, make_setup

    rig = _rig("1", 404)
    config, motion, mesh = trial_config("bracket", rig, 404)
    model = load_model(mesh)
    syms = model_symmetries(model.vertices)
    setup = make_setup(rig, model)
    textured = make_setup(rig, model, replace(InitOptions(), plain_faces=False, max_outer_parallel_confirm=-1),
                          tree=setup.tree)
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        fs0 = cell.next_frameset()
        T0 = cell.true_object_pose()
        for _ in range(5):
            fs5 = cell.next_frameset()
        T5 = cell.true_object_pose()
    res0, rep0 = initialize(textured, fs0)
    assert res0 is not None and res0.provisional and rep0.mode == "provisional" and rep0.plain
    T_pending = res0.T_world_object
    assert _sym_add_frac(T_pending, T0, model, syms) > 0.5
    res5, rep5 = initialize(textured, fs5, pending_T_world_object=T_pending, attempt=1, pending_age_s=5 / 26)
    # Not confirmed: the true pose, provisional in its turn (or accepted outright).
    assert res5 is not None and rep5.mode != "confirm"
    assert _sym_add_frac(res5.T_world_object, T5, model, syms) < 0.1
    # With the outline rule (the default) frame 0 does not take the clutter fit.
    res_d, _ = initialize(make_setup(rig, model, replace(InitOptions(), plain_faces=False), tree=setup.tree), fs0)
    assert res_d is None or _sym_add_frac(res_d.T_world_object, T0, model, syms) < 0.1


def test_a_provisional_start_is_tracked_but_published_only_once_confirmed():
    """The same trial through the tracker (initialiser on every 5th frame): the filter
    starts at once from frame 0's provisional pose (the fit to clutter, 71% off) but
    publishes nothing while it is provisional; the initialiser goes on looking, its
    frame-5 call puts the part's true pose first and the filter is started again from
    it (``Tracker.offer``), which the frame-10 call confirms. Tracked without waiting,
    a provisional start is published as soon as it is confirmed: a correct one-camera
    L-block start (rig seed 410) whose frame-5 call judged the view accidental was
    published 41 frames in; now at 10. (The outline rule off, as above: with it frame 0
    gives the true pose.)"""
    from vespro.tracker import Tracker

    rig = _rig("1", 404)
    config, motion, mesh = trial_config("bracket", rig, 404)
    model = load_model(mesh)
    syms = model_symmetries(model.vertices)
    ini = make_initializer(rig, model, plain_faces=False, max_outer_parallel_confirm=-1)
    tr = Tracker(rig, model, initializer=lambda fs: None if fs.index % 5 else ini(fs))
    tr.initializer.await_confirmation = ini.await_confirmation
    starts, published = [], []
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        for k in range(16):
            out = tr.process(cell.next_frameset())
            T_true = cell.true_object_pose()
            if k % 5 == 0:
                starts.append((tr.provisional, _sym_add_frac(tr.ekf.pose, T_true, model, syms)))
            if out.status == "tracking":
                published.append((k, _sym_add_frac(out.T_world_object, T_true, model, syms)))
    assert starts[0][0] and starts[0][1] > 0.5  # the clutter fit, tracked provisionally
    assert tr.starts_replaced >= 1 and starts[1][1] < 0.1
    assert published and published[0][0] <= 12 and max(e for _, e in published) < 0.1, published


def test_a_one_camera_start_that_never_confirms_is_dropped_not_published():
    """Bracket, rig seed 209, one camera, initialiser on every 5th frame as in
    ``bench/init.py --track``: the pose of frame 5 is right (0.9% of the
    diameter), but the filter's first frames find few corners and it slides off
    with 3-4 of 8 accepted. Kept, it confirmed a pose 28% off on frame 43; now
    it is dropped after ``confirm_within_s`` and a fresh initialisation tracks
    (measured: published from frame 33 at 4.4%). On corners alone (``edge_aid``
    off): the edge-aided update keeps this filter from sliding in the first
    place, and the deadline is for whatever else leaves a start unconfirmed. Likewise the
    start is handed over with the tracker's wide default covariance
    (``start_covariance`` off): with the edge fit's, the first frames' windows are narrow
    and this start does not slide either. And without the initialiser's fallback
    search (``n_quick``), which finds a different start on frame 0."""
    from vespro.tracker import Tracker, TrackerConfig

    rig = _rig("1", 209)
    config, motion, mesh = trial_config("bracket", rig, 209)
    model = load_model(mesh)
    syms = model_symmetries(model.vertices)
    ini = make_initializer(rig, model, replace(InitOptions(), start_covariance=False, n_quick=0))
    tr = Tracker(rig, model, TrackerConfig(edge_aid="off"), initializer=lambda fs: None if fs.index % 5 else ini(fs))
    published = []
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        for _ in range(46):
            out = tr.process(cell.next_frameset())
            if out.status == "tracking":
                published.append(_sym_add_frac(out.T_world_object, cell.true_object_pose(), model, syms))
    assert tr.unconfirmed_drops >= 1
    assert published and max(published) < 0.1, published


def test_the_start_pose_comes_with_its_edge_fit_covariance():
    """Bracket, rig seed 5, one camera: the frame-0 pose (1.8% of the diameter off) is
    handed over with the covariance of its sub-pixel edge fit (2 mm, 0.3-0.5 deg; NEES
    against the truth under the 0.999 chi-square quantile). With it the first frame's
    windows are narrow, 7 of 8 corners are found and every published frame is within 10%
    (measured 0.2-3%). With the tracker's wide default instead the windows took two wrong
    image corners 9-12 px off, the first update moved the pose to 8.6% and the filter slid
    to 20% (the premise, checked here with the edge fits as they were then: every sample
    weighing alike, no edge dropped, no dim corner passed over, and the start's fits at
    their word, ``start_edge_offset_px`` 0; with today's edge fits the wide start stays
    within 7.3%, and with the old ones but dim corners passed over within 7.4%)."""
    from scipy.stats import chi2

    from vespro.ekf import nees
    from vespro.startpose import InitResult
    from vespro.tracker import Tracker, TrackerConfig

    rig = _rig("1", 5)
    config, motion, mesh = trial_config("bracket", rig, 5)
    model = load_model(mesh)
    syms = model_symmetries(model.vertices)
    ini = make_initializer(rig, model)
    frames = []
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        for _ in range(12):
            frames.append((cell.next_frameset(), cell.true_object_pose()))
    res = ini(frames[0][0])
    assert res is not None and res.cov6 is not None
    T_true = min((frames[0][1] @ S for S in syms), key=lambda X: add(res.T_world_object, X, model.vertices))
    assert nees(res.T_world_object, T_true, res.cov6) < chi2.ppf(0.999, 6)
    assert np.sqrt(np.max(np.linalg.eigvalsh(res.cov6[:3, :3]))) < 0.005

    def run(start, old_edge_fits=False):
        tr = Tracker(rig, model, TrackerConfig(dim_corner_frac=0.0, start_edge_offset_px=0.0)
                     if old_edge_fits else TrackerConfig())
        if old_edge_fits:
            tr.edge_aid.spacing_px = tr.edge_aid.edge_outlier_px = 0.0
        tr.start(start, frames[0][0].t_ns)
        errs, published = [], []
        for fs, T in frames:
            out = tr.process(fs)
            e = _sym_add_frac(tr.ekf.pose, T, model, syms) if tr.ekf is not None else np.inf
            errs.append(e)
            if out.status == "tracking":
                published.append(e)
        return errs, published

    errs, published = run(res)
    assert len(published) >= len(frames) - 2 and max(published) < 0.1, published
    errs_default, _ = run(InitResult(res.T_world_object), old_edge_fits=True)
    assert max(errs_default) > 0.1, errs_default


@pytest.mark.parametrize("rig_file", ["hybrid", "hand"])
def test_warm_up_loads_the_kernels_and_decides_nothing(rig_file):
    """``Initializer.warm_up`` (called by the server's worker at start-up) runs the compiled
    search kernels on a blank image of the first camera, fixed or eye-in-hand, and leaves
    the initialiser as it was."""
    from vespro.rig import load_rig
    from vespro.sim.rigs import CAMERAS_DIR

    rig = load_rig(CAMERAS_DIR / f"{rig_file}.yaml")
    ini = make_initializer(rig, load_model(object_mesh_path("lblock")))
    before = (ini._pending, ini._attempt, ini._seed, ini.last_report)
    ini.warm_up()
    assert (ini._pending, ini._attempt, ini._seed, ini.last_report) == before


def test_a_hidden_camera_is_left_out_for_every_candidate_alike():
    """Box, hybrid rig seed 201, a paddle hiding the part from ``cam_right`` throughout,
    frame 5. Judged each without its own worst camera, a pose 18% of the diameter off
    (fitting ``cam_left`` and the hand camera at 0.78) beat the true pose, whose statistics
    still counted the hidden camera's zeros, and was returned. Judged alike without the
    hidden camera the true pose comes first and that rival makes the view ambiguous: no
    pose, never a wrong one. Without ``hidden_camera`` no candidate passes at all."""
    from vespro.init.initializer import initialize
    from vespro.sim.cell import OccluderSweep

    paddle = OccluderSweep("cam_right", 0.0, duration=100.0, half_travel=0.0)
    setup, model, syms, fs, T_true = _trial_frame("box", "hybrid", 201, 5, occluders=(paddle,))
    res, rep = initialize(setup, fs)
    assert res is None or _sym_add_frac(res.T_world_object, T_true, model, syms) < 0.1
    assert all(c.hidden == "cam_right" and c.n_cameras == 2 for _, c in rep.candidates)
    assert _sym_add_frac(rep.candidates[0][0], T_true, model, syms) < 0.02
    res, rep = initialize(replace(setup, options=replace(setup.options, hidden_camera=False)), fs)
    assert res is None and all(c.hidden == "" for _, c in rep.candidates)


def test_a_pose_explaining_part_of_what_the_best_explains_is_no_rival():
    """Box, one camera, rig seed 404, frame 5: the top face and a dark side face in view.
    The top face fitted alone (14% of the diameter off, its side face left over the belt)
    explains 0.98 of its edges against the true pose's 1.00 and 85% of its edge length,
    all of it edges the true pose explains too: it made the call ambiguous. Seen as
    part of the best's explanation it is no rival, and the true pose is taken
    (provisionally: one face seen openly)."""
    from vespro.init.initializer import _part_of, initialize
    from vespro.init.search import unshared_px

    setup, model, syms, fs, T_true = _trial_frame("box", "1", 404, 5)
    res, rep = initialize(setup, fs)
    (T0, c0), rivals = rep.candidates[0], rep.candidates[1:]
    assert _sym_add_frac(T0, T_true, model, syms) < 0.05
    part = [c for T, c in rivals if _sym_add_frac(T, T_true, model, syms) > 0.1
            and c.inlier_frac >= c0.inlier_frac - setup.options.ambiguity_margin_single]
    assert part and all(_part_of(c, c0, setup.options) for c in part)
    assert all(unshared_px(c, c0) <= 0.05 * c.inlier_px for c in part)
    assert (res is not None and _sym_add_frac(res.T_world_object, T_true, model, syms) < 0.1) or rep.plain, rep.reason
    off = replace(setup, options=replace(setup.options, subset_margin_frac=-1.0))
    res, rep = initialize(off, fs)
    assert res is None and "ambiguous" in rep.reason


# The tracker without its fit gap gate (``TrackerConfig.confirm_max_fit_gap``) and with its
# process noise fixed (``adaptive_motion`` off), for the premises of the one-camera trials below
# that were measured without them: each holds back several of those wrong starts on its own (the
# corners' pose and the edges' lie apart; a start sliding on wrong corners raises the noise and
# widens its own windows until the right ones return).
NO_GAP = {"confirm_max_fit_gap": math.inf, "adaptive_motion": False}


def _published_one_camera(obj, seed, n_frames, tracker=None, **opts):
    """A one-camera bench trial (rig seed ``seed``) run through the tracker (options
    ``tracker``, a dict) with the initialiser (options ``opts``) called on every 5th frame,
    as the server's worker calls it: ADD / diameter of every frame published ``tracking``."""
    from vespro.tracker import Tracker, TrackerConfig

    rig, model, frames = trial_frames(obj, seed, n_frames)
    syms = model_symmetries(model.vertices)
    tr = Tracker(rig, model, TrackerConfig(**(tracker or {})), initializer=Strided(make_initializer(rig, model, **opts)))
    out = []
    for fs, T in frames:
        o = tr.process(fs)
        if o.status == "tracking":
            out.append(_sym_add_frac(o.T_world_object, T, model, syms))
    return out


def test_a_call_confirming_a_provisional_pose_searches_as_hard_as_any():
    """One camera, L-block (rig seed 2017), the tracker with the initialiser every 5th
    frame: a provisional start 58% of the diameter off (the true pose's P3P hypotheses
    ranked out). Its confirming call without the fallback refinement of the ranking
    (``quick_when_pending=False``) found it again first and it was published from frame
    44 (the premise); with it, that call puts the true pose first and nothing wrong is
    published (measured: published from frame 39 at 1.4%; with the
    stricter count of distinct edges, from frame 48 at 2-3%). A confirming
    call also refines deeper down the ranking (``n_refine_confirm``), which finds it too,
    so the premise turns both off."""
    assert max(_published_one_camera("lblock", 2017, 46, quick_when_pending=False, n_refine_confirm=0),
               default=0.0) >= 0.1
    errs = _published_one_camera("lblock", 2017, 52)
    assert errs and max(errs) < 0.1, errs


def test_an_ambiguity_found_earlier_still_holds_when_a_search_misses_the_rival():
    """One camera, box (fresh rig seed 3406): two faces seen, and a pose turned about
    the line of sight, 56% of the diameter off, explains the outline as well as the true
    one (0.91-0.93 of the samples against 0.85-0.87). The calls at frames 0-20 find
    both and return nothing; the call at frame 25 found only the wrong one, took it and
    the track was published from frame 26 (the premise, ``recall_rivals_s`` 0). With the
    ambiguity recalled, that call refines the true pose again, finds the view still
    ambiguous, and nothing wrong is published in the 2 s."""
    assert max(_published_one_camera("box", 3406, 30, recall_rivals_s=0.0), default=0.0) >= 0.1
    errs = _published_one_camera("box", 3406, 52)
    assert max(errs, default=0.0) < 0.1, errs


def test_a_start_whose_edge_fits_allow_an_offset_waits_for_its_depth():
    """One camera, box (rig seed 1618): one side face seen edge on, a pose 15.7% of the
    diameter off explains more image edge than the true one at frame 25, and the edge fits
    that follow it claim a 1.2-1.6 mm position std while 10-16 mm off along the line of
    sight. With the start's edge fits claiming that (``start_edge_offset_px`` 0, an
    earlier default) the track was published from frame 30 at 9.4% and reached 10.5% at frame 35
    (the premise: a wrong lock of the benches; ``recall_margin_factor`` 1 as then: a pose
    recalled from an earlier ambiguity now rivals the wrong one by its edge length
    and refuses it too). With each edge allowed 0.6 px as a whole
    until the track is confirmed (the default), the start is never
    confirmed: its fits no longer hold it, it wanders 1-25% off on 3-6 corners, the fits'
    vetoes drop it at frame 33, and nothing is published (measured: nothing in 52 frames,
    a miss instead of a wrong lock). The shading rules the wrong pose out
    as a rival (``shade_rival_ratio``, off for the premise) and the true pose is published
    from frame 6, at most 6.1% off."""
    assert max(_published_one_camera("box", 1618, 40, tracker={"start_edge_offset_px": 0.0}, recall_margin_factor=1.0,
                                     shade_rival_ratio=0.0), default=0.0) >= 0.1
    errs = _published_one_camera("box", 1618, 40)
    assert max(errs, default=0.0) < 0.1, errs


@pytest.mark.parametrize("obj,seed", [("box", 805), ("bracket", 1203)])
def test_an_accurate_start_on_few_corners_is_published_within_the_second(obj, seed):
    """One camera, the initialiser every 5th frame: accurate starts that find few of the
    corners they select. Box 805 shows one face's 4 corners (its edge fits find 78-88% of
    the outline, under the 90% that lets 4 confirm in two frames); bracket 1203 accepts
    3-4 of 7 (the rest on dark faces, unfound, none rejected). Without the slower
    confirmation (``confirm_slow_frames`` 0) neither is published within 26 frames (the
    premise: box 805 never, bracket 1203 from frame 39 after its first start was dropped
    unconfirmed); with it (the default: 4 frames with 4 or more corners and an agreeing
    edge fit) both are (measured: box 805 from frame 5, 0.4-2.9% of the diameter;
    bracket 1203 from frame 7, 0.7-2.1%)."""
    assert _published_one_camera(obj, seed, 26, tracker={"confirm_slow_frames": 0}) == []
    errs = _published_one_camera(obj, seed, 26)
    assert errs and max(errs) < 0.1, errs


def test_a_confirming_call_looks_deeper_than_a_proposing_one():
    """One camera, L-block 4801 (a set not used for tuning), the initialiser every 5th
    frame: a pose 75% of the diameter off explains the L's lower step alone (439 px of
    image edges). Taken provisionally at frame 0, it was confirmed by the call at frame
    5 and published from frame 6 while the confirming call refined only the first 9
    distinct candidates (``n_refine_confirm`` 0, the premise): the true pose (669 px)
    lay further down the ranking. Refining the first 40 there puts the true pose first
    (measured: 0.5% off at frame 5, published from frame 6 at 0.6-1.6%)."""
    assert max(_published_one_camera("lblock", 4801, 8, n_refine_confirm=0)) >= 0.1
    errs = _published_one_camera("lblock", 4801, 12)
    assert errs and max(errs) < 0.1, errs


def test_what_only_the_deeper_confirming_search_finds_must_pass_strictly():
    """One camera, box 5214 (a set not used for tuning), the initialiser every 5th frame:
    a provisional start at frame 20 that the filter takes to 2-8% of the diameter. The
    call confirming it at frame 25 refines 40 distinct candidates; one of those past the
    first nine, 1.9 diameters off, explains more edge length than the pending pose but
    passes only provisionally. Counted as any candidate (``confirm_deeper_strict`` False,
    the premise) it replaces the pending pose, the next call confirms it, and it is
    published from frame 30; counted only on a strict pass, the pending pose is confirmed
    (measured: published from frame 29 at 0.8-3.8%)."""
    assert max(_published_one_camera("box", 5214, 32, confirm_deeper_strict=False), default=0.0) >= 0.1
    errs = _published_one_camera("box", 5214, 34)
    assert errs and max(errs) < 0.1, errs


def test_a_provisional_pose_upheld_by_the_next_call_is_confirmed():
    """One camera, bracket 1611, the initialiser every 5th frame: a provisional start at
    frame 5 within 1% of the diameter, which the filter tracks. The call at frame 10 finds
    it again first among its candidates (the most edge length, no rival) but on that frame
    it agrees with 0.62 of its edges, under the 0.7 of the checks, and nothing passes; later
    calls find the bracket's slot clutter first. Without upholding (``confirm_upheld``
    False, the premise) nothing is published in the first 20 frames (measured: not within
    52); upheld, the start is confirmed at frame 10 and published from there (measured:
    0.2-2.8%)."""
    assert not _published_one_camera("bracket", 1611, 20, confirm_upheld=False)
    errs = _published_one_camera("bracket", 1611, 16)
    assert len(errs) >= 5 and max(errs) < 0.1, errs


def test_a_pose_with_a_side_face_beside_its_outline_is_not_taken():
    """One camera, L-block 5008 (a set not used for tuning), the initialiser every 5th
    frame: the L face seen nearly head-on, a side face of its shade joining it in the image
    into one larger L, the dark strip of another side face along its long edge. A pose
    nearer and untilted matches that larger L (its six edges apart, no strip) and leaves
    the dark strip outside its outline, the strip's far edge running beside it. Without
    the rule (``max_outer_parallel_confirm`` negative, the premise) it is taken at frame 0
    and published from frame 5 at 11-13% of the diameter; with it nothing wrong is
    published (measured: nothing in 12 frames)."""
    assert max(_published_one_camera("lblock", 5008, 8, max_outer_parallel_confirm=-1), default=0.0) >= 0.1
    errs = _published_one_camera("lblock", 5008, 12)
    assert max(errs, default=0.0) < 0.1, errs


def test_a_face_seen_head_on_whose_strips_show_no_width_is_not_confirmed():
    """One camera, box (rig seed 4610): a grey box on the dark belt, its top and side faces
    of one shade, so the image shows a plain quadrilateral. Another face of the box, head-on
    and 0.24 m nearer with its side faces seen edge on, explains it better than the true
    pose (whose crease is not seen). A strip's end edge lying on the rail's edge behind
    made its fifth distinct edge: without the strip rule the initialiser returns it
    provisionally at frame 50 (the premise: 1.7 diameters off); with it
    (``min_strips_apart_confirm`` 1, the default) nothing wrong is published in 60 frames
    (measured: nothing published)."""
    rig, model, frames = trial_frames("box", 4610, 51)
    syms = model_symmetries(model.vertices)
    res = make_initializer(rig, model, min_strips_apart_confirm=0)(frames[50][0])
    assert res is not None and res.provisional
    assert _sym_add_frac(res.T_world_object, frames[50][1], model, syms) > 1.0
    assert make_initializer(rig, model)(frames[50][0]) is None
    errs = _published_one_camera("box", 4610, 60)
    assert max(errs, default=0.0) < 0.1, errs


@pytest.mark.parametrize("obj,seed,n_frames", [("bracket", 6005, 10), ("box", 6208, 14), ("lblock", 7214, 16)])
def test_a_start_is_first_confirmed_after_frames_that_did_not_jump(obj, seed, n_frames):
    """One camera, seeds not used for tuning, the initialiser every 5th frame:
    accurate starts (bracket 6005 2.3% of the diameter off, box 6208 4%, L-block 7214 1.9%)
    whose next update took a wrong set of corners and jumped: the bracket to 11.1% on frame
    1, the box 6% to 10.7% on frame 5, the L-block 6.7% to 8.2% on frame 1, its velocity
    then carrying it to 14.2% on frame 2. Those frames confirmed the filter and were
    published (the premise, the step gates off, and the fit gap gate that came later,
    ``confirm_max_fit_gap``, which holds back the box and the L-block on its own). With the
    gates (a frame that moved the pose over 5% of the diameter from its prediction breaks
    the run of strong frames; a confirmed frame moving over 10% counts as bad) nothing over
    10% is published and the tracks are, a few frames later (measured: from
    frames 4, 8 and 5, at 0.9%, 6.6% and 9.3%, then 0.1-6%; with the gap gate too,
    from frames 4, 11 and 12, at 0.9%, 3.4% and 1.3%, then 0.1-6.8%)."""
    off = {"confirm_max_step_frac": math.inf, "max_step_frac": math.inf, "confirm_max_fit_gap": math.inf}
    assert max(_published_one_camera(obj, seed, n_frames, tracker=off), default=0.0) >= 0.1
    errs = _published_one_camera(obj, seed, n_frames)
    assert len(errs) >= 3 and max(errs) < 0.1, errs


@pytest.mark.parametrize("obj,seed", [("box", 7019), ("lblock", 7018)])
def test_a_pose_found_rivalled_stays_a_rival_within_wider_margins(obj, seed):
    """One camera, seeds not used for tuning, the initialiser every 5th frame. Box 7019: a
    pose 1.6 diameters off, the box's outline read inside out, explains 378 px of image edges
    where the true pose explains 302 and agrees with fewer of its edges (0.98 against 0.99).
    Calls at frames 15 and 20 found the two alike and returned nothing; the call at frame 25,
    the true pose at 0.799 of the wrong one's edge length (a rival needs 0.8), took the wrong
    one and it was published. L-block 7018: calls at frames 0-15 found the true pose and
    poses 23-27% off alike; the call at frame 20 proposed one 20.6% off (443 px; the true
    pose 344, 0.78 of it) and the next confirmed it, published from frame 25. Both the
    premise, ``recall_margin_factor`` 1: a recalled pose no wider a rival than a new one. A
    recalled pose rivals within twice either margin, here the edge length's (0.6): nothing
    is published in the first 30 frames."""
    assert max(_published_one_camera(obj, seed, 30, recall_margin_factor=1.0), default=0.0) >= 0.1
    assert _published_one_camera(obj, seed, 30) == []


def test_the_filters_pose_rivals_as_it_is_where_its_refinement_scores_lower():
    """One camera, bracket (rig seed 7809), frame 25: the bracket seen nearly edge-on beside
    the belt's rail. Refined on the oriented edge distances, even the true pose slides 22.6%
    of the diameter off to a pose the verification scores lower on both counts (0.62 of its
    edges over 506 px against 0.70 over 555 px). As the filter's pose, a rival, it is kept
    as it is (``keep_better_start``; off, the refinement stands)."""
    from vespro.init.initializer import _checked, _own_pose, _refined, _views

    rig, model, frames = trial_frames("bracket", 7809, 26)
    syms = model_symmetries(model.vertices)
    fs, T_true = frames[25]
    off, on = (make_initializer(rig, model, keep_better_start=k).setup for k in (False, True))
    views = _views(on, fs)
    T_ref = _refined(T_true, views, on)
    refined = (T_ref, _checked(T_ref, views, on))
    assert _sym_add_frac(refined[0], T_true, model, syms) >= 0.1
    assert _own_pose(T_true, refined, views, off) is refined
    T_own, c_own = _own_pose(T_true, refined, views, on)
    assert np.allclose(T_own, T_true)
    assert c_own.inlier_frac > refined[1].inlier_frac and c_own.inlier_px > refined[1].inlier_px


def test_the_filters_own_pose_rivals_the_searchs_best():
    """One camera, bracket (rig seed 7809), the initialiser every 5th frame: a provisional
    start 32% of the diameter off slid on the filter's own updates to within 1% by frame 14;
    the calls at frames 15-25 found poses 27-33% off first and put them in its place, and the
    call at frame 30 confirmed one, published at 13.9%, then 8.5-9% (the premise, either
    ``keep_better_start`` or ``held_rival`` off). With both, the filter's pose as it is makes
    those calls ambiguous; the filter keeps its pose and is published from frame 30 (measured:
    at 1.9%, then at most 5.8% to frame 51)."""
    for off in ({"keep_better_start": False}, {"held_rival": False}):
        assert max(_published_one_camera("bracket", 7809, 32, tracker=NO_GAP, **off), default=0.0) >= 0.1, off
    errs = _published_one_camera("bracket", 7809, 36)
    assert len(errs) >= 3 and max(errs) < 0.1, errs


def test_the_filters_own_pose_is_never_returned_as_it_is():
    """One camera, box (rig seed 6809), the initialiser every 5th frame: a provisional start
    5.6% of the diameter off tracked to 0.6%, then the filter jumped 11% in one frame to 15%
    off. Returned as it was where it scored above its refinement, that pose was confirmed by
    the call at frame 20 and published at 18.7%. As a rival only, nothing over 10% is
    published (measured: from frame 40, at 5.1%)."""
    assert max(_published_one_camera("box", 6809, 52), default=0.0) < 0.1


def test_a_call_finding_the_pending_pose_again_returns_its_own_refinement():
    """One camera, L-block (rig seed 6601), the initialiser every 5th frame: the filter of a
    provisional start tracked to 0.8% by frame 9. The call at frame 10 found its pose again
    but returned its best, a neighbour 9.7% off and 10.1% from the filter: the tracker took
    that for another pose, started again from it, and the track was published at 5-10%, one
    frame at 10.2% (the premise, ``confirm_own_refinement`` off). Returning the pending
    pose's own refinement (3.9% off, passing) confirms the filter as it is (measured:
    published from frame 11 at 2.3%, at most 4.7% to frame 51). Box 8200, whose filter was
    14.8% off and whose refinement (3.1%) was the best, is still started again from it
    (published from frame 10, at most 3.2%)."""
    assert max(_published_one_camera("lblock", 6601, 30, tracker=NO_GAP, confirm_own_refinement=False),
               default=0.0) >= 0.1
    errs = _published_one_camera("lblock", 6601, 30)
    assert len(errs) >= 10 and max(errs) < 0.06, errs
    errs = _published_one_camera("box", 8200, 16)
    assert len(errs) >= 3 and max(errs) < 0.06, errs


def test_a_rival_whose_faces_straddle_the_image_shades_leaves_a_box_unambiguous():
    """One camera, box (rig seed 417), the initialiser every 5th frame: every call found the
    true pose and a rival agreeing with about as many edges (0.88 vs 0.95, 0.79 vs 0.79), and
    nothing was published in 52 frames (the premise, ``shade_rival_ratio`` 0). The rivals'
    faces straddle the boundaries between the box's shades, where the true pose's faces each
    hold one (``InitOptions.shade_rival_*``; measured: published from frame 1 at 2.9%, at
    most 3.7% to frame 51)."""
    assert _published_one_camera("box", 417, 30, shade_rival_ratio=0.0) == []
    errs = _published_one_camera("box", 417, 30)
    assert len(errs) >= 20 and max(errs) < 0.06, errs


def test_a_pose_with_a_face_over_two_shades_is_not_published():
    """One camera, L-block (rig seed 6014), the initialiser every 5th frame: the part turned
    over about its long axis (67% of the diameter off) explains the outline as well as the
    true pose and more of the image edges (0.84 against 0.69); it was taken at frame 30 and
    published from frame 32 (the premise, ``plain_max_shade_step`` 0). Its back face lies
    over two of the part's faces 2.9 grey levels apart, too faint for an edge (ratio 0.06):
    refused, nothing wrong is published (measured: nothing in 52 frames)."""
    assert max(_published_one_camera("lblock", 6014, 36, tracker=NO_GAP, plain_max_shade_step=0.0),
               default=0.0) >= 0.1
    assert max(_published_one_camera("lblock", 6014, 36), default=0.0) < 0.1


def test_a_start_whose_corners_and_edges_tell_two_poses_is_not_published():
    """One camera, box (rig seed 5006): dark side faces on the dark belt, 4-5 corners
    found, each biased 1-2 px towards its lit neighbour frame after frame. A start 3.4%
    off (frame 30) was pulled by them to 10.8% while the edge fits stayed 1-4% from the
    true pose, and was confirmed and published from frame 34 at 10.8-11.4% (the premise,
    ``confirm_max_fit_gap`` off). With the gap gate the frames whose fit lies over 6%
    of the diameter from the filter do not confirm it: nothing wrong is published
    (measured: nothing in 52 frames)."""
    assert max(_published_one_camera("box", 5006, 38, tracker=NO_GAP), default=0.0) >= 0.1
    assert max(_published_one_camera("box", 5006, 38), default=0.0) < 0.1


def test_the_cameras_searched_side_by_side_give_the_same_answer_and_survive_a_fork(monkeypatch):
    """Each camera's features and hypotheses run on threads of their own: the answer is the
    one-camera-at-a-time answer to the bit, and a process forked after a search (the
    server's start worker) searches with threads of its own (its parent's are not there:
    without a fresh pool it waited for them for ever)."""
    import multiprocessing as mp

    from vespro.init import initializer as init_mod

    setup, model, syms, fs, T_true = _trial_frame("box", "3", 4, 0)
    ini = init_mod.Initializer(setup)
    side = ini(fs)
    assert side is not None and _sym_add_frac(side.T_world_object, T_true, model, syms) < 0.1
    assert init_mod._POOL is not None or init_mod._cores() < 2  # (the cameras were searched side by side)
    monkeypatch.setattr(init_mod, "_cores", lambda: 1)
    one = ini(fs)
    assert np.array_equal(one.T_world_object, side.T_world_object)
    monkeypatch.undo()

    def child(q):
        res = ini(fs)
        q.put(None if res is None else res.T_world_object)

    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=child, args=(q,))
    p.start()
    try:
        got = q.get(timeout=60)
    finally:
        p.join(5)
        if p.is_alive():
            p.kill()
    assert np.array_equal(got, side.T_world_object)
