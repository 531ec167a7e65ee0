"""Solid BSP tree of a closed model, for batched line-of-sight queries.

The tree is an auto-partition: every node's plane is one of the model's
distinct face planes (``Model.plane_normals``, oriented as the face it was
taken from), and the polygons (triangle fragments) lying in that plane within
the node's cell are stored at the node. Polygons that straddle a node's plane
are split. Because the model is a closed, outward-oriented solid, an empty side
is a leaf whose cell is entirely outside (front side) or entirely inside (back
side) the solid: a "solid-leaf" tree (Naylor). A segment is blocked by the
solid exactly when part of it lies in an inside leaf, so the occlusion query
only clips segments against node planes, level by level for all segments at
once, and never tests polygons; the polygons stay in the tree (and the cache)
for other uses such as rendering or hit reporting.

Robustness: CAD coordinates are float32, so a "planar" face is planar only to
~1e-8 m. Before building, vertices are moved (by ~1e-8 m) onto the exact planes
of their faces (``planar_vertices``); every later side test is then exact up to
float64 rounding, and the cells are consistently inside or outside. A
fitted-plane tree with a matching tolerance instead leaves thin slabs of wrong
inside/outside along nearly coplanar faces (seen on boolean-union models).

Splitting-plane heuristic: among the planes of the largest faces present in
the node (up to ``max_candidates``), pick the one minimising
``split_weight * splits + |front - back|`` (triangle counts), which keeps the
tree shallow and the number of fragments small.

Storage is flat numpy arrays (one row per node, child indices, CSR polygon
lists), so a tree is cached as ``.npz`` keyed by the model's content hash.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vespro.jit import njit
from vespro.model import Model

__all__ = [
    "OUT",
    "IN",
    "FORMAT_VERSION",
    "BSPTree",
    "build_bsp",
    "planar_vertices",
    "save_bsp",
    "load_bsp",
    "load_or_build_bsp",
    "default_cache_dir",
    "segment_blocked",
]

#: Leaf codes in the child arrays (non-negative values are node indices).
OUT = -1
IN = -2

#: Bump when the build or the file layout changes: old cache files are ignored.
FORMAT_VERSION = 2

_ARRAYS = (
    "normal", "offset", "face", "front", "back", "node_plane", "plane_normal", "plane_offset",
    "bounds", "poly_ptr", "poly_vertices", "poly_face",
)


def _ro(a, dtype=None):
    a = np.array(a, dtype=dtype)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class BSPTree:
    """Solid-leaf BSP tree of one model, in that model's (object) frame.

    Attributes
    ----------
    normal : ndarray, shape (N, 3)
        Unit normal of each node plane (the outward normal of the face it came
        from), object frame.
    offset : ndarray, shape (N,)
        Plane offset ``d`` in ``normal . x = d``, m.
    face : ndarray, shape (N,), int64
        Planar face (``Model.faces`` index) whose plane the node uses.
    front, back : ndarray, shape (N,), int64
        Child node index, or ``OUT`` (-1) / ``IN`` (-2) for a leaf outside /
        inside the solid. Node 0 is the root.
    node_plane : ndarray, shape (N,), int64
        Distinct (unoriented) plane of each node: ``normal[i] == s *
        plane_normal[node_plane[i]]`` with ``s = +-1``, exactly.
    plane_normal, plane_offset : ndarray, shapes (Q, 3), (Q,)
        The distinct planes used by the nodes (fewer than nodes: a plane is
        reused in several cells), for per-plane distance tables.
    bounds : ndarray, shape (2, 3)
        Axis-aligned box (min, max) containing the solid, m; segments are
        clipped to it first (outside it everything is outside the solid).
    poly_ptr : ndarray, shape (N + 1,), int64
        The polygons of node ``i`` are ``poly_ptr[i]:poly_ptr[i+1]``.
    poly_vertices : ndarray, shape (Q, 3, 3)
        Triangle fragments lying in their node's plane, m.
    poly_face : ndarray, shape (Q,), int64
        Planar face each fragment comes from.
    content_hash : str
        ``Model.content_hash`` of the model it was built from.
    depth : int
        Longest root-to-leaf path (number of nodes).
    plane_eps : float
        Plane thickness used by the build and the queries, m (float64
        rounding only).
    build_seconds : float
        Wall time of the original build (kept when loaded from the cache).
    """

    normal: np.ndarray
    offset: np.ndarray
    face: np.ndarray
    front: np.ndarray
    back: np.ndarray
    node_plane: np.ndarray
    plane_normal: np.ndarray
    plane_offset: np.ndarray
    bounds: np.ndarray
    poly_ptr: np.ndarray
    poly_vertices: np.ndarray
    poly_face: np.ndarray
    content_hash: str
    depth: int
    plane_eps: float = 0.0
    build_seconds: float = 0.0

    @property
    def n_nodes(self) -> int:
        return int(self.normal.shape[0])

    @property
    def n_polygons(self) -> int:
        return int(self.poly_vertices.shape[0])

    def contains(self, P: np.ndarray) -> np.ndarray:
        """Whether points are inside the solid (points on a plane go to the back).

        Parameters
        ----------
        P : ndarray, shape (M, 3)
            Object frame, m.

        Returns
        -------
        ndarray, shape (M,), bool
        """
        P = np.asarray(P, dtype=float).reshape(-1, 3)
        node = np.zeros(len(P), dtype=np.int64)
        idx = np.arange(len(P))
        out = np.zeros(len(P), dtype=bool)
        while idx.size:
            h = np.einsum("ij,ij->i", P[idx], self.normal[node]) - self.offset[node]
            node = np.where(h > 0, self.front[node], self.back[node])
            out[idx[node == IN]] = True
            keep = node >= 0
            idx, node = idx[keep], node[keep]
        return out

    def plane_distances(self, P: np.ndarray) -> np.ndarray:
        """Signed distances of points to the distinct planes, shape (M, Q), m.

        For fixed points (a model's own corners) this is set-up work that
        ``segments_blocked_from`` reuses on every query.
        """
        P = np.asarray(P, dtype=float).reshape(-1, 3)
        return P @ self.plane_normal.T - self.plane_offset

    @property
    def node_sign(self) -> np.ndarray:
        """+1 / -1 per node: its orientation relative to ``plane_normal[node_plane]``."""
        sg = self.__dict__.get("_sign")
        if sg is None:
            sg = np.where(np.einsum("ij,ij->i", self.normal, self.plane_normal[self.node_plane]) < 0, -1.0, 1.0)
            sg.setflags(write=False)
            object.__setattr__(self, "_sign", sg)  # derived cache, not state
        return sg

    def clip_to_bounds(self, A: np.ndarray, B: np.ndarray, t_lo, t_hi):
        """Clip segments ``A + t (B - A)``, ``t in [t_lo, t_hi]``, to ``bounds``.

        ``A`` is (3,) or (K, 3), ``B`` (K, 3). Returns new (t_lo, t_hi), each
        (K,); an empty piece has ``t_hi <= t_lo``. Exact: the solid lies in
        the box, so nothing outside it can block.
        """
        d = B - A
        t0 = np.array(np.broadcast_to(t_lo, (B.shape[0],)), dtype=float)
        t1 = np.array(np.broadcast_to(t_hi, (B.shape[0],)), dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (self.bounds[0] - A) / d
            tb = (self.bounds[1] - A) / d
        lo = np.fmin(ta, tb)  # fmin/fmax skip the NaN of 0/0 (d = 0 on an axis)
        hi = np.fmax(ta, tb)
        # d == 0: inside the slab -> no constraint (+-inf); outside -> empty.
        A_ = np.broadcast_to(A, B.shape)
        flat = d == 0
        out_slab = flat & ((A_ < self.bounds[0]) | (A_ > self.bounds[1]))
        lo = np.where(flat, np.where(out_slab, np.inf, -np.inf), lo)
        hi = np.where(flat, np.where(out_slab, -np.inf, np.inf), hi)
        return np.maximum(t0, lo.max(1)), np.minimum(t1, hi.min(1))

    def segments_blocked(self, A: np.ndarray, B: np.ndarray, t_lo=0.0, t_hi=1.0, min_length: float = 0.0) -> np.ndarray:
        """Whether segments pass through the solid.

        The segment ``i`` is ``x(t) = A[i] + t (B[i] - A[i])`` for ``t`` in
        ``[t_lo[i], t_hi[i]]``; it is blocked when a piece of it longer than
        ``min_length`` (in ``t``) lies in an inside cell. Trimming ``t`` keeps
        the surfaces at the segment ends (a corner on the model itself) from
        counting.

        Parameters
        ----------
        A : ndarray, shape (K, 3) or (3,)
            Segment starts, object frame, m; a single point (3,) when all
            segments start there (a camera centre), which is faster.
        B : ndarray, shape (K, 3)
            Segment ends, object frame, m.
        t_lo, t_hi : float or ndarray, shape (K,)
        min_length : float
            Pieces this short (in ``t``) are ignored: tangent touches.

        Returns
        -------
        ndarray, shape (K,), bool

        Notes
        -----
        A compiled depth-first walk per segment (:func:`_blocked_kernel`) with
        the arithmetic of the breadth-first NumPy walk it replaced: the box clip
        of :meth:`clip_to_bounds`, then per piece the plane distances ``A . n -
        d`` and ``B . n - d`` (summed in ``np.einsum``'s order), the crossing
        and the sides. The same answers (``tests/vespro/test_init_kernels.py``
        keeps that walk as the reference).
        """
        B = np.ascontiguousarray(B, dtype=float).reshape(-1, 3)
        A = np.asarray(A, dtype=float)
        k = B.shape[0]
        if A.shape == (3,):
            h_start = self.normal @ A - self.offset  # the common start's distance to every node plane
            a, A_rows = A, np.empty((0, 3))
        else:
            h_start, a, A_rows = self.offset, np.zeros(3), np.ascontiguousarray(A.reshape(-1, 3))  # (h_start, a unused)
        return _blocked_kernel(a, A_rows, B, self.bounds, h_start, self.normal, self.offset, _per_segment(t_lo, k),
                               _per_segment(t_hi, k), float(min_length), self._children, float(self.plane_eps))

    def segments_blocked_from(
        self, a: np.ndarray, B: np.ndarray, end_dist: np.ndarray, rows: np.ndarray, t_lo=0.0, t_hi=1.0
    ) -> np.ndarray:
        """``segments_blocked`` from one start point to fixed, pre-measured ends.

        Parameters
        ----------
        a : ndarray, shape (3,)
            Common start (camera centre), object frame, m.
        B : ndarray, shape (K, 3)
            Segment ends (``end_dist`` rows ``rows`` measured these), m.
        end_dist : ndarray, shape (R, Q)
            ``plane_distances`` of all candidate end points (set-up).
        rows : ndarray, shape (K,), int
            The end point (row of ``end_dist``) of each segment.
        t_lo, t_hi : float or ndarray, shape (K,)

        Returns
        -------
        ndarray, shape (K,), bool

        Notes
        -----
        The walk of :meth:`segments_blocked` (:func:`_blocked_from_kernel`), with
        the ends' plane distances read from ``end_dist``; the same answers
        (checked against it and against ray casting in the tests).
        """
        a = np.asarray(a, dtype=float).reshape(3)
        B = np.ascontiguousarray(B, dtype=float).reshape(-1, 3)
        k = B.shape[0]
        h_start = self.normal @ a - self.offset
        rows = np.ascontiguousarray(rows, dtype=np.int64)
        t0, t1 = _per_segment(t_lo, k), _per_segment(t_hi, k)
        return _blocked_from_kernel(a, B, self.bounds, h_start, self.node_sign, self.node_plane,
                                    np.ascontiguousarray(end_dist, dtype=float), rows, t0, t1, self._children,
                                    float(self.plane_eps))

    @property
    def _children(self) -> np.ndarray:
        ch = self.__dict__.get("_ch")
        if ch is None:
            ch = np.stack([self.front, self.back], axis=1)  # (N, 2): child by side (0 front, 1 back)
            ch.setflags(write=False)
            object.__setattr__(self, "_ch", ch)  # derived cache, not state
        return ch

    def arrays(self) -> dict:
        return {name: getattr(self, name) for name in _ARRAYS}


def _per_segment(t, k):
    """``t`` (scalar or (k,)) as a contiguous float64 array (k,); as is when it already is one."""
    if type(t) is np.ndarray and t.dtype == np.float64 and t.shape == (k,) and t.flags.c_contiguous:
        return t
    return np.ascontiguousarray(np.broadcast_to(np.asarray(t, dtype=float), (k,)))


@njit
def _blocked_from_kernel(a, B, bounds, h_start, sign, plane, end_dist, rows, t_lo, t_hi, children, pe):
    """Compiled core of :meth:`BSPTree.segments_blocked_from`; returns (K,) bool."""
    k = B.shape[0]
    out = np.zeros(k, dtype=np.bool_)
    st_node = np.empty(children.shape[0] + 2, dtype=np.int64)
    st_t = np.empty((children.shape[0] + 2, 2))
    for i in range(k):
        out[i] = segment_blocked(a, B[i, 0], B[i, 1], B[i, 2], bounds, h_start, sign, plane, end_dist, rows[i],
                                 t_lo[i], t_hi[i], children, pe, st_node, st_t)
    return out


@njit
def segment_blocked(a, bx, by, bz, bounds, h_start, sign, plane, end_dist, row, t0, t1, children, pe, st_node, st_t):
    """Whether the segment ``a -> (bx, by, bz)``, ``t in [t0, t1]``, passes through the solid.

    Clip to ``bounds`` (as :meth:`BSPTree.clip_to_bounds`), then walk the tree
    (:func:`_walk`) with the start's plane distances ``h_start`` and the end's
    in row ``row`` of ``end_dist``. The tree arrays are a :class:`BSPTree`'s
    (``bounds``, ``node_sign``, ``node_plane``, its children, ``plane_eps``), as
    :meth:`BSPTree.segments_blocked_from` passes them; ``st_node`` and ``st_t`` are
    scratch stacks of ``len(children) + 2`` rows, reused from one call to the next.
    """
    for ax in range(3):
        bv = bx if ax == 0 else (by if ax == 1 else bz)
        d = bv - a[ax]
        if d == 0.0:
            if a[ax] < bounds[0, ax] or a[ax] > bounds[1, ax]:
                return False  # parallel to the slab and outside it: empty
            continue
        ta = (bounds[0, ax] - a[ax]) / d
        tb = (bounds[1, ax] - a[ax]) / d
        lo = min(ta, tb)
        hi = max(ta, tb)
        if lo > t0:
            t0 = lo
        if hi < t1:
            t1 = hi
    # (A, B, normal, offset: unused with the tabled end distances; any arrays of their types)
    return _walk(t0, t1, 0.0, 0, False, end_dist, h_start, end_dist, end_dist, h_start, True, sign, plane, end_dist,
                 row, children, pe, st_node, st_t)


@njit
def _blocked_kernel(a, A, B, bounds, h_start, normal, offset, t_lo, t_hi, min_length, children, pe):
    """Compiled core of :meth:`BSPTree.segments_blocked`; returns (K,) bool.

    Segments start at the rows of ``A`` (K, 3), or with ``A`` empty all at ``a``
    (3,), whose plane distances are ``h_start``."""
    k = B.shape[0]
    out = np.zeros(k, dtype=np.bool_)
    st_node = np.empty(children.shape[0] + 2, dtype=np.int64)
    st_t = np.empty((children.shape[0] + 2, 2))
    own_a = A.shape[0] > 0
    sign, plane, end_dist = np.empty(0), np.empty(0, dtype=np.int64), np.empty((0, 0))  # (no tabled ends)
    for i in range(k):
        if own_a:
            t0, t1 = _clip_to_bounds(A[i, 0], A[i, 1], A[i, 2], B[i], bounds, t_lo[i], t_hi[i])
        else:
            t0, t1 = _clip_to_bounds(a[0], a[1], a[2], B[i], bounds, t_lo[i], t_hi[i])
        out[i] = _walk(t0, t1, min_length, i, own_a, A, h_start, B, normal, offset, False, sign, plane, end_dist, 0,
                       children, pe, st_node, st_t)
    return out


@njit
def _nan_max(x, y):
    """``np.maximum`` of two floats (a NaN wins)."""
    return x if (np.isnan(x) or x > y) else y


@njit
def _nan_min(x, y):
    """``np.minimum`` of two floats (a NaN wins)."""
    return x if (np.isnan(x) or x < y) else y


@njit
def _clip_to_bounds(a0, a1, a2, b, bounds, t0, t1):
    """:meth:`BSPTree.clip_to_bounds` of one segment ``a -> b`` with its NaN rules: the new ``(t0, t1)``."""
    lo_all, hi_all = -np.inf, np.inf
    for ax in range(3):
        av = a0 if ax == 0 else (a1 if ax == 1 else a2)
        d = b[ax] - av
        if d == 0.0:
            if av < bounds[0, ax] or av > bounds[1, ax]:
                lo, hi = np.inf, -np.inf  # parallel to the slab and outside it: empty
            else:
                lo, hi = -np.inf, np.inf
        else:
            ta = (bounds[0, ax] - av) / d
            tb = (bounds[1, ax] - av) / d
            # np.fmin / np.fmax: a NaN loses to a number
            lo = tb if np.isnan(ta) else (ta if (np.isnan(tb) or ta < tb) else tb)
            hi = tb if np.isnan(ta) else (ta if (np.isnan(tb) or ta > tb) else tb)
        lo_all = _nan_max(lo_all, lo)
        hi_all = _nan_min(hi_all, hi)
    return _nan_max(t0, lo_all), _nan_min(t1, hi_all)


@njit
def _plane_dist(P, i, normal, offset, node):
    """``P[i] . normal[node] - offset[node]``, the products summed as ``np.einsum("ij,ij->i")``
    sums them (its two-lane SIMD loop: ``(x0 n0 + x2 n2) + x1 n1``)."""
    return ((P[i, 0] * normal[node, 0] + P[i, 2] * normal[node, 2]) + P[i, 1] * normal[node, 1]) - offset[node]


@njit
def _walk(t0, t1, min_length, i, own_a, A, h_start, B, normal, offset, tabled_b, sign, plane, end_dist, row, children,
          pe, st_node, st_t):
    """Whether segment ``i``, ``t in [t0, t1]`` (clipped to the bounds), passes through the solid.

    Walks the tree depth first with a stack of ``(node, t0, t1)`` pieces
    (``st_node``, ``st_t``: room for depth + 1 of them). Per piece: the
    start's distance to the node plane (with ``own_a`` from ``A[i]``, else
    ``h_start[node]``), the end's (with ``tabled_b`` ``sign[node] *
    end_dist[row, plane[node]]``, else from ``B[i]``), the crossing and the
    side of each part; a part longer than ``min_length`` (in ``t``) in an
    inside leaf blocks.
    """
    if not (t1 - t0 > min_length):
        return False
    st_node[0] = 0
    st_t[0, 0] = t0
    st_t[0, 1] = t1
    top = 1
    while top > 0:
        top -= 1
        node = st_node[top]
        p0 = st_t[top, 0]
        p1 = st_t[top, 1]
        ha = _plane_dist(A, i, normal, offset, node) if own_a else h_start[node]
        hb = sign[node] * end_dist[row, plane[node]] if tabled_b else _plane_dist(B, i, normal, offset, node)
        dh = hb - ha
        h0 = ha + p0 * dh
        h1 = ha + p1 * dh
        # Within plane_eps of the plane counts as on it, so a piece that only
        # touches a plane at an end is not split into a sliver.
        b0 = h0 < -pe
        b1 = h1 < -pe
        f0 = h0 > pe
        f1 = h1 > pe
        # Side of the first part of the piece (1: back). A piece lying in the
        # plane is a grazing view and goes front.
        side0 = 1 if (b0 or ((not f0) and b1)) else 0
        c0 = children[node, side0]
        if (b0 and f1) or (f0 and b1):
            ts = -ha / dh
            c1 = children[node, 1 - side0]
            if c1 == IN and (min_length <= 0.0 or p1 - ts > min_length):
                return True
            if c1 >= 0:
                st_node[top] = c1
                st_t[top, 0] = ts
                st_t[top, 1] = p1
                top += 1
            p1 = ts
        if c0 == IN and (min_length <= 0.0 or p1 - p0 > min_length):
            return True
        if c0 >= 0:
            st_node[top] = c0
            st_t[top, 0] = p0
            st_t[top, 1] = p1
            top += 1
    return False


def planar_vertices(model: Model, max_move_rel: float = 1e-4):
    """Model vertices moved onto their faces' planes.

    Each vertex becomes the point nearest to it on all the distinct planes of
    its faces (least squares; directions the planes do not pin down keep the
    original coordinate). CAD files store float32, so a planar face is planar
    only to ~1e-8 m; after this it is planar to float64 rounding, which a
    consistent BSP needs: classifying vertices against a fitted plane with a
    matching tolerance leaves thin slabs of wrong inside/outside along nearly
    coplanar faces.

    Parameters
    ----------
    model : Model
    max_move_rel : float
        A vertex that would move more than this times the model diameter
        keeps its position (an ill-posed set of nearly parallel planes).

    Returns
    -------
    V : ndarray, shape (V, 3)
        m, object frame.
    face_planar : ndarray, shape (P,), bool
        Whether each face's vertices now lie on its plane to float64 rounding;
        the BSP falls back to exact triangle planes for the others.
    """
    V = np.array(model.vertices, dtype=float)
    F = np.asarray(model.triangles)
    tplane = np.asarray(model.face_plane)[np.asarray(model.triangle_face)]
    vp = np.unique(np.stack([F.ravel(), np.repeat(tplane, 3)], 1), axis=0)  # (vertex, plane) pairs
    ptr = np.concatenate([[0], np.cumsum(np.bincount(vp[:, 0], minlength=len(V)))])
    pn, pd = np.asarray(model.plane_normals), np.asarray(model.plane_offsets)
    limit = max_move_rel * model.diameter
    one = np.flatnonzero(np.diff(ptr) == 1)  # on a single plane: project
    p1 = vp[ptr[one], 1]
    V[one] += (pd[p1] - np.einsum("ij,ij->i", pn[p1], V[one]))[:, None] * pn[p1]
    for v in np.flatnonzero(np.diff(ptr) > 1):
        ps = vp[ptr[v] : ptr[v + 1], 1]
        Nm = pn[ps]
        r = pd[ps] - Nm @ V[v]
        U, s, Wt = np.linalg.svd(Nm, full_matrices=False)
        keep = s > 1e-9
        step = Wt[keep].T @ ((U[:, keep].T @ r) / s[keep])
        if np.linalg.norm(step) <= limit:
            V[v] += step
    fn, fd = np.asarray(model.face_normals), np.asarray(model.face_offsets)
    res = np.abs(np.einsum("fvj,fj->fv", V[F], fn[model.triangle_face]) - fd[model.triangle_face][:, None]).max(1)
    tol = 1e-12 * model.diameter + 8 * np.finfo(float).eps * np.abs(V).max()
    face_planar = np.ones(len(model.faces), dtype=bool)
    face_planar[np.asarray(model.triangle_face)[res > tol]] = False
    return V, face_planar


def build_bsp(model: Model, max_candidates: int = 24, split_weight: float = 6.0, rel_eps: float = 1e-11) -> BSPTree:
    """Build the solid BSP tree of a model.

    Node planes are the model's distinct planes (``Model.plane_normals``),
    oriented as the face they come from, with the vertices first moved onto
    them (``planar_vertices``, moves of ~1e-8 m) so that every vertex is
    classified by its true side of every plane and every cell is consistently
    inside or outside. Triangles of a face that cannot be made planar that way
    keep their own exact planes.

    Parameters
    ----------
    model : Model
    max_candidates : int
        Planes scored per node: those of the largest faces (by fragment area)
        present in the node.
    split_weight : float
        Cost of one split relative to one triangle of imbalance.
    rel_eps : float
        Plane thickness as a fraction of the model diameter, for float64
        rounding only: points closer count as on the plane.

    Returns
    -------
    BSPTree
    """
    t_start = time.perf_counter()
    eps = rel_eps * model.diameter
    Vp, face_planar = planar_vertices(model)
    F = np.asarray(model.triangles)
    tri = Vp[F]  # (F, 3, 3)
    tface = np.asarray(model.triangle_face)
    # Plane (unoriented id) and orientation of every source triangle.
    pn = [np.asarray(model.plane_normals)]
    pd = [np.asarray(model.plane_offsets)]
    tplane = np.asarray(model.face_plane)[tface].copy()
    tsign = np.asarray(model.face_plane_sign)[tface].copy()
    loose = np.flatnonzero(~face_planar[tface])
    if loose.size:
        cr = np.cross(tri[loose, 1] - tri[loose, 0], tri[loose, 2] - tri[loose, 0])
        n = cr / np.linalg.norm(cr, axis=1, keepdims=True)
        tplane[loose] = len(pd[0]) + np.arange(loose.size)
        tsign[loose] = 1.0
        pn.append(n)
        pd.append(np.einsum("ij,ij->i", n, tri[loose, 0]))
    pn, pd = np.concatenate(pn), np.concatenate(pd)

    normal, offset, face, nplane, front, back, polys, psrc = [], [], [], [], [], [], [], []
    # Stack of (fragments (M, 3, 3), source triangles (M,), parent, is_front_child, depth).
    stack = [(tri, np.arange(len(F)), -1, True, 1)]
    depth = 0
    while stack:
        T, S, parent, is_front, dep = stack.pop()
        i = len(normal)
        if parent >= 0:
            (front if is_front else back)[parent] = i
        depth = max(depth, dep)
        s = _choose_source(T, S, tplane, tsign, pn, pd, eps, max_candidates, split_weight)
        n, d = tsign[s] * pn[tplane[s]], tsign[s] * pd[tplane[s]]
        h = T @ n - d  # (M, 3)
        h[tplane[S] == tplane[s]] = 0.0  # fragments in this very plane
        pos = (h > eps).any(1)
        neg = (h < -eps).any(1)
        on = ~pos & ~neg
        span = pos & neg
        only_f = pos & ~neg
        only_b = neg & ~pos
        Tf, Sf = [T[only_f]], [S[only_f]]
        Tb, Sb = [T[only_b]], [S[only_b]]
        for j in np.flatnonzero(span):
            pf, pb = _split_triangle(T[j], h[j], eps)
            Tf.append(pf)
            Sf.append(np.full(len(pf), S[j]))
            Tb.append(pb)
            Sb.append(np.full(len(pb), S[j]))
        Tf, Sf = np.concatenate(Tf), np.concatenate(Sf)
        Tb, Sb = np.concatenate(Tb), np.concatenate(Sb)
        normal.append(n)
        offset.append(d)
        face.append(tface[s])
        nplane.append(tplane[s])
        front.append(OUT)
        back.append(IN)
        polys.append(T[on])
        psrc.append(S[on])
        # Push back first so the front subtree is numbered right after its parent.
        if len(Tb):
            stack.append((Tb, Sb, i, False, dep + 1))
        if len(Tf):
            stack.append((Tf, Sf, i, True, dep + 1))

    counts = np.array([len(p) for p in polys], dtype=np.int64)
    psrc = np.concatenate(psrc).astype(np.int64)
    used, node_plane = np.unique(np.array(nplane, dtype=np.int64), return_inverse=True)
    pad = eps + 1e-12
    bounds = np.stack([Vp.min(0) - pad, Vp.max(0) + pad])
    return BSPTree(
        normal=_ro(np.array(normal, dtype=float).reshape(-1, 3)),
        offset=_ro(np.array(offset, dtype=float)),
        face=_ro(np.array(face, dtype=np.int64)),
        front=_ro(np.array(front, dtype=np.int64)),
        back=_ro(np.array(back, dtype=np.int64)),
        node_plane=_ro(node_plane.astype(np.int64)),
        plane_normal=_ro(pn[used]),
        plane_offset=_ro(pd[used]),
        bounds=_ro(bounds),
        poly_ptr=_ro(np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)),
        poly_vertices=_ro(np.concatenate(polys).reshape(-1, 3, 3)),
        poly_face=_ro(tface[psrc]),
        content_hash=model.content_hash,
        depth=int(depth),
        plane_eps=float(eps),
        build_seconds=time.perf_counter() - t_start,
    )


def _choose_source(T, S, tplane, tsign, pn, pd, eps, max_candidates, split_weight) -> int:
    """Source triangle whose oriented plane splits the fragments ``T`` (M, 3, 3) best."""
    key = 2 * tplane[S] + (tsign[S] < 0)
    keys, first, local = np.unique(key, return_index=True, return_inverse=True)
    if keys.size == 1:
        return int(S[0])
    e1, e2 = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
    area = np.bincount(local, weights=np.linalg.norm(np.cross(e1, e2), axis=1), minlength=keys.size)
    # Largest planes first ("prefer planes of large faces"); stable so that
    # ties keep a deterministic order.
    top = np.argsort(-area, kind="stable")[:max_candidates]
    src = S[first[top]]
    sg = tsign[src]
    h = np.einsum("kc,mvc->kmv", sg[:, None] * pn[tplane[src]], T) - (sg * pd[tplane[src]])[:, None, None]
    h[tplane[S][None, :] == tplane[src][:, None]] = 0.0  # (K, M, 3)
    pos = (h > eps).any(2)
    neg = (h < -eps).any(2)
    n_span = (pos & neg).sum(1)
    n_front = (pos & ~neg).sum(1)
    n_back = (neg & ~pos).sum(1)
    score = split_weight * n_span + np.abs(n_front - n_back)
    return int(src[int(np.argmin(score))])


def _split_triangle(tri, h, eps):
    """Split one triangle (3, 3) with vertex plane distances h (3,).

    Returns the front and back pieces as triangle arrays (a, 3, 3), (b, 3, 3).
    """
    h = np.where(np.abs(h) <= eps, 0.0, h)
    fpoly, bpoly = [], []
    for k in range(3):
        p, q = tri[k], tri[(k + 1) % 3]
        hp, hq = h[k], h[(k + 1) % 3]
        if hp >= 0:
            fpoly.append(p)
        if hp <= 0:
            bpoly.append(p)
        if (hp > 0 and hq < 0) or (hp < 0 and hq > 0):
            x = p + (hp / (hp - hq)) * (q - p)
            fpoly.append(x)
            bpoly.append(x)
    return _fan(fpoly), _fan(bpoly)


def _fan(poly):
    if len(poly) < 3:
        return np.zeros((0, 3, 3))
    return np.array([[poly[0], poly[j], poly[j + 1]] for j in range(1, len(poly) - 1)])


def default_cache_dir() -> Path:
    """``$VESPRO_BSP_CACHE`` if set, else ``~/.cache/vespro/bsp``."""
    env = os.environ.get("VESPRO_BSP_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "vespro" / "bsp"


def _cache_path(model: Model, cache_dir: Path) -> Path:
    return Path(cache_dir) / f"{model.content_hash}.v{FORMAT_VERSION}.npz"


def save_bsp(tree: BSPTree, path) -> None:
    """Write a tree atomically (temporary file then rename) as ``.npz``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = np.array(
        [tree.content_hash, str(FORMAT_VERSION), str(tree.depth), repr(tree.plane_eps), repr(tree.build_seconds)]
    )
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, meta=meta, **tree.arrays())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def load_bsp(path, content_hash: str) -> BSPTree:
    """Read a cached tree; raises ``ValueError`` if it is corrupt or for another model."""
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = [str(s) for s in z["meta"]]
            arrs = {name: z[name] for name in _ARRAYS}
    except Exception as e:
        raise ValueError(f"{path}: unreadable BSP cache ({type(e).__name__}: {e})") from e
    if len(meta) != 5 or meta[0] != content_hash or meta[1] != str(FORMAT_VERSION):
        raise ValueError(f"{path}: BSP cache is for another model or format")
    n = arrs["normal"].shape[0]
    ok = (
        n > 0
        and arrs["normal"].shape == (n, 3)
        and all(arrs[k].shape == (n,) for k in ("offset", "face", "front", "back"))
        and arrs["poly_ptr"].shape == (n + 1,)
        and arrs["poly_vertices"].ndim == 3
        and arrs["poly_vertices"].shape[1:] == (3, 3)
        and arrs["poly_face"].shape == (arrs["poly_vertices"].shape[0],)
        and int(arrs["poly_ptr"][-1]) == arrs["poly_vertices"].shape[0]
        and all(np.all((arrs[k] >= IN) & (arrs[k] < n)) for k in ("front", "back"))
        and arrs["node_plane"].shape == (n,)
        and arrs["plane_normal"].ndim == 2
        and arrs["plane_normal"].shape[1:] == (3,)
        and arrs["plane_offset"].shape == (arrs["plane_normal"].shape[0],)
        and np.all((arrs["node_plane"] >= 0) & (arrs["node_plane"] < arrs["plane_offset"].shape[0]))
        and arrs["bounds"].shape == (2, 3)
        and np.all(np.isfinite(arrs["normal"]))
        and np.all(np.isfinite(arrs["offset"]))
    )
    # Children always have larger indices than their parent (pre-order), so a
    # tree that passes this check cannot loop.
    idx = np.arange(n)
    ok = ok and all(np.all((arrs[k] < 0) | (arrs[k] > idx)) for k in ("front", "back"))
    if not ok:
        raise ValueError(f"{path}: BSP cache has inconsistent arrays")
    return BSPTree(
        **{k: _ro(v) for k, v in arrs.items()},
        content_hash=meta[0],
        depth=int(meta[2]),
        plane_eps=float(meta[3]),
        build_seconds=float(meta[4]),
    )


def load_or_build_bsp(model: Model, cache_dir=None, use_cache: bool = True) -> BSPTree:
    """The model's BSP tree, from the disk cache if there, else built and cached.

    Parameters
    ----------
    model : Model
    cache_dir : str or Path, optional
        Defaults to ``default_cache_dir()``.
    use_cache : bool
        False builds without touching the disk.

    A corrupt or mismatching cache file is rebuilt and overwritten; a cache
    directory that cannot be written only costs the rebuild next time.
    """
    if not use_cache:
        return build_bsp(model)
    path = _cache_path(model, Path(cache_dir) if cache_dir is not None else default_cache_dir())
    if path.is_file():
        try:
            return load_bsp(path, model.content_hash)
        except ValueError:
            pass
    tree = build_bsp(model)
    try:
        save_bsp(tree, path)
    except OSError:
        pass
    return tree
