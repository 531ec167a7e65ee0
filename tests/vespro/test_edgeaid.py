"""Edge-aided pose measurements (vespro.edgeaid) and the one-camera tracker that uses them.

Simulator frames; ground truth for scoring only.
"""

import numpy as np
import pytest
from scipy.stats import chi2
from strided import Strided
from trial_frames import trial_frames as _trial_frames

from vespro.edgeaid import EdgeAid
from vespro.ekf import nees
from vespro.metrics import add
from vespro.model import load_model
from vespro.se3 import exp_so3, transform_from_rt
from vespro.sim.cell import SimCell
from vespro.sim.trials import model_symmetries, random_rig, trial_config
from vespro.startpose import InitResult
from vespro.tracker import Tracker, TrackerConfig


def _published_errors(tr, frames, model, syms):
    """Run a tracker over (frame set, true pose) pairs: ADD / diameter of every published frame."""
    errs = []
    for fs, T_true in frames:
        out = tr.process(fs)
        if out.status == "tracking":
            errs.append(min(add(out.T_world_object, T_true @ S, model.vertices) for S in syms) / model.diameter)
    return errs


@pytest.mark.parametrize("obj,seed", [("box", 6), ("lblock", 12)])
def test_edges_fit_the_pose_a_lone_camera_sees_loosely(obj, seed):
    """From the true pose, or moved 2.5% of the diameter along the line of sight and
    tilted 2 deg, the edge fit (two Gauss-Newton rounds) lands on the same pose (within
    0.5% of the diameter; measured 0.3%),
    within 3% of the truth (measured 2.2-2.3%: one view's edges fix the depth to a few
    mm), with a covariance its error agrees with (NEES 5-8; under the 0.999 chi-square)."""
    rig, model, frames = _trial_frames(obj, seed, 1)
    fs, T_true = frames[0]
    cam = rig.cameras[0]
    T_wc = cam.T_world_camera
    ray = T_true[:3, 3] - T_wc[:3, 3]
    ray /= np.linalg.norm(ray)
    syms = model_symmetries(model.vertices)
    aid = EdgeAid(rig, model)
    fits, starts = [], []
    for tilt_deg, along in [(0.0, 0.0), (0.0, 0.025), (2.0, 0.0), (2.0, 0.025)]:
        T0 = transform_from_rt(exp_so3([0.0, np.deg2rad(tilt_deg), 0.0]) @ T_true[:3, :3],
                               T_true[:3, 3] + along * model.diameter * ray)
        m = aid.measure(cam.name, fs.images[cam.name], T_wc, T0)
        assert m is not None
        starts.append(T0)
        Ts = min((T_true @ S for S in syms), key=lambda X: add(m.T_world_object, X, model.vertices))
        assert add(m.T_world_object, Ts, model.vertices) < 0.03 * model.diameter
        assert nees(m.T_world_object, Ts, m.cov6) < chi2.ppf(0.999, 6)
        fits.append(m.T_world_object)
    for T in fits[1:]:
        assert add(T, fits[0], model.vertices) < 0.005 * model.diameter
    # The aid reuses its gradient block from call to call (crops of other sizes): each fit is
    # the one a fresh aid makes, to the bit.
    for T0, T in zip(starts[::-1], fits[::-1]):
        assert np.array_equal(EdgeAid(rig, model).measure(cam.name, fs.images[cam.name], T_wc, T0).T_world_object, T)
    # Nothing to fit in a blank image, nor from a pose behind the camera or not finite.
    assert aid.measure(cam.name, np.zeros_like(fs.images[cam.name]), T_wc, fits[0]) is None
    behind = fits[0].copy()
    behind[:3, 3] = T_wc[:3, 3] - 0.5 * ray
    assert aid.measure(cam.name, fs.images[cam.name], T_wc, behind) is None
    assert aid.measure(cam.name, fs.images[cam.name], T_wc, np.full((4, 4), np.nan)) is None


def test_one_camera_track_held_by_the_edges():
    """Bracket, rig seed 3, one camera, started from the initialiser's pose (3% of the
    diameter off): on corners alone the track slid to 11-20% in its first frames and was
    published there (every corner within 3 px); with the edge fits every published frame is
    within 10% (measured 0.3-4.5%)."""
    from vespro.init import make_initializer

    rig, model, frames = _trial_frames("bracket", 3, 12)
    ini = make_initializer(rig, model)
    res = ini(frames[0][0])
    assert res is not None
    syms = model_symmetries(model.vertices)

    def run(mode):
        tr = Tracker(rig, model, TrackerConfig(edge_aid=mode))
        tr.start(res, frames[0][0].t_ns)
        return tr, _published_errors(tr, frames, model, syms)

    tr, errs = run("single")
    assert tr.edge_updates >= len(frames) - 1 and len(errs) >= len(frames) - 2
    assert max(errs) < 0.1, errs
    _, errs_off = run("off")
    assert max(errs_off) > 0.1, errs_off  # the premise: corners alone let it slide


