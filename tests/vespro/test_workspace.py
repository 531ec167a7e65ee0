"""The cell's working volume (vespro.workspace): its option and the start's search keeping to it."""

import numpy as np
import pytest
from trial_frames import trial_frames

from vespro.errors import InputError
from vespro.init import make_initializer
from vespro.metrics import add_sym
from vespro.se3 import exp_so3
from vespro.sim.trials import model_symmetries
from vespro.workspace import box_centre, centres_inside, parse_workspace


def test_a_working_volume_is_six_numbers_of_a_box():
    assert parse_workspace(None) is None
    assert parse_workspace("0.6,-0.3,0.5,1.2,0.3,0.8") == (0.6, -0.3, 0.5, 1.2, 0.3, 0.8)
    for bad in ("0,0,0,1,1", "0,0,1,1,1,0.5", "a,b,c,d,e,f", "0,0,0,1,1,inf"):
        with pytest.raises(InputError, match="--workspace: expected six numbers"):
            parse_workspace(bad)


def test_the_centre_not_the_origin_is_tested_for_every_pose():
    rng = np.random.default_rng(3)
    vertices = rng.uniform(-0.05, 0.05, (20, 3)) + [0.2, 0.0, 0.0]  # the centre 20 cm along x from the origin
    c = box_centre(vertices)
    R = np.stack([exp_so3(rng.normal(size=3)) for _ in range(200)])
    t = rng.uniform(-0.4, 0.4, (200, 3))
    w = (-0.1, -0.2, -0.3, 0.3, 0.2, 0.1)
    got = centres_inside(R, t, c, w)
    want = [all(w[i] <= (Rk @ c + tk)[i] <= w[i + 3] for i in range(3)) for Rk, tk in zip(R, t)]
    assert got.tolist() == want and 0 < got.sum() < 200
    assert centres_inside(R, t, c, None).all()


def test_the_search_keeps_to_the_working_volume():
    """Two cameras: with the working volume around the part the call answers the pose it
    answers without one; with the volume a metre beside the part, neither its answer nor any
    candidate puts the part's centre outside it."""
    rig, model, frames = trial_frames("box", 0, 1, 2)
    fs, T_true = frames[0]
    syms = model_symmetries(model.vertices)
    free = make_initializer(rig, model)(fs)
    assert free is not None and add_sym(free.T_world_object, T_true, model.vertices, syms) < 0.05 * model.diameter
    around = tuple(np.r_[T_true[:3, 3] - 0.3, T_true[:3, 3] + 0.3])
    res = make_initializer(rig, model, workspace=around)(fs)
    assert res is not None and add_sym(res.T_world_object, free.T_world_object, model.vertices, syms) < \
        1e-3 * model.diameter
    beside = tuple(np.r_[T_true[:3, 3] + [1.0, -0.3, -0.3], T_true[:3, 3] + [1.6, 0.3, 0.3]])
    ini = make_initializer(rig, model, workspace=beside)
    res = ini(fs)
    poses = ([res.T_world_object] if res is not None else []) + [T for T, *_ in ini.last_report.candidates]
    c = box_centre(model.vertices)
    assert all(centres_inside(T[:3, :3], T[:3, 3], c, beside)[0] for T in poses)


def test_a_search_whose_candidates_all_left_the_volume_answers_none(monkeypatch):
    """Refinement can carry every candidate out of the working volume (each hypothesis started
    inside it): the call then answers none, with its reason, instead of deciding among nothing."""
    import vespro.init.initializer as ini_mod

    rig, model, frames = trial_frames("box", 0, 1, 2)
    fs, T_true = frames[0]
    inside = tuple(np.r_[T_true[:3, 3] - 0.3, T_true[:3, 3] + 0.3])
    T_out = T_true.copy()
    T_out[:3, 3] += [1.0, 0.0, 0.0]  # where a refinement went, a metre off
    setup = ini_mod.make_setup(rig, model, ini_mod.InitOptions(workspace=inside))
    monkeypatch.setattr(ini_mod, "_hypotheses", lambda setup, views, attempt: (np.array([T_true]), 1))
    monkeypatch.setattr(ini_mod, "_verified", lambda *a, **k: ([(T_out, None)], [T_out]))
    res, rep = ini_mod.initialize(setup, fs)
    assert res is None and rep.reason == "no candidate in the working volume"
