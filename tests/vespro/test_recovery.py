"""Loss and recovery: every camera occluded for two seconds mid-sequence.

The tracker must report ``lost`` within a few frames of the occlusion and
re-acquire the part (automatic initialisation, seeded by the last good pose and
velocity) within one second after it is visible again, without ever
publishing a wrong pose as ``tracking``.
"""

import numpy as np
import pytest

from vespro.groundtruth import read_groundtruth
from vespro.init import make_initializer
from vespro.recording import Recording
from vespro.rig import load_rig
from vespro.sim.cell import CameraDropout, CellConfig
from vespro.sim.imaging import ImageEffects
from vespro.sim.motion import Conveyor
from vespro.sim.record import record
from vespro.sim.rigs import CAMERAS_DIR
from vespro.sim.scene import MODELS_DIR
from vespro.track import make_tracker, track_recording


def test_all_cameras_occluded_for_two_seconds_lost_then_reacquired(tmp_path):
    drops = (CameraDropout("cam_left", 1.0, 3.0), CameraDropout("cam_right", 1.0, 3.0))
    cfg = CellConfig(MODELS_DIR / "objects" / "lblock.stl", load_rig(CAMERAS_DIR / "fixed2.yaml"),
                     effects=ImageEffects(noise_px=0.5), dropouts=drops)
    path = record(tmp_path / "rec", cfg, Conveyor(speed=0.05, y0=-0.2), 110, "lblock")
    rec = Recording(path)
    _, _, T = read_groundtruth(path)
    tr = make_tracker(rec)
    tr.initializer = make_initializer(rec.rig, tr.model)
    outs = track_recording(rec, tr)  # no starting pose: initialised from the images
    t = rec.t
    lost = [t[o.index] for o in outs if o.status == "lost" and t[o.index] >= 1.0]
    back = [t[o.index] for o in outs if o.status == "tracking" and t[o.index] >= 3.0]
    # Measured: lost at 1.116 s (3 frames), re-acquired at 3.04 s (the first frame seen again).
    assert lost and lost[0] - 1.0 < 0.25  # "within a few frames"
    assert back and back[0] - 3.0 < 1.0
    assert all(o.status != "tracking" for o in outs if 1.2 <= t[o.index] < 3.0)
    errs = [np.linalg.norm(o.T_world_object[:3, 3] - T[o.index][:3, 3]) for o in outs if o.status == "tracking"]
    assert max(errs) < 0.1 * tr.model.diameter  # no wrong lock, before or after


@pytest.fixture(scope="module")
def paddle_dir(tmp_path_factory):
    """Where the paddle recordings are made, once for the module."""
    return tmp_path_factory.mktemp("paddle")


def _paddle_recording(directory, rig="fixed3", hide="cam_top"):
    """An L-block on the belt, a paddle hiding it from camera ``hide`` of a fixed rig
    throughout (40 frames, recorded once per directory, rig and camera): (recording,
    ground truth)."""
    from vespro.sim.cell import OccluderSweep

    cfg = CellConfig(MODELS_DIR / "objects" / "lblock.stl", load_rig(CAMERAS_DIR / f"{rig}.yaml"),
                     effects=ImageEffects(noise_px=0.5),
                     occluders=(OccluderSweep(hide, 0.0, duration=100.0, half_travel=0.0),))
    path = directory / f"rec-{rig}-{hide}"
    if not path.exists():
        record(path, cfg, Conveyor(speed=0.05, y0=-0.1), 40, "lblock")
    return Recording(path), read_groundtruth(path)[2]


def _hidden_run(directory, rig="fixed3", hide="cam_top", **init_options):
    """A paddle hiding the part from one camera of a fixed rig throughout; tracked from
    the images alone. Returns (outputs, recording times, ground truth, tracker)."""
    from vespro.tracker import TrackerConfig

    rec, T = _paddle_recording(directory, rig, hide)
    blind = {} if init_options.get("hidden_camera", True) else {"blind_found_fraction": 0.0}
    tr = make_tracker(rec, TrackerConfig(**blind))
    tr.initializer = make_initializer(rec.rig, tr.model, **init_options)
    return track_recording(rec, tr), rec.t, T, tr


def test_a_camera_hidden_by_an_unknown_body_neither_blocks_initialisation_nor_tracking(paddle_dir):
    """Something the model does not know (the arm, a paddle here) hides the part from one
    of three cameras: the two others find it (``InitOptions.hidden_camera``), confirm it and
    track it (``TrackerConfig.blind_found_fraction``); with both rules off it is never found."""
    outs, t, T, tr = _hidden_run(paddle_dir)
    tracking = [o for o in outs if o.status == "tracking"]
    assert tracking and t[tracking[0].index] < 0.5, [o.status for o in outs]
    assert len(tracking) >= len(outs) - 10  # then held to the end
    errs = [np.linalg.norm(o.T_world_object[:3, 3] - T[o.index][:3, 3]) for o in tracking]
    assert max(errs) < 0.05 * tr.model.diameter
    assert tr.blind_frames >= len(tracking) - 1
    outs, *_ = _hidden_run(paddle_dir, hidden_camera=False)
    assert all(o.status != "tracking" for o in outs)


