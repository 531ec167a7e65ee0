"""What capture hands to the tracker: one synchronised set of camera frames.

A :class:`FrameSet` carries only what a real cell has at a capture instant: the
images (one per rig camera, ``None`` where an image is missing), the capture
stamp, and the measured pose of each eye-in-hand camera (from the arm's joint
sensors). It never carries ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["FrameSet"]


@dataclass(frozen=True)
class FrameSet:
    """Synchronised frames of every camera at one capture instant.

    Attributes
    ----------
    index : int
        Capture index, from 0.
    t_ns : int
        Capture stamp, ns (simulated or monotonic clock).
    images : dict[str, ndarray | None]
        Per camera name: 8-bit grey (H, W) or BGR (H, W, 3) image, or None if missing.
    T_world_camera : dict[str, ndarray]
        Per eye-in-hand camera name: measured camera pose (4, 4) at this instant.
    """

    index: int
    t_ns: int
    images: dict
    T_world_camera: dict = field(default_factory=dict)

    @property
    def t(self) -> float:
        """Capture time, s."""
        return self.t_ns * 1e-9

    def grey(self, name: str) -> np.ndarray | None:
        """The named camera's image as 8-bit grey, or None if missing."""
        import cv2

        img = self.images.get(name)
        if img is None:
            return None
        return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
