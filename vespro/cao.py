"""ViSP ``.cao`` CAD models (the format of ViSP's model-based tracker) as triangles.

A ``.cao`` file holds, after a ``V1`` (or ``V2``) header and optional
``load("part.cao", t=[x; y; z], tu=[a; b; c])`` lines that include other files
(paths relative to the including file, ``t`` in metres, ``tu`` a theta-u
rotation in radians, or in degrees with a ``deg`` suffix), five sections, each
a count followed by that many lines:

1. 3D points ``X Y Z`` (``V2`` adds two image coordinates, ignored);
2. 3D lines ``i j`` (point indices);
3. faces from lines ``n l0 l1 ... l(n-1)`` (line indices, chained into a loop);
4. faces from points ``n p0 p1 ... p(n-1)``;
5. cylinders and 6. circles (both optional at the end of the file).

Text after the numbers a line needs is ignored (ViSP reads it as a comment or
as ``name=...`` parameters); lines starting with ``#`` and blank lines are
skipped; CRLF line endings are read as LF. Coordinates are in the file's unit
(ViSP models are in metres); the caller scales them (``vespro.model.load_model``).

Faces are polygons wound counter-clockwise seen from outside (as ViSP's face
visibility test needs). Convex polygons are split as a fan; concave ones by a
constrained Delaunay triangulation (shapely) of the polygon in its plane.
Lines that bound no face add no surface and are ignored. Cylinders and circles
are refused: the tracker follows corners and straight edges, and a round
surface has neither; a polygonal approximation would make corners that the
real part does not have.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .model import ModelError
from .se3 import exp_so3, transform_from_rt

__all__ = ["CaoError", "read_cao", "triangulate_polygon"]

#: Points closer than this (m) after the include transforms are one vertex.
MERGE_TOL = 1e-9


class CaoError(ModelError):
    """A ``.cao`` file that cannot be read; the message names file and line."""


class _Lines:
    """The meaningful lines of a file: (line number, tokens), comments skipped."""

    def __init__(self, path: Path):
        self.path = path
        try:
            text = path.read_bytes().decode("utf-8", errors="replace")
        except OSError as e:
            raise CaoError(f"{path}: cannot read ({e.strerror or e})") from None
        self.rows = []
        for k, raw in enumerate(text.replace("\r\n", "\n").replace("\r", "\n").split("\n"), start=1):
            s = raw.strip()
            if s and not s.startswith("#"):
                self.rows.append((k, s))
        self.i = 0

    def peek(self):
        return self.rows[self.i] if self.i < len(self.rows) else None

    def next(self, what: str):
        if self.i >= len(self.rows):
            last = self.rows[-1][0] if self.rows else 0
            raise CaoError(f"{self.path}:{last}: file ends where {what} was expected")
        row = self.rows[self.i]
        self.i += 1
        return row

    def numbers(self, what: str, n: int | None, kind=float):
        """Leading numbers of the next line: ``n`` of them (or a count then that many if None)."""
        k, s = self.next(what)
        toks = s.split()
        vals = []
        for t in toks:
            try:
                vals.append(kind(t) if kind is float else _int(t))
            except ValueError:
                break
        need = n
        if n is None:  # "count idx idx ..."
            if not vals:
                raise CaoError(f"{self.path}:{k}: {what}: expected a count, got {s!r}")
            need = 1 + int(vals[0])
            if vals[0] < 0:
                raise CaoError(f"{self.path}:{k}: {what}: negative count {vals[0]}")
        if len(vals) < need:
            raise CaoError(f"{self.path}:{k}: {what}: expected {need} number(s), got {s!r}")
        return k, vals[:need]


def _int(t: str) -> int:
    v = float(t)
    if v != int(v):
        raise ValueError(t)
    return int(v)


def _count(lines: _Lines, what: str) -> int:
    k, (n,) = lines.numbers(f"number of {what}", 1, kind=int)
    if n < 0:
        raise CaoError(f"{lines.path}:{k}: negative number of {what}: {n}")
    return n


_LOAD = re.compile(r"^load\s*\(\s*\"([^\"]*)\"(.*)\)", re.IGNORECASE)


def _vector(text: str, key: str, where: str):
    m = re.search(key + r"\s*=\s*\[([^\]]*)\]", text)
    if m is None:
        return None
    vals = []
    for v in m.group(1).split(";"):
        v = v.strip()
        scale = 1.0
        if v.endswith("deg"):
            v, scale = v[:-3], np.pi / 180.0
        elif v.endswith("rad"):
            v = v[:-3]
        try:
            vals.append(float(v) * scale)
        except ValueError:
            raise CaoError(f"{where}: {key}=[...] needs three numbers separated by ';', got {m.group(1)!r}") from None
    if len(vals) != 3:
        raise CaoError(f"{where}: {key}=[...] needs three numbers separated by ';', got {m.group(1)!r}")
    return vals


def read_cao(path, _stack: tuple = ()) -> tuple[np.ndarray, np.ndarray]:
    """Read a ``.cao`` file (and the files it loads) as one triangle mesh.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    vertices : ndarray, shape (V, 3)
        In the file's unit, object frame; coincident points merged.
    triangles : ndarray, shape (F, 3), int64
        Counter-clockwise seen from outside, as the file's faces are wound.

    Raises
    ------
    CaoError
        Missing file, bad header, malformed or out-of-range entry, an include
        cycle, a cylinder or circle; the message names the file and line.
    """
    V, F = _read(Path(path), np.eye(4), _stack)
    if len(F) == 0:
        raise CaoError(f"{path}: no faces (a .cao needs faces from points or from lines to make a surface)")
    key = np.round(V / MERGE_TOL).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return V[first], inv.reshape(-1)[F]


def _read(path: Path, T_top_file: np.ndarray, stack: tuple):
    path = path.resolve() if path.exists() else path
    if not path.is_file():
        where = f" (loaded from {stack[-1]})" if stack else ""
        raise CaoError(f"{path}: no such file{where}")
    if path in stack:
        raise CaoError(f"{stack[-1]}: load() cycle: {path} includes itself")
    lines = _Lines(path)
    row = lines.next("the header V1")
    k, s = row
    if not re.match(r"^V\d+\b", s):
        raise CaoError(f"{path}:{k}: expected the header V1, got {s!r}")

    Vs, Fs, nv = [], [], 0
    while (row := lines.peek()) is not None and row[1][:4].lower() == "load":
        lines.next("load")
        k, s = row
        m = _LOAD.match(s)
        if m is None:
            raise CaoError(f"{path}:{k}: expected load(\"file.cao\"), got {s!r}")
        where = f"{path}:{k}"
        t = _vector(m.group(2), "t", where) or [0.0, 0.0, 0.0]
        tu = _vector(m.group(2), "tu", where) or [0.0, 0.0, 0.0]
        T = transform_from_rt(exp_so3(tu), t)
        sub = Path(m.group(1))
        if not sub.is_absolute():
            sub = path.parent / sub
        V, F = _read(sub, T_top_file @ T, stack + (path,))
        Vs.append(V)
        Fs.append(F + nv)
        nv += len(V)

    n_pts = _count(lines, "3D points")
    P = np.zeros((n_pts, 3))
    for i in range(n_pts):
        _, P[i] = lines.numbers(f"3D point {i}", 3)
    n_lines = _count(lines, "3D lines")
    L = np.zeros((n_lines, 2), np.int64)
    for i in range(n_lines):
        k, L[i] = lines.numbers(f"3D line {i}", 2, kind=int)
        _check_index(L[i], n_pts, f"{path}:{k}", "point")
    faces = []
    for i in range(_count(lines, "faces from lines")):
        k, vals = lines.numbers(f"face from lines {i}", None, kind=int)
        _check_index(vals[1:], n_lines, f"{path}:{k}", "line")
        faces.append((k, _chain_lines(L[vals[1:]], f"{path}:{k}")))
    for i in range(_count(lines, "faces from points")):
        k, vals = lines.numbers(f"face from points {i}", None, kind=int)
        _check_index(vals[1:], n_pts, f"{path}:{k}", "point")
        faces.append((k, list(vals[1:])))
    for what in ("3D cylinders", "3D circles"):
        if lines.peek() is None:  # older files end after the faces
            break
        k = lines.peek()[0]
        if _count(lines, what):
            raise CaoError(f"{path}:{k}: {what} are not supported (the tracker follows corners and straight edges; "
                           f"a round surface has neither): remove them, or model the part as polygon faces or as a "
                           f"mesh file (STL, OBJ, PLY)")

    tris = []
    for k, loop in faces:
        if len(loop) < 3:
            raise CaoError(f"{path}:{k}: a face needs at least 3 points, got {len(loop)}")
        if len(set(loop)) != len(loop):
            raise CaoError(f"{path}:{k}: a face repeats a point ({loop})")
        tri = triangulate_polygon(P[loop])
        if tri is None:
            raise CaoError(f"{path}:{k}: face {loop} is not a simple polygon (its sides cross or it has no area)")
        tris.append(np.asarray(loop, np.int64)[tri])
    Ph = np.c_[P, np.ones(n_pts)] @ T_top_file.T
    Vs.append(Ph[:, :3])
    Fs.append((np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)) + nv)
    return np.concatenate(Vs), np.concatenate(Fs)


def _check_index(idx, n: int, where: str, kind: str) -> None:
    bad = [int(i) for i in idx if not 0 <= int(i) < n]
    if bad:
        raise CaoError(f"{where}: {kind} index {bad[0]} out of range (the file declares {n} {kind}s)")


def _chain_lines(L: np.ndarray, where: str) -> list[int]:
    """Point loop of a face given by its lines, in the direction of its first line."""
    loop = [int(L[0, 0]), int(L[0, 1])]
    rest = [tuple(map(int, e)) for e in L[1:]]
    while rest:
        for j, (a, b) in enumerate(rest):
            if a == loop[-1] or b == loop[-1]:
                nxt = b if a == loop[-1] else a
                rest.pop(j)
                break
        else:
            raise CaoError(f"{where}: the face's lines do not form one closed loop")
        if nxt == loop[0]:
            if rest:
                raise CaoError(f"{where}: the face's lines do not form one closed loop")
            return loop
        loop.append(nxt)
    raise CaoError(f"{where}: the face's lines do not form one closed loop")


def triangulate_polygon(P: np.ndarray) -> np.ndarray | None:
    """Triangles of a planar polygon, wound as the polygon is.

    Parameters
    ----------
    P : ndarray, shape (n, 3)
        Vertices in order, n >= 3.

    Returns
    -------
    ndarray, shape (n - 2, 3), int64, or None
        Indices into ``P``; None when the polygon has no area or its sides
        cross.
    """
    n = len(P)
    normal = np.cross(P, np.roll(P, -1, axis=0)).sum(0)  # Newell: 2 * area * unit normal
    area2 = float(np.linalg.norm(normal))
    if area2 <= 1e-18:
        return None
    normal /= area2
    u = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    Q = np.stack([(P - P[0]) @ u, (P - P[0]) @ v], 1)  # counter-clockwise about the normal
    d = np.roll(Q, -1, 0) - Q
    turn = d[:, 0] * np.roll(d, -1, 0)[:, 1] - d[:, 1] * np.roll(d, -1, 0)[:, 0]
    import shapely

    poly = shapely.Polygon(Q)
    if not poly.is_valid:
        return None
    if np.all(turn > 1e-9 * area2):  # strictly convex: a fan (no three points in a line)
        return np.stack([np.zeros(n - 2, np.int64), np.arange(1, n - 1), np.arange(2, n)], 1)
    index = {tuple(q): i for i, q in enumerate(Q.tolist())}
    out = []
    for t in shapely.get_parts(shapely.constrained_delaunay_triangles(poly)):
        c = shapely.get_coordinates(t)[:3]
        tri = [index[tuple(q)] for q in c.tolist()]
        a, b, cc = Q[tri]
        if (b[0] - a[0]) * (cc[1] - a[1]) - (b[1] - a[1]) * (cc[0] - a[0]) < 0:
            tri = tri[::-1]
        out.append(tri)
    return np.asarray(out, np.int64)
