"""CAD models of tracked parts: loading, validation, planar faces and features.

A model is a closed triangle mesh in the object frame (metres), read from STL,
OBJ, PLY or ViSP ``.cao`` (``vespro.cao``). Loading states the CAD unit
(``load_model(path, unit="mm")`` scales on load), validates the mesh at the
boundary (watertight, consistently wound with outward normals, no zero-area
triangles, a size that looks like metres; a file whose faces all point inward
is turned right way out with a note) and derives what the tracker and the
visibility query need. Open surfaces are refused: occlusion (``vespro.bsp``)
and corner visibility take the model as a solid. Commands that hand the model
to the simulator or a recording take it through ``model_file_in_metres``.
What the tracker and the visibility query get:

- planar faces: coplanar, edge-adjacent triangles merged into polygons (outer
  loop plus holes), each with its plane ``n . x = d`` (``n`` the outward unit
  normal, m) and its triangles;
- corners: vertices where at least three distinct planes meet and whose plane
  normals span 3D (so the corner is a well-defined point, not a point on a line
  of planes), with the planar faces around each;
- sharp edges: maximal straight segments between two planar faces with
  different normals, with both normals and a convex/concave flag.

Everything is computed once; the resulting ``Model`` is frozen and its arrays
are read-only (shared/STYLE.md: set-up is built once, never mutated).
"""

from __future__ import annotations

import hashlib
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError

__all__ = [
    "ModelError",
    "PlanarFace",
    "Model",
    "UNIT_SCALE",
    "load_model",
    "model_file_in_metres",
    "default_model_cache_dir",
    "model_from_arrays",
    "box_model",
]

#: Metres per CAD unit.
UNIT_SCALE = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "in": 0.0254}

#: A model whose largest extent exceeds this (m) was almost surely drawn in mm.
MAX_EXTENT_M = 5.0
#: ... and one smaller than this (m) was stated in a unit too large (a metre
#: file loaded as millimetres).
MIN_EXTENT_M = 1e-3

#: Two triangles (or planar faces) are coplanar when their normals differ by
#: less than this angle (rad) ...
COPLANAR_ANGLE = 1e-4
#: ... and their vertices lie within this fraction of the model size of each
#: other's plane. STL stores float32 (relative error ~6e-8), so these are a few
#: hundred times the rounding error and far below any real CAD feature.
COPLANAR_REL_DIST = 1e-6
#: A triangle whose area is below this fraction of (model size)^2 is degenerate.
DEGENERATE_REL_AREA = 1e-14

_SUPPORTED = (".stl", ".obj", ".ply", ".cao")

#: How to state the unit, for messages: the command-line option and the argument.
UNIT_HINT = "pass --model-unit {unit} on the command line (unit=\"{unit}\" to load_model)"


class ModelError(InputError):
    """A CAD file that cannot be read or is not a valid closed solid."""


def _ro(a: np.ndarray, dtype=None) -> np.ndarray:
    a = np.array(a, dtype=dtype)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class PlanarFace:
    """One planar face of a model: coplanar, edge-connected triangles.

    Attributes
    ----------
    normal : ndarray, shape (3,)
        Outward unit normal, object frame.
    offset : float
        Plane offset ``d`` in ``normal . x = d``, m.
    area : float
        m^2.
    triangles : ndarray, shape (k,), int64
        Indices into ``Model.triangles``.
    loops : tuple of ndarray, each shape (m,), int64
        Vertex indices (into ``Model.vertices``) of the boundary loops; the
        first is the outer loop (counter-clockwise seen from outside, i.e.
        about ``normal``), the others are holes (clockwise).
    """

    normal: np.ndarray
    offset: float
    area: float
    triangles: np.ndarray
    loops: tuple


