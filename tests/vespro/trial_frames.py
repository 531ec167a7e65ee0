"""Test helper: the frames of a ``bench/init.py`` trial, rendered once."""

from dataclasses import replace

import numpy as np

from vespro.model import load_model
from vespro.sim.cell import OccluderSweep, SimCell
from vespro.sim.trials import random_rig, trial_config


def trial_frames(obj, seed, n, n_cameras=1, hide=False):
    """(rig, model, [(frame set, true pose)] * n) of a trial (rig seed as in bench/init.py;
    ``hide``: a paddle held between the rig's first camera and the part)."""
    rig = random_rig(np.random.default_rng(10_000 + seed), n_cameras)
    config, motion, mesh = trial_config(obj, rig, seed)
    if hide:
        config = replace(config, occluders=(OccluderSweep(rig.cameras[0].name, 0.0, duration=1e3, half_travel=0.0),))
    model = load_model(mesh)
    out = []
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        for _ in range(n):
            out.append((cell.next_frameset(), cell.true_object_pose()))
    return rig, model, out
