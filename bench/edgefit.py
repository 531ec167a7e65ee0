"""Benchmark of the one-camera edge fit's accuracy: fits started from the true pose.

Each trial is a one-camera cell (``vespro.sim.trials``, the same rigs and start
poses as ``bench/init.py --rigs 1``); on frames 0, 10, 20 and 30 the tracker's
edge fit (:class:`vespro.edgeaid.EdgeAid`) is started from the true pose and
scored against it (the evaluator reads the truth; the fit does not): the error
along the camera's line of sight (the direction one camera sees worst) and
the symmetry-aware ADD, both as a percentage of the object's diameter, the
NEES of the fit's covariance, fits refused, and the time of a fit. A fit that
is unbiased and consistent lands within its own covariance (NEES median near
5.3 for 6 dof) and its errors shrink when the image noise does.

The baseline runs in the same process on the same frames: the edge fit with
every sample weighing alike and no edge dropped (``spacing_px`` and
``edge_outlier_px`` 0).

Usage: ``python3 bench/edgefit.py [--seeds 40-59] [--objects box,lblock,bracket]
[--noise 0.5] [--jobs 2]``
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from multiprocessing import Pool
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402

from bench._table import print_table, stats_ms  # noqa: E402

CONFIGS = {"default": {}, "base": dict(spacing_px=0.0, edge_outlier_px=0.0)}


def _views(args):
    """Edge fits of one trial from the true pose: (config, along-ray %, ADD %, NEES, seconds) rows."""
    from vespro.edgeaid import EdgeAid
    from vespro.ekf import nees
    from vespro.metrics import add_sym
    from vespro.model import load_model
    from vespro.sim.cell import SimCell
    from vespro.sim.trials import model_symmetries, random_rig, trial_config

    obj, seed, noise = args
    rig = random_rig(np.random.default_rng(10_000 + seed), 1)
    config, motion, mesh = trial_config(obj, rig, seed, noise_px=noise)
    model = load_model(mesh)
    syms = model_symmetries(model.vertices)
    cam = rig.cameras[0]
    T_wc = cam.T_world_camera
    aids = {k: EdgeAid(rig, model, **v) for k, v in CONFIGS.items()}
    rows = []
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        for k in range(31):
            fs = cell.next_frameset()
            if k % 10:
                continue
            T = cell.true_object_pose()
            ray = (T[:3, 3] - T_wc[:3, 3]) / np.linalg.norm(T[:3, 3] - T_wc[:3, 3])
            for name, aid in aids.items():
                if k == 0:
                    aid.measure(cam.name, fs.images[cam.name], T_wc, T)  # warm-up: compiled kernels load
                t0 = time.perf_counter()
                m = aid.measure(cam.name, fs.images[cam.name], T_wc, T)
                dt = time.perf_counter() - t0
                if m is None:
                    rows.append((name, np.nan, np.nan, np.nan, dt))
                    continue
                along = 100 * abs((m.T_world_object[:3, 3] - T[:3, 3]) @ ray) / model.diameter
                e = 100 * add_sym(m.T_world_object, T, model.vertices, syms) / model.diameter
                rows.append((name, along, e, nees(m.T_world_object, T, m.cov6), dt))
    return rows


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="40-59", help="a seed or a range, e.g. 40-59")
    ap.add_argument("--objects", default="box,lblock,bracket")
    ap.add_argument("--noise", type=float, default=0.5, help="image displacement noise, px (0: none)")
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args(argv)
    jobs = [(o, s, a.noise) for o in a.objects.split(",") for s in _seeds(a.seeds)]
    with Pool(a.jobs) as pool:
        rows = [r for rr in pool.map(_views, jobs) for r in rr]
    table, p90 = [], {}
    for name in CONFIGS:
        r = np.array([x[1:] for x in rows if x[0] == name], float)
        ok = np.isfinite(r[:, 0])
        along, e, ne, dt = r[ok, 0], r[ok, 1], r[ok, 2], r[:, 3]
        p90[name] = np.percentile(along, 90)
        med_ms, p99_ms = stats_ms(dt)
        table.append([name, int(ok.sum()), int((~ok).sum()), float(np.median(along)), float(p90[name]),
                      float(np.median(e)), float(np.percentile(e, 90)), int(np.sum(e > 5)), float(np.median(ne)),
                      med_ms, p99_ms])
    print_table(["fit", "views", "refused", "along % med", "along % p90", "ADD % med", "ADD % p90", "ADD > 5%",
                 "NEES med", "ms med", "ms p99"], table,
                title=f"Edge fits from the true pose, one camera, seeds {a.seeds}, image noise {a.noise} px")
    print(f"along-ray p90 ratio default/base = {p90['default'] / p90['base']:.2f}")


if __name__ == "__main__":
    main()