@dataclass(frozen=True, eq=False)
class Model:
    """A validated closed CAD model and its tracking features (object frame, m).

    Frozen, with read-only arrays; compared by identity (``content_hash``
    says whether two models have the same geometry).

    Attributes
    ----------
    name : str
    source : str
        File it was loaded from ("" if built from arrays).
    vertices : ndarray, shape (V, 3)
        m.
    triangles : ndarray, shape (F, 3), int64
        Counter-clockwise seen from outside.
    triangle_face : ndarray, shape (F,), int64
        Planar face of each triangle.
    faces : tuple of PlanarFace, length P
    face_normals : ndarray, shape (P, 3)
        Outward unit normals.
    face_offsets : ndarray, shape (P,)
        ``d`` of each face plane ``n . x = d``, m.
    face_areas : ndarray, shape (P,)
        m^2.
    face_plane : ndarray, shape (P,), int64
        Index of the face's plane: faces in one plane (adjacent or not, facing
        either way) share one plane, so coplanarity is an identity.
    face_plane_sign : ndarray, shape (P,)
        +1 or -1: ``face_normals[f] == face_plane_sign[f] * plane_normals[face_plane[f]]``
        (and the same for offsets), exactly.
    plane_normals : ndarray, shape (Q, 3)
        Distinct planes of the model (unit normals), object frame.
    plane_offsets : ndarray, shape (Q,)
        Their offsets, m.
    corner_vertex : ndarray, shape (C,), int64
        Vertex index of each corner.
    corners : ndarray, shape (C, 3)
        Corner positions, m.
    corner_face_ptr, corner_face_idx : ndarray, int64
        Corner -> planar faces incidence in CSR form: the faces around corner
        ``i`` are ``corner_face_idx[corner_face_ptr[i]:corner_face_ptr[i+1]]``.
    corner_face_table : ndarray, shape (C, K), int64
        The same incidence padded with -1 (K = most faces at one corner), for
        vectorised use.
    corner_convex, corner_concave : ndarray, shape (C,), bool
        All sharp edges at the corner are convex (resp. concave); both False
        for a saddle corner.
    edge_vertices : ndarray, shape (E, 2), int64
        End vertices of each sharp edge (a maximal straight segment).
    edge_faces : ndarray, shape (E, 2), int64
        The two planar faces along the edge.
    edge_normals : ndarray, shape (E, 2, 3)
        Their outward normals.
    edge_convex : ndarray, shape (E,), bool
        True for a convex (outward) edge, False for a concave (re-entrant) one.
    bounds : ndarray, shape (2, 3)
        Axis-aligned bounding box (min, max), m.
    diameter : float
        Largest distance between two vertices, m.
    volume : float
        m^3, positive.
    content_hash : str
        sha256 hex digest of the float64 vertices and int64 triangles (after
        unit scaling): the key of derived caches such as the BSP tree.
    unit : str
        The CAD unit the file was stated in.
    """

    name: str
    source: str
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_face: np.ndarray
    faces: tuple
    face_normals: np.ndarray
    face_offsets: np.ndarray
    face_areas: np.ndarray
    face_plane: np.ndarray
    face_plane_sign: np.ndarray
    plane_normals: np.ndarray
    plane_offsets: np.ndarray
    corner_vertex: np.ndarray
    corners: np.ndarray
    corner_face_ptr: np.ndarray
    corner_face_idx: np.ndarray
    corner_face_table: np.ndarray
    corner_convex: np.ndarray
    corner_concave: np.ndarray
    edge_vertices: np.ndarray
    edge_faces: np.ndarray
    edge_normals: np.ndarray
    edge_convex: np.ndarray
    bounds: np.ndarray
    diameter: float
    volume: float
    content_hash: str
    unit: str = "m"

    @property
    def n_corners(self) -> int:
        return int(self.corners.shape[0])

    def corner_faces(self, i: int) -> np.ndarray:
        """Planar faces (indices into ``faces``) around corner ``i``."""
        return self.corner_face_idx[self.corner_face_ptr[i] : self.corner_face_ptr[i + 1]]

    @property
    def edge_points(self) -> np.ndarray:
        """End points of the sharp edges, shape (E, 2, 3), m."""
        return self.vertices[self.edge_vertices]