def test_four_corners_and_the_whole_outline_confirm_a_lone_camera():
    """Box, rig seed 18, one camera: the top face's 4 corners are all it can select (the
    side face is dark on the dark belt). From a start 2.7% of the diameter off, the edge
    fits find 92-96% of the visible edge samples, so the track is published from the
    second frame on and stays within 10% of the diameter (measured 0.4-5.4%); asking for
    more than the whole outline (``confirm_outline_min_found`` above 1) and no slower
    confirmation (``confirm_slow_frames`` 0) leaves it unpublished: 4 corners alone never
    confirm. With the slower confirmation alone it is published two frames later."""
    rig, model, frames = _trial_frames("box", 18, 14)
    syms = model_symmetries(model.vertices)
    rng = np.random.default_rng(0)
    fs0, T0_true = frames[0]
    # A start 2-3% of the diameter off, as the initialiser's on this trial (2.8%).
    T0 = transform_from_rt(exp_so3(rng.normal(0, 0.01, 3)) @ T0_true[:3, :3], T0_true[:3, 3] + [0.002, -0.002, 0.003])

    def run(cfg):
        tr = Tracker(rig, model, cfg)
        tr.start(InitResult(T0), fs0.t_ns)
        out = [(tr.process(fs), T) for fs, T in frames]
        errs = [min(add(o.T_world_object, T @ S, model.vertices) for S in syms) / model.diameter
                for o, T in out if o.status == "tracking"]
        return tr, [o.n_accepted for o, _ in out], errs

    tr, n_acc, errs = run(TrackerConfig())
    assert max(n_acc) == 4  # the premise: never more than four corners
    assert len(errs) >= len(frames) - 4 and max(errs) < 0.1, errs
    _, _, errs_off = run(TrackerConfig(confirm_outline_min_found=1.01, confirm_slow_frames=0))
    assert errs_off == []
    # The slower confirmation (four such frames) publishes it two frames later.
    _, _, errs_slow = run(TrackerConfig(confirm_outline_min_found=1.01))
    assert len(errs_slow) == len(errs) - 2 and max(errs_slow) < 0.1, errs_slow


def test_edges_veto_a_start_that_slid_on_wrong_corners():
    """Bracket, rig seed 210, one camera, initialiser on every 5th frame: the frame-0 pose is
    1.8% of the diameter off; on the next frame six wrong corners 3-7 px off (the part's
    many similar corners) move it 26 mm along the line of sight and it slides to 38%,
    where 6-7 corners keep agreeing. Without the edge veto that pose is confirmed and
    published (the premise, checked here); with it the edge fits (35-40% of the outline
    found, against 71% by the first fit) keep it unconfirmed, it is dropped after 5 vetoed frames and a fresh start is
    published within the second (measured: from frame 17 at 3%). Run with the edge fits as
    when this was found: taken at their residuals' word (``found_power`` 0), every sample
    weighing alike, no edge dropped, the highest gradient peak taken and no contrast memory
    (``spacing_px``, ``edge_outlier_px``, ``near_peak_frac`` 0, ``contrast_ratio`` None). With their
    covariance raised for the outline they miss, or with the edges weighed by their image
    and those left off dropped, this start no longer slides (measured: at most 3.3% without
    the veto); nor with the corners its first fit saw dim passed over (``dim_corner_frac``;
    the premise is run without, as when this was found: measured at most 4.3% without the
    veto). The veto stays as the guard behind those. Both runs take the start's edge fits at
    their word (``start_edge_offset_px`` 0): allowing each edge 0.6 px as a whole, the start
    does not slide either (measured: 3.4% with neither the veto nor the dim rule)."""
    from vespro.init import make_initializer

    rig, model, frames = _trial_frames("bracket", 210, 26)
    ini = make_initializer(rig, model)
    syms = model_symmetries(model.vertices)
    starts = {}

    def hook(fs):
        if fs.index % 5:
            return None
        if fs.index not in starts:
            starts[fs.index] = ini(fs)
        return starts[fs.index]

    def run(cfg):
        tr = Tracker(rig, model, cfg, initializer=hook)
        tr.edge_aid.found_power = 0.0  # the fits at their residuals' word, as when this was found
        tr.edge_aid.spacing_px = tr.edge_aid.edge_outlier_px = 0.0
        tr.edge_aid.near_peak_frac = 0.0  # the highest gradient peak
        tr.edge_aid.contrast_ratio = None  # no edge contrast memory
        return tr, _published_errors(tr, frames, model, syms)

    tr, errs = run(TrackerConfig(start_edge_offset_px=0.0))
    assert tr.unconfirmed_drops >= 1
    assert errs and max(errs) < 0.1, errs
    _, errs_off = run(TrackerConfig(confirm_edge_veto=False, dim_corner_frac=0.0, start_edge_offset_px=0.0))
    assert errs_off and max(errs_off) > 0.1, errs_off


