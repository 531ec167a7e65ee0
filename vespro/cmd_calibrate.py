"""``vespro calibrate``: intrinsics, fixed-camera extrinsics and hand-eye, into a rig file.

Each subcommand reads a folder of images (plus poses where needed), as from
real cameras; with ``--sim`` it first fills that folder from the simulated cell
(a board rendered as a textured plane, lens distortion of the simulated rig
applied), then runs the same code path. Results update one rig file
(``cameras.yaml``, shared/spec/recording.md) usable with ``vespro record --rig``.

Folder layouts:

- intrinsics: ``DIR/*.png`` (one camera);
- extrinsics: ``DIR/<camera>/<placement>.png`` and the board's world poses in
  ``DIR/board_poses.csv`` (``placement,x,y,z,qw,qx,qy,qz``) or ``--board-pose``;
- hand-eye: ``DIR/<index>.png`` and ``DIR/flange_poses.csv``
  (``index,x,y,z,qw,qx,qy,qz``: the link's pose in the robot base/world frame).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_DISTORTION = (-0.22, 0.09, 0.0006, -0.0004, -0.015)
# Board defaults per job: fine squares close up (intrinsics, hand-eye), large ones
# for fixed cameras about a metre away (extrinsics).
BOARD_DEFAULTS = {
    "intrinsics": ("11x8", 0.028, 0.021),
    "hand-eye": ("11x8", 0.028, 0.021),
    "extrinsics": ("9x6", 0.045, 0.034),
}


def _squares(s: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in s.lower().split("x"))
        assert x >= 3 and y >= 3
    except (ValueError, AssertionError):
        raise argparse.ArgumentTypeError(f"--squares takes NXxNY (squares, each >= 3), e.g. 9x6, got {s!r}") from None
    return x, y


def _coeffs(s: str):
    try:
        v = tuple(float(x) for x in s.split(","))
        assert len(v) == 5
    except (ValueError, AssertionError):
        raise argparse.ArgumentTypeError(f"distortion takes k1,k2,p1,p2,k3, got {s!r}") from None
    return v


def _add_board(p, job: str) -> None:
    sq, size, marker = BOARD_DEFAULTS[job]
    g = p.add_argument_group("board")
    g.add_argument("--board", choices=["charuco", "chessboard"], default="charuco", help="board kind")
    g.add_argument("--squares", type=_squares, default=_squares(sq), metavar="NXxNY", help=f"squares along x and y (default {sq})")
    g.add_argument("--square-size", type=float, default=size, help="square side, m")
    g.add_argument("--marker-size", type=float, default=marker, help="ChArUco marker side, m")
    g.add_argument("--dictionary", default="DICT_5X5_100", help="ChArUco ArUco dictionary (OpenCV name)")


def _add_sim(p, rig: str, views: int | None) -> None:
    g = p.add_argument_group("simulation (--sim: capture DIR from the simulated cell first)")
    g.add_argument("--sim", action="store_true", help="render the board in the simulated cell into DIR, then calibrate")
    g.add_argument("--sim-rig", default=rig, help="simulated cameras: standard rig name or cameras.yaml (the truth)")
    g.add_argument("--sim-distortion", type=_coeffs, default=DEFAULT_DISTORTION, metavar="K1,K2,P1,P2,K3",
                   help="lens distortion given to every simulated camera")
    g.add_argument("--sim-noise", type=float, default=0.0, metavar="SIGMA_PX",
                   help="geometric pixel noise of the simulated images (smooth random displacement), px")
    g.add_argument("--sim-intensity-noise", type=float, default=0.0, metavar="SIGMA",
                   help="sensor noise of the simulated images, grey levels")
    if views:
        g.add_argument("--sim-views", type=int, default=views, help="number of views to capture")
    g.add_argument("--seed", type=int, default=0, help="random seed of the simulated poses")


def add_parser(sub) -> None:
    p = sub.add_parser("calibrate", help="calibrate cameras (intrinsics, extrinsics, hand-eye) into a rig file",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    jobs = p.add_subparsers(dest="job", metavar="JOB")

    pi = jobs.add_parser("intrinsics", help="camera matrix and plumb_bob distortion of one camera",
                         formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    pi.add_argument("images", type=Path, help="folder of board images of one camera")
    pi.add_argument("--rig", type=Path, required=True, help="rig file to write or update")
    pi.add_argument("--camera", required=True, help="camera name in the rig file")
    pi.add_argument("--min-views", type=int, default=6, help="fewest usable views")
    pi.add_argument("--coverage-png", type=Path, help="coverage map to write (default: <rig>_<camera>_coverage.png beside the rig file)")
    pi.add_argument("--refine-rounds", type=int, default=2,
                    help="rounds of re-locating the corners on the board plane through the calibration, each "
                         "followed by a new calibration (0: the detector's corners only)")
    _add_board(pi, "intrinsics")
    _add_sim(pi, "fixed1", 30)
    pi.set_defaults(func=run_intrinsics)

    pe = jobs.add_parser("extrinsics", help="T_world_camera of fixed cameras from a board at known world poses",
                         formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    pe.add_argument("images", type=Path, help="folder with one sub-folder of images per camera")
    pe.add_argument("--rig", type=Path, required=True, help="rig file holding the cameras' intrinsics; poses are updated")
    pe.add_argument("--board-poses", type=Path, help="CSV placement,x,y,z,qw,qx,qy,qz (default IMAGES/board_poses.csv)")
    pe.add_argument("--board-pose", help="x,y,z,qw,qx,qy,qz: T_world_board when there is a single placement")
    _add_board(pe, "extrinsics")
    _add_sim(pe, "fixed3", None)
    pe.add_argument("--sim-placements", type=int, default=4, help="with --sim: board placements (1-4)")
    pe.set_defaults(func=run_extrinsics)

    ph = jobs.add_parser("hand-eye", help="T_link_camera of an eye-in-hand camera from arm poses",
                         formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ph.add_argument("images", type=Path, help="folder of images of the eye-in-hand camera")
    ph.add_argument("--rig", type=Path, required=True, help="rig file holding the camera's intrinsics; mounting is updated")
    ph.add_argument("--camera", required=True, help="camera name in the rig file")
    ph.add_argument("--link", default="flange", help="robot body the camera rides on")
    ph.add_argument("--poses", type=Path, help="CSV index,x,y,z,qw,qx,qy,qz of T_world_link (default IMAGES/flange_poses.csv)")
    ph.add_argument("--min-views", type=int, default=5, help="fewest usable views")
    _add_board(ph, "hand-eye")
    _add_sim(ph, "hand", 15)
    ph.set_defaults(func=run_hand_eye)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


# -- helpers -----------------------------------------------------------------
def board_spec(args):
    from .calib.board import BoardSpec

    try:
        return BoardSpec(args.board, args.squares[0], args.squares[1], args.square_size,
                         args.marker_size if args.board == "charuco" else None, args.dictionary)
    except ValueError as e:
        raise SystemExit(f"vespro calibrate: {e}") from None


def _sim_rig(args, names: list[str] | None = None):
    """The simulated (true) rig: standard or given rig, with --sim-distortion."""
    from .camera import CameraIntrinsics
    from .rig import Rig, RigCamera, load_rig
    from .sim.rigs import rig_path

    rig = load_rig(rig_path(args.sim_rig))
    cams = [RigCamera(c.name, CameraIntrinsics(c.intrinsics.width, c.intrinsics.height, c.intrinsics.K,
                                               args.sim_distortion),
                      c.mount, c.T_world_camera, c.link, c.T_link_camera)
            for c in rig if names is None or c.name in names]
    return Rig(tuple(cams))


def _effects(args):
    from .sim.imaging import ImageEffects

    return ImageEffects(noise_px=args.sim_noise, intensity_noise=args.sim_intensity_noise)


def _seed_rig_intrinsics(args, sim_rig) -> None:
    """In --sim mode, cameras missing from --rig get the simulated intrinsics (as
    if calibrated before); their poses stay to be calibrated."""
    from .calib.io import update_rig_camera
    from .rig import load_rig

    have = load_rig(args.rig).names if args.rig.is_file() else []
    for c in sim_rig:
        if c.name not in have:
            update_rig_camera(args.rig, c.name, intrinsics=c.intrinsics)


def _fresh_folder(folder: Path) -> None:
    """--sim writes into a new or empty folder: old images would mix with new ones."""
    from .calib.errors import CalibrationError

    if folder.exists() and any(folder.iterdir()):
        raise CalibrationError(f"{folder}: --sim captures into a new or empty folder, and this one holds files")


def _detect_all(images: dict, spec) -> tuple[dict, float]:
    from .calib.board import detect_board

    t = time.perf_counter()
    dets = {name: detect_board(img, spec) for name, img in images.items()}
    return dets, time.perf_counter() - t


def _fmt_pose(T) -> str:
    from .se3 import pq_from_transform

    return " ".join(f"{v:.6f}" for v in pq_from_transform(T))


def _guard(fn):
    def run(args) -> int:
        from .calib.errors import CalibrationError
        from .rig import RigError

        try:
            return fn(args)
        except RigError as e:  # a malformed rig file: the user's to fix, as every bad input file
            print(f"vespro calibrate: error: {e}", file=sys.stderr)
            return 2
        except CalibrationError as e:  # the images cannot give a calibration
            print(f"vespro calibrate: error: {e}", file=sys.stderr)
            return 1
    return run


# -- intrinsics ----------------------------------------------------------------
@_guard
def run_intrinsics(args) -> int:
    import cv2

    from .calib.intrinsics import calibrate_intrinsics, coverage_image
    from .calib.io import list_images, load_images, update_rig_camera

    spec = board_spec(args)
    if args.sim:
        from .sim.board import capture_intrinsics

        _fresh_folder(args.images)

        truth = _sim_rig(args, [args.camera])
        if args.camera not in truth.names:
            raise SystemExit(f"vespro calibrate: camera {args.camera!r} is not in the simulated rig {args.sim_rig}")
        t = time.perf_counter()
        capture_intrinsics(truth, args.camera, spec, args.images, args.sim_views, args.seed, _effects(args))
        print(f"simulated capture: {args.sim_views} views in {args.images} ({time.perf_counter() - t:.1f} s)")
    images = load_images(list_images(args.images))
    size = next(iter(images.values())).shape[1::-1]
    dets, t_det = _detect_all(images, spec)
    res = calibrate_intrinsics(dets, spec, size, min_views=args.min_views, images=images,
                               refine_rounds=args.refine_rounds)
    intr = res.intrinsics
    print(f"board: {spec.describe()}; {len(images)} images {size[0]}x{size[1]}, detection {t_det:.2f} s")
    for n in images:
        if n in res.view_rms_px:
            print(f"  {n}: {len(res.detections[n]):3d} corners, RMS {res.view_rms_px[n]:.4f} px")
        elif n in res.rejected and np.isnan(res.rejected[n]):
            print(f"  {n}: rejected, too few corners read through the calibration")
        elif n in res.rejected:
            print(f"  {n}: rejected as outlier (RMS {res.rejected[n]:.3f} px)")
        else:
            print(f"  {n}: board not found")
    if res.refine_rounds:
        print(f"reprojection RMS {res.rms_px:.4f} px over {len(res.used)} views after {res.refine_rounds} rounds of "
              f"corner refinement on the board plane ({res.rms_px_detected:.3f} px from the detector's corners)")
    else:
        print(f"reprojection RMS {res.rms_px:.3f} px over {len(res.used)} views")
    print(f"fx {intr.fx:.3f}  fy {intr.fy:.3f}  cx {intr.cx:.3f}  cy {intr.cy:.3f} px "
          f"(std {res.std[0]:.3f} {res.std[1]:.3f} {res.std[2]:.3f} {res.std[3]:.3f})")
    print("distortion k1 k2 p1 p2 k3: " + " ".join(f"{v:.6f}" for v in intr.dist))
    png = args.coverage_png or args.rig.with_name(f"{args.rig.stem}_{args.camera}_coverage.png")
    cv2.imwrite(str(png), coverage_image(res.coverage, [res.detections[n] for n in res.used], size))
    gaps = ", ".join(f"{g:.0f}" for g in res.coverage.corner_gap_px)
    print(f"coverage {100 * res.coverage.fraction:.0f}% of the image, nearest board corner to the image corners "
          f"(TL, TR, BL, BR) {gaps} px, map in {png}")
    for w in res.coverage.warnings + ((res.refine_note,) if res.refine_note else ()):
        print(f"warning: {w}", file=sys.stderr)
    update_rig_camera(args.rig, args.camera, intrinsics=intr)
    print(f"wrote camera {args.camera!r} intrinsics to {args.rig}")
    if args.sim:
        from .calib.intrinsics import undistortion_error

        true = _sim_rig(args, [args.camera])[args.camera].intrinsics
        mx, rms = undistortion_error(intr, true)
        print(f"against the simulator: fx {100 * (intr.fx / true.fx - 1):+.3f}%  fy {100 * (intr.fy / true.fy - 1):+.3f}%  "
              f"cx {100 * (intr.cx / true.cx - 1):+.3f}%  cy {100 * (intr.cy / true.cy - 1):+.3f}%; "
              f"undistortion map error max {mx:.3f} px, RMS {rms:.3f} px")
    return 0


# -- extrinsics ----------------------------------------------------------------
@_guard
def run_extrinsics(args) -> int:
    from .calib.errors import CalibrationError
    from .calib.extrinsics import calibrate_extrinsics
    from .calib.io import list_images, load_images, lookup_pose, parse_pose, read_pose_csv, update_rig_camera
    from .rig import load_rig
    from .se3 import pose_error

    spec = board_spec(args)
    truth = None
    if args.sim:
        from .sim.board import capture_extrinsics

        _fresh_folder(args.images)

        truth = _sim_rig(args)
        truth = truth.subset([c.name for c in truth if c.is_fixed])
        _seed_rig_intrinsics(args, truth)
        capture_extrinsics(truth, spec, args.images, args.sim_placements, _effects(args), args.seed)
        print(f"simulated capture: {args.sim_placements} placements x {len(truth)} cameras in {args.images}")
    if not args.rig.is_file():
        raise CalibrationError(f"{args.rig}: rig file not found; calibrate the cameras' intrinsics first")
    rig = load_rig(args.rig)
    if not args.images.is_dir():
        raise CalibrationError(f"{args.images}: image folder not found")
    cam_dirs = sorted(d for d in args.images.iterdir() if d.is_dir() and list_images(d))
    if not cam_dirs:
        raise CalibrationError(f"{args.images}: no camera sub-folders with images (expected IMAGES/<camera>/*.png)")
    unknown = [d.name for d in cam_dirs if d.name not in rig.names]
    if unknown:
        raise CalibrationError(f"image folder(s) {unknown} name no camera of {args.rig} ({rig.names})")
    moving = [d.name for d in cam_dirs if not rig[d.name].is_fixed]
    if moving:
        raise CalibrationError(f"camera(s) {moving} ride on the robot (eye_in_hand in {args.rig}): "
                               "calibrate them with 'vespro calibrate hand-eye'")
    dets, t_det = {}, 0.0
    for d in cam_dirs:
        ds, t = _detect_all(load_images(list_images(d)), spec)
        t_det += t
        dets.update({(d.name, p): v for p, v in ds.items()})
    placements = sorted({p for _, p in dets})
    if args.board_pose:
        if len(placements) != 1:
            raise CalibrationError(f"--board-pose gives one placement but the images show {len(placements)} "
                                   f"({placements}); give --board-poses CSV")
        known = {placements[0]: parse_pose(args.board_pose, "--board-pose")}
    else:
        csv = args.board_poses or (args.images / "board_poses.csv")
        poses = read_pose_csv(csv, "placement")
        known = {p: lookup_pose(poses, p) for p in placements if lookup_pose(poses, p) is not None}
    res = calibrate_extrinsics(dets, {c.name: c.intrinsics for c in rig}, known, spec)
    print(f"board: {spec.describe()}; placements {placements} (known: {sorted(known)}), detection {t_det:.2f} s")
    for (c, p), d in sorted(dets.items()):
        state = (f"{len(d):3d} corners, RMS {res.view_rms_px[(c, p)]:.3f} px" if (c, p) in res.view_rms_px else
                 f"rejected as outlier (RMS {res.rejected[(c, p)]:.3f} px)" if (c, p) in res.rejected else
                 "board not found")
        print(f"  {c}/{p}: {state}")
    for c, T in res.T_world_camera.items():
        line = f"{c}: T_world_camera {_fmt_pose(T)}  RMS {res.rms_px[c]:.3f} px"
        if truth is not None and c in truth.names:
            dp, da = pose_error(T, truth[c].T_world_camera)
            line += f"  (vs simulator: {dp * 1e3:.3f} mm, {np.rad2deg(da):.4f} deg)"
        print(line)
        update_rig_camera(args.rig, c, T_world_camera=T)
    print(f"updated {len(res.T_world_camera)} camera pose(s) in {args.rig}")
    return 0


# -- hand-eye --------------------------------------------------------------------
@_guard
def run_hand_eye(args) -> int:
    from .calib.errors import CalibrationError
    from .calib.handeye import calibrate_hand_eye
    from .calib.io import list_images, load_images, lookup_pose, read_pose_csv, update_rig_camera
    from .rig import load_rig
    from .se3 import pose_error

    spec = board_spec(args)
    truth = None
    if args.sim:
        from .sim.board import capture_handeye

        _fresh_folder(args.images)

        truth = _sim_rig(args, [args.camera])
        if args.camera not in truth.names:
            raise SystemExit(f"vespro calibrate: camera {args.camera!r} is not in the simulated rig {args.sim_rig}")
        _seed_rig_intrinsics(args, truth)
        capture_handeye(truth, args.camera, spec, args.images, args.sim_views, args.seed, effects=_effects(args))
        print(f"simulated capture: {args.sim_views} arm poses in {args.images}")
    if not args.rig.is_file():
        raise CalibrationError(f"{args.rig}: rig file not found; calibrate the camera's intrinsics first")
    rig = load_rig(args.rig)
    if args.camera not in rig.names:
        raise CalibrationError(f"{args.rig}: no camera {args.camera!r} (cameras: {rig.names}); calibrate its intrinsics first")
    images = load_images(list_images(args.images))
    poses = read_pose_csv(args.poses or (args.images / "flange_poses.csv"), "index")
    T_base_link = {n: lookup_pose(poses, n) for n in images if lookup_pose(poses, n) is not None}
    dets, t_det = _detect_all(images, spec)
    res = calibrate_hand_eye(T_base_link, dets, rig[args.camera].intrinsics, spec, min_views=args.min_views)
    print(f"board: {spec.describe()}; {len(res.used)} views used, board not found in {list(res.failed) or 'none'}; "
          f"detection {t_det:.2f} s")
    print(f"{'method':22s} {'spread mm':>9s} {'spread deg':>10s} {'RMS px':>8s}" + ("  vs simulator" if truth else ""))
    for name, c in res.candidates.items():
        line = f"{c.method:22s} {c.spread_m * 1e3:9.3f} {np.rad2deg(c.spread_rad):10.4f} {c.rms_px:8.3f}"
        if truth is not None:
            dp, da = pose_error(c.T_link_camera, truth[args.camera].T_link_camera)
            line += f"  {dp * 1e3:.3f} mm {np.rad2deg(da):.4f} deg"
        print(line)
    print(f"chosen: {res.best.method}; T_{args.link}_camera {_fmt_pose(res.best.T_link_camera)}")
    print(f"board in the world: {_fmt_pose(res.best.T_base_board)}")
    update_rig_camera(args.rig, args.camera, link=args.link, T_link_camera=res.best.T_link_camera)
    print(f"wrote camera {args.camera!r} mounting (eye_in_hand on {args.link}) to {args.rig}")
    return 0