def content_hash(vertices: np.ndarray, triangles: np.ndarray) -> str:
    """sha256 hex digest of float64 vertices and int64 triangles (little endian)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(triangles, dtype="<i8").tobytes())
    return h.hexdigest()


def load_model(path, unit: str = "m", name: str | None = None) -> Model:
    """Load and validate a closed CAD mesh (STL, OBJ, PLY or ViSP ``.cao``).

    A mesh whose faces all point inward (inside out) is turned right way out,
    with a note on standard error; every other defect is refused.

    Parameters
    ----------
    path : str or Path
    unit : {"m", "cm", "mm", "in"}
        The unit the file is drawn in; coordinates are scaled to metres.
    name : str, optional
        Defaults to the file stem.

    Returns
    -------
    Model

    Raises
    ------
    ModelError
        Unreadable, empty or garbage file; mesh that is not a valid closed
        solid; a size that suggests another unit than ``unit``. The message
        names the file and says what to do.
    """
    model, notes = _load(Path(path), unit, name)
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    return model


def _load(path: Path, unit: str, name: str | None):
    if unit not in UNIT_SCALE:
        raise ValueError(f"unknown unit {unit!r}; use one of {sorted(UNIT_SCALE)}")
    if path.suffix.lower() not in _SUPPORTED:
        raise ModelError(f"{path}: unsupported file type {path.suffix!r}; use one of {_SUPPORTED}")
    if not path.is_file():
        raise ModelError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise ModelError(f"{path}: file is empty")
    if path.suffix.lower() == ".cao":
        from .cao import read_cao

        vertices, faces = read_cao(path)
    else:
        vertices, faces = _read_mesh(path)
    notes: list = []
    model = model_from_arrays(vertices, faces, unit=unit, name=name or path.stem, source=str(path),
                              fix_inside_out=notes)
    return model, notes


def default_model_cache_dir() -> Path:
    """``$VESPRO_MODEL_CACHE`` if set, else ``~/.cache/vespro/models``."""
    import os

    env = os.environ.get("VESPRO_MODEL_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "vespro" / "models"


def model_file_in_metres(path, unit: str = "m", cache_dir=None) -> Path:
    """A validated mesh file in metres for consumers that read files (simulator, recordings).

    The file itself when it is an STL, OBJ or PLY drawn in metres that loads
    as is; otherwise (another unit, a ``.cao``, an inside-out mesh turned
    right way out) the validated model written as a binary STL in metres, in
    ``cache_dir/<content hash>/<file stem>.stl`` (the stem names the object).

    Parameters
    ----------
    path : str or Path
    unit : str
        Key of ``UNIT_SCALE``: the unit the file is drawn in.
    cache_dir : str or Path, optional
        Defaults to ``default_model_cache_dir()``.

    Raises
    ------
    ModelError
        As ``load_model``.
    """
    path = Path(path)
    model, notes = _load(path, unit, None)
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    if unit == "m" and not notes and path.suffix.lower() in (".stl", ".obj", ".ply"):
        return path
    out = Path(cache_dir or default_model_cache_dir()) / model.content_hash[:16] / f"{path.stem}.stl"
    if not out.is_file():
        import os
        import tempfile

        import trimesh

        out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".stl", dir=out.parent)
        os.close(fd)
        trimesh.Trimesh(model.vertices, model.triangles, process=False).export(tmp, file_type="stl")
        os.replace(tmp, out)  # atomic: concurrent processes see a whole file or none
    return out


def _read_mesh(path: Path):
    import trimesh

    try:
        # process=True merges STL's duplicated vertices; validate=False keeps
        # degenerate and duplicate faces so that we can reject them by name.
        mesh = trimesh.load(str(path), force="mesh", process=True, validate=False)
    except Exception as e:  # trimesh raises many kinds on garbage
        raise ModelError(f"{path}: cannot read mesh ({type(e).__name__}: {e})") from e
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=float)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
    if faces.size == 0 or vertices.size == 0:
        raise ModelError(f"{path}: no triangles found (empty or not a {path.suffix} mesh)")
    return vertices, faces


def box_model(extents, center=(0.0, 0.0, 0.0), name: str = "box") -> Model:
    """An axis-aligned box, e.g. to approximate an arm link as an occluder.

    Parameters
    ----------
    extents : array_like, shape (3,)
        Side lengths, m.
    center : array_like, shape (3,)
        Box centre in the body frame, m.
    """
    import trimesh

    ext = np.asarray(extents, dtype=float)
    if ext.shape != (3,) or np.any(ext <= 0):
        raise ValueError(f"box extents must be 3 positive lengths, got {ext}")
    m = trimesh.creation.box(extents=ext)
    return model_from_arrays(np.asarray(m.vertices) + np.asarray(center, float), m.faces, name=name)


def model_from_arrays(vertices, triangles, unit: str = "m", name: str = "model", source: str = "",
                      fix_inside_out: list | None = None) -> Model:
    """Validate a triangle mesh and derive its planar faces, corners and edges.

    Parameters
    ----------
    vertices : array_like, shape (V, 3)
        In ``unit``.
    triangles : array_like, shape (F, 3), int
        Vertex indices; counter-clockwise seen from outside.
    unit : str
        Key of ``UNIT_SCALE``.
    name, source : str
        Used in messages and kept in the model.
    fix_inside_out : list, optional
        When given, a mesh whose faces all point inward is turned right way
        out and a note saying so is appended to this list; otherwise such a
        mesh is refused.

    Raises
    ------
    ModelError
        See ``load_model``.
    """
    where = source or name
    if unit not in UNIT_SCALE:
        raise ValueError(f"unknown unit {unit!r}; use one of {sorted(UNIT_SCALE)}")
    V = np.asarray(vertices, dtype=float)
    F = np.asarray(triangles)
    if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] == 0:
        raise ModelError(f"{where}: vertices must have shape (V, 3), V > 0; got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or F.shape[0] == 0:
        raise ModelError(f"{where}: triangles must have shape (F, 3), F > 0; got {F.shape}")
    if not np.all(np.isfinite(V)):
        raise ModelError(f"{where}: vertices contain non-finite values")
    if not np.issubdtype(F.dtype, np.integer) or F.min() < 0 or F.max() >= V.shape[0]:
        raise ModelError(f"{where}: triangle indices must be integers in [0, {V.shape[0]})")
    F = F.astype(np.int64)
    V = V * UNIT_SCALE[unit]
    # Drop vertices no triangle uses (OBJ files carry them); keep order.
    used = np.unique(F)
    if used.size != V.shape[0]:
        remap = -np.ones(V.shape[0], dtype=np.int64)
        remap[used] = np.arange(used.size)
        V, F = V[used], remap[F]

    extents = V.max(0) - V.min(0)
    size = float(extents.max())
    if size > MAX_EXTENT_M:
        raise ModelError(f"{where}: largest extent {size:.4g} m exceeds {MAX_EXTENT_M:g} m with the file read in "
                         f"{unit}: drawn in millimetres? {UNIT_HINT.format(unit='mm')}")
    if size <= 0:
        raise ModelError(f"{where}: all vertices coincide")
    if size < MIN_EXTENT_M:
        raise ModelError(f"{where}: largest extent {size:.4g} m is below {MIN_EXTENT_M * 1e3:g} mm with the file "
                         f"read in {unit}: state the unit it is drawn in, e.g. {UNIT_HINT.format(unit='m')}")

    # Degenerate triangles: repeated indices or (near) zero area.
    cross = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    dbl_area = np.linalg.norm(cross, axis=1)
    bad = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2])
    bad |= 0.5 * dbl_area <= DEGENERATE_REL_AREA * size * size
    if np.any(bad):
        raise ModelError(
            f"{where}: {int(bad.sum())} degenerate (zero-area) triangle(s), "
            f"first at index {int(np.flatnonzero(bad)[0])}"
        )

    # Edge structure: a closed, consistently wound mesh has every undirected
    # edge exactly twice, once in each direction.
    nV = V.shape[0]
    d_edges = F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)  # directed, 3 per triangle
    d_tri = np.repeat(np.arange(F.shape[0]), 3)
    u_key = np.minimum(d_edges[:, 0], d_edges[:, 1]) * nV + np.maximum(d_edges[:, 0], d_edges[:, 1])
    _, u_inv, u_cnt = np.unique(u_key, return_inverse=True, return_counts=True)
    if np.any(u_cnt == 1):
        raise ModelError(
            f"{where}: not watertight: {int(np.sum(u_cnt == 1))} boundary edge(s): an open surface (a hole, or a "
            f"missing face such as walls without a top); the tracker needs a closed solid: add the missing faces"
        )
    if np.any(u_cnt > 2):
        raise ModelError(f"{where}: not a manifold: {int(np.sum(u_cnt > 2))} edge(s) shared by more than two triangles")
    d_key = d_edges[:, 0] * nV + d_edges[:, 1]
    if np.unique(d_key).size != d_key.size:
        raise ModelError(f"{where}: inconsistent winding (some triangles are flipped relative to their neighbours): "
                         f"wind every face counter-clockwise seen from outside")
    volume = float(np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6.0)
    if volume < 0 and fix_inside_out is not None:
        F = np.ascontiguousarray(F[:, ::-1])
        cross = -cross
        volume = -volume
        d_edges = F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        u_key = np.minimum(d_edges[:, 0], d_edges[:, 1]) * nV + np.maximum(d_edges[:, 0], d_edges[:, 1])
        _, u_inv, u_cnt = np.unique(u_key, return_inverse=True, return_counts=True)
        fix_inside_out.append(f"{where}: every face pointed inward (the mesh was inside out); "
                              f"reversed them all so that they point outward")
    if volume <= 0:
        raise ModelError(f"{where}: normals point inward (volume {volume:.3g} m^3 <= 0): all faces are flipped; "
                         f"reverse the order of every face's vertices")

    tri_n = cross / dbl_area[:, None]
    tri_area = 0.5 * dbl_area

    # Pair the two directed occurrences of each undirected edge.
    order = np.argsort(u_inv, kind="stable")
    pair = order.reshape(-1, 2)  # rows: the two directed-edge ids of one edge
    ta, tb = d_tri[pair[:, 0]], d_tri[pair[:, 1]]
    ea = d_edges[pair[:, 0]]  # (a, b) as in triangle ta
    # Third vertex of each triangle opposite the edge.
    third_b = F[tb].sum(1) - ea.sum(1)
    third_a = F[ta].sum(1) - ea.sum(1)

    dist_tol = COPLANAR_REL_DIST * size
    cos_tol = np.cos(COPLANAR_ANGLE)
    ndot = np.einsum("ij,ij->i", tri_n[ta], tri_n[tb])
    off_b = np.abs(np.einsum("ij,ij->i", tri_n[ta], V[third_b] - V[ea[:, 0]]))
    off_a = np.abs(np.einsum("ij,ij->i", tri_n[tb], V[third_a] - V[ea[:, 0]]))
    coplanar = (ndot > cos_tol) & (off_a < dist_tol) & (off_b < dist_tol)

    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nF = F.shape[0]
    g = coo_matrix((np.ones(int(coplanar.sum())), (ta[coplanar], tb[coplanar])), shape=(nF, nF))
    n_faces, tri_face = connected_components(g, directed=False)
    tri_face = tri_face.astype(np.int64)

    # Plane of each face: area-weighted normal, area-weighted offset.
    face_area = np.bincount(tri_face, weights=tri_area, minlength=n_faces)
    nsum = np.stack([np.bincount(tri_face, weights=tri_n[:, k] * tri_area, minlength=n_faces) for k in range(3)], 1)
    face_n = nsum / np.linalg.norm(nsum, axis=1, keepdims=True)
    centroid = V[F].mean(1)
    w_d = np.einsum("ij,ij->i", face_n[tri_face], centroid) * tri_area
    face_d = np.bincount(tri_face, weights=w_d, minlength=n_faces)
    face_d /= face_area

    # Faces in one plane (not necessarily adjacent, either orientation) share
    # one exact plane: the BSP and the corner test need "same plane" to be an
    # identity, not a tolerance. Greedy clustering, largest faces first.
    plane_of_face, sign_of_face, reps = _cluster_planes(face_n, face_d, face_area, cos_tol, dist_tol)
    w = face_area * sign_of_face
    n_planes = len(reps)
    pn = np.stack([np.bincount(plane_of_face, weights=w * face_n[:, k], minlength=n_planes) for k in range(3)], 1)
    pn /= np.linalg.norm(pn, axis=1, keepdims=True)
    pd = np.bincount(plane_of_face, weights=w * face_d, minlength=n_planes)
    pd /= np.bincount(plane_of_face, weights=face_area, minlength=n_planes)
    face_n = pn[plane_of_face] * sign_of_face[:, None]
    face_d = pd[plane_of_face] * sign_of_face

    # Boundary loops of each face: directed edges whose twin lies in another face.
    fa, fb = tri_face[ta], tri_face[tb]
    sharp_pair = fa != fb
    twin = np.empty(d_edges.shape[0], dtype=np.int64)
    twin[pair[:, 0]] = pair[:, 1]
    twin[pair[:, 1]] = pair[:, 0]
    boundary = tri_face[d_tri] != tri_face[d_tri[twin]]
    loops_of_face = _face_loops(V, d_edges[boundary], tri_face[d_tri[boundary]], n_faces, face_n)

    tris_of_face = np.argsort(tri_face, kind="stable")
    tri_ptr = np.concatenate([[0], np.cumsum(np.bincount(tri_face, minlength=n_faces))])
    faces = tuple(
        PlanarFace(
            normal=_ro(face_n[i]),
            offset=float(face_d[i]),
            area=float(face_area[i]),
            triangles=_ro(tris_of_face[tri_ptr[i] : tri_ptr[i + 1]], np.int64),
            loops=tuple(_ro(lp, np.int64) for lp in loops_of_face[i]),
        )
        for i in range(n_faces)
    )

    # Sharp edges: mesh edges between faces with different normals, merged into
    # maximal straight segments per face pair.
    sa, sb = fa[sharp_pair], fb[sharp_pair]
    s_edge = ea[sharp_pair]
    s_third_b = third_b[sharp_pair]
    convex_mesh_edge = np.einsum("ij,ij->i", face_n[sa], V[s_third_b] - V[s_edge[:, 0]]) < 0
    edge_vertices, edge_faces, edge_convex = _merge_edges(s_edge, sa, sb, convex_mesh_edge)

    # Corners: vertices with >= 3 distinct face planes whose normals span 3D.
    vf = np.unique(np.stack([F.ravel(), np.repeat(tri_face, 3)], 1), axis=0)  # (vertex, face) pairs, sorted
    v_ptr = np.concatenate([[0], np.cumsum(np.bincount(vf[:, 0], minlength=nV))])
    corner_v, c_faces = [], []
    for v in np.flatnonzero(np.diff(v_ptr) >= 3):
        fs = vf[v_ptr[v] : v_ptr[v + 1], 1]
        distinct = np.unique(plane_of_face[fs])
        if len(distinct) < 3:
            continue
        # Smallest singular value of the distinct normals: 0 when all planes
        # share a line direction (no point feature there).
        if np.linalg.svd(pn[distinct], compute_uv=False)[2] < 1e-3:
            continue
        corner_v.append(v)
        c_faces.append(fs)
    corner_v = np.asarray(corner_v, dtype=np.int64)
    c_ptr = np.concatenate([[0], np.cumsum([len(f) for f in c_faces])]).astype(np.int64)
    c_idx = np.concatenate(c_faces).astype(np.int64) if c_faces else np.zeros(0, np.int64)
    kmax = max([len(f) for f in c_faces], default=0)
    table = -np.ones((len(c_faces), kmax), dtype=np.int64)
    for i, f in enumerate(c_faces):
        table[i, : len(f)] = f

    # Corner convexity from the sharp edges that end at it.
    c_cvx = np.ones(len(corner_v), bool)
    c_ccv = np.ones(len(corner_v), bool)
    pos = {int(v): i for i, v in enumerate(corner_v)}
    for (a, b), cv in zip(edge_vertices, edge_convex):
        for v in (int(a), int(b)):
            i = pos.get(v)
            if i is not None:
                c_cvx[i] &= bool(cv)
                c_ccv[i] &= not cv

    hull_pts = V
    try:
        from scipy.spatial import ConvexHull

        hull_pts = V[ConvexHull(V).vertices]
    except Exception:  # flat or tiny point sets: fall back to all vertices
        pass
    diff = hull_pts[:, None, :] - hull_pts[None, :, :]
    diameter = float(np.sqrt((diff * diff).sum(-1).max()))

    return Model(
        name=name,
        source=source,
        vertices=_ro(V),
        triangles=_ro(F, np.int64),
        triangle_face=_ro(tri_face, np.int64),
        faces=faces,
        face_normals=_ro(face_n),
        face_offsets=_ro(face_d),
        face_areas=_ro(face_area),
        face_plane=_ro(plane_of_face, np.int64),
        face_plane_sign=_ro(sign_of_face),
        plane_normals=_ro(pn),
        plane_offsets=_ro(pd),
        corner_vertex=_ro(corner_v, np.int64),
        corners=_ro(V[corner_v].reshape(-1, 3)),
        corner_face_ptr=_ro(c_ptr),
        corner_face_idx=_ro(c_idx),
        corner_face_table=_ro(table),
        corner_convex=_ro(c_cvx),
        corner_concave=_ro(c_ccv),
        edge_vertices=_ro(edge_vertices.reshape(-1, 2), np.int64),
        edge_faces=_ro(edge_faces.reshape(-1, 2), np.int64),
        edge_normals=_ro(face_n[edge_faces.reshape(-1, 2)].reshape(-1, 2, 3)),
        edge_convex=_ro(edge_convex, bool),
        bounds=_ro(np.stack([V.min(0), V.max(0)])),
        diameter=diameter,
        volume=volume,
        content_hash=content_hash(V, F),
        unit=unit,
    )


def _cluster_planes(face_n, face_d, face_area, cos_tol, dist_tol):
    """Group faces lying in one plane (either orientation).

    Returns (plane index per face (P,), sign per face (P,) float, representative faces).
    """
    P = len(face_n)
    plane = -np.ones(P, dtype=np.int64)
    sign = np.ones(P)
    reps: list[int] = []
    rep_n = np.zeros((0, 3))
    rep_d = np.zeros(0)
    for f in np.argsort(-face_area, kind="stable"):
        if reps:
            c = rep_n @ face_n[f]
            s = np.where(c >= 0, 1.0, -1.0)
            hit = np.flatnonzero((np.abs(c) > cos_tol) & (np.abs(face_d[f] - s * rep_d) < dist_tol))
            if hit.size:
                plane[f] = hit[0]
                sign[f] = s[hit[0]]
                continue
        plane[f] = len(reps)
        reps.append(int(f))
        rep_n = np.vstack([rep_n, face_n[f]])
        rep_d = np.append(rep_d, face_d[f])
    return plane, sign, reps


def _face_loops(V, b_edges, b_face, n_faces, face_n):
    """Chain each face's boundary edges into closed loops, outer loop first."""
    loops = [[] for _ in range(n_faces)]
    order = np.argsort(b_face, kind="stable")
    ptr = np.concatenate([[0], np.cumsum(np.bincount(b_face, minlength=n_faces))])
    for f in range(n_faces):
        edges = b_edges[order[ptr[f] : ptr[f + 1]]]
        out: dict[int, list[int]] = {}
        for a, b in edges:
            out.setdefault(int(a), []).append(int(b))
        face_loops = []
        while out:
            start = next(iter(out))
            loop = [start]
            cur = start
            while True:
                nxt = out[cur].pop()
                if not out[cur]:
                    del out[cur]
                if nxt == start:
                    break
                loop.append(nxt)
                cur = nxt
                if cur not in out:  # open chain: malformed, stop rather than loop
                    break
            face_loops.append(np.asarray(loop, dtype=np.int64))
        n = face_n[f]

        def signed_area(lp):
            P = V[lp]
            return 0.5 * float(n @ np.cross(P, np.roll(P, -1, axis=0)).sum(0))

        face_loops.sort(key=lambda lp: -signed_area(lp))
        loops[f] = face_loops
    return loops


