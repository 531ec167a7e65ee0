"""A simulated scenario from command-line options: the options, their parsers, the cell they configure.

``vespro record``, ``vespro serve`` (sim and world sources) and the accuracy suites
(:mod:`vespro.suite`) describe a scenario with the same options; :func:`build_config`
turns them into the cell's configuration, its motion and the object's name.
"""

from __future__ import annotations

import argparse

import numpy as np

from ..options import add_model_unit_option

__all__ = ["DEFAULT_DISTORTION", "parse_resolution", "parse_dropout", "parse_count", "parse_distortion",
           "add_scenario_options", "build_config"]

DEFAULT_DISTORTION = (-0.22, 0.09, 0.0006, -0.0004, -0.015)


def parse_resolution(s: str) -> tuple[int, int]:
    """``--resolution``: ``WxH`` (640x480) as (width, height)."""
    try:
        w, h = (int(x) for x in s.lower().split("x"))
        assert w > 0 and h > 0
    except (ValueError, AssertionError):
        raise argparse.ArgumentTypeError(f"resolution must look like 640x480, got {s!r}") from None
    return w, h


def parse_dropout(s: str):
    """``--drop``: ``CAMERA:T0:T1`` (seconds) as a camera dropout."""
    from .cell import CameraDropout

    try:
        cam, t0, t1 = s.split(":")
        return CameraDropout(cam, float(t0), float(t1))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--drop takes CAMERA:T0:T1 (seconds), got {s!r}") from None


def parse_count(s: str) -> int:
    """A count >= 0 (``--clutter``)."""
    try:
        n = int(s)
        assert n >= 0
    except (ValueError, AssertionError):
        raise argparse.ArgumentTypeError(f"expected a count >= 0, got {s!r}") from None
    return n


def parse_distortion(s: str):
    """``--distortion-coeffs``: ``k1,k2,p1,p2,k3`` as a tuple."""
    try:
        v = tuple(float(x) for x in s.split(","))
        assert len(v) == 5
    except (ValueError, AssertionError):
        raise argparse.ArgumentTypeError(f"--distortion-coeffs takes k1,k2,p1,p2,k3, got {s!r}") from None
    return v


def add_scenario_options(p: argparse.ArgumentParser, rate_default: float | None = 26.0) -> None:
    """Options describing a simulated scenario (shared by record, serve, demo).

    ``rate_default=None`` (serve): ``--rate`` unset means a camera's own rate, 26 Hz otherwise.
    """
    p.add_argument("--object", default="bracket",
                   help="object name in models/objects (box, lblock, bracket) or a model file (STL, OBJ, PLY, ViSP .cao)")
    add_model_unit_option(p)
    p.add_argument("--rig", default="fixed2", help="standard rig in cameras/ (fixed1, fixed2, fixed3, hand, hybrid) or a cameras.yaml path")
    p.add_argument("--motion", default="conveyor", choices=["conveyor", "sinusoid", "random", "static"],
                   help="conveyor: on the belt; sinusoid: free 6-DoF sinusoids; random: random smooth 6-DoF; static")
    p.add_argument("--rate", type=float, default=rate_default,
                   help="capture rate, Hz" + ("" if rate_default is not None else
                                              "; unset (%(default)s): a camera stream's own rate, 26 for the simulated cell"))
    p.add_argument("--resolution", type=parse_resolution, help="image size WxH (scales the rig's intrinsics)")
    p.add_argument("--speed", type=float, help="belt speed in m/s (conveyor, default 0.1) or frequency scale of free motions (default 1)")
    p.add_argument("--amplitude", type=float, help="free motions: position amplitude per axis, m (default 0.05)")
    p.add_argument("--rot-amplitude-deg", type=float, help="free motions: rotation amplitude per axis, degrees (default 17)")
    p.add_argument("--stop-time", type=float, help="conveyor: time (s) at which the belt stops smoothly")
    p.add_argument("--noise", type=float, default=0.0, metavar="SIGMA_PX",
                   help="geometric pixel noise: std (px) of a smooth random displacement of image features")
    p.add_argument("--intensity-noise", type=float, default=0.0, metavar="SIGMA", help="sensor noise, grey levels")
    p.add_argument("--blur", type=float, default=0.0, metavar="SIGMA_PX", help="Gaussian blur sigma, px")
    p.add_argument("--distortion", action="store_true",
                   help=f"give every camera plumb_bob lens distortion {DEFAULT_DISTORTION} (written to cameras.yaml, applied to images)")
    p.add_argument("--distortion-coeffs", type=parse_distortion, help="with --distortion: k1,k2,p1,p2,k3")
    p.add_argument("--occluder", action="store_true",
                   help="a paddle passes in front of the first fixed camera for 1.5 s from 40%% of the run")
    p.add_argument("--drop", type=parse_dropout, action="append", default=[], metavar="CAM:T0:T1",
                   help="no images from CAM between T0 and T1 seconds (repeatable)")
    p.add_argument("--render-samples", type=int, default=4,
                   help="render multisampling (anti-aliasing); 0 halves render time (use a little --blur)")
    p.add_argument("--mono", action="store_true",
                   help="monochrome cameras: 8-bit grey images (a third of the imaging and writing work)")
    p.add_argument("--arm", default="home", choices=["home", "watch"],
                   help="home: arm parked; watch: flange hovers over the working area (eye-in-hand view)")
    p.add_argument("--encoder-noise", type=float, default=0.0, help="joint sensor noise, rad")
    p.add_argument("--clutter", type=parse_count, default=0, metavar="N",
                   help="N textured items in the background (a pattern on the belt, panels behind it, boxes and "
                        "patches on the floor), placed by --seed")
    p.add_argument("--distractor", action="append", default=[], metavar="KIND",
                   help="another object in view of every fixed camera, beside the part's path (repeatable): "
                        "near (the part's footprint, 70%% of its height), block, cylinder, or a part "
                        "(box, lblock, bracket); its poses go to distractors.csv (evaluators only)")
    p.add_argument("--distractor-motion", choices=["static", "belt"], default="static",
                   help="distractors stand still, or ride the belt beside the part (conveyor motion)")
    p.add_argument("--textured-part", action="store_true", help="grey patterns printed on the part's faces")
    p.add_argument("--seed", type=int, default=0, help="random seed (noise, random motion, clutter, distractors)")


