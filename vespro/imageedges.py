"""Image edges of a model at a pose: the measurement primitives every edge user shares.

A model edge is measured in an image along its projected normal (a
correspondence line): which model edges a camera sees at a pose (back-face
culling, and the BSP line of sight for a non-convex part), where their points
project, and the image gradient those lines read, with the intensity noise
that sets how strong a gradient must be to be an edge at all. The
initialiser's scores (:mod:`vespro.init.search`), the pose fits on image edges
that the initialiser and the tracker's edge aid share (:mod:`vespro.edgefit`)
and the pose likelihood (:mod:`vespro.likelihood`) all measure through these
functions.

Model features (edge samples, faces, edges) come from
:func:`vespro.init.modelfeat.model_features`; any object with the same
attributes will do.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from .jit import njit
from .numerics import front_face_mask, transform_point
from .se3 import invert_transform

__all__ = ["EdgeImage", "image_gradient", "image_noise", "sobel_noise_gain", "project_points", "projection_box",
           "front_faces", "edge_visible", "visible_samples", "silhouette_sides"]


def image_gradient(img: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Sobel (3x3) gradient of the Gaussian-smoothed image, of the strongest channel.

    Parameters
    ----------
    img : ndarray, shape (H, W) or (H, W, C), uint8
    sigma : float
        Smoothing std, px (0: none).

    Returns
    -------
    dx, dy : ndarray, shape (H, W), int16
        d/du and d/dv (as Canny wants them); an object can differ from its
        background in hue alone, so per pixel the channel of largest magnitude.
    """
    f = cv2.GaussianBlur(img, (0, 0), sigma) if sigma > 0 else img
    dx = cv2.Sobel(f, cv2.CV_16S, 1, 0, ksize=3)
    dy = cv2.Sobel(f, cv2.CV_16S, 0, 1, ksize=3)
    if dx.ndim == 3:
        mag = dx.astype(np.int32) ** 2 + dy.astype(np.int32) ** 2
        k = np.argmax(mag, axis=2)[..., None]
        dx = np.take_along_axis(dx, k, 2)[..., 0]
        dy = np.take_along_axis(dy, k, 2)[..., 0]
    return np.ascontiguousarray(dx), np.ascontiguousarray(dy)


def image_noise(img: np.ndarray) -> float:
    """Std of the additive intensity noise of an image, grey levels (largest over channels).

    Immerkaer's difference of Laplacians (1996), which cancels smooth shading,
    with the median instead of the mean of its magnitude so that the edges and
    texture of a scene (a minority of pixels) do not count: ``median |c| =
    0.6745 x 6 sigma`` for Gaussian noise (on every other pixel of every
    other row: enough samples). Zero for a noise-free rendering.
    """
    chans = [img] if img.ndim == 2 else [img[..., k] for k in range(img.shape[2])]
    out = 0.0
    for c in chans:
        if c.dtype == np.uint8:
            m = _laplace_diff_median(c)
        else:  # (any other depth: the same estimate by OpenCV and NumPy)
            r = cv2.filter2D(c.astype(np.float32), -1, _LAPLACE_DIFF)[1:-1:2, 1:-1:2]
            m = float(np.median(np.abs(r)))
        out = max(out, m / (0.6745 * 6.0))
    return out


_LAPLACE_DIFF = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


