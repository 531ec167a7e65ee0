"""``vespro import``: bring another tool's data in as a recording."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub) -> None:
    from .options import add_model_unit_option

    p = sub.add_parser("import", help="bring another tool's data in as a recording (ViSP)",
                       description="Convert another tool's data into a recording (shared/spec/recording.md).")
    subs = p.add_subparsers(dest="import_command", metavar="FORMAT")
    v = subs.add_parser(
        "visp", help="a ViSP model-based tracking folder -> recording",
        description="A ViSP tutorial folder (image sequence NAME/, model NAME.cao, camera NAME.xml, optional "
                    "start pose NAME.0.pos) becomes a recording with one fixed camera cam0 whose frame is the "
                    "world frame; the start pose (ViSP's cMo) is written to init_pose.txt for --init-pose.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    v.add_argument("folder", type=Path, help="ViSP folder, e.g. /usr/share/visp-images-data/ViSP-images/mbt")
    v.add_argument("-o", "--out", type=Path, help="recording folder to create (default: out/NAME)")
    v.add_argument("--name", help="sequence name: NAME.cao, NAME.xml, NAME/ (default: the folder's only .cao)")
    v.add_argument("--rate", type=float, default=30.0, help="capture rate to stamp the frames with, Hz")
    v.add_argument("--images", type=Path, help="image sequence folder (default: FOLDER/NAME)")
    v.add_argument("--camera", type=Path, help="ViSP camera .xml (default: FOLDER/NAME.xml)")
    v.add_argument("--pose", type=Path, help="start pose .pos, ViSP cMo (default: FOLDER/NAME.0.pos if present)")
    v.add_argument("--frames", type=int, help="import only the first N images")
    add_model_unit_option(v)
    v.add_argument("--overwrite", action="store_true", help="replace an existing recording folder")
    v.add_argument("--no-progress", action="store_true")
    v.set_defaults(func=run_visp)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def run_visp(args) -> int:
    from .errors import InputError
    from .visp import import_visp

    progress = None
    if not args.no_progress:
        from functools import partial

        from tqdm import tqdm

        progress = partial(tqdm, unit="image", desc="import")
    try:
        res = import_visp(args.folder, args.out, name=args.name, rate_hz=args.rate, images=args.images,
                          camera=args.camera, pose=args.pose, frames=args.frames, unit=args.model_unit,
                          overwrite=args.overwrite, progress=progress)
    except FileExistsError as e:
        raise InputError(f"{e}; pass --overwrite to replace it") from None
    for note in res["notes"]:
        print(f"note: {note}")
    rec = res["recording"]
    print(f"wrote recording {rec} ({res['frames']} frames, camera cam0)")
    if res["init_pose"] is not None:
        print(f"start pose in {res['init_pose']}; track with:")
        print(f"  vespro track {rec} --init-pose {res['init_pose']} -o {rec / 'poses.csv'}")
    else:
        print("no start pose (.0.pos) found; track with the automatic start or give one:")
        print(f"  vespro track {rec} -o {rec / 'poses.csv'}   # or --init-pose x,y,z,qw,qx,qy,qz")
    return 0
