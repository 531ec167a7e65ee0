"""Camera calibration: intrinsics, fixed-camera extrinsics and hand-eye.

Pure functions on detections and poses live in :mod:`.intrinsics`,
:mod:`.extrinsics` and :mod:`.handeye` (with the AX = XB solvers in
:mod:`.axxb` and single-view board pose in :mod:`.pose`); board definitions and
detection in :mod:`.board`; corners re-located on the board plane through a
calibration (and ChArUco corners the detector missed) in :mod:`.refine`; reading image folders, pose files and updating rig
files in :mod:`.io`. ``vespro calibrate`` (:mod:`vespro.cmd_calibrate`) is the thin
command-line layer over them.

Board frame (every board): origin at the outer corner of square (0, 0) (the
top-left square of the printed pattern, black), x along the ``squares_x``
direction, y along ``squares_y`` (down the printed page), z = x cross y, into
the board (away from a viewer of the printed face). OpenCV's ChArUco boards use
the same frame.
"""

from .errors import CalibrationError

__all__ = ["CalibrationError"]
