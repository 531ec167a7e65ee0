"""Brute-force reference for the visibility tests and the bench.

Independent of vespro.bsp: Moller-Trumbore ray/triangle intersection of every
line of sight against every triangle (no acceleration structure).
"""

from __future__ import annotations

import numpy as np


def segments_hit_triangles(O, E, tri, t_lo, t_hi, chunk=2_000_000):
    """Whether segments O + t (E - O), t in (t_lo, t_hi), cross any triangle.

    O, E : (K, 3); tri : (F, 3, 3); t_lo, t_hi : (K,). Returns (K,) bool.
    Edges are inclusive (u, v >= 0, u + v <= 1), so a segment through the
    shared edge of two triangles of one face is caught by at least one.
    """
    O = np.asarray(O, float).reshape(-1, 3)
    E = np.asarray(E, float).reshape(-1, 3)
    t_lo = np.broadcast_to(t_lo, (len(O),))
    t_hi = np.broadcast_to(t_hi, (len(O),))
    out = np.zeros(len(O), bool)
    v0 = tri[:, 0]
    e1 = tri[:, 1] - v0
    e2 = tri[:, 2] - v0
    step = max(1, chunk // max(1, len(tri)))
    for s in range(0, len(O), step):
        o = O[s : s + step, None, :]
        d = (E[s : s + step] - O[s : s + step])[:, None, :]
        p = np.cross(d, e2[None])
        det = np.einsum("kfi,fi->kf", p, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            tv = o - v0[None]
            u = np.einsum("kfi,kfi->kf", tv, p) * inv
            q = np.cross(tv, e1[None])
            v = np.einsum("kfi,kfi->kf", d, q) * inv
            t = np.einsum("fi,kfi->kf", e2, q) * inv
        hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1)
        hit &= (t > t_lo[s : s + step, None]) & (t < t_hi[s : s + step, None])
        out[s : s + step] = hit.any(1)
    return out


def brute_visible(model, c, facing_eps, end_eps, occluders=()):
    """Visibility mask of model corners from camera centre c (object frame).

    occluders: sequence of (T_object_body, body_model) in the same object frame.
    The corner's line of sight is the segment corner -> camera with end_eps
    metres trimmed at both ends; the facing rule is the documented one.
    """
    P = np.asarray(model.corners)
    dist = np.linalg.norm(c[None] - P, axis=1)
    # Documented rule: some face at the corner has the camera in front of its
    # plane by more than facing_eps * distance. Loop per corner and face.
    facing = np.zeros(len(P), bool)
    for i in range(len(P)):
        for f in model.corner_faces(i):
            if model.face_normals[f] @ c - model.face_offsets[f] > facing_eps * dist[i]:
                facing[i] = True
    t_lo = np.minimum(end_eps / dist, 0.5)
    t_hi = 1 - t_lo
    tris = [model.vertices[model.triangles]]
    for T, m in occluders:
        V = m.vertices @ T[:3, :3].T + T[:3, 3]
        tris.append(V[m.triangles])
    tri = np.concatenate(tris)
    blocked = np.zeros(len(P), bool)
    idx = np.flatnonzero(facing)
    blocked[idx] = segments_hit_triangles(P[idx], np.broadcast_to(c, (idx.size, 3)), tri, t_lo[idx], t_hi[idx])
    return facing & ~blocked


def segment_edge_clearance(c, p, edge_pts, exclude_point=None, tol=1e-12):
    """Smallest distance (m) from segment c-p to the edges (E, 2, 3).

    Edges with an end at exclude_point (the corner itself) are skipped: they
    touch the line of sight at its end by construction.
    """
    a0, a1 = edge_pts[:, 0], edge_pts[:, 1]
    if exclude_point is not None:
        keep = (np.linalg.norm(a0 - exclude_point, axis=1) > tol) & (np.linalg.norm(a1 - exclude_point, axis=1) > tol)
        a0, a1 = a0[keep], a1[keep]
    if len(a0) == 0:
        return np.inf
    # Dense sampling of the closest-point problem would be approximate; solve
    # the 2x2 segment-segment problem exactly with clamping.
    d1 = (p - c)[None]
    d2 = a1 - a0
    r = c[None] - a0
    a = np.einsum("ij,ij->i", d1, d1)
    e = np.einsum("ij,ij->i", d2, d2)
    f = np.einsum("ij,ij->i", d2, r)
    b = np.einsum("ij,ij->i", d1, d2)
    cc = np.einsum("ij,ij->i", d1, r)
    den = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(den > 1e-30, np.clip((b * f - cc * e) / den, 0, 1), 0.0)
        t = (b * s + f) / e
    t = np.clip(t, 0, 1)
    s = np.where(t <= 0, np.clip(-cc / a, 0, 1), np.where(t >= 1, np.clip((b - cc) / a, 0, 1), s))
    q = c[None] + s[:, None] * d1 - (a0 + t[:, None] * d2)
    return float(np.sqrt(np.einsum("ij,ij->i", q, q)).min())


def winding_number(V, F, P, chunk=200):
    """Generalised winding number of points P (M, 3) w.r.t. the closed mesh (V, F).

    Sum of signed solid angles (van Oosterom & Strackee) over 4 pi: 1 inside,
    0 outside. An independent inside test for the BSP tree.
    """
    out = []
    for s in range(0, len(P), chunk):
        p = P[s : s + chunk, None, :]
        a, b, c = V[F[:, 0]][None] - p, V[F[:, 1]][None] - p, V[F[:, 2]][None] - p
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        dot = lambda x, y: np.einsum("pfi,pfi->pf", x, y)  # noqa: E731
        den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb
        out.append((2 * np.arctan2(det, den)).sum(1) / (4 * np.pi))
    return np.concatenate(out)
