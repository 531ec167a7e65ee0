"""Other objects in view of the cameras: distractors that are not the tracked part.

Kinds:

- ``near``: the part's own mesh scaled in height by :data:`NEAR_HEIGHT_SCALE`
  (the same footprint, a different height): the object the tracker must not
  take for the part;
- ``block``, ``cylinder``: a plain box or cylinder of random size;
- a library object name (``box``, ``lblock``, ``bracket``): another part.

Each rests upright on the belt (or, off the belt, on a plain plinth as high as
the belt) beside the part's path, at the place nearest to that path that keeps
clear of it and lies fully in view of every fixed camera
(:func:`place_distractors`); static, or carried along the belt with the part.
A distractor's frame is the frame its shape is drawn in (for ``near`` the
part's CAD frame, so the part's model drawn at the distractor's pose covers its
footprint). Its poses are known to evaluators only (``distractors.csv``,
:mod:`vespro.groundtruth`); the tracker sees it only in the images.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from ..camera import project_points
from ..rig import Rig
from ..se3 import exp_so3, invert_transform, transform_from_rt
from .scene import BELT_CENTER_X, BELT_TOP_Z

__all__ = ["Distractor", "DISTRACTOR_KINDS", "NEAR_HEIGHT_SCALE", "DISTRACTOR_MOTIONS", "place_distractors",
           "add_distractors"]

NEAR_HEIGHT_SCALE = 0.7
DISTRACTOR_KINDS = ("near", "block", "cylinder", "box", "lblock", "bracket")
DISTRACTOR_MOTIONS = ("static", "belt")
BELT_HALF_WIDTH = 0.17
RAIL_OUTER = 0.205  # the belt's rails reach this far from its centre line (m)
CLEARANCE = 0.02  # between the part's and a distractor's footprints, m
VIEW_MARGIN = 0.04  # fraction of the image kept clear at the borders


@dataclass(frozen=True)
class Distractor:
    """One distractor: its shape and its trajectory.

    Attributes
    ----------
    name : str
        MuJoCo body name (``distractor_<i>``).
    kind : str
    mesh : Path or None
        Mesh file of the mesh kinds (drawn with ``scale``).
    scale : tuple
        Mesh scale per axis.
    half : tuple
        Box half sizes (block) or (radius, radius, half height) (cylinder), m.
    lo, hi : ndarray (3,)
        Bounds of the shape in its frame, m.
    T0 : ndarray (4, 4)
        ``T_world_distractor`` at t = 0.
    belt : Conveyor or None
        Carried along +y by this belt (its ``travel(t)``, speed changes and stop included); static if None.
    plinth : bool
        Stands on a plinth beside the belt.
    """

    name: str
    kind: str
    mesh: Path | None
    scale: tuple
    half: tuple
    lo: np.ndarray
    hi: np.ndarray
    T0: np.ndarray
    belt: object = None
    plinth: bool = False

    def pose(self, t: float) -> np.ndarray:
        """``T_world_distractor`` at time ``t`` (s)."""
        T = np.array(self.T0, dtype=float)
        if self.belt is not None:
            T[1, 3] += self.belt.travel(t)
        return T

    @property
    def center(self) -> np.ndarray:
        """Centre of the shape's bounds in its own frame, m."""
        return 0.5 * (np.asarray(self.lo) + np.asarray(self.hi))

    @property
    def radius(self) -> float:
        """Horizontal radius of the footprint about the frame's z axis, m."""
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        return float(np.hypot(max(-lo[0], hi[0]), max(-lo[1], hi[1])))

    def corners(self) -> np.ndarray:
        lo, hi = np.asarray(self.lo), np.asarray(self.hi)
        return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def _shape(kind: str, part_mesh: Path, rng: np.random.Generator):
    """(mesh, scale, half, lo, hi) of a kind."""
    import trimesh

    if kind in ("near", "box", "lblock", "bracket"):
        if kind == "near":
            mesh, scale = Path(part_mesh), (1.0, 1.0, NEAR_HEIGHT_SCALE)
        else:
            from ..library import object_mesh_path

            mesh, scale = object_mesh_path(kind), (1.0, 1.0, 1.0)
        b = trimesh.load(str(mesh), force="mesh").bounds * np.asarray(scale)
        return mesh, scale, (), b[0], b[1]
    if kind == "block":
        half = tuple(rng.uniform(0.02, 0.05, 3))
        return None, (1.0, 1.0, 1.0), half, np.array([-half[0], -half[1], 0.0]), np.array([half[0], half[1], 2 * half[2]])
    if kind == "cylinder":
        r, hz = rng.uniform(0.02, 0.045), rng.uniform(0.02, 0.05)
        return None, (1.0, 1.0, 1.0), (r, r, hz), np.array([-r, -r, 0.0]), np.array([r, r, 2 * hz])
    raise ValueError(f"unknown distractor {kind!r}; choose from {', '.join(DISTRACTOR_KINDS)}")


def _in_view(rig: Rig, pts_world: np.ndarray) -> bool:
    """Every point in front of every fixed camera and inside its image (with a margin)."""
    for cam in rig:
        if not cam.is_fixed:
            continue
        intr = cam.intrinsics
        uv, z = project_points(intr, invert_transform(cam.T_world_camera), pts_world)
        mx, my = VIEW_MARGIN * intr.width, VIEW_MARGIN * intr.height
        if not (np.all(z > 0) and np.all((uv[:, 0] >= mx) & (uv[:, 0] <= intr.width - 1 - mx)
                                         & (uv[:, 1] >= my) & (uv[:, 1] <= intr.height - 1 - my))):
            return False
    return True


