"""A cluttered, textured background for the simulated cell.

:func:`add_clutter` adds ``n`` static, textured items around the working area,
seeded: a pattern on the belt under the part's path (the first item),
upright panels behind the belt (what the fixed cameras see behind the part),
low boxes and flat patches on the floor around the conveyor. Each item has its
own small grey texture (:mod:`vespro.sim.textures`) at its own scale, so the
images hold edges of every length and contrast near the part. The belt item
prints a pattern on the belt itself (no extra geometry, nothing for the part
to sink into). Items stay out
of the fixed cameras' lines of sight to the working area: they are behind or
below it, never in front of it.
"""

from __future__ import annotations

import mujoco
import numpy as np

from ..camera import project_points
from ..se3 import invert_transform
from .scene import BELT_CENTER_X
from .textures import add_texture, grey_pattern

__all__ = ["add_clutter", "CLUTTER_KINDS"]

#: Kinds of items, in the order they are added (then cycled).
CLUTTER_KINDS = ("belt", "panel", "floor_box", "floor_patch")


def _item(rng: np.random.Generator, kind: str) -> tuple[list, list, float]:
    """(half sizes, centre, yaw) of one item of ``kind``."""
    if kind == "panel":  # upright, behind the belt as the fixed cameras see it
        half = [rng.uniform(0.005, 0.02), rng.uniform(0.08, 0.22), rng.uniform(0.25, 0.45)]
        return half, [rng.uniform(0.45, 0.68), rng.uniform(-0.45, 0.45), half[2]], rng.uniform(-0.5, 0.5)
    if kind == "floor_box":  # low, beside the conveyor
        half = [rng.uniform(0.04, 0.12), rng.uniform(0.04, 0.12), rng.uniform(0.04, 0.18)]
        side = rng.choice([-1.0, 1.0])
        x = BELT_CENTER_X + side * rng.uniform(0.28, 0.45) if rng.random() < 0.5 else rng.uniform(0.45, 0.65)
        return half, [x, rng.uniform(-0.6, 0.6), half[2]], rng.uniform(-np.pi, np.pi)
    if kind == "floor_patch":
        half = [rng.uniform(0.10, 0.30), rng.uniform(0.10, 0.30), 0.001]
        x = rng.uniform(0.35, 0.70) if rng.random() < 0.5 else rng.uniform(1.12, 1.45)
        return half, [x, rng.uniform(-0.7, 0.7), 0.002], rng.uniform(-np.pi, np.pi)
    raise ValueError(f"unknown clutter kind {kind!r}")


def _seen(rig, p: np.ndarray) -> bool:
    """Whether a world point is well inside the image of some fixed camera of the rig (any, without a rig)."""
    if rig is None or not any(c.is_fixed for c in rig):
        return True
    for cam in rig:
        if cam.is_fixed:
            uv, z = project_points(cam.intrinsics, invert_transform(cam.T_world_camera), p[None])
            w, h = cam.intrinsics.width, cam.intrinsics.height
            if z[0] > 0 and 0.1 * w <= uv[0, 0] < 0.9 * w and 0.1 * h <= uv[0, 1] < 0.9 * h:
                return True
    return False


def add_clutter(s: mujoco.MjSpec, n: int, seed: int = 0, rig=None) -> None:
    """Add ``n`` textured items to the cell (see the module docstring).

    Parameters
    ----------
    s : mujoco.MjSpec
    n : int
        Number of items (0: none).
    seed : int
        Sizes, places, greys and patterns.
    rig : Rig, optional
        Items are placed where some fixed camera sees them (the belt is always seen).
    """
    if n < 0:
        raise ValueError(f"clutter must be a count >= 0, got {n}")
    rng = np.random.default_rng([seed, 7103])
    for i in range(n):
        kind = CLUTTER_KINDS[0 if i == 0 else 1 + (i - 1) % (len(CLUTTER_KINDS) - 1)]
        if kind == "belt":  # dark, like a worn belt with marks on it
            s.geom("belt").material = add_texture(s, f"clutter_{i}", grey_pattern(rng, mean=0.22, spread=0.18,
                                                                                  n_marks=40),
                                                  per_metre=rng.uniform(2.0, 4.0))
            continue
        for _ in range(200):
            half, pos, yaw = _item(rng, kind)
            if _seen(rig, np.array(pos) + [0.0, 0.0, half[2]]):
                break
        mat = add_texture(s, f"clutter_{i}", grey_pattern(rng, mean=rng.uniform(0.25, 0.75), n_marks=30),
                          per_metre=rng.uniform(4.0, 8.0))
        s.worldbody.add_geom(name=f"clutter_{i}", type=mujoco.mjtGeom.mjGEOM_BOX, size=half, pos=pos,
                             quat=[np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)], material=mat,
                             contype=0, conaffinity=0)
