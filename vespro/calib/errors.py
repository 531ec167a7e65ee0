"""The one exception of the calibration package."""

from __future__ import annotations

from ..errors import InputError


class CalibrationError(InputError):
    """Calibration input that cannot give a result: no board found, too few
    views, images of mixed sizes, inconsistent pose files... The message names
    the images or the file and field concerned."""
