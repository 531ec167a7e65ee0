"""Which corner features of a model a camera can see.

A corner is visible from the camera centre ``c`` when

1. at least one planar face around it is front-facing:
   ``n . (c - p) > facing_eps * |c - p|`` (``facing_eps`` is the cosine of the
   smallest angle between the line of sight and the face plane that still
   counts; grazing views below it do not), and
2. the line of sight from ``c`` to the corner ``p`` does not pass through the
   solid of any body in the scene. The last ``end_eps`` metres at the corner
   (and the first at the camera) are ignored, so the corner's own faces do not
   block it where they meet it.

The occlusion test runs all lines of sight at once through each body's solid
BSP tree (``vespro.bsp``), in that body's frame.

For each visible corner the result also gives the viewing angle (between the
line of sight and the normal of the most front-facing face at the corner), and,
given intrinsics, its pixel position, depth and its distance in pixels to the
object's projected outline (the boundary of the image region the object covers,
holes included; a corner on the outline gets 0).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from vespro.bsp import BSPTree, segment_blocked
from vespro.camera import CameraIntrinsics, distort_normalized, project_points
from vespro.jit import njit
from vespro.model import Model
from vespro.se3 import check_transform, invert_transform, transform_points

__all__ = [
    "Visibility",
    "SceneBody",
    "VisibilityScene",
    "DEFAULT_FACING_EPS",
    "DEFAULT_END_EPS",
    "corner_facing",
    "visible_corners",
    "query_visibility",
    "silhouette_distance",
]

#: cos(89.994 deg): faces seen closer than ~0.006 deg to edge-on do not count.
DEFAULT_FACING_EPS = 1e-4
#: Ignore this much (m) of each line of sight at its ends. Well above the float32
#: rounding of CAD coordinates (~1e-8 m, which the BSP snaps away), so grazing
#: views along a face at the corner stay stable; 0.03 px at 0.2 m and f = 600 px.
DEFAULT_END_EPS = 1e-5
#: Silhouette distances below this (px) are reported as 0: a corner on the
#: outline lands there up to floating-point rounding of the projection.
SILHOUETTE_SNAP_PX = 1e-6
#: Under lens distortion the outline is drawn with straight pieces at most this
#: long (ideal px): chord sag below ~1e-3 px for the distortions of real lenses.
OUTLINE_PIECE_PX = 4.0
#: Outline rings smaller than this (px^2) are numerical cracks, not see-through gaps.
MIN_RING_AREA_PX2 = 1e-6


def _freeze(a):
    a.setflags(write=False)
    return a


def _ro(a, dtype=None):
    a = np.array(a, dtype=dtype)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Visibility:
    """Visible corners of one body for one camera pose.

    Attributes
    ----------
    mask : ndarray, shape (C,), bool
        Visibility of every corner of the model.
    indices : ndarray, shape (K,), int64
        Indices (into ``Model.corners``) of the visible corners, ascending.
    points : ndarray, shape (K, 3)
        Their positions, object frame, m.
    view_angle : ndarray, shape (K,)
        Angle between the line of sight (corner -> camera) and the normal of
        the most front-facing face at the corner, rad, in [0, pi/2).
    distance : ndarray, shape (K,)
        Camera centre to corner, m.
    uv : ndarray, shape (K, 2)
        Pixel position (distortion applied); NaN without intrinsics.
    depth : ndarray, shape (K,)
        Depth along the optical axis, m.
    silhouette_distance : ndarray, shape (K,)
        Distance in pixels to the object's projected outline; NaN without
        intrinsics or when part of the object is behind the camera.
    """

    mask: np.ndarray
    indices: np.ndarray
    points: np.ndarray
    view_angle: np.ndarray
    distance: np.ndarray
    uv: np.ndarray
    depth: np.ndarray
    silhouette_distance: np.ndarray


def corner_facing(model: Model, c_object: np.ndarray, facing_eps: float = DEFAULT_FACING_EPS):
    """Front-facing test of each corner's faces.

    A face counts as front-facing for a corner ``p`` when the camera is in
    front of its plane by more than ``facing_eps * |c - p|``:
    ``n . c - d > facing_eps * |c - p|`` (the corner lies on the plane, so
    this is ``n . (c - p) > facing_eps * |c - p|``).

    Parameters
    ----------
    model : Model
    c_object : ndarray, shape (3,)
        Camera centre, object frame, m.
    facing_eps : float
        Cosine margin, see the module docstring.

    Returns
    -------
    facing : ndarray, shape (C,), bool
        At least one face at the corner is front-facing.
    cos_best : ndarray, shape (C,)
        Largest ``(n . c - d) / |c - p|`` over the corner's faces: the cosine
        of the angle between the line of sight and that face's normal.
    dist : ndarray, shape (C,)
        ``|c - p|``, m.
    """
    # Camera height over every face plane, then gathered per corner; the -1
    # padding of the incidence table picks the appended -inf.
    h = np.append(model.face_normals @ c_object - model.face_offsets, -np.inf)
    best = h[model.corner_face_table].max(1) if model.corner_face_table.shape[1] else np.full(model.n_corners, -np.inf)
    d = c_object - model.corners
    dist = np.sqrt(np.einsum("ij,ij->i", d, d))
    with np.errstate(divide="ignore", invalid="ignore"):
        cos_best = best / dist
    facing = cos_best > facing_eps
    return facing, cos_best, dist


def _trim(dist, end_eps):
    t_lo = np.minimum(end_eps / dist, 0.5)
    return t_lo, 1.0 - t_lo


def visible_corners(
    model: Model,
    tree: BSPTree,
    c_object: np.ndarray,
    facing_eps: float = DEFAULT_FACING_EPS,
    end_eps: float = DEFAULT_END_EPS,
) -> np.ndarray:
    """Visibility mask of a single body's corners from a camera centre.

    Parameters
    ----------
    model : Model
    tree : BSPTree
        ``model``'s tree.
    c_object : ndarray, shape (3,)
        Camera centre in the object frame, m.

    Returns
    -------
    ndarray, shape (C,), bool
    """
    c_object = np.asarray(c_object, dtype=float).reshape(3)
    facing, _, dist = corner_facing(model, c_object, facing_eps)
    idx = np.flatnonzero(facing)
    t_lo, t_hi = _trim(dist[idx], end_eps)
    blocked = tree.segments_blocked(c_object, model.corners[idx], t_lo, t_hi)
    mask = np.zeros(model.n_corners, dtype=bool)
    mask[idx[~blocked]] = True
    return mask


def query_visibility(
    body: "SceneBody",
    T_camera_object: np.ndarray,
    intr: CameraIntrinsics | None = None,
    facing_eps: float = DEFAULT_FACING_EPS,
    end_eps: float = DEFAULT_END_EPS,
) -> Visibility:
    """Visible corners of one body alone, with per-feature details.

    Parameters
    ----------
    body : SceneBody
        Model and tree (set up once).
    T_camera_object : ndarray, shape (4, 4)
        Pose of the object in the camera frame.
    intr : CameraIntrinsics, optional
        Needed for ``uv`` and ``silhouette_distance``.

    Returns
    -------
    Visibility
    """
    T = check_transform(T_camera_object, "T_camera_object")  # named in the message
    return VisibilityScene([body]).query(0, np.eye(4), [T], intr, facing_eps, end_eps)


#: Largest corner x plane table (entries) a body precomputes: 8M float64 = 64 MB.
MAX_TABLE_ENTRIES = 1 << 23


@dataclass(frozen=True, eq=False)
class SceneBody:
    """One rigid body of a scene: its model and tree (both in its own frame).

    Set-up also measures the distances of the model's corners to every plane
    of the tree (``corner_plane_dist``, shape (C, Q), m; None when larger than
    ``MAX_TABLE_ENTRIES``), which the corner queries then only look up.
    """

    name: str
    model: Model
    tree: BSPTree
    corner_plane_dist: np.ndarray | None = field(init=False, repr=False, compare=False, default=None)
    #: Bounding sphere (centre (3,) in the body frame, radius m), to skip
    #: bodies that no line of sight comes near.
    sphere: tuple = field(init=False, repr=False, compare=False, default=None)

    def __post_init__(self):
        if self.tree.content_hash != self.model.content_hash:
            raise ValueError(f"body {self.name!r}: BSP tree was built for another model")
        ctr = 0.5 * (self.model.bounds[0] + self.model.bounds[1])
        object.__setattr__(self, "sphere", (_ro(ctr), float(np.linalg.norm(self.model.vertices - ctr, axis=1).max())))
        if self.model.n_corners * self.tree.plane_offset.shape[0] <= MAX_TABLE_ENTRIES:
            object.__setattr__(self, "corner_plane_dist", _ro(self.tree.plane_distances(self.model.corners)))

    def corners_blocked(self, c_object: np.ndarray, idx: np.ndarray, t_lo, t_hi) -> np.ndarray:
        """Whether the lines of sight from ``c_object`` (3,) to corners ``idx`` (K,) are blocked by this body."""
        if self.corner_plane_dist is not None:
            return self.tree.segments_blocked_from(
                c_object, self.model.corners[idx], self.corner_plane_dist, idx, t_lo, t_hi
            )
        return self.tree.segments_blocked(c_object, self.model.corners[idx], t_lo, t_hi)

    def visible_mask(
        self, c_object: np.ndarray, facing_eps: float = DEFAULT_FACING_EPS, end_eps: float = DEFAULT_END_EPS
    ) -> np.ndarray:
        """Visibility of this body's corners, alone, from camera centre ``c_object`` (3,); shape (C,), bool."""
        c_object = np.asarray(c_object, dtype=float).reshape(3)
        facing, _, dist = corner_facing(self.model, c_object, facing_eps)
        idx = np.flatnonzero(facing)
        t_lo, t_hi = _trim(dist[idx], end_eps)
        mask = np.zeros(self.model.n_corners, dtype=bool)
        mask[idx[~self.corners_blocked(c_object, idx, t_lo, t_hi)]] = True
        return mask


