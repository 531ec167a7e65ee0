"""Command-line options several commands share, and what they set up.

The model file's unit (``--model-unit``), the tracker's options (``--features``,
``--selection``, ``--decision``, ``--textured``, ``--init-pose``...) and the
symmetry rule (``--symmetry``), with the tracker configuration, the
initialiser's options and the initialiser they give, and the line saying
which rule picks a symmetric part's frame.
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["add_model_unit_option", "add_tracker_options", "add_symmetry_option", "tracker_config",
           "init_options", "initializer_for", "say_symmetry"]


def add_model_unit_option(p: argparse.ArgumentParser) -> None:
    """``--model-unit``: the unit a model file is drawn in (scaled to metres on load)."""
    p.add_argument("--model-unit", choices=["m", "cm", "mm", "in"], default="m",
                   help="unit the model file is drawn in (ViSP .cao models are in metres)")


def add_tracker_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--init-pose", metavar="x,y,z,qw,qx,qy,qz|FILE",
                   help="object pose T_world_object at the first frame (overrides automatic initialisation), "
                        "or a file holding it (e.g. the init_pose.txt that `vespro import` writes)")
    p.add_argument("--features", type=int, default=8, help="features selected per camera and frame")
    p.add_argument("--selection", choices=["information", "quality"], default="quality",
                   help="feature selection: information-greedy (log-det) or the classic quality index")
    p.add_argument("--sigma-px", type=float, default=0.5, help="corner measurement noise std, px")
    p.add_argument("--textured", action="store_true",
                   help="the part's faces carry texture or markings: image edges inside its faces do not count "
                        "against a pose found by one camera (by default faces are taken as plain, as CAD parts "
                        "of one material are; see InitOptions.plain_faces)")
    p.add_argument("--decision", choices=["rules", "bank"], default="rules",
                   help="what decides the published status: the confirmation rules, or the hypothesis bank "
                        "weighing the initialiser's poses by the image likelihood (texture counts as clutter "
                        "there: the initialiser then takes every part as textured)")
    p.add_argument("--workspace", metavar="x0,y0,z0,x1,y1,z1",
                   help="the cell's working volume, world frame, m (the part's centre lies in it: on the conveyor, "
                        "in the bin): the start's search considers no pose outside it, nor does the bank hold one")
    add_symmetry_option(p)


def add_symmetry_option(p: argparse.ArgumentParser) -> None:
    from .symmetry import HELP, RULES

    p.add_argument("--symmetry", choices=RULES, default=RULES[0], help=HELP)


def say_symmetry(prog: str, tracker, given: bool, reacquires: bool) -> None:
    """On stderr: the part is symmetric, and which rule picks its frame (nothing otherwise)."""
    from .symmetry import describe

    line = describe(tracker.model.name, len(tracker.symmetries), tracker.config.symmetry, given, reacquires)
    if line:
        print(f"{prog}: {line}", file=sys.stderr, flush=True)


def workspace_of(args) -> tuple | None:
    """``--workspace`` as six floats, or None; bad text is one line (:class:`vespro.errors.InputError`)."""
    from .workspace import parse_workspace

    return parse_workspace(getattr(args, "workspace", None))


def tracker_config(args):
    from .tracker import TrackerConfig

    workspace_of(args)  # a bad one is refused whether or not a search runs
    return TrackerConfig(features_per_camera=args.features, selection=args.selection, sigma_px=args.sigma_px,
                         decision=getattr(args, "decision", "rules"), symmetry=args.symmetry)


def init_options(args) -> dict:
    """``InitOptions`` fields the command line sets (``--workspace``; ``--textured``; ``--decision bank``: the bank's
    likelihood takes texture inside the faces as clutter, so the plain-face checks stay off)."""
    from .init import decision_options

    return {**decision_options(getattr(args, "decision", "rules"), getattr(args, "textured", False)),
            "workspace": workspace_of(args)}


def initializer_for(args, rec, model):
    """The automatic initialiser, unless --init-pose was given; None when unavailable."""
    if args.init_pose:
        return None
    try:
        from .init import make_initializer
    except ImportError:
        return None
    return make_initializer(rec.rig, model, **init_options(args))
