"""Solid BSP tree of a closed model, for batched line-of-sight queries.

The tree is an auto-partition: every node's plane is the plane of one of the
model's planar faces, and the polygons (triangle fragments) lying in that plane
within the node's cell are stored at the node. Polygons that straddle a node's
plane are split. Because the model is a closed, outward-oriented solid, an
empty side is a leaf whose cell is entirely outside (front side) or entirely
inside (back side) the solid: a "solid-leaf" tree (Naylor). A segment is
blocked by the solid exactly when part of it lies in an inside leaf, so the
occlusion query only clips segments against node planes and never tests
polygons; the polygons stay in the tree (and the cache) for other uses such as
rendering or hit reporting.

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

from vespro.model import Model

__all__ = ["OUT", "IN", "BSPTree", "build_bsp", "load_or_build_bsp", "default_cache_dir", "FORMAT_VERSION"]

#: Leaf codes in the child arrays (non-negative values are node indices).
OUT = -1
IN = -2

#: Bump when the build or the file layout changes: old cache files are ignored.
FORMAT_VERSION = 1

_ARRAYS = ("normal", "offset", "face", "front", "back", "poly_ptr", "poly_vertices", "poly_face")


def _ro(a, dtype=None):
    a = np.array(a, dtype=dtype)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
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
    build_seconds : float
        Wall time of the build (0 when loaded from cache is not recorded: the
        build time of the original build is kept).
    """

    normal: np.ndarray
    offset: np.ndarray
    face: np.ndarray
    front: np.ndarray
    back: np.ndarray
    poly_ptr: np.ndarray
    poly_vertices: np.ndarray
    poly_face: np.ndarray
    content_hash: str
    depth: int
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

    def segments_blocked(self, A: np.ndarray, B: np.ndarray, t_lo=0.0, t_hi=1.0, min_length: float = 0.0) -> np.ndarray:
        """Whether segments pass through the solid.

        The segment ``i`` is ``x(t) = A[i] + t (B[i] - A[i])`` for ``t`` in
        ``[t_lo[i], t_hi[i]]``; it is blocked when a piece of it longer than
        ``min_length`` (in ``t``) lies in an inside cell. Trimming ``t`` keeps
        the surfaces at the segment ends (a corner on the model itself) from
        counting.

        Parameters
        ----------
        A, B : ndarray, shape (K, 3)
            Segment ends, object frame, m.
        t_lo, t_hi : float or ndarray, shape (K,)
        min_length : float
            Pieces this short (in ``t``) are ignored: tangent touches.

        Returns
        -------
        ndarray, shape (K,), bool
        """
        A = np.asarray(A, dtype=float).reshape(-1, 3)
        B = np.asarray(B, dtype=float).reshape(-1, 3)
        k = A.shape[0]
        blocked = np.zeros(k, dtype=bool)
        seg = np.arange(k)
        node = np.zeros(k, dtype=np.int64)
        t0 = np.broadcast_to(np.asarray(t_lo, dtype=float), (k,)).copy()
        t1 = np.broadcast_to(np.asarray(t_hi, dtype=float), (k,)).copy()
        live = t1 - t0 > min_length
        seg, node, t0, t1 = seg[live], node[live], t0[live], t1[live]
        N, D, FR, BK = self.normal, self.offset, self.front, self.back
        # Distances of the ends to every node plane are computed lazily per
        # visited (segment, node) pair: the tree can be far larger than the
        # number of pairs visited.
        while seg.size:
            n = N[node]
            d = D[node]
            ha = np.einsum("ij,ij->i", A[seg], n) - d
            hb = np.einsum("ij,ij->i", B[seg], n) - d
            dh = hb - ha
            h0 = ha + t0 * dh
            h1 = ha + t1 * dh
            gf = (h0 > 0) | (h1 > 0)
            gb = (h0 < 0) | (h1 < 0)
            gf |= ~(gf | gb)  # lying in the plane: a grazing view, call it front
            span = gf & gb
            with np.errstate(divide="ignore", invalid="ignore"):
                ts = np.where(span, -ha / dh, 0.0)
            first_front = h0 > 0
            # Front piece: [t0, ts] if it starts in front, else [ts, t1].
            f0 = np.where(span & ~first_front, ts, t0)[gf]
            f1 = np.where(span & first_front, ts, t1)[gf]
            b0 = np.where(span & first_front, ts, t0)[gb]
            b1 = np.where(span & ~first_front, ts, t1)[gb]
            seg = np.concatenate([seg[gf], seg[gb]])
            node = np.concatenate([FR[node[gf]], BK[node[gb]]])
            t0 = np.concatenate([f0, b0])
            t1 = np.concatenate([f1, b1])
            inside = node == IN
            if inside.any():
                hit = inside & (t1 - t0 > min_length)
                blocked[seg[hit]] = True
                keep = (node >= 0) & ~blocked[seg]
            else:
                keep = node >= 0
            seg, node, t0, t1 = seg[keep], node[keep], t0[keep], t1[keep]
        return blocked

    def arrays(self) -> dict:
        return {name: getattr(self, name) for name in _ARRAYS}