class VisibilityScene:
    """Several rigid bodies that occlude each other's features.

    Set up once from the bodies; each query takes the current poses. The
    scene holds no state between queries.

    Parameters
    ----------
    bodies : sequence of SceneBody
    """

    def __init__(self, bodies: Sequence[SceneBody]):
        self.bodies = tuple(bodies)
        if not self.bodies:
            raise ValueError("a scene needs at least one body")
        names = [b.name for b in self.bodies]
        if len(set(names)) != len(names):
            raise ValueError(f"body names must be unique, got {names}")

    @property
    def names(self) -> tuple:
        return tuple(b.name for b in self.bodies)

    def index(self, name: str) -> int:
        """Scene index of body ``name``."""
        if name not in self.names:
            raise ValueError(f"no body {name!r} in the scene; have {list(self.names)}")
        return self.names.index(name)

    def query(
        self,
        body: int | str,
        T_world_camera: np.ndarray,
        T_world_bodies: Sequence[np.ndarray],
        intr: CameraIntrinsics | None = None,
        facing_eps: float = DEFAULT_FACING_EPS,
        end_eps: float = DEFAULT_END_EPS,
        check: bool = True,
    ) -> Visibility:
        """Visible corners of one body, with every body of the scene occluding.

        Parameters
        ----------
        body : int or str
            Index or name of the body whose corners are queried.
        T_world_camera : ndarray, shape (4, 4)
            Camera pose (OpenCV optical frame) in the world.
        T_world_bodies : sequence of ndarray, each (4, 4)
            Pose of every body, in scene order.
        intr : CameraIntrinsics, optional
            Needed for ``uv`` and ``silhouette_distance``.
        facing_eps, end_eps : float
            Tolerances, see the module docstring.
        check : bool
            Validate the poses (shape, finite, proper rotations). A caller whose
            poses are its own filter's and a validated rig's (the tracker, every
            frame) may skip it: 20 us a pose.

        Returns
        -------
        Visibility
        """
        i = self.index(body) if isinstance(body, str) else int(body)
        if len(T_world_bodies) != len(self.bodies):
            raise ValueError(f"need {len(self.bodies)} body poses, got {len(T_world_bodies)}")
        if check:
            T_world_camera = check_transform(T_world_camera, "T_world_camera")
            Tb = [check_transform(T, f"T_world_{b.name}") for T, b in zip(T_world_bodies, self.bodies)]
        else:
            Tb = list(T_world_bodies)
        model = self.bodies[i].model
        T_camera_object = invert_transform(T_world_camera) @ Tb[i]
        T_object_camera = invert_transform(T_camera_object)
        c = T_object_camera[:3, 3]

        own = self.bodies[i]
        if own.corner_plane_dist is not None:
            # facing test, trims and the body's own occlusion in one compiled pass
            tree = own.tree
            idx, t_lo, t_hi, blocked, cos_best, dist = _facing_blocked_kernel(
                np.ascontiguousarray(c), model.face_normals, model.face_offsets, model.corner_face_table, model.corners,
                float(facing_eps), float(end_eps), tree.normal, tree.offset, tree.node_sign, tree.node_plane,
                own.corner_plane_dist, tree.bounds, tree._children, float(tree.plane_eps))
        else:
            facing, cos_best, dist = corner_facing(model, c, facing_eps)
            idx = np.flatnonzero(facing)
            t_lo, t_hi = _trim(dist[idx], end_eps)
            blocked = own.corners_blocked(c, idx, t_lo, t_hi)
        P = model.corners[idx]
        for j, other in enumerate(self.bodies):
            if j == i or blocked.all():
                continue
            T_j_i = invert_transform(Tb[j]) @ Tb[i]
            live = np.flatnonzero(~blocked)
            c_j = transform_points(T_j_i, c[None])[0]  # camera centre in body j's frame
            Bj = transform_points(T_j_i, P[live])
            near = _segments_near_sphere(c_j, Bj, *other.sphere)
            if not near.any():
                continue
            sel = live[near]
            blocked[sel] = other.tree.segments_blocked(c_j, Bj[near], t_lo[sel], t_hi[sel])
        vis = idx[~blocked]
        mask = np.zeros(model.n_corners, dtype=bool)
        mask[vis] = True

        k = vis.size
        P = model.corners[vis]
        sil = np.full(k, np.nan)
        if intr is not None:
            uv, depth = project_points(intr, T_camera_object, P)
            if k:
                sil = silhouette_distance(model, T_camera_object, intr, uv)
        else:
            uv = np.full((k, 2), np.nan)
            depth = transform_points(T_camera_object, P)[:, 2]
        # all arrays below are fresh (no one else holds them): made read-only in place
        return Visibility(
            mask=_freeze(mask),
            indices=_freeze(vis.astype(np.int64, copy=False)),
            points=_freeze(P.reshape(-1, 3)),
            view_angle=_freeze(np.arccos(np.minimum(np.maximum(cos_best[vis], -1.0), 1.0))),  # np.clip, less its overhead
            distance=_freeze(dist[vis]),
            uv=_freeze(uv.reshape(-1, 2)),
            depth=_freeze(depth),
            silhouette_distance=_freeze(sil),
        )