def test_edge_vetoes_count_since_the_start_not_in_a_row():
    """Bracket, rig seed 210, one camera, default edge fits, the initialiser on every 5th
    frame: the frame-0 start is 1.6% of the diameter off (0.72 of the outline found) and
    slides along the line of sight on wrong corners. Its fits find 0.41-0.54 of the outline;
    two of them just over 0.7 of the start's broke a run of vetoes, and counted in a row the
    slid start was confirmed 40% off. Counted since the start, the fifth veto (frame 6) drops
    it; the start of frame 10 is published from frame 15, all within 10% (measured 4.3%).
    Run with the start's edge fits at their word (``start_edge_offset_px`` 0), as when this
    was found."""
    from vespro.init import make_initializer

    rig, model, frames = _trial_frames("bracket", 210, 26)
    syms = model_symmetries(model.vertices)

    def run(cfg):
        ini = make_initializer(rig, model)
        tr = Tracker(rig, model, cfg, initializer=lambda fs: None if fs.index % 5 else ini(fs))
        return tr, _published_errors(tr, frames, model, syms)

    tr, errs = run(TrackerConfig(start_edge_offset_px=0.0))
    assert tr.unconfirmed_drops >= 1
    assert len(errs) >= 8 and max(errs) < 0.1, errs
    # With the start's edge fits allowing each edge 0.6 px as a whole (not the default), the
    # frame-0 start does not slide: published from frame 4, within 10% (measured 6.4%).
    tr, errs = run(TrackerConfig(start_edge_offset_px=0.6))
    assert tr.unconfirmed_drops == 0
    assert len(errs) >= 16 and max(errs) < 0.1, errs


def test_fits_that_find_half_the_outline_count_for_less():
    """L-block, rig seed 610, one camera, started at frame 30 from the true pose: its dark
    face leaves 48-61% of the outline to find (40-52% weighted by image length). Taken at
    their residuals' word, those fits (3 mm position std each) pulled the published track
    29 mm along the line of sight, up to 17.6% of the diameter (the premise, ``found_power``
    0, checked here); divided by the squared found fraction they leave it within 10%
    (measured 6.0%). With so little of the outline found the edges do not help confirm the
    start: it waits for 6 corners and is published from frame 40, on 14 of the 18 frames
    from there (3 corners on frames 44 and 54-56). The premise is run without the edge
    contrast memory (``contrast_ratio`` None), as when this was found: with it, the fits taken
    at their word also stay within 10% (measured 5.4%), the edges that found a neighbour's
    image edge no longer finding one of another sign and strength."""
    rig, model, frames = _trial_frames("lblock", 610, 58)
    syms = model_symmetries(model.vertices)

    def run(found_power, contrast_ratio=None):
        tr = Tracker(rig, model, TrackerConfig())
        tr.edge_aid.found_power = found_power
        tr.edge_aid.contrast_ratio = contrast_ratio
        tr.start(InitResult(frames[30][1]), frames[30][0].t_ns)
        return _published_errors(tr, frames[30:], model, syms)

    errs = run(EdgeAid(rig, model).found_power)
    assert len(errs) >= 12 and max(errs) < 0.1, errs
    errs_off = run(0.0)
    assert max(errs_off) > 0.1, errs_off
    errs_memory = run(0.0, EdgeAid(rig, model).contrast_ratio)
    assert len(errs_memory) >= 12 and max(errs_memory) < 0.1, errs_memory


def test_edge_contrast_is_expected_after_two_frames_with_the_same_faces_seen():
    """Three samples on two edges: a sample is expected once two accepted frames saw it with its
    edge's faces seen alike; the running mean moves by ``rate`` of each new frame; a sample
    not seen keeps what it had; a change of the faces seen starts its edge's samples again."""
    from vespro.edgeaid import EdgeContrast

    mem = EdgeContrast(np.array([0, 0, 1]), rate=0.5, min_frames=2)
    side = np.array([3, 1])
    mem.learn(np.array([100.0, -40.0, np.nan]), side)
    assert np.all(np.isnan(mem.expect(side)))
    mem.learn(np.array([80.0, -60.0, 20.0]), side)
    np.testing.assert_allclose(mem.expect(side), [90.0, -50.0, np.nan])
    mem.learn(np.array([np.nan, np.nan, 30.0]), side)
    np.testing.assert_allclose(mem.expect(side), [90.0, -50.0, 25.0])
    moved = np.array([1, 1])  # edge 0 has lost one of its faces
    np.testing.assert_allclose(mem.expect(moved), [np.nan, np.nan, 25.0])
    mem.learn(np.array([-70.0, -70.0, 30.0]), moved)
    assert np.all(np.isnan(mem.expect(moved)[:2])) and np.all(mem.frames[:2] == 1)


