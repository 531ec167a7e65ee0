"""ViSP's real textured cube (Debian ``visp-images-data``, ``mbt/cube``) tracked with no flag and no pose.

An 84 mm cube (corners as ``mbt/cube.cao``) seen by one camera (ViSP's
``px py u0 v0``, no distortion), 218 grey frames at 25 Hz (the stamps here).
The tracker runs with its initialiser and nothing else, once per decision
(``TrackerConfig.decision``), and the table gives, per decision: the first
frame published ``tracking``, the frames published ``tracking`` among those
run, the ADD of frame 0's published pose from ViSP's hand-set start pose
(``cube.0.pos``, 1-3 px off the image's outline; % of the diameter), and the
per-frame time (median, p99; the initialiser's calls included). With
``--overlay DIR`` it writes the bank's published outline over frames 0, 100
and 200.

With ``--textured`` the initialiser is told the part's faces are textured
(``vespro serve --textured``); with the bank deciding it never assumes plain
faces (as ``vespro serve --decision bank``: texture is clutter to the likelihood).

Usage: ``python3 bench/visp_cube.py [--frames 218] [--decisions rules,bank] [--rules-frames 30] [--overlay DIR] [--textured]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vespro.camera import CameraIntrinsics  # noqa: E402
from vespro.frames import FrameSet  # noqa: E402
from vespro.imageedges import project_points  # noqa: E402
from vespro.init import decision_options, make_initializer  # noqa: E402
from vespro.metrics import add_sym, discrete_symmetries  # noqa: E402
from vespro.model import box_model  # noqa: E402
from vespro.rig import Rig, RigCamera  # noqa: E402
from vespro.se3 import exp_so3  # noqa: E402
from vespro.tracker import Tracker, TrackerConfig  # noqa: E402

DATA = Path("/usr/share/visp-images-data/ViSP-images/mbt")
K = np.array([[547.7367575, 0, 338.7036994], [0, 542.0744058, 234.5083345], [0, 0, 1]])


def start_pose() -> np.ndarray:
    """ViSP's start pose ``cMo`` (translation, then theta-u) as ``T_world_object`` (world = camera)."""
    pos = np.loadtxt(DATA / "cube.0.pos")
    T = np.eye(4)
    T[:3, 3] = pos[:3]
    T[:3, :3] = exp_so3(pos[3:])
    return T


def run(decision: str, n: int, overlay: Path | None, textured: bool = False) -> dict:
    model = box_model([0.084] * 3, center=(-0.042, 0.042, 0.042), name="cube")
    img0 = cv2.imread(str(DATA / "cube" / "image0000.pgm"), cv2.IMREAD_GRAYSCALE)
    rig = Rig((RigCamera("cam", CameraIntrinsics(img0.shape[1], img0.shape[0], K), T_world_camera=np.eye(4)),))
    tr = Tracker(rig, model, TrackerConfig(decision=decision), initializer=make_initializer(rig, model, **decision_options(decision, textured)))
    syms = discrete_symmetries(model.vertices)
    out = dict(first=None, tracked=0, add0=float("nan"), ms=[])
    for k in range(n):
        img = cv2.imread(str(DATA / "cube" / f"image{k:04d}.pgm"), cv2.IMREAD_GRAYSCALE)
        fs = FrameSet(k, int(k * 40e6), {"cam": img})
        t = time.perf_counter()
        o = tr.process(fs)
        out["ms"].append((time.perf_counter() - t) * 1e3)
        if o.status == "tracking":
            out["tracked"] += 1
            if out["first"] is None:
                out["first"] = k
            if k == 0:
                out["add0"] = add_sym(o.T_world_object, start_pose(), model.vertices, syms) / model.diameter * 100
        if overlay is not None and k in (0, 100, 200):
            vis = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
            if o.T_world_object is not None:
                ua, _ = project_points(K, o.T_world_object, model.vertices[model.edge_vertices[:, 0]])
                ub, _ = project_points(K, o.T_world_object, model.vertices[model.edge_vertices[:, 1]])
                for a, b in zip(ua, ub):
                    cv2.line(vis, tuple(np.round(a).astype(int)), tuple(np.round(b).astype(int)), (0, 0, 255), 1,
                             cv2.LINE_AA)
            cv2.putText(vis, f"frame {k}: {o.status} p={o.probability:.3f}", (10, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                        (0, 0, 255), 1, cv2.LINE_AA)
            overlay.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(overlay / f"cube_{decision}{'_textured' if textured else ''}_{k:03d}.png"), vis)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=218)
    ap.add_argument("--rules-frames", type=int, default=30,
                    help="frames run with the rules (each refused start costs about a second)")
    ap.add_argument("--decisions", default="rules,bank")
    ap.add_argument("--overlay", type=Path, default=None)
    ap.add_argument("--textured", action="store_true", help="the initialiser told the part is textured (vespro's --textured)")
    a = ap.parse_args(argv)
    if not (DATA / "cube" / "image0000.pgm").exists():
        raise SystemExit("visp-images-data is not installed (apt install visp-images-data)")
    print(f"{'decision':>8} {'frames':>6} {'first':>5} {'tracked':>7} {'ADD0 %':>6} {'median ms':>9} {'p99 ms':>7}")
    for d in a.decisions.split(","):
        n = min(a.frames, a.rules_frames) if d == "rules" else a.frames
        r = run(d, n, a.overlay, a.textured)
        print(f"{d:>8} {n:>6} {str(r['first']):>5} {r['tracked']:>7} {r['add0']:>6.2f} "
              f"{np.median(r['ms']):>9.1f} {np.percentile(r['ms'], 99):>7.1f}", flush=True)


if __name__ == "__main__":
    main()