def place_distractors(kinds, part_mesh: Path, rig: Rig, times: np.ndarray, part_poses: np.ndarray,
                      part_radius: float, motion: str = "static", belt=None,
                      seed: int = 0) -> tuple[Distractor, ...]:
    """Distractors of the given kinds, placed beside the part's path (see the module docstring).

    Parameters
    ----------
    kinds : sequence of str
    part_mesh : Path
        The tracked part's mesh (for ``near``).
    rig : Rig
        Only its fixed cameras are used (a distractor lies in view of each).
    times : ndarray (N,)
        Capture times, s.
    part_poses : ndarray (N, 4, 4)
        The part's ``T_world_object`` at those times.
    part_radius : float
        Radius of a ball about the part's frame origin holding the part, m.
    motion : str
        ``static`` or ``belt`` (carried along +y by ``belt``, the part's :class:`~vespro.sim.motion.Conveyor`).
    belt : Conveyor, optional
    seed : int

    Raises
    ------
    ValueError
        Unknown kind or motion, or no place in view of every fixed camera.
    """
    if motion not in DISTRACTOR_MOTIONS:
        raise ValueError(f"distractor motion must be one of {', '.join(DISTRACTOR_MOTIONS)}, got {motion!r}")
    if motion == "belt" and belt is None:
        raise ValueError("distractors riding the belt need the part on the belt (conveyor motion)")
    rng = np.random.default_rng([seed, 4409])
    belt = belt if motion == "belt" else None
    times = np.asarray(times, float)
    path = np.asarray(part_poses)[:, :3, 3]
    # Part centre track: frame origin plus a ball; sampled sparsely (enough for clearance).
    step = max(1, len(times) // 40)
    ts, ps = times[::step], path[::step]
    travel = np.zeros((len(ts), 3))
    if belt is not None:
        travel[:, 1] = [belt.travel(x) for x in ts]
    placed: list[Distractor] = []
    tracks: list[np.ndarray] = []
    xs = np.arange(BELT_CENTER_X - 0.40, BELT_CENTER_X + 0.40 + 1e-9, 0.02)
    ys = np.arange(-0.50, 0.50 + 1e-9, 0.02)
    for i, kind in enumerate(kinds):
        mesh, scale, half, lo, hi = _shape(kind, part_mesh, rng)
        yaw = rng.uniform(-np.pi, np.pi)
        R = exp_so3([0.0, 0.0, yaw])
        proto = Distractor(f"distractor_{i}", kind, mesh, scale, half, np.asarray(lo), np.asarray(hi), np.eye(4), belt)
        r = proto.radius
        corners = proto.corners() @ R.T
        best = None
        for x in xs:
            off = abs(x - BELT_CENTER_X)
            on_belt = off + r <= BELT_HALF_WIDTH - 0.005
            if not on_belt and (off - r - 0.01 < RAIL_OUTER or motion == "belt"):
                continue
            for y in ys:
                p0 = np.array([x, y, BELT_TOP_Z])
                track = p0 + travel
                clear = np.min(np.hypot(*(track[:, :2] - ps[:, :2]).T)) - r - part_radius
                for d, dt in zip(placed, tracks):
                    clear = min(clear, np.min(np.hypot(*(track[:, :2] - dt[:, :2]).T)) - r - d.radius)
                if clear < CLEARANCE:
                    continue
                cost = clear + (0.0 if on_belt else 0.05) + 1e-4 * rng.random()
                if best is not None and cost >= best[0]:
                    continue
                pts = (corners[None] + track[[0, -1], None, :]).reshape(-1, 3)
                if _in_view(rig, pts):
                    best = (cost, p0, on_belt)
        if best is None:
            raise ValueError(f"no place for distractor {kind!r} beside the part's path in view of every fixed camera")
        _, p0, on_belt = best
        placed.append(Distractor(f"distractor_{i}", kind, mesh, scale, half, np.asarray(lo), np.asarray(hi),
                                 transform_from_rt(R, p0), belt, plinth=not on_belt))
        tracks.append(p0 + travel)
    return tuple(placed)


def add_distractors(s: mujoco.MjSpec, distractors, rgba=(0.60, 0.62, 0.66, 1.0)) -> None:
    """Add each distractor as a mocap body (named ``d.name``) at its t = 0 pose, plinths as static boxes.

    Distractors share the part's colour: only their shape tells them apart.
    """
    from ..se3 import quat_from_matrix

    if not distractors:
        return
    mat = s.add_material(name="distractor_mat")
    mat.rgba = list(rgba)
    mat.specular = 0.35
    mat.shininess = 0.4
    for d in distractors:
        body = s.worldbody.add_body(name=d.name, mocap=True, pos=d.T0[:3, 3].tolist(),
                                    quat=quat_from_matrix(d.T0[:3, :3]).tolist())
        kw = dict(material="distractor_mat", contype=0, conaffinity=0, group=2)
        if d.mesh is not None:
            s.add_mesh(name=f"{d.name}_mesh", file=str(d.mesh), scale=list(d.scale))
            body.add_geom(name=f"{d.name}_geom", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{d.name}_mesh", **kw)
        elif d.kind == "block":
            body.add_geom(name=f"{d.name}_geom", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(d.half),
                          pos=[0, 0, d.half[2]], **kw)
        else:
            body.add_geom(name=f"{d.name}_geom", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[d.half[0], d.half[2], 0],
                          pos=[0, 0, d.half[2]], **kw)
        if d.plinth and d.belt is None:
            h = 0.5 * BELT_TOP_Z
            p = d.T0[:3, 3]
            s.worldbody.add_geom(name=f"{d.name}_plinth", type=mujoco.mjtGeom.mjGEOM_BOX,
                                 size=[d.radius + 0.01, d.radius + 0.01, h - 0.0005], pos=[p[0], p[1], h - 0.0005],
                                 material="frame_mat", contype=0, conaffinity=0)
