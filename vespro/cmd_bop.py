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
    e = bs.add_parser("export", help="recording (+ poses.csv) -> BOP dataset folder")
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
    from .recording import RecordingError

    try:
        out = export_bop(args.recording, args.out, args.poses, overwrite=args.overwrite)
    except (RecordingError, FileExistsError, FileNotFoundError, ValueError) as e:
        print(f"vespro bop export: {e}", file=sys.stderr)
        return 2
    print(f"wrote BOP dataset {out}")
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