def test_the_edge_contrast_memory_keeps_a_one_camera_box_off_a_dark_seam():
    """Box, rig seed 1618, one camera, started at frame 15 from the true pose: its top edge meets
    a brighter plate behind it (grey 127 against 134) with a dark seam a pixel wide between,
    a weak falling and a strong rising edge 2.5 px apart. Without the contrast memory
    (``contrast_ratio`` None) the search's nearest comparable peak flips between them and the
    published track slides to 11.5% of the diameter at frames 34-35 (the premise, checked
    here); with it each sample keeps to the edge it saw and the track stays within 8%
    (measured 6.1%), as many frames published."""
    rig, model, frames = _trial_frames("box", 1618, 45)
    syms = model_symmetries(model.vertices)

    def run(contrast_ratio):
        tr = Tracker(rig, model, TrackerConfig())
        tr.edge_aid.contrast_ratio = contrast_ratio
        tr.start(InitResult(frames[15][1]), frames[15][0].t_ns)
        return tr, _published_errors(tr, frames[15:], model, syms)

    _, errs_off = run(None)
    assert max(errs_off) > 0.1, errs_off
    tr, errs = run(EdgeAid(rig, model).contrast_ratio)
    assert len(errs) >= len(errs_off) - 1 and max(errs) < 0.08, errs
    memory = tr._contrast[rig.cameras[0].name]
    assert np.count_nonzero(memory.frames >= memory.min_frames) > 100  # the samples seen were learnt


def test_three_corners_and_the_outline_keep_a_one_camera_track():
    """Box, rig seed 41, one camera, started from the true pose (with a start covariance of
    1 mm and 1 mrad, as tight as the initialiser's edge fit gives): four corners are selectable
    and from frame 4 one of them is lost against the belt, leaving 3 accepted, while the edge
    fits find 84-91% of the outline. With ``min_accepted_with_edges`` 3 the track is published
    on every frame from the second (within 5% of the diameter; measured 4.8%); with 4 (the
    corners alone decide) every frame from 4 on is bad and the track is lost (the premise).
    (Started with the tracker's wide default covariance instead, its first frames move the
    pose 5-7% of the diameter, more than a first confirmation may, ``confirm_max_step_frac``.)"""
    rig, model, frames = _trial_frames("box", 41, 14)
    syms = model_symmetries(model.vertices)
    start = InitResult(frames[0][1], cov6=np.diag([1e-6] * 6))

    tr = Tracker(rig, model, TrackerConfig(min_accepted_with_edges=4))
    tr.start(start, frames[0][0].t_ns)
    statuses = [tr.process(fs).status for fs, _ in frames]
    assert statuses[3] == "tracking" and set(statuses[4:]) == {"lost"}, statuses
    for bad in (0, 5):
        with pytest.raises(ValueError, match="min_accepted_with_edges"):
            TrackerConfig(min_accepted_with_edges=bad)
    tr = Tracker(rig, model, TrackerConfig())
    tr.start(start, frames[0][0].t_ns)
    errs = _published_errors(tr, frames, model, syms)
    assert len(errs) == len(frames) - 1 and max(errs) < 0.05, errs


def test_undistorting_a_box_gives_the_crop_of_the_whole():
    """The edge fit remaps only a box around the part: the same pixels as remapping the
    whole image and cropping (and a camera without distortion passes the crop through)."""
    from vespro.camera import CameraIntrinsics
    from vespro.init.features import Undistorter

    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (480, 640), dtype=np.uint8)
    box = (100, 50, 260, 170)
    for dist in (np.array([-0.2, 0.05, 0.001, -0.001, 0.0]), np.zeros(5)):
        und = Undistorter(CameraIntrinsics(640, 480, K, dist))
        np.testing.assert_array_equal(und(img, box), und(img)[50:170, 100:260])




@pytest.mark.parametrize("obj,seed,first,n,off_min,on_max", [("box", 18, 0, 8, 0.0019, 0.0008),
                                                             ("lblock", 51, 34, 8, 0.0044, 0.0030),
                                                             ("lblock", 610, 48, 8, 0.0065, 0.0010)])
