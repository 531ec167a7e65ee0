"""Which of a symmetric part's equivalent poses the tracker reports.

A symmetric part (a box: the identity and three half turns about its centre) looks
the same at ``T`` and at ``T @ S`` for each of its symmetries ``S``
(:func:`vespro.metrics.discrete_symmetries`), so no image tells those poses apart.

A pose the user gives (``--init-pose``) is kept exactly as given: the object frame is
the user's, and nothing changes it. Where the tracker has to choose by itself (a start
from the automatic initialiser, a re-acquisition after a loss) it follows one rule
(``TrackerConfig.symmetry``, ``--symmetry``):

``continuity`` (default)
    After a loss, the equivalent pose nearest in orientation to the last good track:
    the object frame stays on the same faces (a face marked for grasping keeps its
    axis) unless the part was turned over while unseen. Before any track (the first
    start) as ``up``.
``up``
    Always the one whose z axis points most nearly up in the world; among those alike
    in that (a cube's quarter turns about the vertical) the one whose x axis points
    most nearly along the world's x. The frame follows the world, not the faces.
"""

from __future__ import annotations

import numpy as np

__all__ = ["RULES", "HELP", "choose", "describe"]

RULES = ("continuity", "up")

HELP = ("how the tracker picks among a symmetric part's equivalent poses (a box looks the same turned "
        "half a turn) when it chooses by itself; a pose given with --init-pose is always kept as given. "
        "Upright means: z most nearly up in the world, then x most nearly along the world's x. "
        "continuity: upright at the first automatic start, after a loss the one nearest the last good "
        "track (the frame stays on the same faces, as a grasp by a marked face needs); up: always upright "
        "(the frame follows the world)")

_TIE = 1e-9  # z components this close are alike (the candidates are exact axis permutations)


def _upright(cands: list[np.ndarray]) -> np.ndarray:
    z = max(T[2, 2] for T in cands)
    return max((T for T in cands if T[2, 2] >= z - _TIE), key=lambda T: T[0, 0])


def choose(T_world_object: np.ndarray, symmetries, rule: str, T_last: np.ndarray | None = None) -> np.ndarray:
    """The equivalent pose ``T_world_object @ S`` (``S`` among ``symmetries``) the ``rule`` picks.

    ``T_last``: the last good track's pose (None before any), which ``continuity``
    stays nearest to. With fewer than two symmetries the pose is returned unchanged.
    """
    if rule not in RULES:
        raise ValueError(f"symmetry rule must be one of {', '.join(RULES)}, got {rule!r}")
    if len(symmetries) < 2:
        return T_world_object
    cands = [T_world_object @ S for S in symmetries]
    if rule == "continuity" and T_last is not None:
        R0 = T_last[:3, :3]
        return max(cands, key=lambda T: np.trace(R0.T @ T[:3, :3]))
    return _upright(cands)


def describe(name: str, n_equivalent: int, rule: str, given: bool, reacquires: bool) -> str | None:
    """One line telling a user that the part is symmetric and how its frame is chosen
    (None for a part without symmetry). ``given``: the start pose is the user's;
    ``reacquires``: the tracker looks for the part again after a loss."""
    if n_equivalent < 2:
        return None
    head = f"{name} is symmetric: {n_equivalent} poses look alike; "
    if given:
        head += "the start pose given is kept as given"
    elif rule == "up":
        return head + "the tracker reports the one with z most nearly up in the world (--symmetry up)"
    else:
        head += "the tracker starts from the one with z most nearly up in the world"
    if not reacquires:
        return head
    after = ("the one nearest the last good track" if rule == "continuity"
             else "the one with z most nearly up in the world")
    return f"{head}; after a loss, {after} (--symmetry {rule})"