def _merge_edges(s_edge, sa, sb, convex):
    """Merge collinear mesh edges with the same face pair into maximal segments.

    Returns (edge_vertices (E, 2), edge_faces (E, 2), edge_convex (E,)).
    """
    if len(s_edge) == 0:
        return np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64), np.zeros(0, bool)
    lo, hi = np.minimum(sa, sb), np.maximum(sa, sb)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, key in enumerate(zip(lo.tolist(), hi.tolist())):
        groups.setdefault(key, []).append(i)
    ev, ef, ec = [], [], []
    for (fa, fb), ids in groups.items():
        adj: dict[int, list[int]] = {}
        for i in ids:
            a, b = int(s_edge[i, 0]), int(s_edge[i, 1])
            adj.setdefault(a, []).append(b)
            adj.setdefault(b, []).append(a)
        cvx = bool(convex[ids[0]])
        seen: set[int] = set()
        # Walk chains from their ends (degree 1); what remains are cycles,
        # impossible for straight segments but handled for safety.
        starts = [v for v, nb in adj.items() if len(nb) == 1] + list(adj)
        for s in starts:
            if s in seen:
                continue
            seen.add(s)
            prev, cur = None, s
            while True:
                nxt = [w for w in adj[cur] if w != prev and w not in seen]
                if not nxt:
                    break
                prev, cur = cur, nxt[0]
                seen.add(cur)
            if cur != s:
                ev.append((s, cur))
                ef.append((fa, fb))
                ec.append(cvx)
    return np.asarray(ev, np.int64), np.asarray(ef, np.int64), np.asarray(ec, bool)