def test_edge_fits_weigh_edges_by_their_image_and_drop_edges_left_off(obj, seed, first, n, off_min, on_max):
    """Fitted from the true pose without image noise, one-camera views read the part off along
    the line of sight when every edge sample weighs alike and every edge counts:
    box (rig seed 18, two faces nearly edge on, the edges between them foreshortened to
    13-20 px with 47 samples each) 1.9-2.5 mm farther; L-block (seed 51, the step's top face a
    1 px strip) 4.5-5.8 mm farther; L-block (seed 610, a dark face on the dark belt: two
    silhouette edges found on a neighbouring image edge 2-2.6 px away, frames 48-55) 7-10 mm
    nearer. With each edge weighing at most one sample per 2 px of its image (``spacing_px``)
    and edges whose residuals the fit leaves over 1 px off on average dropped
    (``edge_outlier_px``), the defaults: 0.3-0.6, 2.1-2.8 and 0.0-0.7 mm. Both with the
    highest gradient peak taken, as then: with the nearest of comparable peaks
    (``near_peak_frac``, now the default) the first two stay within those bounds, the third
    0.1-7.5 mm nearer (see :class:`vespro.edgeaid.EdgeAid`)."""
    rig = random_rig(np.random.default_rng(10_000 + seed), 1)
    config, motion, mesh = trial_config(obj, rig, seed, noise_px=0.0)
    model = load_model(mesh)
    cam = rig.cameras[0]
    T_wc = cam.T_world_camera
    aids = {"alike": EdgeAid(rig, model, spacing_px=0.0, edge_outlier_px=0.0, near_peak_frac=0.0),
            "default": EdgeAid(rig, model, near_peak_frac=0.0)}
    assert aids["default"].spacing_px == 2.0 and aids["default"].edge_outlier_px == 1.0
    depth = {g: [] for g in aids}
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        for k in range(first + n):
            fs = cell.next_frameset()
            if k < first:
                continue
            T = cell.true_object_pose()
            ray = (T[:3, 3] - T_wc[:3, 3]) / np.linalg.norm(T[:3, 3] - T_wc[:3, 3])
            for g, aid in aids.items():
                m = aid.measure(cam.name, fs.images[cam.name], T_wc, T)
                assert m is not None
                depth[g].append((m.T_world_object[:3, 3] - T[:3, 3]) @ ray)
    assert min(np.abs(depth["alike"])) > off_min, depth["alike"]  # the premise
    assert max(np.abs(depth["default"])) < on_max, depth["default"]


@pytest.mark.parametrize("seed", [200, 53])
def test_a_face_seen_as_a_strip_leaves_the_outline_whole(seed):
    """A box lying flat seen from above by one camera (rig seeds 200, 53): its top face and
    the strips of side faces under 3 px wide, whose two long edges are one image edge.
    Fitted from the true pose on frames 0-5, the samples fitted are 62-82% of those searched
    (the strip's second edge loses its image edge to the nearer parallel one, and the 31-47
    samples of an edge foreshortened to 2-3 px count one each): the outline looked half
    missing and the track was never confirmed. Weighted by image length, with the samples
    that lost their edge to a strip's other side counted as found, 98-100% is found."""
    rig, model, frames = _trial_frames("box", seed, 6)
    cam = rig.cameras[0]
    aid = EdgeAid(rig, model)
    raw, found = [], []
    for fs, T in frames:
        m = aid.measure(cam.name, fs.images[cam.name], cam.T_world_camera, T)
        assert m is not None
        raw.append(m.fit.n_samples / m.fit.n_searched)
        found.append(m.fit.found_frac)
    assert max(raw) < 0.85, raw  # the premise: counted sample by sample, a third seems missing
    assert min(found) > 0.95, found


def _box_run(seed, n, rig_kind=1, hide=False, **opts):
    """Published errors of a box trial (the initialiser, options ``opts``, on every 5th frame)."""
    from vespro.init import make_initializer

    rig, model, frames = _trial_frames("box", seed, n, rig_kind, hide)
    ini = make_initializer(rig, model, **opts)
    tr = Tracker(rig, model, initializer=lambda fs: None if fs.index % 5 else ini(fs))
    return _published_errors(tr, frames, model, model_symmetries(model.vertices))


def test_a_box_seen_from_above_with_a_side_face_apart_is_published():
    """Box lying flat, one camera above it (rig seed 803): one open face and 5 edges, under
    the 7 a one-camera pose needs; a side face's strip stands apart from the top face in the
    image. Accepted as provisional (``min_supported_edges_confirm``), found again by the
    next call and confirmed by the tracker, it is published from frame 5 within 10% of the
    diameter (measured 2-3%); with 7 edges asked for, nothing is published in the second."""
    errs = _box_run(803, 26)
    assert len(errs) >= 18 and max(errs) < 0.1, errs
    assert _box_run(803, 26, min_supported_edges_confirm=7) == []


@pytest.mark.parametrize("seed", [200, 17])
def test_a_box_seen_head_on_by_one_camera_is_not_published(seed):
    """Box lying flat, one camera straight above it (rig seeds 200 and 17): one open face,
    the side faces' strips under a few px, so their far edges lie on the image edges of
    the top face's own and the tilt rests on nothing (``min_distinct_edges_confirm``).
    Nothing is published in the second; not asking for distinct edges nor for a strip's
    width (``min_strips_apart_confirm``, which refuses these views as well), these two
    tracks happen to stay within 10% of the diameter (3-7%), but see the next test."""
    assert _box_run(seed, 26) == []
    errs = _box_run(seed, 26, min_distinct_edges_confirm=0, min_strips_apart_confirm=0)
    assert len(errs) >= 18 and max(errs) < 0.1, errs