@njit
def _facing_blocked_kernel(c, face_normals, face_offsets, table, corners, facing_eps, end_eps, normal, offset, sign,
                           plane, corner_plane_dist, bounds, children, plane_eps):
    """:func:`corner_facing`, :func:`_trim` and ``SceneBody.corners_blocked`` in one pass.

    Returns the facing corners ``idx`` (K,), their trims ``t_lo``, ``t_hi`` (K,),
    whether the body itself blocks them (K,), and ``cos_best``, ``dist`` (C,) of
    every corner. The same formulas as those functions; the dot products are
    summed left to right (NumPy's matrix-vector products may round differently).
    """
    nf = face_normals.shape[0]
    h = np.empty(nf + 1)
    for f in range(nf):
        h[f] = face_normals[f, 0] * c[0] + face_normals[f, 1] * c[1] + face_normals[f, 2] * c[2] - face_offsets[f]
    h[nf] = -np.inf  # the -1 padding of the incidence table
    n_nodes = normal.shape[0]
    h_start = np.empty(n_nodes)
    for q in range(n_nodes):
        h_start[q] = normal[q, 0] * c[0] + normal[q, 1] * c[1] + normal[q, 2] * c[2] - offset[q]
    C = corners.shape[0]
    cos_best = np.empty(C)
    dist = np.empty(C)
    idx = np.empty(C, dtype=np.int64)
    k = 0
    for i in range(C):
        best = -np.inf
        for j in range(table.shape[1]):
            best = max(best, h[table[i, j]])
        dx, dy, dz = c[0] - corners[i, 0], c[1] - corners[i, 1], c[2] - corners[i, 2]
        dist[i] = math.sqrt(dx * dx + dy * dy + dz * dz)
        cos_best[i] = best / dist[i]
        if cos_best[i] > facing_eps:
            idx[k] = i
            k += 1
    idx = idx[:k]
    t_lo = np.empty(k)
    t_hi = np.empty(k)
    blocked = np.zeros(k, dtype=np.bool_)
    st_node = np.empty(n_nodes + 2, dtype=np.int64)
    st_t = np.empty((n_nodes + 2, 2))
    for m in range(k):
        i = idx[m]
        t_lo[m] = min(end_eps / dist[i], 0.5)
        t_hi[m] = 1.0 - t_lo[m]
        blocked[m] = segment_blocked(c, corners[i, 0], corners[i, 1], corners[i, 2], bounds, h_start, sign, plane,
                                     corner_plane_dist, i, t_lo[m], t_hi[m], children, plane_eps, st_node, st_t)
    return idx, t_lo, t_hi, blocked, cos_best, dist


