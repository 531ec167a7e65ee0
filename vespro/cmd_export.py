"""``vespro export``: a run in the formats other tools open (``export mcap``: ROS 2 messages in MCAP)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub) -> None:
    p = sub.add_parser("export", help="write a run in another tool's format (MCAP of ROS 2 messages)",
                       description="Write a recorded run in a format other tools open.")
    fmt = p.add_subparsers(dest="format", metavar="FORMAT", required=True)
    m = fmt.add_parser(
        "mcap", help="ROS 2 messages in an MCAP file (Foxglove, Rerun, ros2 bag)",
        description=(
            "Write a recording as ROS 2 messages in an MCAP file: each camera's images (sensor_msgs/Image) "
            "and calibration (sensor_msgs/CameraInfo), the cameras and the part on /tf and /tf_static, the "
            "tracker's poses with covariance (geometry_msgs/PoseWithCovarianceStamped, covariance in ROS "
            "order: x y z, then rotation about the world X Y Z axes), its velocity and status, and the servo's "
            "time histories. Stamps are the recording's capture times. Needs pip install 'vespro[interop]'."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    m.add_argument("recording", type=Path, help="the recording folder")
    m.add_argument("--poses", type=Path, help="the tracker's poses.csv of this recording")
    m.add_argument("--servo", type=Path, metavar="DIR", help="the folder of 'servo run --record DIR' (servo.npz)")
    m.add_argument("--servo-t0-ns", type=int, metavar="NS",
                   help="with --servo: the clock's stamp of the recording's first frame set "
                        "(default: t0_ns of server.json beside the recording)")
    m.add_argument("-o", "--out", type=Path, required=True, help="the .mcap file to write")
    m.set_defaults(func=run_mcap)


def run_mcap(args) -> int:
    from .mcap_export import export_mcap

    counts = export_mcap(args.recording, args.out, poses=args.poses, servo=args.servo, servo_t0_ns=args.servo_t0_ns)
    width = max(map(len, counts), default=0)
    for topic, n in counts.items():
        print(f"  {topic:<{width}}  {n}")
    print(f"vespro export: wrote {args.out} ({sum(counts.values())} messages on {len(counts)} topics)")
    return 0