def test_a_box_seen_head_on_past_a_paddle_is_not_locked_wrong():
    """Two cameras (rig seed 4), a paddle hiding the first: the other sees the box's top
    face 9-12 deg from head-on, 110 px across. A pose 7.6% of the diameter off, its
    tilt wrong, explains 6 edges there, but only the top face's 4 stand apart: not asking
    for distinct edges (nor for a strip's width, ``min_strips_apart_confirm``, which alone
    refuses it as well), it was confirmed and published 12-22% off (a wrong lock); by
    default nothing wrong is published."""
    errs = _box_run(4, 20, rig_kind=2, hide=True, min_distinct_edges_confirm=0, min_strips_apart_confirm=0)
    assert errs and max(errs) >= 0.1, errs  # the premise
    errs = _box_run(4, 20, rig_kind=2, hide=True)
    assert all(e < 0.1 for e in errs), errs


@pytest.fixture(scope="module")
def box_1618_edge_on():
    """Rig seed 1618, one camera, box, frame 30, no image noise: along one silhouette
    edge a face seen edge on shows as a dark line a pixel wide (grey 126 / 97 / 134).
    (rig, model, frame set, true pose, unit line of sight to the part)."""
    from dataclasses import replace

    from vespro.sim.imaging import ImageEffects

    rig = random_rig(np.random.default_rng(10_000 + 1618), 1)
    config, motion, mesh = trial_config("box", rig, 1618)
    model = load_model(mesh)
    with SimCell(replace(config, effects=ImageEffects()), motion) as cell:
        cell.settle_arm()
        for _ in range(31):
            fs = cell.next_frameset()
        T_true = cell.true_object_pose()
    ray = T_true[:3, 3] - rig.cameras[0].T_world_camera[:3, 3]
    return rig, model, fs, T_true, ray / np.linalg.norm(ray)


def test_the_edge_search_takes_the_near_side_of_a_face_seen_edge_on(box_1618_edge_on):
    """Taking the highest gradient peak, the search finds that edge on the line's far
    side, 1.9 px out, and the fit from the true pose lands 18 mm (over 10% of the
    diameter) nearer along the line of sight, claiming about 4 mm; the nearest of the
    peaks at least 0.6 times the highest (``near_peak_frac``, the default) keeps it
    within 4%."""
    rig, model, fs, T_true, ray = box_1618_edge_on
    cam = rig.cameras[0]

    def along(**kw):
        m = EdgeAid(rig, model, **kw).measure(cam.name, fs.images[cam.name], cam.T_world_camera, T_true)
        return float((m.T_world_object[:3, 3] - T_true[:3, 3]) @ ray)

    assert abs(along(near_peak_frac=0.0)) > 0.08 * model.diameter
    assert abs(along()) < 0.04 * model.diameter


def test_an_edge_offset_the_depth_absorbs_lies_inside_the_offset_covariance(box_1618_edge_on):
    """The same view with the highest peak taken: the fit's residuals are small
    (0.2-0.4 px) and its covariance claims about 4 mm along the line of sight, over
    3.5 sigma from its error. Allowing each edge a common offset of 1 px
    (``edge_offset_px``) adds only to the covariance (the fit is the same) and takes
    the error within 2 sigma."""
    rig, model, fs, T_true, ray = box_1618_edge_on
    cam = rig.cameras[0]
    T_wc = cam.T_world_camera

    def fit(offset_px):
        aid = EdgeAid(rig, model, edge_offset_px=offset_px, near_peak_frac=0.0)
        m = aid.measure(cam.name, fs.images[cam.name], T_wc, T_true)
        return m, float(np.sqrt(ray @ m.cov6[:3, :3] @ ray))

    m0, sd0 = fit(0.0)
    m1, sd1 = fit(1.0)
    err = float((m0.T_world_object[:3, 3] - T_true[:3, 3]) @ ray)
    assert np.allclose(m0.T_world_object, m1.T_world_object)
    assert abs(err) > 0.08 * model.diameter and abs(err) > 3.5 * sd0, (err, sd0)
    assert abs(err) < 2.0 * sd1, (err, sd1)
    assert np.all(np.linalg.eigvalsh(m1.cov6 - m0.cov6) > -1e-12)
    # The offset given per call (the tracker's start_edge_offset_px) is the same thing.
    m2 = EdgeAid(rig, model, near_peak_frac=0.0).measure(cam.name, fs.images[cam.name], T_wc, T_true,
                                                         edge_offset_px=1.0)
    assert np.allclose(m2.cov6, m1.cov6)
    with pytest.raises(ValueError, match="edge_offset_px"):
        TrackerConfig(edge_offset_px=-1.0)
    with pytest.raises(ValueError, match="start_edge_offset_px"):
        TrackerConfig(start_edge_offset_px=float("nan"))