def build_bsp(model: Model, max_candidates: int = 24, split_weight: float = 6.0, rel_eps: float = 1e-7) -> BSPTree:
    """Build the solid BSP tree of a model.

    Parameters
    ----------
    model : Model
    max_candidates : int
        Planes scored per node: those of the largest faces (by fragment area)
        in the node.
    split_weight : float
        Cost of one split relative to one triangle of imbalance.
    rel_eps : float
        Plane thickness as a fraction of the model diameter: vertices closer
        than this to a plane count as on it (float32 CAD coordinates are good
        to ~6e-8 relative).

    Returns
    -------
    BSPTree
    """
    t_start = time.perf_counter()
    eps = rel_eps * model.diameter
    fn, fd = np.asarray(model.face_normals), np.asarray(model.face_offsets)
    tri = np.asarray(model.vertices)[np.asarray(model.triangles)]  # (F, 3, 3)
    tface = np.asarray(model.triangle_face)

    normal, offset, face, front, back, polys, pface = [], [], [], [], [], [], []
    # Stack of (triangles, their faces, parent node, is_front_child, depth).
    stack = [(tri, tface, -1, True, 1)]
    depth = 0
    while stack:
        T, TF, parent, is_front, dep = stack.pop()
        i = len(normal)
        if parent >= 0:
            (front if is_front else back)[parent] = i
        depth = max(depth, dep)
        f = _choose_face(T, TF, fn, fd, eps, max_candidates, split_weight)
        n, d = fn[f], fd[f]
        h = T @ n - d  # (M, 3)
        pos = (h > eps).any(1)
        neg = (h < -eps).any(1)
        on = ~pos & ~neg
        span = pos & neg
        only_f = pos & ~neg
        only_b = neg & ~pos
        Tf, TFf = [T[only_f]], [TF[only_f]]
        Tb, TFb = [T[only_b]], [TF[only_b]]
        for j in np.flatnonzero(span):
            pf, pb = _split_triangle(T[j], h[j], eps)
            Tf.append(pf)
            TFf.append(np.full(len(pf), TF[j]))
            Tb.append(pb)
            TFb.append(np.full(len(pb), TF[j]))
        Tf, TFf = np.concatenate(Tf), np.concatenate(TFf)
        Tb, TFb = np.concatenate(Tb), np.concatenate(TFb)
        normal.append(n)
        offset.append(d)
        face.append(f)
        front.append(OUT)
        back.append(IN)
        polys.append(T[on])
        pface.append(TF[on])
        # Push back first so the front subtree is numbered right after its parent.
        if len(Tb):
            stack.append((Tb, TFb, i, False, dep + 1))
        if len(Tf):
            stack.append((Tf, TFf, i, True, dep + 1))

    counts = np.array([len(p) for p in polys], dtype=np.int64)
    return BSPTree(
        normal=_ro(np.array(normal, dtype=float).reshape(-1, 3)),
        offset=_ro(np.array(offset, dtype=float)),
        face=_ro(np.array(face, dtype=np.int64)),
        front=_ro(np.array(front, dtype=np.int64)),
        back=_ro(np.array(back, dtype=np.int64)),
        poly_ptr=_ro(np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)),
        poly_vertices=_ro(np.concatenate(polys).reshape(-1, 3, 3)),
        poly_face=_ro(np.concatenate(pface).astype(np.int64)),
        content_hash=model.content_hash,
        depth=int(depth),
        build_seconds=time.perf_counter() - t_start,
    )


def _choose_face(T, TF, fn, fd, eps, max_candidates, split_weight) -> int:
    """Face whose plane splits the triangles ``T`` (M, 3, 3) best."""
    faces, local = np.unique(TF, return_inverse=True)
    if faces.size == 1:
        return int(faces[0])
    e1, e2 = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
    area = np.bincount(local, weights=np.linalg.norm(np.cross(e1, e2), axis=1), minlength=faces.size)
    # Largest faces first; stable so that ties keep a deterministic order.
    cand = faces[np.argsort(-area, kind="stable")[:max_candidates]]
    h = np.einsum("kc,mvc->kmv", fn[cand], T) - fd[cand][:, None, None]  # (K, M, 3)
    pos = (h > eps).any(2)
    neg = (h < -eps).any(2)
    n_span = (pos & neg).sum(1)
    n_front = (pos & ~neg).sum(1)
    n_back = (neg & ~pos).sum(1)
    score = split_weight * n_span + np.abs(n_front - n_back)
    return int(cand[int(np.argmin(score))])


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
    meta = np.array([tree.content_hash, str(FORMAT_VERSION), str(tree.depth), repr(tree.build_seconds)])
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
    if len(meta) != 4 or meta[0] != content_hash or meta[1] != str(FORMAT_VERSION):
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
        build_seconds=float(meta[3]),
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
