"""Calibration accuracy and time per stage against the simulator's truth.

Three tables:

- intrinsics of cam_left (640x480, plumb_bob k1=-0.22 k2=0.09 p1=0.0006
  p2=-0.0004 k3=-0.015): plain chessboard (whole board in view) vs ChArUco
  (may run off the image), same board geometry and pose generator; and
  ChArUco with 2 grey levels of sensor noise, and with 0.3 px geometric pixel
  noise (a displacement field, so the corners really move) + the sensor noise.
  Each capture calibrated twice: from the detector's corners ("detector",
  ``refine_rounds=0``) and with the corners re-located on the board plane
  through the calibration ("read", the default: 2 rounds, ChArUco corners the
  detector lost at the border added); ``--seeds N`` runs only these, over
  seeds 0..N-1;
- extrinsics of the three fixed cameras (fixed3, same distortion, true
  intrinsics): PnP from the best single view (baseline) vs the joint refinement
  over four known placements;
- hand-eye of the "hand" camera: each closed-form method vs the refined one.

Undistortion error ("undist"): the distorted-to-ideal pixel maps of the
estimated and of the true model (each with its own camera matrix, as
``cv2.undistort`` does) compared every 4 px over the whole image, first and
last rows and columns included; RMS and max. "corner gap": the largest
distance from an image corner pixel to the nearest detected board corner (how
far the model is extrapolated there).

The last row of the extrinsics and hand-eye tables runs the chain a user runs:
intrinsics calibrated first (from the simulated images, "read"), then the pose
stage with them instead of the true intrinsics.

Times are wall-clock seconds per stage on this machine (capture = MuJoCo render
+ imaging + PNG write). Usage: ``python bench/calibrate.py [--views N] [--seed S] [--seeds N]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from _table import print_table  # noqa: E402

from vespro.calib.board import BoardSpec, detect_board  # noqa: E402
from vespro.calib.extrinsics import calibrate_extrinsics  # noqa: E402
from vespro.calib.handeye import calibrate_hand_eye  # noqa: E402
from vespro.calib.intrinsics import calibrate_intrinsics, undistortion_error  # noqa: E402
from vespro.calib.io import list_images, load_images, lookup_pose, read_pose_csv  # noqa: E402
from vespro.camera import CameraIntrinsics  # noqa: E402
from vespro.rig import Rig, RigCamera, load_rig  # noqa: E402
from vespro.se3 import pose_error  # noqa: E402
from vespro.sim.imaging import ImageEffects  # noqa: E402
from vespro.sim.board import capture_extrinsics, capture_handeye, capture_intrinsics  # noqa: E402
from vespro.sim.rigs import CAMERAS_DIR  # noqa: E402

DIST = (-0.22, 0.09, 0.0006, -0.0004, -0.015)


def _with_dist(rig: Rig) -> Rig:
    return Rig(tuple(RigCamera(c.name, CameraIntrinsics(c.intrinsics.width, c.intrinsics.height, c.intrinsics.K, DIST),
                               c.mount, c.T_world_camera, c.link, c.T_link_camera) for c in rig))


def _timed(fn, *a, **k):
    t = time.perf_counter()
    out = fn(*a, **k)
    return out, time.perf_counter() - t


def _intrinsics_rows(tmp: Path, kind: str, noise: float, views: int, seed: int, grey_noise: float = 2.0):
    """Capture once, calibrate from the detector's corners and with the reading
    rounds; one table row each. Returns the rows and the read calibration.
    ``noise``: geometric pixel noise (px); with it or with ``noise`` < 0 (sensor
    noise only), ``grey_noise`` grey levels of sensor noise."""
    rig = _with_dist(load_rig(CAMERAS_DIR / "fixed1.yaml"))
    true = rig["cam_left"].intrinsics
    spec = BoardSpec(kind, 11, 8, 0.028, 0.021 if kind == "charuco" else None)
    folder = tmp / f"intr_{kind}_{noise}_{seed}"
    effects = ImageEffects(noise_px=max(noise, 0.0), intensity_noise=grey_noise) if noise else None
    _, t_cap = _timed(capture_intrinsics, rig, "cam_left", spec, folder, views, seed, effects)
    images = load_images(list_images(folder))
    dets, t_det = _timed(lambda: {n: detect_board(i, spec) for n, i in images.items()})
    rows = []
    for rounds in (0, 2):
        res, t_cal = _timed(calibrate_intrinsics, dets, spec, (true.width, true.height), images=images,
                            refine_rounds=rounds)
        e = res.intrinsics
        mx, rms = undistortion_error(e, true, step_px=4)
        rel = 100 * np.array([e.fx / true.fx - 1, e.fy / true.fy - 1, e.cx / true.cx - 1, e.cy / true.cy - 1])
        name = kind + _noise_name(noise, grey_noise) + (", read" if rounds else ", detector")
        rows.append([name, seed, f"{len(res.used)}/{views}", t_cap, t_det, t_cal, res.rms_px, *np.round(rel, 3).tolist(),
                     rms, mx, float(res.coverage.corner_gap_px.max())])
    return rows, res


def _noise_name(noise: float, grey_noise: float = 2.0) -> str:
    if noise > 0:
        return f" +{noise} px, {grey_noise:g} grey noise"
    return f" +{grey_noise:g} grey noise" if noise < 0 else ""


INTR_HEADER = ["board, corners", "seed", "views", "capture s", "detect s", "calib s", "RMS px", "fx %", "fy %", "cx %",
               "cy %", "undist RMS px", "undist max px", "corner gap px"]


def bench_intrinsics(tmp: Path, views: int, seed: int):
    rows = []
    charuco = None
    for kind, noise in (("chessboard", 0.0), ("charuco", 0.0), ("charuco", -1.0), ("charuco", 0.3)):
        r, res = _intrinsics_rows(tmp, kind, noise, views, seed)
        rows += r
        if kind == "charuco" and charuco is None:
            charuco = res
    print_table(INTR_HEADER, rows,
                title=f"Intrinsics, cam_left 640x480 with distortion ({views} views, seed {seed}); errors vs truth. "
                      "'detector': OpenCV's corners; 'read': re-located on the board plane through the "
                      "calibration, 2 rounds")
    print()
    return charuco.intrinsics


def bench_intrinsics_seeds(tmp: Path, views: int, seeds) -> None:
    for kind, noise in (("charuco", 0.0), ("chessboard", 0.0), ("charuco", -1.0), ("charuco", 0.3)):
        rows = []
        for seed in seeds:
            rows += _intrinsics_rows(tmp, kind, noise, views, seed)[0]
        rows.sort(key=lambda r: (r[0], r[1]))
        print_table(INTR_HEADER, rows, title=f"Intrinsics over seeds, {kind}{_noise_name(noise)}, "
                    f"cam_left 640x480, {views} views")
        print()


def bench_extrinsics(tmp: Path, cam_left_calibrated=None) -> None:
    rig = _with_dist(load_rig(CAMERAS_DIR / "fixed3.yaml"))
    spec = BoardSpec("charuco", 9, 6, 0.045, 0.034)
    folder = tmp / "ext"
    _, t_cap = _timed(capture_extrinsics, rig, spec, folder, 4)
    dets, t_det = {}, 0.0
    for c in rig.names:
        images = load_images(list_images(folder / c))
        d, t = _timed(lambda: {(c, p): detect_board(i, spec) for p, i in images.items()})
        dets.update(d)
        t_det += t
    known = read_pose_csv(folder / "board_poses.csv", "placement")
    known = {p: lookup_pose(known, p) for p in {p for _, p in dets}}
    res, t_cal = _timed(calibrate_extrinsics, dets, {c.name: c.intrinsics for c in rig}, known, spec)
    rows = []
    for c in rig:
        dp0, da0 = pose_error(res.T_world_camera_pnp[c.name], c.T_world_camera)
        dp, da = pose_error(res.T_world_camera[c.name], c.T_world_camera)
        n = sum(1 for k in res.view_rms_px if k[0] == c.name)
        rows.append([c.name, n, dp0 * 1e3, np.rad2deg(da0), dp * 1e3, np.rad2deg(da), res.rms_px[c.name]])
    if cam_left_calibrated is not None:
        # The chain a user runs: cam_left's intrinsics from the ChArUco calibration above.
        intr = {c.name: c.intrinsics for c in rig}
        intr["cam_left"] = cam_left_calibrated
        res2 = calibrate_extrinsics(dets, intr, known, spec)
        dp0, da0 = pose_error(res2.T_world_camera_pnp["cam_left"], rig["cam_left"].T_world_camera)
        dp, da = pose_error(res2.T_world_camera["cam_left"], rig["cam_left"].T_world_camera)
        rows.append(["cam_left (calib. intr.)", 4, dp0 * 1e3, np.rad2deg(da0), dp * 1e3, np.rad2deg(da),
                     res2.rms_px["cam_left"]])
    print_table(["camera", "views", "PnP mm", "PnP deg", "joint mm", "joint deg", "joint RMS px"], rows,
                title=f"Extrinsics, fixed3 with distortion, 4 known placements "
                      f"(capture {t_cap:.2f} s, detect {t_det:.2f} s, solve {t_cal:.2f} s)")
    print()


def bench_hand_eye(tmp: Path, seed: int) -> None:
    rig = _with_dist(load_rig(CAMERAS_DIR / "hand.yaml"))
    cam = rig["hand"]
    spec = BoardSpec("charuco", 11, 8, 0.028, 0.021)
    folder = tmp / "he"
    _, t_cap = _timed(capture_handeye, rig, "hand", spec, folder, 15, seed)
    images = load_images(list_images(folder))
    poses = read_pose_csv(folder / "flange_poses.csv", "index")
    dets, t_det = _timed(lambda: {n: detect_board(i, spec) for n, i in images.items()})
    res, t_cal = _timed(calibrate_hand_eye, {n: lookup_pose(poses, n) for n in images}, dets, cam.intrinsics, spec)
    rows = []
    for c in res.candidates.values():
        dp, da = pose_error(c.T_link_camera, cam.T_link_camera)
        rows.append([c.method + (" *" if c is res.best else ""), dp * 1e3, np.rad2deg(da), c.spread_m * 1e3,
                     np.rad2deg(c.spread_rad), c.rms_px])
    # The chain a user runs: the hand camera's intrinsics calibrated first (the arm
    # holds it still while the board moves), then hand-eye with them.
    ifolder = tmp / "hand_intr"
    capture_intrinsics(rig, "hand", spec, ifolder, 30, seed)
    iimages = load_images(list_images(ifolder))
    idets = {n: detect_board(i, spec) for n, i in iimages.items()}
    intr = calibrate_intrinsics(idets, spec, (640, 480), images=iimages).intrinsics
    res2 = calibrate_hand_eye({n: lookup_pose(poses, n) for n in images}, dets, intr, spec)
    c = res2.best
    dp, da = pose_error(c.T_link_camera, cam.T_link_camera)
    rows.append([c.method + ", calib. intr.", dp * 1e3, np.rad2deg(da), c.spread_m * 1e3, np.rad2deg(c.spread_rad),
                 c.rms_px])
    print_table(["method (* chosen)", "err mm", "err deg", "spread mm", "spread deg", "RMS px"], rows,
                title=f"Hand-eye, 'hand' camera with distortion, 15 arm poses "
                      f"(capture {t_cap:.2f} s, detect {t_det:.2f} s, all solvers {t_cal:.2f} s)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=30, help="intrinsics views")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", type=int, default=0,
                    help="only the intrinsics rows, for seeds 0..N-1 (how much they vary with the capture)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if args.seeds:
            bench_intrinsics_seeds(tmp, args.views, range(args.seeds))
            return
        cam_left = bench_intrinsics(tmp, args.views, args.seed)
        bench_extrinsics(tmp, cam_left)
        bench_hand_eye(tmp, args.seed)


if __name__ == "__main__":
    main()