def test_a_corner_whose_edges_showed_no_contrast_is_dim():
    """Box, one camera: a corner is dim when fewer than two of its edges' samples next to it
    were seen with at least ``min_frac`` of the median contrast of the samples seen (a sample
    not learnt, or learnt with other faces of its edge seen, counts as seen); nothing learnt,
    nothing dim."""
    from vespro.edgeaid import EdgeContrast

    rig, model, frames = _trial_frames("box", 6, 1)
    aid = EdgeAid(rig, model)
    T_co = np.linalg.solve(rig.cameras[0].T_world_camera, frames[0][1])
    side = aid.edge_side(T_co)
    ids = np.arange(model.n_corners)
    mem = EdgeContrast(aid.mf.sample_edge)
    assert aid.corners_shown(mem, T_co, ids, 0.45).all()  # nothing learnt
    c = np.full(len(aid.mf.sample_p), 200.0)
    ends = aid.corner_ends
    assert ends.shape == (8, 3) and np.all(ends >= 0)  # a box: three edges at every corner
    c[ends[0]] = -30.0  # corner 0's three edges dim next to it
    c[ends[1, :2]] = 50.0  # corner 1: one edge bright
    c[ends[2, :2]] = [50.0, np.nan]  # corner 2: one bright, one not seen this frame
    mem.learn(c, side)
    shown = aid.corners_shown(mem, T_co, ids, 0.45)
    assert not shown[0] and not shown[1] and shown[2:].all()
    mem.frames[ends[2, 0]] = 0  # corner 2: now one dim edge not learnt either
    assert aid.corners_shown(mem, T_co, ids, 0.45)[2]
    mem.frames[ends[2, 0]] = 1
    mem.side[aid.mf.sample_edge == aid.mf.sample_edge[ends[1, 0]]] = -1  # learnt with other faces seen
    assert aid.corners_shown(mem, T_co, ids, 0.45)[1]
    assert aid.corners_shown(mem, T_co, ids, 0.2)[0] == False  # noqa: E712 (30 < 0.2 * 200 = 40)
    assert aid.corners_shown(mem, T_co, ids, 0.1)[0]


def test_edge_side_equals_the_numpy_formulation():
    """The compiled faces-seen code of each edge against front_faces (NumPy), at random poses
    about the camera's, and with the camera centre in a face's plane (its test on rounding)."""
    from test_init_kernels import bitwise

    from vespro.imageedges import front_faces
    from vespro.se3 import exp_so3, transform_from_rt

    if not bitwise():
        pytest.skip("this platform's BLAS accumulates otherwise than numerics.dot3")

    for name in ("box", "lblock"):
        rig, model, frames = _trial_frames(name, 6, 1)
        aid = EdgeAid(rig, model)
        ef = aid.mf.edge_faces
        T0 = np.linalg.solve(rig.cameras[0].T_world_camera, frames[0][1])
        rng = np.random.default_rng(8)
        sides = set()
        for k in range(300):
            T_co = T0 @ transform_from_rt(exp_so3(rng.normal(size=3) * 1.5), rng.normal(size=3) * 0.05)
            if k % 2 == 0:  # the camera centre on a face's plane (to rounding)
                n, d = aid.mf.face_normals[k % len(aid.mf.face_normals)], aid.mf.face_offsets[k % len(aid.mf.face_normals)]
                c = np.linalg.solve(T_co[:3, :3], -T_co[:3, 3])
                T_co[:3, 3] = -T_co[:3, :3] @ (c - (n @ c + d) * n)
            front = front_faces(T_co[None, :3, :3], T_co[None, :3, 3], aid.mf)[0]
            ref = front[ef[:, 0]].astype(np.int64) + 2 * front[ef[:, 1]].astype(np.int64)
            side = aid.edge_side(T_co)
            assert side.dtype == ref.dtype and np.array_equal(side, ref)
            sides.add(side.tobytes())
        assert len(sides) > 10


def test_edge_contrast_learns_and_expects_as_the_numpy_formulation():
    """The compiled memory against its NumPy code, frame after frame: NaN contrasts (not seen),
    faces seen changing, samples seen for the first time."""
    from vespro.edgeaid import EdgeContrast

    rng = np.random.default_rng(21)
    edge = rng.integers(0, 12, 300)
    mem = EdgeContrast(edge, rate=0.3, min_frames=2)
    ref = {"contrast": np.full(300, np.nan), "frames": np.zeros(300, np.int64), "side": np.full(300, -1, np.int64)}
    for frame in range(40):
        c = rng.normal(0.0, 100.0, 300)
        c[rng.random(300) < 0.3] = np.nan
        side = rng.integers(0, 4, 12) if frame % 7 == 0 else (side if frame else rng.integers(0, 4, 12))
        mem.learn(c, side)
        s = side[edge]  # the NumPy formulation
        seen = np.isfinite(c)
        fresh = seen & ((ref["side"] != s) | (ref["frames"] == 0))
        same = seen & ~fresh
        ref["contrast"][fresh] = c[fresh]
        ref["frames"][fresh] = 1
        ref["side"][fresh] = s[fresh]
        ref["contrast"][same] += 0.3 * (c[same] - ref["contrast"][same])
        ref["frames"][same] += 1
        assert np.array_equal(mem.contrast, ref["contrast"], equal_nan=True)
        assert np.array_equal(mem.frames, ref["frames"]) and np.array_equal(mem.side, ref["side"])
        known = (ref["frames"] >= 2) & (ref["side"] == side[edge])
        assert np.array_equal(mem.expect(side), np.where(known, ref["contrast"], np.nan), equal_nan=True)
    assert np.isfinite(mem.expect(side)).sum() > 100


