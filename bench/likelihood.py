"""Time of the edge likelihood of one pose in one camera (vespro.likelihood), beside an edge fit.

Per part (box, L-block, bracket; one-camera trial frame 0, rig seed as in
``bench/init.py``): the gradient image over the box around the part
(``EdgeImage``, once per camera and frame), the likelihood of the true pose
(``ImageLikelihood``, once per hypothesis) with the edge lines alone and with
the region term (``LikelihoodOptions.region``), and as the baseline the
tracker's edge fit from the true pose (``EdgeAid.measure``, which reads the
same image), each repeated ``--repeat`` times: median and p99 in ms, the ratio
of the likelihood (image and pose) to the fit, and of the likelihood with the
region term to without.

Usage: ``python3 bench/likelihood.py [--repeat 200] [--objects box,lblock,bracket]``
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "vespro"))
os.environ.setdefault("MUJOCO_GL", "egl")

from trial_frames import trial_frames  # noqa: E402

from vespro.bsp import load_or_build_bsp  # noqa: E402
from vespro.edgeaid import EdgeAid  # noqa: E402
from vespro.likelihood import ImageLikelihood, LikelihoodOptions  # noqa: E402
from vespro.se3 import invert_transform  # noqa: E402

SEEDS = {"box": 6, "lblock": 12, "bracket": 3}


def _times(fn, n):
    fn()  # (compiled kernels loaded)
    out = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t) * 1e3)
    return np.median(out), np.percentile(out, 99)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=200)
    ap.add_argument("--objects", default="box,lblock,bracket")
    a = ap.parse_args(argv)
    print(f"{'object':>8} {'samples':>7} {'outline':>7} {'image med':>9} {'p99':>6} {'pose med':>8} {'p99':>6} "
          f"{'+region':>7} {'p99':>6} {'fit med':>7} {'p99':>6} {'ratio':>5} {'region/pose':>11}   (ms)")
    for obj in a.objects.split(","):
        rig, model, frames = trial_frames(obj, SEEDS.get(obj, 0), 1)
        fs, T = frames[0]
        cam = rig.cameras[0]
        tree = load_or_build_bsp(model)
        aid = EdgeAid(rig, model, tree)
        lk = ImageLikelihood(aid.mf, tree)
        lkr = ImageLikelihood(aid.mf, tree, LikelihoodOptions(region=True))
        img = fs.grey(cam.name)
        K = np.asarray(cam.intrinsics.K, float)
        box = lk.box(K, invert_transform(cam.T_world_camera) @ T, img.shape[1], img.shape[0])
        e = lk.edge_image(img, K, box)
        views = [(cam.T_world_camera, e)]
        im = _times(lambda: lk.edge_image(img, K, box), a.repeat)
        po = _times(lambda: lk(T, views), a.repeat)
        rg = _times(lambda: lkr(T, views), a.repeat)
        fit = _times(lambda: aid.measure(cam.name, img, cam.T_world_camera, T), a.repeat)
        c = lkr(T, views).cameras[0]
        print(f"{obj:>8} {c.n_visible:>7} {c.n_outline:>7} {im[0]:>9.2f} {im[1]:>6.2f} {po[0]:>8.2f} {po[1]:>6.2f} "
              f"{rg[0]:>7.2f} {rg[1]:>6.2f} {fit[0]:>7.2f} {fit[1]:>6.2f} {(im[0] + po[0]) / fit[0]:>5.2f} "
              f"{rg[0] / po[0]:>11.2f}", flush=True)


if __name__ == "__main__":
    main()
