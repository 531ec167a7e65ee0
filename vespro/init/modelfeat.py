"""What the initialiser needs from the CAD model, computed once per model.

- edge samples: points along every sharp edge at a fixed 3D spacing, with the
  edge's direction, its two faces and whether it is convex, for chamfer scores;
- corner paths ``(A, B, C)``: two long sharp edges meeting at a vertex ``B``,
  the model side of the P3P correspondences (image corners ``a, b, c`` with
  ``a-b`` and ``b-c`` joined by image edges);
- whether the model is convex (then back-face culling alone decides what is
  visible and the BSP occlusion query can be skipped).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from ..metrics import discrete_symmetries
from ..model import Model

__all__ = ["ModelFeatures", "model_features"]


@dataclass(frozen=True)
class ModelFeatures:
    """Edge samples and corner paths of a model (object frame, m).

    Attributes
    ----------
    edge_a, edge_b : ndarray, shape (E, 3)
        Edge end points.
    edge_len : ndarray, shape (E,)
    edge_faces : ndarray, shape (E, 2), int64
    edge_convex : ndarray, shape (E,), bool
    sample_p : ndarray, shape (S, 3)
        Points along the edges (dense set).
    sample_edge : ndarray, shape (S,), int64
        Edge of each sample.
    coarse : ndarray, shape (Sc,), int64
        Indices into the dense samples: a sparser subset for ranking.
    sparse : ndarray, shape (Ss,), int64
        Two samples on each long edge (the path edges): the first, cheapest
        ranking pass.
    paths : ndarray, shape (Np, 3), int64
        Vertex indices ``(A, B, C)``; edges A-B and B-C are sharp model edges.
    face_normals : ndarray, shape (F, 3)
    face_offsets : ndarray, shape (F,)
    face_centroids : ndarray, shape (F, 3)
    face_areas : ndarray, shape (F,)
    tri_p : ndarray, shape (T, 3, 3)
        Mesh triangles (vertex coordinates), for rasterising the projected
        faces.
    tri_face : ndarray, shape (T,), int64
        Planar face of each triangle.
    vertices : ndarray, shape (V, 3)
        Model vertices.
    symmetries : tuple of ndarray, shape (4, 4)
        Object-frame transforms ``S`` with the part looking the same at
        ``T @ S`` as at ``T`` (identity first; axis-aligned ones,
        :func:`vespro.metrics.discrete_symmetries`).
    end_free : ndarray, shape (E, 2), bool
        Whether no other sharp edge continues the edge straight on past its
        first / second end (in a non-convex part, e.g. an L-block, two edges
        can lie on one line): only free ends are used by the edge-overrun
        check.
    convex : bool
    diameter : float
    """

    edge_a: np.ndarray
    edge_b: np.ndarray
    edge_len: np.ndarray
    edge_faces: np.ndarray
    edge_convex: np.ndarray
    sample_p: np.ndarray
    sample_edge: np.ndarray
    coarse: np.ndarray
    sparse: np.ndarray
    paths: np.ndarray
    face_normals: np.ndarray
    face_offsets: np.ndarray
    face_centroids: np.ndarray
    face_areas: np.ndarray
    tri_p: np.ndarray
    tri_face: np.ndarray
    vertices: np.ndarray
    symmetries: tuple
    end_free: np.ndarray
    convex: bool
    diameter: float


def model_features(model: Model, dense_spacing_frac: float = 1 / 60, coarse_spacing_frac: float = 1 / 15,
                   min_path_edge_frac: float = 0.15, min_path_angle_deg: float = 20.0,
                   min_score_edge_frac: float = 0.0) -> ModelFeatures:
    """Derive edge samples and corner paths.

    Parameters
    ----------
    model : Model
    dense_spacing_frac, coarse_spacing_frac : float
        Sample spacing along edges as a fraction of the model diameter.
    min_path_edge_frac : float
        Edges shorter than this fraction of the diameter are not used in
        corner paths (short edges give ill-conditioned P3P and unreliable image
        corners); they still count in the scores.
    min_path_angle_deg : float
        Least angle between the two edges of a path.
    min_score_edge_frac : float
        Edges shorter than this fraction of the diameter are not sampled.
    """
    V = model.vertices
    ev = model.edge_vertices
    A, B = V[ev[:, 0]], V[ev[:, 1]]
    L = np.linalg.norm(B - A, axis=1)
    diam = model.diameter

    def samples(spacing):
        pts, eid = [], []
        for e in np.flatnonzero(L >= min_score_edge_frac * diam):
            n = max(2, int(np.ceil(L[e] / spacing)))
            t = (np.arange(n) + 0.5) / n
            pts.append(A[e] + t[:, None] * (B[e] - A[e]))
            eid.append(np.full(n, e))
        return np.concatenate(pts), np.concatenate(eid)

    sp, se = samples(dense_spacing_frac * diam)
    # Coarse subset: every k-th dense sample of each edge, at least one per edge.
    k = max(1, int(round(coarse_spacing_frac / dense_spacing_frac)))
    coarse = []
    for e in np.unique(se):
        idx = np.flatnonzero(se == e)
        coarse.extend(idx[k // 2::k] if len(idx) > k else idx[len(idx) // 2: len(idx) // 2 + 1])
    coarse = np.asarray(sorted(coarse), np.int64)

    long_e = np.flatnonzero(L >= min_path_edge_frac * diam)
    sparse = []
    for e in long_e:
        idx = np.flatnonzero(se == e)
        sparse.extend(idx[np.unique(np.rint(np.array([0.3, 0.7]) * (len(idx) - 1)).astype(int))])
    sparse = np.asarray(sorted(sparse), np.int64)
    nbr: dict[int, list[int]] = {}
    for e in long_e:
        a, b = int(ev[e, 0]), int(ev[e, 1])
        nbr.setdefault(a, []).append(b)
        nbr.setdefault(b, []).append(a)
    paths = []
    cos_max = np.cos(np.deg2rad(min_path_angle_deg))
    for b, ns in nbr.items():
        for a in ns:
            for c in ns:
                if a == c:
                    continue
                u, w = V[a] - V[b], V[c] - V[b]
                cosang = u @ w / (np.linalg.norm(u) * np.linalg.norm(w))
                if abs(cosang) < cos_max:
                    paths.append((a, b, c))
    paths = np.asarray(paths, np.int64).reshape(-1, 3)

    try:
        hull_vol = ConvexHull(V).volume
        convex = bool(model.volume >= hull_vol * (1 - 1e-6))
    except Exception:
        convex = False
    tri_c = V[model.triangles].mean(1)
    tri_a = 0.5 * np.linalg.norm(np.cross(V[model.triangles[:, 1]] - V[model.triangles[:, 0]],
                                          V[model.triangles[:, 2]] - V[model.triangles[:, 0]]), axis=1)
    nf = len(model.faces)
    fa = np.bincount(model.triangle_face, weights=tri_a, minlength=nf)
    fc = np.stack([np.bincount(model.triangle_face, weights=tri_a * tri_c[:, k], minlength=nf) for k in range(3)], 1)
    fc /= fa[:, None]
    end_free = np.ones((len(ev), 2), bool)
    U = (B - A) / np.maximum(L, 1e-12)[:, None]
    for e in range(len(ev)):
        for side, (v, d) in enumerate(((ev[e, 0], -U[e]), (ev[e, 1], U[e]))):
            for f in np.flatnonzero((ev[:, 0] == v) | (ev[:, 1] == v)):
                if f == e:
                    continue
                d2 = U[f] if ev[f, 0] == v else -U[f]  # direction leaving v along f
                if d2 @ d > 1 - 1e-6:
                    end_free[e, side] = False
    out = ModelFeatures(A, B, L, model.edge_faces, model.edge_convex, sp, se, coarse, sparse, paths,
                        model.face_normals, model.face_offsets, fc, fa, V[model.triangles],
                        np.asarray(model.triangle_face, np.int64), np.asarray(V, float),
                        tuple(discrete_symmetries(V)), end_free, convex, float(diam))
    for f in ("edge_a", "edge_b", "edge_len", "sample_p", "sample_edge", "coarse", "sparse", "paths", "tri_p", "tri_face", "vertices"):
        getattr(out, f).setflags(write=False)
    return out