@njit
def _laplace_diff_median(img):
    """The median of ``|c|`` of :func:`image_noise` over every other pixel of every other row
    of an 8-bit image, inside the border (NaN: no such pixel): the 3x3 kernel ``[[1, -2, 1], [-2, 4, -2],
    [1, -2, 1]]`` applied to those pixels alone, in integers, and the median read off their
    counts (each ``|c|`` an integer of at most 16 x 255). OpenCV's ``filter2D`` of the float32
    image gives the same integers exactly, and the median of integers (or the mean of the
    middle two) is exact however it is found: the NumPy formulation's value."""
    H, W = img.shape
    counts = np.zeros(16 * 255 + 1, np.int64)
    n = 0
    for y in range(1, H - 1, 2):
        for x in range(1, W - 1, 2):
            c = (np.int32(img[y - 1, x - 1]) - 2 * np.int32(img[y - 1, x]) + np.int32(img[y - 1, x + 1])
                 - 2 * np.int32(img[y, x - 1]) + 4 * np.int32(img[y, x]) - 2 * np.int32(img[y, x + 1])
                 + np.int32(img[y + 1, x - 1]) - 2 * np.int32(img[y + 1, x]) + np.int32(img[y + 1, x + 1]))
            counts[abs(c)] += 1
            n += 1
    if n == 0:
        return np.nan
    lo_rank, hi_rank = (n - 1) // 2, n // 2  # the middle one, or the middle two
    lo = hi = -1
    seen = 0
    for v in range(counts.shape[0]):
        seen += counts[v]
        if lo < 0 and seen > lo_rank:
            lo = v
        if seen > hi_rank:
            hi = v
            break
    return 0.5 * (lo + hi)


@lru_cache(maxsize=8)
def sobel_noise_gain(blur_sigma: float) -> float:
    """Std of one Sobel (3x3) component of Gaussian-smoothed unit white noise."""
    d = np.zeros((41, 41), np.float32)
    d[20, 20] = 1.0
    if blur_sigma > 0:
        d = cv2.GaussianBlur(d, (0, 0), blur_sigma)
    return float(np.sqrt(np.sum(cv2.Sobel(d, cv2.CV_32F, 1, 0, ksize=3) ** 2)))


