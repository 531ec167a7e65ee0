"""A starting pose handed to the tracker: by an initialiser, a user or a recovery."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["InitResult"]


@dataclass(frozen=True)
class InitResult:
    """A starting pose from an initialiser (or a user).

    Attributes
    ----------
    T_world_object : ndarray (4, 4)
    cov6 : ndarray (6, 6) or None
        Pose covariance; the config's initial sigmas when None.
    velocity : ndarray (6,) or None
    hidden : tuple of str
        Cameras the initialiser found the part hidden from (something it does
        not know stands in front: ``InitOptions.hidden_camera``); the tracker
        confirms the start without them (``TrackerConfig.blind_found_fraction``).
    provisional : bool
        The initialiser accepted the pose only provisionally (one camera, the
        looser limits of a part with plain faces): the tracker tracks it but
        publishes it only once the initialiser confirms it
        (``vespro.tracker.Tracker.offer``).
    given : bool
        The user's pose (``--init-pose``): the tracker starts from it exactly, even
        for a symmetric part, whose equivalent poses it otherwise chooses among
        (:mod:`vespro.symmetry`).
    """

    T_world_object: np.ndarray
    cov6: np.ndarray | None = None
    velocity: np.ndarray | None = None
    hidden: tuple = ()
    provisional: bool = False
    given: bool = False
