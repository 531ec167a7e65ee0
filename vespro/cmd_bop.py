"""``vespro bop``: export a recording to the BOP dataset format, or import one back."""

from __future__ import annotations

import sys
from pathlib import Path


def add_parser(sub) -> None:
    p = sub.add_parser(
        "bop", help="export a recording to the BOP format / import a BOP scene",
        description="Interchange with the BOP benchmark (bop.felk.cvut.cz): one BOP scene per camera, "
                    "poses in mm, the model as obj_000001.ply with models_info.json (diameter, symmetries), "
                    "tracker estimates as a BOP19 results CSV.",
    )
    bs = p.add_subparsers(dest="bop_command", metavar="ACTION")
    e = bs.add_parser("export", help="recording (+ poses.csv) -> BOP dataset folder",
                      description="Write a recording as a BOP dataset: one scene per camera.",
                      epilog="Bad input: a malformed recording file stops the export with one line naming the "
                             "file and field, exit status 2. Images that cannot be used (missing, truncated, "
                             "unreadable, not 8-bit, of another size than cameras.yaml gives) are not copied; one "
                             "line per camera at the end counts them, a camera without any usable image is named "
                             "in a warning, and when no camera has one the exit status is 2. Frames whose "
                             "ground-truth pose is not finite are left out of scene_gt.json (a warning names them).")
    e.add_argument("recording", type=Path)
    e.add_argument("out", type=Path, help="BOP dataset folder to create")
    e.add_argument("--poses", type=Path, help="tracker output poses.csv -> vespro_<object>-test.csv")
    e.add_argument("--overwrite", action="store_true")
    e.set_defaults(func=run_export)
    i = bs.add_parser("import", help="BOP dataset or scene folder -> recording (+ groundtruth.csv, poses.csv)")
    i.add_argument("bopdir", type=Path)
    i.add_argument("out", type=Path, help="recording folder to create")
    i.add_argument("--results", type=Path, help="BOP19 results CSV to import as poses.csv")
    i.add_argument("--obj-id", type=int, help="object id (default: the export's, else 1)")
    i.add_argument("--rate", type=float, default=26.0, help="capture rate when the dataset gives no times, Hz")
    i.add_argument("--overwrite", action="store_true")
    i.set_defaults(func=run_import)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def run_export(args) -> int:
    from .bop import export_bop
    from .errors import warn
    from .recording_report import open_recording, report_images

    try:  # bad input (InputError is a ValueError) in one line
        rec = open_recording(args.recording, "bop export")
        out = export_bop(rec, args.out, args.poses, overwrite=args.overwrite,
                         warn=lambda w: warn("bop export", f"warning: {w}"))
        print(f"wrote BOP dataset {out}", flush=True)
        report_images(rec, "bop export")
    except (FileExistsError, FileNotFoundError, ValueError) as e:
        print(f"vespro bop export: {e}", file=sys.stderr)
        return 2
    return 0


def run_import(args) -> int:
    from .bop import import_bop

    try:
        res = import_bop(args.bopdir, args.out, args.results, args.obj_id, args.rate, overwrite=args.overwrite)
    except (FileExistsError, FileNotFoundError, ValueError, KeyError) as e:
        print(f"vespro bop import: {e}", file=sys.stderr)
        return 2
    extra = [x for x, v in (("groundtruth.csv", res["T_true"]), ("poses.csv", res["T_est"])) if v is not None]
    print(f"wrote recording {res['recording']} ({len(res['im_ids'])} frames{', ' if extra else ''}{', '.join(extra)})")
    return 0