def build_config(args) -> tuple:
    """Cell configuration, motion and object name from parsed arguments."""
    from ..camera import CameraIntrinsics
    from ..library import object_mesh_path
    from ..rig import Rig, RigCamera, load_rig
    from .cell import CellConfig, OccluderSweep
    from .imaging import ImageEffects
    from .motion import make_motion
    from .rigs import rig_path

    mesh = object_mesh_path(args.object, getattr(args, "model_unit", "m"))
    rig = load_rig(rig_path(args.rig))
    cams = []
    for c in rig:
        intr = c.intrinsics
        if args.resolution:
            intr = intr.scaled(args.resolution[0] / intr.width)
            if intr.height != args.resolution[1]:
                raise ValueError(f"resolution {args.resolution} does not keep the aspect ratio of camera {c.name}")
        if args.distortion:
            intr = CameraIntrinsics(intr.width, intr.height, intr.K, args.distortion_coeffs or DEFAULT_DISTORTION)
        cams.append(RigCamera(c.name, intr, c.mount, c.T_world_camera, c.link, c.T_link_camera))
    rig = Rig(tuple(cams))
    if any(not c.is_fixed for c in rig) and args.arm == "home":
        args.arm = "watch"  # an eye-in-hand camera on a parked arm sees nothing useful
    duration = getattr(args, "frames", None) or 78
    duration = duration / args.rate
    occluders = ()
    if args.occluder:
        fixed = [c.name for c in rig if c.is_fixed]
        if not fixed:
            raise ValueError("--occluder needs a fixed camera in the rig")
        occluders = (OccluderSweep(fixed[0], 0.4 * duration, min(1.5, 0.5 * duration)),)
    rot = None if args.rot_amplitude_deg is None else float(np.deg2rad(args.rot_amplitude_deg))
    motion = make_motion(args.motion, speed=args.speed, amplitude=args.amplitude, rot_amplitude=rot,
                         seed=args.seed, stop_time=args.stop_time)
    n_frames = getattr(args, "frames", None) or 78
    times = np.arange(n_frames) / args.rate
    path = np.array([motion.pose(t) for t in times])
    distractors = ()
    if getattr(args, "distractor", None):
        import trimesh

        from .distractors import place_distractors

        radius = float(np.max(np.linalg.norm(trimesh.load(str(mesh), force="mesh").vertices, axis=1)))
        if args.distractor_motion == "belt" and args.motion != "conveyor":
            raise ValueError("--distractor-motion belt needs --motion conveyor")
        distractors = place_distractors(args.distractor, mesh, rig, times, path, radius,
                                        args.distractor_motion, motion if args.motion == "conveyor" else None,
                                        args.seed)
    config = CellConfig(
        object_mesh=mesh, rig=rig, rate_hz=args.rate,
        effects=ImageEffects(noise_px=args.noise, intensity_noise=args.intensity_noise, blur_px=args.blur),
        arm=args.arm, encoder_noise=args.encoder_noise, occluders=occluders, dropouts=tuple(args.drop),
        seed=args.seed, render_samples=getattr(args, "render_samples", 4), mono=getattr(args, "mono", False),
        clutter=getattr(args, "clutter", 0), distractors=distractors,
        textured_part=getattr(args, "textured_part", False),
    )
    return config, motion, mesh.stem
