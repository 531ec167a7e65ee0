"""Image features for initialisation: oriented edge distance maps and corners.

Per camera image (undistorted once, so that everything downstream is a plain
pinhole):

- the gradient of the smoothed image, taken per colour channel and keeping the
  strongest channel (an object can differ from its background in hue alone);
- Canny edges from that gradient, each with the orientation of its normal
  (mod pi) quantised into ``n_bins`` bins;
- one distance transform per bin, built from the edge pixels within one bin
  of it: ``dt[k][v, u]`` is the distance (px) from pixel (u, v) to the nearest
  edge pixel whose normal is within ~1.5 bins of bin ``k`` (directional
  chamfer matching, Liu et al. 2010);
- Shi-Tomasi corners refined to sub-pixel, and the pairs of corners joined by
  a straight image edge (most of the segment between them lies on edge pixels
  of the matching orientation).

Nothing here knows the scene: no background, colour or support plane.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import cv2
import numpy as np

from ..camera import CameraIntrinsics
from ..imageedges import image_gradient as _gradient
from ..imageedges import image_noise
from ..imageedges import sobel_noise_gain as _sobel_noise_gain

__all__ = ["EdgeOptions", "CameraFeatures", "Undistorter", "extract_features", "normal_bins", "lookup_dt",
           "image_noise", "canny_thresholds"]


@dataclass(frozen=True)
class EdgeOptions:
    """Feature extraction settings.

    Attributes
    ----------
    n_bins : int
        Orientation bins of edge normals over [0, pi).
    blur_sigma : float
        Gaussian smoothing before the gradient, px.
    canny_low, canny_high : float
        Least Canny hysteresis thresholds on the L2 Sobel (3x3) gradient
        magnitude (grey levels x 4 for a unit step): a plain face against a
        dark background can differ from it by 10-20 grey levels, whose edge
        (magnitude 40-80) the former 40 / 100 lost entirely.
    canny_noise_low, canny_noise_high : float
        The thresholds rise to these multiples of the image's own gradient
        noise (:func:`canny_thresholds`) when that is higher: the magnitude
        of pure noise is Rayleigh-distributed, above 5 sigma once in ~3e5
        pixels.
    dt_max : float
        Distances are clipped to this, px.
    max_corners : int
        Corners per image, spread over tiles of about ``corner_tile_px``.
    corner_tile_px : float
    corner_blur_sigma : float
        Gaussian smoothing before the corner response, px.
    corner_block : int
        Shi-Tomasi block size, px.
    corner_quality : float
        Shi-Tomasi quality level (fraction of the strongest corner response).
    corner_min_distance : float
        px.
    link_min_px, link_max_frac : float
        Corner pairs closer than ``link_min_px`` or farther than
        ``link_max_frac`` x the image diagonal are not linked.
    link_support : float
        Fraction of the samples along a corner pair's segment that must lie
        within ``link_tol_px`` of an edge of that orientation.
    link_tol_px : float
    """

    n_bins: int = 12
    blur_sigma: float = 0.8
    canny_low: float = 20.0
    canny_high: float = 50.0
    canny_noise_low: float = 2.5
    canny_noise_high: float = 5.0
    dt_max: float = 20.0
    max_corners: int = 360
    corner_tile_px: float = 160.0
    corner_blur_sigma: float = 0.6
    corner_block: int = 3
    corner_quality: float = 0.005
    corner_min_distance: float = 4.0
    link_min_px: float = 6.0
    link_max_frac: float = 0.5
    link_support: float = 0.85
    link_tol_px: float = 1.5


@dataclass(frozen=True)
class CameraFeatures:
    """Features of one undistorted camera image.

    Attributes
    ----------
    name : str
    K : ndarray, shape (3, 3)
        Camera matrix of the undistorted image.
    width, height : int
    dt : ndarray, shape (n_bins, H, W), float32
        Oriented distance transforms, px, clipped to ``dt_max``.
    edges : ndarray, shape (H, W), uint8
        Canny edge map (255 on edges).
    corners : ndarray, shape (N, 2)
        Corner pixels (undistorted), float64.
    links : ndarray, shape (L, 2), int64
        Corner index pairs ``i < j`` joined by an image edge.
    grad : ndarray, shape (2, H, W), float32
        Image gradient (d/du, d/dv) of the strongest channel (Sobel 3x3 of
        the smoothed image), for sub-pixel edge search.
    link_ends : ndarray, shape (L, 2), bool
        Whether the edge of each link ends at its first / second corner (it
        does not run on past the corner): an object corner ends the edges
        that meet there, a crossing of two background lines does not.
    grey : ndarray, shape (H, W), uint8, or None
        The undistorted image in grey levels (for the shading of the faces a
        pose paints: :func:`vespro.init.search.face_interiors`).
    grey_noise : float
        Std of ``grey``'s intensity noise (:func:`image_noise`), grey levels.
    """

    name: str
    K: np.ndarray
    width: int
    height: int
    dt: np.ndarray
    edges: np.ndarray
    corners: np.ndarray
    links: np.ndarray
    link_ends: np.ndarray
    grad: np.ndarray
    grey: np.ndarray | None = None
    grey_noise: float = 0.0


class Undistorter:
    """Remaps images of a distorted camera to the ideal pinhole with the same K.

    Built once per camera (set-up); a camera without distortion passes images
    through untouched.
    """

    def __init__(self, intr: CameraIntrinsics):
        self.intr = intr
        self.maps = None
        if intr.has_distortion:
            self.maps = cv2.initUndistortRectifyMap(intr.K, intr.dist, None, intr.K,
                                                    (intr.width, intr.height), cv2.CV_16SC2)

    def __call__(self, img: np.ndarray, box: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """The undistorted image, or only its pixels ``[y0:y1, x0:x1]`` for ``box = (x0, y0, x1, y1)``
        (the remap of those pixels alone: the same values as cropping the whole)."""
        if self.maps is None:
            return img if box is None else img[box[1]:box[3], box[0]:box[2]]
        m0, m1 = self.maps
        if box is not None:
            x0, y0, x1, y1 = box
            m0, m1 = m0[y0:y1, x0:x1], m1[y0:y1, x0:x1]
        return cv2.remap(img, m0, m1, cv2.INTER_LINEAR)


def normal_bins(angle: np.ndarray, n_bins: int) -> np.ndarray:
    """Bin index of normal angles (rad, any range, taken mod pi)."""
    a = np.mod(angle, np.pi)
    return np.minimum((a * (n_bins / np.pi)).astype(np.int64), n_bins - 1)


def lookup_dt(dt: np.ndarray, bins: np.ndarray, uv: np.ndarray, outside: float) -> np.ndarray:
    """Nearest-pixel oriented distance at pixels; ``outside`` off the image.

    Parameters
    ----------
    dt : ndarray, shape (B, H, W)
    bins : ndarray, shape (...), int
    uv : ndarray, shape (..., 2)
        Pixels (may be NaN).
    outside : float

    Returns
    -------
    ndarray, shape (...), float32
    """
    _, H, W = dt.shape
    u = np.rint(uv[..., 0])
    v = np.rint(uv[..., 1])
    inside = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    ui = np.where(inside, u, 0).astype(np.int64)
    vi = np.where(inside, v, 0).astype(np.int64)
    d = dt[bins, vi, ui]
    return np.where(inside, d, np.float32(outside))


def canny_thresholds(img: np.ndarray, opt: EdgeOptions, noise: float | None = None) -> tuple[float, float]:
    """(low, high) Canny thresholds for an image: the floors, raised with its noise
    (``noise``: :func:`image_noise` of ``img`` where already known)."""
    sg = (image_noise(img) if noise is None else noise) * _sobel_noise_gain(opt.blur_sigma)
    return max(opt.canny_low, opt.canny_noise_low * sg), max(opt.canny_high, opt.canny_noise_high * sg)


def extract_features(name: str, img: np.ndarray, K: np.ndarray, opt: EdgeOptions = EdgeOptions()) -> CameraFeatures:
    """Edges, oriented distance maps, corners and corner links of one image.

    Parameters
    ----------
    name : str
    img : ndarray, shape (H, W) or (H, W, 3), uint8
        Undistorted grey or BGR image.
    K : ndarray, shape (3, 3)
    opt : EdgeOptions

    Returns
    -------
    CameraFeatures
    """
    f = edge_maps(name, img, K, opt)
    pts = detect_corners(f.grey, opt)
    if pts is None or len(pts) == 0:
        corners = np.zeros((0, 2))
    else:
        pts = cv2.cornerSubPix(f.grey, pts.astype(np.float32), (2, 2), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01))
        corners = pts.reshape(-1, 2).astype(np.float64)
    links = link_corners(corners, f.dt, opt, np.hypot(f.width, f.height))
    ends = link_ends(corners, links, f.dt, opt)
    for a in (corners, links, ends):
        a.setflags(write=False)
    return replace(f, corners=corners, links=links, link_ends=ends)


def edge_maps(name: str, img: np.ndarray, K: np.ndarray, opt: EdgeOptions = EdgeOptions()) -> CameraFeatures:
    """The edge half of :func:`extract_features`: edges, oriented distance maps, gradient and grey
    image; no corners (what a pose refinement on the edges needs, :func:`vespro.edgefit.refine_pose`)."""
    H, W = img.shape[:2]
    dx, dy = _gradient(img, opt.blur_sigma)
    noise = image_noise(img)
    lo, hi = canny_thresholds(img, opt, noise)
    edges = cv2.Canny(dx, dy, lo, hi, L2gradient=True)
    vv, uu = np.nonzero(edges)
    b = normal_bins(np.arctan2(dy[vv, uu].astype(float), dx[vv, uu].astype(float)), opt.n_bins)
    dt = np.empty((opt.n_bins, H, W), np.float32)
    for k in range(opt.n_bins):
        near = (np.abs(((b - k) + opt.n_bins // 2) % opt.n_bins - opt.n_bins // 2) <= 1)
        mask = np.full((H, W), 255, np.uint8)
        mask[vv[near], uu[near]] = 0
        d = cv2.distanceTransform(mask, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        np.minimum(d, opt.dt_max, out=d)
        dt[k] = d
    grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    grad = np.stack([dx, dy]).astype(np.float32)
    grey = np.array(grey, np.uint8)  # (a copy: the caller's image may be reused)
    grey_noise = noise if img.ndim == 2 else image_noise(grey)
    corners, links, ends = np.zeros((0, 2)), np.zeros((0, 2), np.int64), np.zeros((0, 2), bool)
    for a in (dt, edges, corners, links, ends, grad, grey):
        a.setflags(write=False)
    return CameraFeatures(name, np.asarray(K, float), W, H, dt, edges, corners, links, ends, grad, grey, grey_noise)


def detect_corners(grey: np.ndarray, opt: EdgeOptions) -> np.ndarray | None:
    """Shi-Tomasi corners per image tile, each tile with its own quality scale.

    One global quality threshold lets high-contrast clutter take every slot
    and starve a low-contrast part; tiles of ~160 px (about a part's size)
    each keep their best corners.

    Returns
    -------
    ndarray, shape (N, 1, 2), float32, or None
    """
    H, W = grey.shape
    # Smoothing first: staircase (aliased) lines give corner responses of
    # their own all along them.
    grey = cv2.GaussianBlur(grey, (0, 0), opt.corner_blur_sigma) if opt.corner_blur_sigma > 0 else grey
    nx, ny = max(1, round(W / opt.corner_tile_px)), max(1, round(H / opt.corner_tile_px))
    per = max(8, opt.max_corners // (nx * ny))
    # Each tile is searched in its own pixels and a margin the response reads (the Sobel,
    # the block, the 3x3 maximum): the same corners as a whole-image search masked to the
    # tile, which computed the response over the whole image once per tile.
    m = opt.corner_block // 2 + 3
    out = []
    for iy in range(ny):
        for ix in range(nx):
            x0, x1 = ix * W // nx, (ix + 1) * W // nx
            y0, y1 = iy * H // ny, (iy + 1) * H // ny
            X0, Y0, X1, Y1 = max(0, x0 - m), max(0, y0 - m), min(W, x1 + m), min(H, y1 + m)
            sub = grey[Y0:Y1, X0:X1]
            mask = np.zeros_like(sub)
            mask[y0 - Y0:y1 - Y0, x0 - X0:x1 - X0] = 255
            p = cv2.goodFeaturesToTrack(sub, per, opt.corner_quality, opt.corner_min_distance, mask=mask,
                                        blockSize=opt.corner_block)
            if p is not None:
                out.append(p.reshape(-1, 2) + np.float32([X0, Y0]))
    if not out:
        return None
    pts = np.concatenate(out)
    # Drop near-duplicates across tile borders.
    keep = np.ones(len(pts), bool)
    for i in range(len(pts)):
        if keep[i]:
            d = np.linalg.norm(pts[i + 1:] - pts[i], axis=1)
            keep[i + 1:][d < opt.corner_min_distance] = False
    return pts[keep].reshape(-1, 1, 2).astype(np.float32)


def link_ends(corners: np.ndarray, links: np.ndarray, dt: np.ndarray, opt: EdgeOptions) -> np.ndarray:
    """Whether each link's edge stops at its corners (see ``CameraFeatures.link_ends``).

    Samples the straight continuation past each end, from 2.5 px to 2.5 px +
    a quarter of the link length (4 to 10 px); the edge runs on when most of
    them lie on edges of the link's orientation.

    Returns
    -------
    ndarray, shape (L, 2), bool
    """
    if len(links) == 0:
        return np.zeros((0, 2), bool)
    a, b = corners[links[:, 0]], corners[links[:, 1]]
    d = b - a
    L = np.hypot(d[:, 0], d[:, 1])
    u = d / L[:, None]
    ext = np.clip(0.25 * L, 4.0, 10.0)
    s = 2.5 + np.linspace(0.0, 1.0, 6)[None, :] * ext[:, None]  # (L, 6)
    bins = normal_bins(np.arctan2(d[:, 0], -d[:, 1]), dt.shape[0])
    bb = np.broadcast_to(bins[:, None], s.shape)
    past_a = a[:, None, :] - s[..., None] * u[:, None, :]
    past_b = b[:, None, :] + s[..., None] * u[:, None, :]
    on_a = np.mean(lookup_dt(dt, bb, past_a, np.inf) <= opt.link_tol_px, axis=1)
    on_b = np.mean(lookup_dt(dt, bb, past_b, np.inf) <= opt.link_tol_px, axis=1)
    return np.stack([on_a < 0.6, on_b < 0.6], 1)


def link_corners(corners: np.ndarray, dt: np.ndarray, opt: EdgeOptions, diag: float) -> np.ndarray:
    """Corner pairs joined by a straight edge of the matching orientation.

    Returns
    -------
    ndarray, shape (L, 2), int64
    """
    n = len(corners)
    if n < 2:
        return np.zeros((0, 2), np.int64)
    i, j = np.triu_indices(n, 1)
    d = corners[j] - corners[i]
    L = np.hypot(d[:, 0], d[:, 1])
    ok = (L >= opt.link_min_px) & (L <= opt.link_max_frac * diag)
    i, j, d, L = i[ok], j[ok], d[ok], L[ok]
    fr = np.linspace(0.12, 0.88, 12)
    bins = normal_bins(np.arctan2(d[:, 0], -d[:, 1]), dt.shape[0])  # normal of (dx, dy) is (-dy, dx)
    # A pair is kept when at most `misses` of its 12 samples are off the edge. Most pairs of
    # an image's corners are not joined by an edge: two samples spread along them reject
    # those that miss both (the same decision, on a sixth of the samples).
    misses = max((k for k in range(13) if (12 - k) / 12 >= opt.link_support), default=-1)
    if misses < 2:
        first = fr[[3, 8]]
        q = corners[i][:, None, :] + first[None, :, None] * d[:, None, :]
        off = lookup_dt(dt, np.broadcast_to(bins[:, None], q.shape[:2]), q, np.inf) > opt.link_tol_px
        maybe = off.sum(axis=1) <= misses
        i, j, d, bins = i[maybe], j[maybe], d[maybe], bins[maybe]
    # Keep a few px clear of the corners themselves, where other edges meet.
    pts = corners[i][:, None, :] + fr[None, :, None] * d[:, None, :]
    dist = lookup_dt(dt, np.broadcast_to(bins[:, None], pts.shape[:2]), pts, np.inf)
    keep = np.mean(dist <= opt.link_tol_px, axis=1) >= opt.link_support
    return np.stack([i[keep], j[keep]], 1).astype(np.int64)