def test_a_seeded_reinitialisation_leaves_out_a_camera_the_part_is_hidden_from(paddle_dir):
    """After a loss the initialiser first refines the last good pose (a seed). A camera
    the part is hidden from (the paddle before ``cam_top``) agrees with none of those
    refinements, so every seeded start failed on "a camera disagrees" and the call fell
    through to the full search. Judged without that camera, as the search's candidates
    are, the seed is taken at once (mode ``seed``) and the start names the camera."""
    from vespro.model import load_model
    from vespro.se3 import exp_so3

    rec, T = _paddle_recording(paddle_dir)
    model = load_model(MODELS_DIR / "objects" / "lblock.stl")
    k = 20
    seed = T[k].copy()
    seed[:3, :3] = exp_so3(np.array([0.02, -0.01, 0.015])) @ seed[:3, :3]
    seed[:3, 3] += [0.004, -0.003, 0.002]
    modes = {}
    for rule in (True, False):
        ini = make_initializer(rec.rig, model, hidden_camera=rule)
        ini.reseed(seed)
        res = ini(rec.frameset(k))
        modes[rule] = (ini.last_report.mode, None if res is None else res)
    mode, res = modes[True]
    assert mode == "seed" and res.hidden == ("cam_top",)
    assert np.linalg.norm(res.T_world_object[:3, 3] - T[k][:3, 3]) < 0.02 * model.diameter
    assert modes[False][0] != "seed"


def test_with_two_cameras_one_hidden_the_other_initialises_and_tracks_alone(paddle_dir):
    """Two fixed cameras, the right one behind a paddle throughout: the left one finds the
    part under the one-camera rules (``InitResult.hidden`` names the right camera, so the
    tracker confirms it by the left alone) and tracks it with its edges, to one-camera
    accuracy (measured: from frame 7, 33 of 40 frames, max 4.1 mm); never with the rules off."""
    outs, t, T, tr = _hidden_run(paddle_dir, rig="fixed2", hide="cam_right")
    tracking = [o for o in outs if o.status == "tracking"]
    assert tracking and t[tracking[0].index] < 1.0, [o.status for o in outs]
    assert len(tracking) >= len(outs) - 15
    errs = [np.linalg.norm(o.T_world_object[:3, 3] - T[o.index][:3, 3]) for o in tracking]
    assert max(errs) < 0.1 * tr.model.diameter
    outs, *_ = _hidden_run(paddle_dir, rig="fixed2", hide="cam_right", hidden_camera=False)
    assert all(o.status != "tracking" for o in outs)


def test_with_the_bank_a_camera_hidden_by_an_unknown_body_costs_a_pose_little(paddle_dir):
    """Decision "bank", two fixed cameras, the right one behind a paddle throughout: each
    camera's evidence is a mixture with a blocked view (``BankOptions.p_visible``), so the
    right camera, which finds none of the part's edges, costs the right pose at most
    ``log(1 - p_visible)`` a frame: published within the first second and tracked to the end
    (measured: from frame 6, every frame). Counting every camera and every edge as seeing
    (``p_visible`` and ``p_edge`` 1), the hidden camera refutes the right pose on every frame
    and it is never published (with the edge mixture alone, a hidden camera's edges cost
    ``log(1 - p_edge)`` each, which refutes it too little)."""
    from dataclasses import replace

    from vespro.tracker import TrackerConfig

    rec, T = _paddle_recording(paddle_dir, "fixed2", "cam_right")

    def run(every_view_seen=False):
        tr = make_tracker(rec, TrackerConfig(decision="bank"))
        if every_view_seen:
            tr.bank.options = replace(tr.bank.options, p_visible=1.0, p_edge=1.0)
        tr.initializer = make_initializer(rec.rig, tr.model, plain_faces=False)
        outs = track_recording(rec, tr)
        return [o for o in outs if o.status == "tracking"
                and np.linalg.norm(o.T_world_object[:3, 3] - T[o.index][:3, 3]) < 0.1 * tr.model.diameter], outs

    right, outs = run()
    assert right and rec.t[right[0].index] < 1.0, [o.status for o in outs]
    assert len(right) >= len(outs) - 15
    assert all(o in right for o in outs if o.status == "tracking")  # nothing else published
    right, _ = run(every_view_seen=True)
    assert right == []