def _corners_shown_numpy(aid, contrast, T_co, ids, min_frac):
    """``EdgeAid.corners_shown`` in NumPy, as it was before it was compiled."""
    side = aid.edge_side(T_co)
    known = (contrast.frames >= 1) & (contrast.side == side[contrast.edge]) & np.isfinite(contrast.contrast)
    if not known.any() or ids.size == 0:
        return np.ones(ids.size, bool)
    level = min_frac * float(np.median(np.abs(contrast.contrast[known])))
    s = aid.corner_ends[ids]
    valid = s >= 0
    sk = np.where(valid, s, 0)
    strong = valid & known[sk] & (np.abs(np.nan_to_num(contrast.contrast[sk])) >= level)
    unknown = valid & ~known[sk]
    return (strong | unknown).sum(axis=1) >= 2


def test_corners_shown_equals_the_numpy_formulation():
    """The compiled rule against the NumPy code on random memories (odd and even counts of known
    samples, NaN contrasts, samples learnt with other faces seen, levels at a sample's magnitude)."""
    from vespro.edgeaid import EdgeContrast

    rig, model, frames = _trial_frames("box", 6, 1)
    aid = EdgeAid(rig, model)
    T_co = np.linalg.solve(rig.cameras[0].T_world_camera, frames[0][1])
    side = aid.edge_side(T_co)
    rng = np.random.default_rng(3)
    ids = np.arange(model.n_corners)
    n = len(aid.mf.sample_p)
    dims = 0
    for trial in range(60):
        mem = EdgeContrast(aid.mf.sample_edge)
        c = rng.choice([-1.0, 1.0], n) * rng.uniform(0.0, 250.0, n)
        c[rng.random(n) < 0.1] = np.nan
        c[aid.corner_ends[rng.integers(0, 8, 3)]] *= 0.05
        mem.learn(c, side)
        mem.frames[rng.random(n) < 0.2] = 0
        mem.side[rng.random(n) < 0.1] = -1
        k = np.flatnonzero((mem.frames >= 1) & (mem.side == side[mem.edge]) & np.isfinite(mem.contrast))
        if (len(k) + trial) % 2:  # odd and even counts of known samples in turn
            mem.frames[k[-1]] = 0
        # Corner 0: two ends exactly at the level (strong: >=), one dim; below the median, so
        # that setting them leaves it as it is.
        e0 = aid.corner_ends[0]
        mem.frames[e0], mem.side[e0], mem.contrast[e0] = 1, side[mem.edge[e0]], 1e-3
        known = (mem.frames >= 1) & (mem.side == side[mem.edge]) & np.isfinite(mem.contrast)
        mem.contrast[e0[:2]] = 0.3 * np.median(np.abs(mem.contrast[known]))
        assert _corners_shown_numpy(aid, mem, T_co, ids[:1], 0.3)[0]
        for frac in (0.0, 0.3, 0.45, 0.9):
            sub = ids[rng.random(8) < 0.8]
            a = aid.corners_shown(mem, T_co, sub, frac)
            assert np.array_equal(a, _corners_shown_numpy(aid, mem, T_co, sub, frac))
            dims += int((~a).sum())
    assert dims > 20  # the rule did say no, often
    assert aid.corners_shown(EdgeContrast(aid.mf.sample_edge), T_co, ids, 0.45).all()


@pytest.mark.parametrize("seed", [2800, 3219])
def test_a_one_camera_bracket_does_not_slide_on_the_corners_of_its_dark_face(seed):
    """Bracket, one camera (fresh rig seeds 2800 and 3219), the initialiser on every 5th frame:
    found at frame 0 within 1% of the diameter. A side face shows dark on a dark background:
    its outer corners have no image corner, and their windows (5-6 px, the velocity still
    unknown) measured a hole's rim or a nearby corner of the part 2-4 px off. Taking them,
    the track slid 4 deg and was published 11.3% / 10.8% off (the premise, ``dim_corner_frac``
    0, checked here). By default the corners whose edges the first edge fit saw without
    contrast are not selected: published from frames 1-2, all within 5% (measured 2.1% / 2.7%)."""
    from vespro.init import make_initializer

    rig, model, frames = _trial_frames("bracket", seed, 26)
    syms = model_symmetries(model.vertices)

    def run(**cfg):
        tr = Tracker(rig, model, TrackerConfig(**cfg), initializer=Strided(make_initializer(rig, model)))
        return tr, _published_errors(tr, frames, model, syms)

    _, errs_off = run(dim_corner_frac=0.0, adaptive_motion=False)  # the premise, as measured
    assert errs_off and max(errs_off) > 0.1, errs_off
    tr, errs = run()
    assert len(errs) >= 23 and max(errs) < 0.05, errs
    assert tr.dim_skipped > 0
