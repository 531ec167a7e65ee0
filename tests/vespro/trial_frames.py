"""Test helper: the frames of a ``bench/init.py`` trial, rendered once.

The last few trials asked for are kept with their cells open: asked again (a test's
premise run and its run with the rule on, or the next test on the same trial), a trial
returns copies of the frames already rendered and renders only those beyond them, from
where its cell stopped (a trial's first frames do not depend on how many follow).
:func:`close_trials` closes the kept cells (at the latest when the process ends).
"""

import atexit
from collections import OrderedDict
from dataclasses import replace

import numpy as np

from vespro.model import load_model
from vespro.sim.cell import OccluderSweep, SimCell
from vespro.sim.trials import random_rig, trial_config

#: Trials kept rendered, the most recently asked for.
KEPT_TRIALS = 3

_kept: OrderedDict = OrderedDict()


def _rig_config(obj, seed, n_cameras, hide):
    rig = random_rig(np.random.default_rng(10_000 + seed), n_cameras)
    config, motion, mesh = trial_config(obj, rig, seed)
    if hide:
        config = replace(config, occluders=(OccluderSweep(rig.cameras[0].name, 0.0, duration=1e3, half_travel=0.0),))
    return rig, config, motion, mesh


class _Trial:
    """One trial's cell, settled, and the frames it rendered so far."""

    def __init__(self, obj, seed, n_cameras, hide):
        _, config, motion, _ = _rig_config(obj, seed, n_cameras, hide)
        self.cell = SimCell(config, motion)
        self.cell.settle_arm()
        self.frames = []

    def first(self, n):
        while len(self.frames) < n:
            self.frames.append((self.cell.next_frameset(), self.cell.true_object_pose()))
        return self.frames[:n]


def _copy(fs):
    return replace(fs, images={k: None if im is None else im.copy() for k, im in fs.images.items()},
                   T_world_camera={k: T.copy() for k, T in fs.T_world_camera.items()})


def trial_frames(obj, seed, n, n_cameras=1, hide=False):
    """(rig, model, [(frame set, true pose)] * n) of a trial (rig seed as in bench/init.py;
    ``hide``: a paddle held between the rig's first camera and the part). Rig, model and
    frames are the caller's own (fresh objects, images copied)."""
    key = (obj, seed, n_cameras, hide)
    trial = _kept.pop(key, None) or _Trial(*key)
    _kept[key] = trial
    while len(_kept) > KEPT_TRIALS:
        _kept.popitem(last=False)[1].cell.close()
    rig, _, _, mesh = _rig_config(*key)
    return rig, load_model(mesh), [(_copy(fs), T.copy()) for fs, T in trial.first(n)]


def close_trials():
    """Close the kept trials' cells."""
    while _kept:
        _kept.popitem()[1].cell.close()


# The simulated cells kept for the last trials are closed when the test process ends.
atexit.register(close_trials)
