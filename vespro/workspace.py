"""The cell's working volume: where the part can be, as its user states it.

A box of the world frame, ``(x0, y0, z0, x1, y1, z1)`` in metres, that holds the
part's centre (of its bounding box) whenever the cameras should find it: the
stretch of conveyor they watch, the bin. It is the prior over poses: the
initialiser's search keeps no hypothesis outside it, and the hypothesis bank
holds none (:mod:`vespro.bank`). Without one, any pose in the cameras' view is
possible.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError

__all__ = ["parse_workspace", "check_workspace", "centres_inside", "box_centre"]


def check_workspace(w) -> tuple:
    """``w`` as six floats; ValueError naming what is expected when it is not a box."""
    a = np.asarray(w, float).ravel() if w is not None else np.zeros(0)
    if a.shape != (6,) or not np.all(np.isfinite(a)) or np.any(a[3:] <= a[:3]):
        raise ValueError(f"workspace must be six numbers x0,y0,z0,x1,y1,z1 (m) with x1 > x0, y1 > y0, z1 > z0, "
                         f"got {w!r}")
    return tuple(float(v) for v in a)


def parse_workspace(text: str | None) -> tuple | None:
    """``--workspace x0,y0,z0,x1,y1,z1`` as six floats (None when not given); bad text raises
    :class:`vespro.errors.InputError` with one line saying what is expected."""
    if text is None:
        return None
    try:
        return check_workspace([float(v) for v in text.split(",")])
    except ValueError:
        raise InputError(f"--workspace: expected six numbers x0,y0,z0,x1,y1,z1 in metres with x1 > x0, y1 > y0 "
                         f"and z1 > z0 (the working volume's corners, world frame), got {text!r}") from None


def box_centre(vertices: np.ndarray) -> np.ndarray:
    """The centre of a part's bounding box, object frame (3,)."""
    v = np.asarray(vertices, float)
    return 0.5 * (v.min(axis=0) + v.max(axis=0))


def centres_inside(R_world_object: np.ndarray, t_world_object: np.ndarray, centre: np.ndarray,
                   workspace: tuple | None) -> np.ndarray:
    """Whether each pose (rotations (N, 3, 3), translations (N, 3)) puts ``centre`` in the
    working volume: bool (N,), all True without one."""
    R = np.asarray(R_world_object, float).reshape(-1, 3, 3)
    t = np.asarray(t_world_object, float).reshape(-1, 3)
    if workspace is None:
        return np.ones(len(R), bool)
    c = R @ np.asarray(centre, float) + t
    w = np.asarray(workspace, float)
    return np.all((c >= w[:3]) & (c <= w[3:]), axis=1)
