"""Why the initialiser fails on given trials: failure classes and overlay images.

For each (object, rig kind, seed) trial of ``bench/init.py`` and each listed
frame, runs one initialiser call and classifies what happened, using the
simulator's ground truth (an evaluator, so allowed here):

- ``no-hypothesis``: no P3P hypothesis of the first camera within 10% of the
  diameter (ADD) of the true pose;
- ``ranked-out``: one exists but the refined candidates hold none near the
  truth (ranked below the ones refined, or refined away);
- ``rejected: <reason>``: a refined candidate is near the truth but fails
  verification (the reason is the verdict on the true pose, refined from the
  truth, when it fails too);
- ``ambiguous``: the near-true candidate passes but a rival makes it ambiguous;
- ``ok`` / ``WRONG`` (a pose returned with ADD at or above 10%).

An overlay PNG per trial and frame goes to ``--out`` (model edges at the true
pose in green, at the best candidate in red, detected corners in magenta).

Usage: ``python3 bench/init_failures.py --objects box --rig 1 --seeds 4,7,17
[--frames 0,5] [--out /tmp/init_failures]``
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("MUJOCO_GL", "egl")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from vespro.edgefit import refine_pose, refine_subpixel  # noqa: E402
from vespro.imageedges import visible_samples  # noqa: E402
from vespro.init import make_initializer  # noqa: E402
from vespro.init.initializer import _accept_plain, _verdict, _views, initialize  # noqa: E402
from vespro.init.search import check_pose, image_paths, p3p_hypotheses  # noqa: E402
from vespro.library import object_mesh_path  # noqa: E402
from vespro.metrics import add  # noqa: E402
from vespro.model import load_model  # noqa: E402
from vespro.se3 import invert_transform  # noqa: E402
from vespro.sim.cell import SimCell  # noqa: E402
from vespro.sim.trials import model_symmetries, random_rig, trial_config  # noqa: E402


def _sym_add_frac(T, T_true, model, syms):
    return min(add(T, T_true @ S, model.vertices) for S in syms) / model.diameter


def _draw(img, K, T_co, mf, tree, colour):
    idx = visible_samples(T_co, mf, tree)
    X = mf.sample_p[idx] @ T_co[:3, :3].T + T_co[:3, 3]
    uv = X[:, :2] / X[:, 2:3] * K[[0, 1], [0, 1]] + K[:2, 2]
    for u, v in uv:
        if np.isfinite(u) and np.isfinite(v) and 0 <= u < img.shape[1] and 0 <= v < img.shape[0]:
            cv2.circle(img, (int(round(u)), int(round(v))), 1, colour, -1)


def classify(obj, rig_kind, seed, frames, out_dir):
    model = load_model(object_mesh_path(obj))
    syms = model_symmetries(model.vertices)
    rng = np.random.default_rng(10_000 + seed)
    if rig_kind == "hybrid":
        rig = random_rig(rng, 2, hand=True)
    elif rig_kind == "hand":
        rig = random_rig(rng, 0, hand=True)
    else:
        rig = random_rig(rng, int(rig_kind))
    config, motion, _ = trial_config(obj, rig, seed)
    setup = make_initializer(rig, model).setup
    mf, opt = setup.mf, setup.options
    rows = []
    with SimCell(config, motion) as cell:
        cell.settle_arm()
        for k in range(max(frames) + 1):
            fs = cell.next_frameset()
            if k not in frames:
                continue
            T_true = cell.true_object_pose()
            views = _views(setup, fs)
            v = views[0]
            T_cw = invert_transform(v.T_world_camera)
            R, t = p3p_hypotheses(v.feat, mf, model.vertices, image_paths(v.feat, max_paths=opt.max_image_paths))
            T_ct = T_cw @ T_true
            P = [model.vertices @ (T_ct @ S)[:3, :3].T + (T_ct @ S)[:3, 3] for S in syms]
            Ph = np.einsum("vj,nij->nvi", model.vertices, R) + t[:, None]
            best_h = (min(float(np.min(np.linalg.norm(Ph - p[None], axis=2).mean(1))) for p in P) / model.diameter
                      if len(R) else np.inf)
            res, rep = initialize(setup, fs)
            cands = [(_sym_add_frac(T, T_true, model, syms), c) for T, c in rep.candidates]
            Tr = refine_subpixel(refine_pose(T_true, views, mf, setup.tree), views, mf, setup.tree)
            chk_true = check_pose(Tr, views, mf, setup.tree, opt.verify_tol_px, require_fixed=opt.require_fixed_view)
            true_ok, _, true_why = _verdict(chk_true, opt)
            if not true_ok and chk_true.n_cameras == 1 and opt.plain_faces:
                true_why = f"{true_why}; plain-face limits: {_accept_plain(chk_true, opt)[1]}"
            if res is not None:
                a = _sym_add_frac(res.T_world_object, T_true, model, syms)
                cls = "ok" if a < 0.1 else f"WRONG (ADD {a:.3f})"
            elif rep.plain:
                cls = "ok (awaiting confirmation)"
            elif best_h >= 0.1:
                cls = "no-hypothesis"
            elif not any(a < 0.1 for a, _ in cands):
                cls = "ranked-out" if true_ok else f"ranked-out; true pose rejected: {true_why}"
            elif not true_ok:
                cls = f"rejected: {true_why}"
            else:
                cls = f"ambiguous: {rep.reason}"
            rows.append((obj, rig_kind, seed, k, cls, round(best_h, 3), rep.reason))
            print(f"{obj} rig {rig_kind} seed {seed} frame {k}: {cls} (best hypothesis ADD {best_h:.3f}; "
                  f"call: {rep.reason or 'accepted'})", flush=True)
            if out_dir is not None:
                img = setup.undistort[v.feat.name](fs.images[v.feat.name])
                img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
                for u, w in v.feat.corners:
                    cv2.circle(img, (int(u), int(w)), 3, (255, 0, 255), 1)
                _draw(img, v.feat.K, T_ct, mf, setup.tree, (0, 255, 0))
                if rep.candidates:
                    _draw(img, v.feat.K, T_cw @ rep.candidates[0][0], mf, setup.tree, (0, 0, 255))
                cv2.imwrite(str(Path(out_dir) / f"{obj}_{rig_kind}_{seed}_{k}.png"), img)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--objects", default="box")
    ap.add_argument("--rig", default="1")
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--frames", default="0")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    if a.out:
        Path(a.out).mkdir(parents=True, exist_ok=True)
    frames = [int(f) for f in a.frames.split(",")]
    for obj in a.objects.split(","):
        for s in a.seeds.split(","):
            classify(obj, a.rig, int(s), frames, a.out)


if __name__ == "__main__":
    main()
