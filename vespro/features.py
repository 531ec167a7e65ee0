"""Which model corners make good image features.

A model corner (a vertex where three or more planes meet) is a good feature
only if the image shows a real corner there: two *strong* edges (a large
dihedral angle between their faces, so they appear as high-contrast lines)
meeting at an angle clearly below 180 degrees. Vertices of a finely faceted
hole, for example, meet the definition of a corner but image as a gentle bend
of a curve, and a detector finds something else nearby. Computed once per
model.
"""

from __future__ import annotations

import numpy as np

from .model import Model

__all__ = ["salient_corners"]


def salient_corners(model: Model, min_dihedral_deg: float = 40.0, max_angle_deg: float = 140.0,
                    min_angle_deg: float = 20.0) -> np.ndarray:
    """Mask of corners with two strong incident edges at a sharp enough angle.

    Parameters
    ----------
    model : Model
    min_dihedral_deg : float
        An edge is strong if the normals of its two faces differ by at least this.
    max_angle_deg, min_angle_deg : float
        The 3D angle between the two strong edges must lie in this range (a
        nearly straight pair is no corner; a very thin wedge images as a line).

    Returns
    -------
    ndarray, shape (C,), bool
    """
    n = model.edge_normals
    cos_dihedral = np.einsum("ei,ei->e", n[:, 0], n[:, 1])
    strong = cos_dihedral <= np.cos(np.deg2rad(min_dihedral_deg))
    ev = model.edge_vertices
    V = model.vertices
    lo, hi = np.cos(np.deg2rad(max_angle_deg)), np.cos(np.deg2rad(min_angle_deg))
    out = np.zeros(model.n_corners, dtype=bool)
    for i, v in enumerate(model.corner_vertex):
        inc = np.flatnonzero(strong & ((ev[:, 0] == v) | (ev[:, 1] == v)))
        if inc.size < 2:
            continue
        other = np.where(ev[inc, 0] == v, ev[inc, 1], ev[inc, 0])
        d = V[other] - V[v]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        c = d @ d.T
        iu = np.triu_indices(inc.size, 1)
        out[i] = bool(np.any((c[iu] >= lo) & (c[iu] <= hi)))
    return out
