"""Random initialisation trials: random start poses and random rigs.

Used by the initialiser's tests and ``bench/init.py``. A trial is a simulated
cell with the object at a random pose in the cameras' common view, drifting
slowly (a random smooth motion about that pose), seen by a random subset of
the standard cameras whose placements may be perturbed. Ground truth comes from
the simulator (:meth:`SimCell.true_object_pose`), for scoring only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..library import object_mesh_path
from ..rig import Rig, RigCamera, load_rig
from ..se3 import exp_so3, transform_from_rt
from .motion import Motion, RandomSmooth, Static
from .rigs import rig_path
from .scene import BELT_TOP_Z

__all__ = ["WORK_CENTER", "random_start_pose", "random_rig", "DriftAbout", "trial_config", "model_symmetries"]

#: Centre of the working area where start poses are drawn, world, m.
WORK_CENTER = np.array([0.90, 0.0, 0.60])


def random_start_pose(vertices: np.ndarray, rng: np.random.Generator, center=WORK_CENTER,
                      half_range=(0.05, 0.08, 0.03), clearance: float = 0.01) -> np.ndarray:
    """A random ``T_world_object`` near ``center``: uniform random orientation,
    position uniform in ``center +- half_range`` (m), then lifted so that the
    lowest model vertex stays ``clearance`` above the belt top.

    Parameters
    ----------
    vertices : ndarray, shape (V, 3)
        Model vertices, object frame, m.
    rng : numpy Generator
    """
    q_xyzw = Rotation.random(random_state=rng).as_quat()
    R = Rotation.from_quat(q_xyzw).as_matrix()
    p = np.asarray(center, float) + rng.uniform(-1, 1, 3) * np.asarray(half_range)
    zmin = np.min(vertices @ R.T, axis=0)[2] + p[2]
    p[2] += max(0.0, BELT_TOP_Z + clearance - zmin)
    return transform_from_rt(R, p)


@dataclass(frozen=True)
class DriftAbout(Motion):
    """Random smooth drift of small amplitude about a start pose (object frame rotation)."""

    start: np.ndarray
    amplitude: float = 0.005
    rot_amplitude: float = 0.03
    seed: int = 0

    def pose(self, t: float) -> np.ndarray:
        m = RandomSmooth(amplitude=self.amplitude, rot_amplitude=self.rot_amplitude, seed=self.seed,
                         center=np.eye(4))
        D = m.pose(t) - m.pose(0.0) + np.eye(4)  # displacement starting at identity
        R = self.start[:3, :3] @ exp_so3(_rotvec(m.pose(0.0)[:3, :3].T @ m.pose(t)[:3, :3]))
        return transform_from_rt(R, self.start[:3, 3] + D[:3, 3])


def _rotvec(R):
    return Rotation.from_matrix(R).as_rotvec()


STANDARD_CAMERAS = ("cam_left", "cam_right", "cam_top")


def random_rig(rng: np.random.Generator, n_cameras: int, hand: bool = False, perturb_m: float = 0.05,
               perturb_rad: float = 0.05) -> Rig:
    """A subset of the standard fixed cameras, placements perturbed, plus the hand camera.

    Each fixed camera is moved by up to ``perturb_m`` per axis and rotated by
    up to ``perturb_rad`` about a random axis; its view centre stays near the
    working area.
    """
    full = load_rig(rig_path("fixed3"))
    names = list(rng.choice(STANDARD_CAMERAS, size=n_cameras, replace=False))
    cams = []
    for n in names:
        c = full[n]
        dR = exp_so3(rng.normal(size=3) / np.sqrt(3) * perturb_rad)
        T = np.array(c.T_world_camera)
        T = transform_from_rt(dR @ T[:3, :3], T[:3, 3] + rng.uniform(-perturb_m, perturb_m, 3))
        cams.append(RigCamera(c.name, c.intrinsics, "fixed", T_world_camera=T))
    if hand:
        cams.append(load_rig(rig_path("hybrid"))["hand"])
    return Rig(tuple(cams))


def trial_config(object_name: str, rig: Rig, seed: int, noise_px: float = 0.5, drift: bool = True):
    """Cell config and motion of one trial (object at a random start pose).

    Returns
    -------
    config : CellConfig
    motion : Motion
    mesh : Path
    """
    from ..model import load_model
    from .cell import CellConfig
    from .imaging import ImageEffects

    mesh = object_mesh_path(object_name)
    model = load_model(mesh)
    rng = np.random.default_rng(seed)
    T0 = random_start_pose(model.vertices, rng)
    motion = DriftAbout(T0, seed=seed) if drift else Static(T0)
    arm = "watch" if rig.eye_in_hand else "home"
    config = CellConfig(object_mesh=Path(mesh), rig=rig, effects=ImageEffects(noise_px=noise_px), arm=arm, seed=seed)
    return config, motion, mesh


def model_symmetries(vertices: np.ndarray, tol: float = 1e-6) -> list[np.ndarray]:
    """Proper rigid symmetries of a vertex set (object frame), identity first.

    Finds every rotation+translation mapping the vertex set onto itself by
    matching one non-degenerate vertex triple to all triples with the same
    pairwise distances. For scoring only (a symmetric part looks the same in
    all these poses, so no image can tell them apart).

    Returns
    -------
    list of ndarray, shape (4, 4)
        ``S`` with ``T @ S`` indistinguishable from ``T``.
    """
    V = np.asarray(vertices, float)
    n = len(V)
    c = V.mean(0)
    order = np.argsort(-np.linalg.norm(V - c, axis=1))
    a = order[0]
    b = int(np.argmax(np.linalg.norm(V - V[a], axis=1)))
    # Third point: farthest from the line a-b.
    ab = (V[b] - V[a]) / np.linalg.norm(V[b] - V[a])
    r = V - V[a]
    c3 = int(np.argmax(np.linalg.norm(r - np.outer(r @ ab, ab), axis=1)))
    P = V[[a, b, c3]]
    dab, dac, dbc = (np.linalg.norm(P[0] - P[1]), np.linalg.norm(P[0] - P[2]), np.linalg.norm(P[1] - P[2]))
    D = np.linalg.norm(V[:, None] - V[None], axis=2)
    scale = max(1.0, float(D.max()))
    out = []
    from scipy.spatial import cKDTree

    tree = cKDTree(V)
    for i in range(n):
        for j in np.flatnonzero(np.abs(D[i] - dab) < 1e-5 * scale):
            for k in np.flatnonzero((np.abs(D[i] - dac) < 1e-5 * scale) & (np.abs(D[j] - dbc) < 1e-5 * scale)):
                Q = V[[i, j, k]]
                from ..init.p3p import kabsch_batch

                R, t = kabsch_batch(P[None], Q[None])
                W = V @ R[0].T + t[0]
                d, _ = tree.query(W)
                if np.max(d) < 1e-5 * scale:
                    S = transform_from_rt(R[0], t[0])
                    if not any(np.allclose(S, s, atol=1e-6) for s in out):
                        out.append(S)
    out.sort(key=lambda S: np.linalg.norm(S - np.eye(4)))
    return out
