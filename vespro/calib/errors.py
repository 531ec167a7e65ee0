"""The one exception of the calibration package."""

from __future__ import annotations


class CalibrationError(ValueError):
    """Calibration input that cannot give a result: no board found, too few
    views, images of mixed sizes, inconsistent pose files... The message names
    the images or the file and field concerned."""