def project_points(K: np.ndarray, T_camera_object: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of object points.

    Parameters
    ----------
    K : ndarray, shape (3, 3)
    T_camera_object : ndarray, shape (4, 4)
    P : ndarray, shape (N, 3)
        Object frame, m.

    Returns
    -------
    uv : ndarray, shape (N, 2)
        px (inf or NaN for a point at depth 0).
    z : ndarray, shape (N,)
        Depth, m.
    """
    X = P @ T_camera_object[:3, :3].T + T_camera_object[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :2] / X[:, 2:3] * K[[0, 1], [0, 1]] + K[:2, 2], X[:, 2]


def projection_box(K: np.ndarray, T_camera_object: np.ndarray, P: np.ndarray, margin_px: float, width: int,
                   height: int) -> tuple[int, int, int, int] | None:
    """Pixel box ``(x0, y0, x1, y1)`` around the projection of points ``P`` (N, 3) with ``margin_px``
    on every side, clipped to the image; None when a point is behind the camera, a pixel is not
    finite or beyond 1e15, or the box is under 8 px either way.

    Compiled (:func:`_projection_extent`, the tracker's edge fit asks every frame); where a
    point's pixel is NaN or beyond 1e15, as :func:`projection_box_numpy`.
    """
    if len(P) == 1:  # (NumPy multiplies one point otherwise: gemv)
        return projection_box_numpy(K, T_camera_object, P, margin_px, width, height)
    T = np.ascontiguousarray(T_camera_object, dtype=float)
    behind, u0, v0, u1, v1 = _projection_extent(K[0, 0], K[1, 1], K[0, 2], K[1, 2], T, P)
    if behind:
        return None
    if not max(abs(u0), abs(v0), abs(u1), abs(v1)) < 1e15:  # NaN, or beyond NumPy's integer cast
        return projection_box_numpy(K, T_camera_object, P, margin_px, width, height)
    return _clip_box(math.floor(u0 - margin_px), math.floor(v0 - margin_px), math.ceil(u1 + margin_px),
                     math.ceil(v1 + margin_px), width, height)


@njit
def _projection_extent(fx, fy, cx, cy, T, P):
    """(a point at depth <= 1e-6, least u, least v, largest u, largest v) of the pinhole
    projection of ``P`` (N, 3) at ``T`` (4, 4): :func:`project_points`'s arithmetic (the
    rotation as OpenBLAS's gemm, :func:`vespro.numerics.transform_point`), so the same pixels. NaN
    extents where a pixel is NaN (NumPy's min and max propagate it)."""
    u0 = v0 = np.inf
    u1 = v1 = -np.inf
    behind = False
    for i in range(P.shape[0]):
        X0, X1, z = transform_point(T, P[i, 0], P[i, 1], P[i, 2])
        if z <= 1e-6:
            behind = True
        u = X0 / z * fx + cx
        v = X1 / z * fy + cy
        if np.isnan(u) or np.isnan(u0):
            u0 = u1 = np.nan
        else:
            u0 = min(u0, u)
            u1 = max(u1, u)
        if np.isnan(v) or np.isnan(v0):
            v0 = v1 = np.nan
        else:
            v0 = min(v0, v)
            v1 = max(v1, v)
    return behind, u0, v0, u1, v1


def _clip_box(x0, y0, x1, y1, width, height):
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    return int(x0), int(y0), int(x1), int(y1)


def projection_box_numpy(K: np.ndarray, T_camera_object: np.ndarray, P: np.ndarray, margin_px: float, width: int,
                         height: int) -> tuple[int, int, int, int] | None:
    """:func:`projection_box` in NumPy (for any input: a pixel that is not finite included)."""
    uv, z = project_points(K, T_camera_object, P)
    if np.any(z <= 1e-6):
        return None
    if not np.all(np.abs(uv) < 1e15):
        return None  # (a pixel that is not finite, or beyond an integer's range, has no box)
    x0, y0 = np.floor(uv.min(0) - margin_px).astype(int)
    x1, y1 = np.ceil(uv.max(0) + margin_px).astype(int)
    return _clip_box(x0, y0, x1, y1, width, height)


def front_faces(R: np.ndarray, t: np.ndarray, mf) -> np.ndarray:
    """Which faces the camera sees from their outer side, (H, F) bool, for H poses ``R`` (H, 3, 3), ``t`` (H, 3)."""
    n_c = np.matmul(mf.face_normals.astype(R.dtype)[None], R.transpose(0, 2, 1))  # (H, F, 3)
    return mf.face_offsets[None, :] + np.matmul(n_c, t[:, :, None])[..., 0] < 0


def edge_visible(front: np.ndarray, mf) -> np.ndarray:
    """Which model edges can be seen, (H, E) bool, from the faces seen ``front`` (H, F): a convex
    edge when one of its faces is, a concave edge when both are."""
    f0 = front[:, mf.edge_faces[:, 0]]
    f1 = front[:, mf.edge_faces[:, 1]]
    return np.where(mf.edge_convex[None, :], f0 | f1, f0 & f1)


def visible_samples(T_camera_object: np.ndarray, mf, tree=None) -> np.ndarray:
    """Dense edge samples a camera sees at a pose (culling plus self-occlusion).

    Parameters
    ----------
    T_camera_object : ndarray, shape (4, 4)
    mf : ModelFeatures
    tree : BSPTree or None
        Needed for non-convex models (line of sight to the camera centre).

    Returns
    -------
    idx : ndarray, shape (S,), int64
        Indices into ``mf.sample_p``.

    Notes
    -----
    The culling and each sample's segment to the camera centre in one compiled
    pass (:func:`_visible_kernel`), then the tree's walk: the NumPy code's
    arithmetic (:func:`front_faces`, :func:`edge_visible`), the same samples.
    """
    T = np.ascontiguousarray(T_camera_object, dtype=float)
    with_tree = tree is not None and not mf.convex
    cam_o = invert_transform(T)[:3, 3] if with_tree else np.zeros(3)
    idx, A, B, t_lo = _visible_kernel(T, mf.face_normals, mf.face_offsets, mf.edge_faces, mf.edge_convex,
                                      mf.sample_edge, mf.sample_p, cam_o, with_tree)
    if with_tree and idx.size:
        idx = idx[~tree.segments_blocked(A, B, t_lo=t_lo, t_hi=1.0, min_length=1e-9)]
    return idx


@njit
def _visible_kernel(T, face_normals, face_offsets, edge_faces, edge_convex, sample_edge, sample_p, cam_o, segments):
    """The samples of the edges :func:`edge_visible` keeps at pose ``T`` (4, 4), and with
    ``segments`` their lines of sight for the tree: starts ``A`` (the samples), ends ``B``
    (``cam_o``, the camera centre in the object frame) and ``t_lo`` (``2e-4 m`` of each
    segment's length, at most 0.1), (K, 3), (K, 3), (K,). The face test:
    :func:`vespro.numerics.front_face_mask`, the same bits."""
    F = face_normals.shape[0]
    front = front_face_mask(T, face_normals, face_offsets)
    E = edge_faces.shape[0]
    vis_e = np.empty(E, np.bool_)
    for e in range(E):
        f0, f1 = edge_faces[e, 0], edge_faces[e, 1]
        s0 = front[f0 + F if f0 < 0 else f0]  # (NumPy's negative index)
        s1 = front[f1 + F if f1 < 0 else f1]
        vis_e[e] = (s0 or s1) if edge_convex[e] else (s0 and s1)
    n = 0
    for i in range(sample_edge.shape[0]):
        if vis_e[sample_edge[i]]:
            n += 1
    idx = np.empty(n, np.int64)
    k = 0
    for i in range(sample_edge.shape[0]):
        if vis_e[sample_edge[i]]:
            idx[k] = i
            k += 1
    m = n if segments else 0
    A = np.empty((m, 3))
    B = np.empty((m, 3))
    t_lo = np.empty(m)
    for j in range(m):
        for r in range(3):
            A[j, r] = sample_p[idx[j], r]
            B[j, r] = cam_o[r]
        d0, d1, d2 = cam_o[0] - A[j, 0], cam_o[1] - A[j, 1], cam_o[2] - A[j, 2]
        seg = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        t = 2e-4 / seg
        t_lo[j] = t if t < 0.1 or np.isnan(t) else 0.1  # np.minimum: NaN stays NaN
    return idx, A, B, t_lo


def silhouette_sides(T_camera_object: np.ndarray, mf, idx: np.ndarray, normals: np.ndarray, K: np.ndarray,
                     tree=None, clear_px: float = 3.0) -> np.ndarray:
    """Which visible samples lie on the part's outline at a pose, and on which side of their line the part is.

    A sample is on the outline when its edge is convex with one face seen from outside and the
    other not (the part's pixels on one side of the projected edge, the background's on the
    other). The part's side is that of the seen face: its direction away from the edge within
    the face points against the other face's outward normal (a convex edge). For a non-convex
    part the background side must show past the part: the line of sight ``clear_px`` beyond
    the outline must miss it (else the edge is outlined against the part's own faces).

    Parameters
    ----------
    T_camera_object : ndarray, shape (4, 4)
    mf : ModelFeatures
    idx : ndarray, shape (S,), int64
        Visible samples (:func:`visible_samples`).
    normals : ndarray, shape (S, 2)
        Unit normals of their projected edges, px.
    K : ndarray, shape (3, 3)
    tree : BSPTree or None
        For a non-convex part (self-occluding outlines).
    clear_px : float
        How far beyond the outline the background is checked, px.

    Returns
    -------
    side : ndarray, shape (S,), float
        +1: the part lies where the normal points; -1: opposite; 0: not on the outline.
    """
    R, t = T_camera_object[:3, :3], T_camera_object[:3, 3]
    se = mf.sample_edge[idx]
    ef = mf.edge_faces[se]
    front = front_faces(R[None], t[None], mf)[0]
    seen = np.where(ef >= 0, front[np.maximum(ef, 0)], False)
    sil = mf.edge_convex[se] & (seen[:, 0] != seen[:, 1])
    side = np.zeros(len(idx))
    if not sil.any():
        return side
    k = np.flatnonzero(sil)
    f_seen = np.where(seen[k, 0], ef[k, 0], ef[k, 1])
    f_other = np.where(seen[k, 0], ef[k, 1], ef[k, 0])
    tdir = (mf.edge_b - mf.edge_a)[se[k]]
    u = np.cross(mf.face_normals[f_seen], tdir)
    n_other = np.where((f_other >= 0)[:, None], mf.face_normals[np.maximum(f_other, 0)], 0.0)
    u *= np.where(np.einsum("ij,ij->i", u, n_other) > 0, -1.0, 1.0)[:, None]
    u /= np.linalg.norm(u, axis=1, keepdims=True) + 1e-300
    P = mf.sample_p[idx[k]]
    X = P @ R.T + t
    D = u @ R.T
    z = X[:, 2]
    duv = np.stack([K[0, 0] * (D[:, 0] * z - X[:, 0] * D[:, 2]), K[1, 1] * (D[:, 1] * z - X[:, 1] * D[:, 2])], 1)
    side[k] = np.sign(np.einsum("ij,ij->i", duv, normals[k]))
    if tree is not None and not mf.convex:
        cam_o = -R.T @ t
        r = P - cam_o
        r /= np.linalg.norm(r, axis=1, keepdims=True)
        w = u - np.einsum("ij,ij->i", u, r)[:, None] * r
        w /= np.linalg.norm(w, axis=1, keepdims=True) + 1e-300
        out = P - (clear_px * z / K[0, 0])[:, None] * w
        blocked = tree.segments_blocked(cam_o, cam_o + 3.0 * (out - cam_o), t_lo=0.0, t_hi=1.0, min_length=1e-9)
        side[k[blocked]] = 0.0
    return side


@dataclass(frozen=True)
class EdgeImage:
    """What a correspondence line reads of one camera image: its gradient and noise.

    Attributes
    ----------
    K : ndarray, shape (3, 3)
        Camera matrix of ``grad``'s pixels (of a crop: the principal point
        moved by the crop's corner).
    grad : ndarray, shape (2, H, W), float32
        d/du, d/dv of the smoothed image (:func:`image_gradient`).
    noise : float
        Std of one gradient component due to the image's intensity noise
        (:func:`image_noise` times :func:`sobel_noise_gain`), same unit as ``grad``.
    grey : ndarray, shape (H, W), uint8, or None
        The smoothed image the gradient is of, grey levels (of a colour image:
        its luma); the region term of :mod:`vespro.likelihood` reads it.
    """

    K: np.ndarray
    grad: np.ndarray
    noise: float
    grey: np.ndarray | None = None

    @classmethod
    def from_image(cls, img: np.ndarray, K: np.ndarray, box: tuple[int, int, int, int] | None = None,
                   blur_sigma: float = 0.8, keep_grey: bool = True) -> "EdgeImage":
        """From an undistorted image (grey or colour, uint8), or its pixels ``box = (x0, y0, x1, y1)``;
        ``keep_grey``: also keep the smoothed grey levels (:attr:`grey`, else None)."""
        K = np.array(K, float)
        if box is not None:
            x0, y0, x1, y1 = box
            img = img[y0:y1, x0:x1]
            K[0, 2] -= x0
            K[1, 2] -= y0
        f = cv2.GaussianBlur(img, (0, 0), blur_sigma) if blur_sigma > 0 else img
        dx, dy = image_gradient(f, 0.0)
        grad = np.stack([dx, dy]).astype(np.float32)
        grey = None
        if keep_grey and f.ndim == 3:
            grey = cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)  # (images are BGR, as OpenCV reads them)
        elif keep_grey:
            grey = f.copy() if f is img else f  # (the caller's pixels stay writable)
        for a in (grad, K) if grey is None else (grad, K, grey):
            a.setflags(write=False)
        return cls(K, grad, image_noise(img) * sobel_noise_gain(blur_sigma), grey)