def _segments_near_sphere(A, B, ctr, r):
    """Whether segments A->B (A (3,) or (K, 3), B (K, 3)) come within r of ctr (3,)."""
    A = np.broadcast_to(A, B.shape)
    d = B - A
    dd = np.einsum("ij,ij->i", d, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(np.einsum("ij,ij->i", ctr - A, d) / dd, 0.0, 1.0)
    t = np.where(dd > 0, t, 0.0)
    q = A + t[:, None] * d - ctr
    return np.einsum("ij,ij->i", q, q) <= r * r


def _outline(model: Model, T_camera_object: np.ndarray, intr: CameraIntrinsics, densify: int):
    """Boundary of the object's projected image region (shapely geometry) or None."""
    import shapely

    V_c = transform_points(T_camera_object, model.vertices)
    if np.any(V_c[:, 2] <= 1e-9):
        return None  # part of the object at or behind the camera plane: no finite outline
    c = invert_transform(T_camera_object)[:3, 3]
    # The projection of a closed solid is the union of its front-facing faces.
    front = np.flatnonzero(model.face_normals @ c - model.face_offsets > 0)
    polys = []
    for f in front:
        rings = []
        for loop in model.faces[f].loops:
            P = model.vertices[loop]
            if densify > 1:
                Q = np.roll(P, -1, axis=0)
                s = (np.arange(densify) / densify)[None, :, None]
                P = (P[:, None, :] * (1 - s) + Q[:, None, :] * s).reshape(-1, 3)
            uv, _ = project_points(intr, T_camera_object, P)
            rings.append(uv)
        poly = shapely.Polygon(rings[0], rings[1:])
        if not poly.is_valid:
            poly = shapely.make_valid(poly)
        polys.append(poly)
    try:
        region = shapely.union_all(polys)
    except shapely.errors.GEOSException:
        # Snap-rounding overlay is robust where floating overlay can fail.
        region = shapely.union_all(polys, grid_size=1e-6)
    # Floating-point union leaves zero-width cracks along shared edges of
    # adjacent faces (rings of ~1e-14 px^2); no real gap is that small.
    parts = []
    for g in getattr(region, "geoms", [region]):
        if isinstance(g, shapely.Polygon) and g.area > MIN_RING_AREA_PX2:
            holes = [r for r in g.interiors if shapely.Polygon(r).area > MIN_RING_AREA_PX2]
            parts.append(shapely.Polygon(g.exterior, holes))
    return shapely.MultiPolygon(parts).boundary if parts else None


class _EdgeTable:
    """Directed boundary edges of a model's planar faces (set up once per model).

    ``a[e] -> b[e]`` runs along a loop of face ``face[e]``; ``twin[e]`` is the
    face on the other side of that edge (the face holding ``b -> a``), -1 if
    none. Loop edges with collinear intermediate vertices stay split.
    """

    def __init__(self, model: Model):
        a, b, f = [], [], []
        for fi, face in enumerate(model.faces):
            for loop in face.loops:
                lp = np.asarray(loop, dtype=np.int64)
                a.append(lp)
                b.append(np.roll(lp, -1))
                f.append(np.full(lp.size, fi, np.int64))
        self.a = np.concatenate(a) if a else np.zeros(0, np.int64)
        self.b = np.concatenate(b) if b else np.zeros(0, np.int64)
        self.face = np.concatenate(f) if f else np.zeros(0, np.int64)
        owner = {(int(x), int(y)): int(fi) for x, y, fi in zip(self.a, self.b, self.face)}
        self.twin = np.array([owner.get((int(y), int(x)), -1) for x, y in zip(self.a, self.b)], dtype=np.int64)


_EDGE_TABLES: "weakref.WeakKeyDictionary[Model, _EdgeTable]" = weakref.WeakKeyDictionary()


def _edge_table(model: Model) -> _EdgeTable:
    tab = _EDGE_TABLES.get(model)
    if tab is None:
        tab = _EDGE_TABLES[model] = _EdgeTable(model)
    return tab


def _outline_segments(model: Model, T_camera_object: np.ndarray, intr: CameraIntrinsics, densify: int):
    """Straight pieces of the object's projected outline, ``(P0 (M, 2), P1 (M, 2))`` px, or None.

    The projected region is the union of the front-facing faces. Its boundary
    lies on the projected edges of front faces whose neighbour across the edge
    is not front-facing (contour edges); a contour edge is split where it
    crosses the boundary of the other front faces' union, and each piece lies
    on the outline unless its midpoint is inside another front face (even-odd
    rule). Exact up to floating point (checked against the shapely union of
    the faces), except in degenerate views where a contour edge overlaps
    another face's edge collinearly.

    The edges are straight in ideal (undistorted) pixels; with ``densify > 1``
    the outline found there is cut into pieces (at least ``densify`` per piece,
    at most ``OUTLINE_PIECE_PX`` long) whose ends are then distorted. This
    assumes the distortion maps the image region one to one, as for any
    usable calibration.
    """
    V_c = transform_points(T_camera_object, model.vertices)
    if np.any(V_c[:, 2] <= 1e-9):
        return None  # part of the object at or behind the camera plane: no finite outline
    tab = _edge_table(model)
    c = invert_transform(T_camera_object)[:3, 3]
    front = model.face_normals @ c - model.face_offsets > 0
    Kc = intr.K
    P0, P1 = _outline_pieces_kernel(V_c, front, tab.a, tab.b, tab.face, tab.twin, len(model.faces),
                                    float(Kc[0, 0]), float(Kc[1, 1]), float(Kc[0, 2]), float(Kc[1, 2]))
    if len(P0) == 0:
        return None
    if densify > 1:
        # The image of a straight outline piece under lens distortion is a
        # curve: cut it into at least ``densify`` pieces of at most
        # OUTLINE_PIECE_PX (ideal px), then distort the piece ends.
        n = np.maximum(densify, np.ceil(np.hypot(*(P1 - P0).T) / OUTLINE_PIECE_PX)).astype(np.int64)
        seg = np.repeat(np.arange(len(P0)), n)
        k = np.arange(seg.size) - np.repeat(np.cumsum(n) - n, n)
        f0, f1 = (k / n[seg])[:, None], ((k + 1) / n[seg])[:, None]
        Q = np.concatenate([P0[seg] * (1 - f0) + P1[seg] * f0, P0[seg] * (1 - f1) + P1[seg] * f1])
        xy = (Q - [Kc[0, 2], Kc[1, 2]]) / [Kc[0, 0], Kc[1, 1]]
        Q = distort_normalized(xy, intr.dist) * [Kc[0, 0], Kc[1, 1]] + [Kc[0, 2], Kc[1, 2]]
        P0, P1 = Q[: seg.size], Q[seg.size :]
    return P0, P1


@njit
def _outline_pieces_kernel(V_c, front, ea, eb, eface, etwin, n_faces, fx, fy, cx, cy):
    """Compiled core of :func:`_outline_segments` (ideal pixels, before any densifying).

    Parameters: camera-frame vertices ``V_c`` (V, 3), per-face front flags (F,), the
    edge table (``a``, ``b``, ``face``, ``twin``, each (E,)) and the pinhole numbers.
    Returns the outline pieces ``P0``, ``P1`` (M, 2); M = 0 when there is no outline.
    The arithmetic is that of the NumPy formulation it replaced, element by element.
    """
    nv = V_c.shape[0]
    uv = np.empty((nv, 2))
    for i in range(nv):
        uv[i, 0] = V_c[i, 0] / V_c[i, 2] * fx + cx
        uv[i, 1] = V_c[i, 1] / V_c[i, 2] * fy + cy
    # edges of front faces; contour edges: the face across is not front-facing (or there is none)
    n_all = ea.shape[0]
    ef = np.empty(n_all, dtype=np.int64)
    m = 0
    for e in range(n_all):
        if front[eface[e]]:
            ef[m] = e
            m += 1
    ef = ef[:m]
    contour = np.zeros(m, dtype=np.bool_)
    is_sface = np.zeros(n_faces, dtype=np.bool_)
    nS = 0
    for j in range(m):
        tw = etwin[ef[j]]
        if not (tw >= 0 and front[tw]):
            contour[j] = True
            is_sface[eface[ef[j]]] = True
            nS += 1
    C = np.empty((m, 2))
    D = np.empty((m, 2))
    for j in range(m):
        C[j, 0] = uv[ea[ef[j]], 0]
        C[j, 1] = uv[ea[ef[j]], 1]
        D[j, 0] = uv[eb[ef[j]], 0]
        D[j, 1] = uv[eb[ef[j]], 1]
    # candidate splitting edges: other contour edges, and edges of faces bordering a contour edge's face
    cols = np.empty(m, dtype=np.int64)
    ncols = 0
    for j in range(m):
        tw = etwin[ef[j]]
        if contour[j] or (tw >= 0 and is_sface[tw]):
            cols[ncols] = j
            ncols += 1
    tol = 1e-9
    # pieces of each contour edge between its crossings
    cap = 4 * nS + 8  # grown when needed
    P0 = np.empty((cap, 2))
    P1 = np.empty((cap, 2))
    psf = np.empty(cap, dtype=np.int64)
    npc = 0
    par = np.empty(ncols + 2)
    for s in range(m):
        if not contour[s]:
            continue
        sf = eface[ef[s]]
        ax, ay = C[s, 0], C[s, 1]
        rx, ry = D[s, 0] - ax, D[s, 1] - ay
        par[0] = 0.0
        par[1] = 1.0
        npar = 2
        for jj in range(ncols):
            q = cols[jj]
            qf = eface[ef[q]]
            if not ((contour[q] and sf != qf) or etwin[ef[q]] == sf):
                continue
            qx, qy = C[q, 0], C[q, 1]
            ex, ey = D[q, 0] - qx, D[q, 1] - qy
            den = rx * ey - ry * ex
            wx, wy = qx - ax, qy - ay
            nt = wx * ey - wy * ex
            if not ((nt > 0 and den > 0) or (nt < 0 and den < 0)):
                continue  # t = nt / den would be <= 0, infinite or NaN: no crossing
            t = nt / den
            if not (t > tol and t < 1 - tol):
                continue
            u = (wx * ry - wy * rx) / den
            if u >= -tol and u <= 1 + tol:
                par[npar] = t
                npar += 1
        # insertion sort of the parameters (a handful)
        for i in range(1, npar):
            v = par[i]
            j = i - 1
            while j >= 0 and par[j] > v:
                par[j + 1] = par[j]
                j -= 1
            par[j + 1] = v
        if npc + npar > cap:
            cap = 2 * (npc + npar)
            P0n, P1n, psfn = np.empty((cap, 2)), np.empty((cap, 2)), np.empty(cap, dtype=np.int64)
            P0n[:npc], P1n[:npc], psfn[:npc] = P0[:npc], P1[:npc], psf[:npc]
            P0, P1, psf = P0n, P1n, psfn
        for i in range(npar - 1):
            t0, t1 = par[i], par[i + 1]
            x0, y0 = ax + t0 * rx, ay + t0 * ry
            x1, y1 = ax + t1 * rx, ay + t1 * ry
            if math.hypot(x1 - x0, y1 - y0) > 1e-9:  # zero-length pieces carry no boundary
                P0[npc, 0], P0[npc, 1] = x0, y0
                P1[npc, 0], P1[npc, 1] = x1, y1
                psf[npc] = sf
                npc += 1
    # keep the pieces whose midpoint is inside no other front face (even-odd rule); the
    # table lists each face's edges together, so a face's crossings are counted over its
    # own run of edges, and only for faces whose box holds the midpoint: the ray from a
    # point above or below the box meets no edge, from a point right of it none, from a
    # point left of it every edge that spans its height, an even number on closed loops
    # (the 1e-6 px margin covers the rounding of the crossing abscissa)
    first = np.full(n_faces, -1, dtype=np.int64)
    last = np.full(n_faces, -1, dtype=np.int64)
    fbox = np.empty((n_faces, 4))
    for j in range(m):
        f = eface[ef[j]]
        if first[f] < 0:
            first[f] = j
            fbox[f, 0] = fbox[f, 2] = C[j, 0]
            fbox[f, 1] = fbox[f, 3] = C[j, 1]
        last[f] = j
        fbox[f, 0] = min(fbox[f, 0], C[j, 0])
        fbox[f, 1] = min(fbox[f, 1], C[j, 1])
        fbox[f, 2] = max(fbox[f, 2], C[j, 0])
        fbox[f, 3] = max(fbox[f, 3], C[j, 1])
    keep = np.zeros(npc, dtype=np.bool_)
    nk = 0
    for p in range(npc):
        mx = 0.5 * (P0[p, 0] + P1[p, 0])
        my = 0.5 * (P0[p, 1] + P1[p, 1])
        inside = False
        for f in range(n_faces):
            if f == psf[p] or first[f] < 0:
                continue
            if my < fbox[f, 1] or my >= fbox[f, 3] or mx < fbox[f, 0] - 1e-6 or mx > fbox[f, 2] + 1e-6:
                continue
            count = 0
            for j in range(first[f], last[f] + 1):
                cxj, cyj, dyj = C[j, 0], C[j, 1], D[j, 1]
                if (cyj > my) != (dyj > my):
                    x_at = cxj + (my - cyj) * ((D[j, 0] - cxj) / (dyj - cyj))
                    if mx < x_at:
                        count += 1
            if count % 2 == 1:
                inside = True
                break
        if not inside:
            keep[p] = True
            nk += 1
    Q0 = np.empty((nk, 2))
    Q1 = np.empty((nk, 2))
    k = 0
    for p in range(npc):
        if keep[p]:
            Q0[k, 0], Q0[k, 1] = P0[p, 0], P0[p, 1]
            Q1[k, 0], Q1[k, 1] = P1[p, 0], P1[p, 1]
            k += 1
    return Q0, Q1


@njit
def _point_segment_distance_kernel(uv, P0, P1):
    """Compiled :func:`_point_segment_distance` (the same arithmetic, checked bit for bit in the tests), shape (K,)."""
    K = uv.shape[0]
    M = P0.shape[0]
    out = np.empty(K)
    for i in range(K):
        best = np.inf
        for j in range(M):
            dx = P1[j, 0] - P0[j, 0]
            dy = P1[j, 1] - P0[j, 1]
            dd = dx * dx + dy * dy
            wx = uv[i, 0] - P0[j, 0]
            wy = uv[i, 1] - P0[j, 1]
            if dd <= 0:
                t = 0.0
            else:
                t = (wx * dx + wy * dy) / dd
                if t < 0.0:
                    t = 0.0
                elif t > 1.0:
                    t = 1.0
            qx = wx - t * dx
            qy = wy - t * dy
            d2 = qx * qx + qy * qy
            if d2 < best:
                best = d2
        out[i] = math.sqrt(best)
    return out


@njit
def _silhouette_kernel(V, T, face_normals, face_offsets, ea, eb, eface, etwin, fx, fy, cx, cy, uv, snap):
    """:func:`silhouette_distance` without lens distortion, compiled: the vertices in the
    camera (NaN everywhere when one is at or behind the camera plane), the front faces,
    the outline (:func:`_outline_pieces_kernel`) and the distances, those below ``snap``
    reported as 0. The products are summed left to right (NumPy's may round differently)."""
    K = uv.shape[0]
    out = np.full(K, np.nan)
    nv = V.shape[0]
    V_c = np.empty((nv, 3))
    for i in range(nv):
        for r in range(3):
            V_c[i, r] = T[r, 0] * V[i, 0] + T[r, 1] * V[i, 1] + T[r, 2] * V[i, 2] + T[r, 3]
        if not V_c[i, 2] > 1e-9:
            return out
    c = np.empty(3)  # the camera centre in the object frame, -R^T t
    for r in range(3):
        c[r] = -(T[0, r] * T[0, 3] + T[1, r] * T[1, 3] + T[2, r] * T[2, 3])
    nf = face_normals.shape[0]
    front = np.empty(nf, dtype=np.bool_)
    for f in range(nf):
        front[f] = face_normals[f, 0] * c[0] + face_normals[f, 1] * c[1] + face_normals[f, 2] * c[2] - face_offsets[f] > 0
    P0, P1 = _outline_pieces_kernel(V_c, front, ea, eb, eface, etwin, nf, fx, fy, cx, cy)
    if P0.shape[0] == 0 or K == 0:
        return out
    d = _point_segment_distance_kernel(uv, P0, P1)
    for i in range(K):
        out[i] = 0.0 if d[i] < snap else d[i]
    return out


def _point_segment_distance(uv, P0, P1):
    """Distance from each point (K, 2) to the nearest segment P0->P1 (M, 2), shape (K,).

    The NumPy formulation, kept as the reference of :func:`_point_segment_distance_kernel`.
    """
    dx, dy = P1[:, 0] - P0[:, 0], P1[:, 1] - P0[:, 1]
    dd = dx * dx + dy * dy
    wx, wy = uv[:, :1] - P0[:, 0], uv[:, 1:] - P0[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip((wx * dx + wy * dy) / dd, 0.0, 1.0)
    t[:, dd <= 0] = 0.0
    qx, qy = wx - t * dx, wy - t * dy
    return np.sqrt(np.min(qx * qx + qy * qy, axis=1))


def silhouette_distance(
    model: Model, T_camera_object: np.ndarray, intr: CameraIntrinsics, uv: np.ndarray
) -> np.ndarray:
    """Distance in pixels from image points to the object's projected outline.

    Parameters
    ----------
    model : Model
    T_camera_object : ndarray, shape (4, 4)
    intr : CameraIntrinsics
    uv : ndarray, shape (K, 2)
        Pixel positions (e.g. projected corners).

    Returns
    -------
    ndarray, shape (K,)
        px; NaN everywhere when part of the object is behind the camera. With
        lens distortion the outline's edges are curves, approximated by 8
        projected pieces per edge.

    Notes
    -----
    Computed from the contour edges (:func:`_outline_segments`), without a
    polygon union; :func:`_silhouette_distance_union` is the slower reference
    (shapely union of the projected front faces), equal within 1e-6 px.
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    if not intr.has_distortion:  # straight edges: all of it in one compiled pass
        tab = _edge_table(model)
        Kc = intr.K
        return _silhouette_kernel(model.vertices, np.ascontiguousarray(T_camera_object, dtype=float), model.face_normals,
                                  model.face_offsets, tab.a, tab.b, tab.face, tab.twin, float(Kc[0, 0]), float(Kc[1, 1]),
                                  float(Kc[0, 2]), float(Kc[1, 2]), np.ascontiguousarray(uv), SILHOUETTE_SNAP_PX)
    segs = _outline_segments(model, T_camera_object, intr, densify=8)
    if segs is None or len(segs[0]) == 0 or len(uv) == 0:
        return np.full(len(uv), np.nan)
    d = _point_segment_distance_kernel(np.ascontiguousarray(uv), *(np.ascontiguousarray(p) for p in segs))
    return np.where(d < SILHOUETTE_SNAP_PX, 0.0, d)


def _silhouette_distance_union(
    model: Model, T_camera_object: np.ndarray, intr: CameraIntrinsics, uv: np.ndarray, densify: int = 8
) -> np.ndarray:
    """Reference for :func:`silhouette_distance`: distance to the boundary of the shapely union of the
    projected front faces (each edge cut into ``densify`` straight pieces under lens distortion)."""
    import shapely

    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    boundary = _outline(model, T_camera_object, intr, densify=densify if intr.has_distortion else 1)
    if boundary is None or boundary.is_empty:
        return np.full(len(uv), np.nan)
    d = shapely.distance(shapely.points(uv), boundary)
    return np.where(d < SILHOUETTE_SNAP_PX, 0.0, d)
