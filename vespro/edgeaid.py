"""Edge-aided pose measurement: the part's outline pins what a lone camera's corners leave loose.

One camera sees 6-8 of the part's corners, each found 1-2 px off (a bevel, a
junction with the background next to it); from those the pose along the line
of sight, coupled with the tilt, is fixed only to a few per cent of the
distance. Seen on random one-camera views: a track confirmed from a start 3%
of the diameter off slid to 11-20% within a few frames while every corner it
used stayed within 3 px of the truth. The part's visible model edges, found
in the image by a one-dimensional search along their projected normals
(hundreds of samples; the initialiser's sub-pixel stage,
:func:`vespro.edgefit.refine_subpixel`, as in RAPiD-style edge trackers),
fit that pose to 0.2-3% of the diameter in the same frames.

:class:`EdgeAid` turns one camera image and the filter's pose into such a
pose with a covariance, for :meth:`vespro.ekf.PoseEKF.update_pose`. The
covariance is the Gauss-Newton one, ``s^2 (J^T W J)^-1``, with ``s`` the
fit's weighted residual RMS (at least ``min_sigma_px``), raised by the number
of samples per edge over two: samples along one straight edge share its
errors (an edge measures an offset and an angle, not one independent
distance per sample). Edges beyond ``max_independent_edges`` count as no more
information: on the bracket (45-55 edges seen, many short: hole rims,
chamfers) the fitted poses' NEES had a median of 20 against 5.3 for 6 dof
when every edge counted; with the cap, box, L-block and bracket views all
give medians of 5-6.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .imageedges import image_gradient as _gradient
from .imageedges import projection_box
from .init.features import Undistorter
from .init.modelfeat import model_features
from .jit import njit
from .memory import ScratchImages
from .numerics import front_face_mask
from .edgefit import CameraView, EdgeFit, refine_subpixel
from .model import Model
from .rig import Rig
from .se3 import invert_transform

__all__ = ["EdgeAid", "EdgeContrast", "EdgeMeasurement"]


@dataclass(frozen=True)
class _GradientImage:
    """The part of an image's features the edge search reads."""

    K: np.ndarray
    grad: np.ndarray  # (2, H, W) float64: the Sobel values (int16) exactly, which the compiled search
    # reads faster than int16 (a conversion at each of its 8 reads a point)


@dataclass(frozen=True)
class EdgeMeasurement:
    """A pose fitted to one camera's edges.

    Attributes
    ----------
    T_world_object : ndarray (4, 4)
    cov6 : ndarray (6, 6)
        Of ``[dp, dtheta]`` (world, rotation on the left), as the filter's.
    fit : EdgeFit
    edge_side : ndarray (E,), int
        Which faces of each model edge the camera sees at the fitted pose
        (:meth:`EdgeAid.edge_side`), to teach an :class:`EdgeContrast` with.
    """

    T_world_object: np.ndarray
    cov6: np.ndarray
    fit: EdgeFit
    edge_side: np.ndarray | None = None


class EdgeContrast:
    """What each edge sample of the part looks like in one camera, learnt over a track's frames.

    A point of a model edge shows in the image as an edge of some sign (which
    side is brighter, along the edge's projected normal) and strength, and both
    stay put from frame to frame while the part moves a little. A search that
    knows them does not take a neighbouring image edge of the other sign, or
    far stronger, for it (the moving-edge trackers check each site's contrast
    against its last the same way). Seen on one-camera tracks: a box whose top
    edge meets a brighter plate behind it (grey 127 against 134) shows there a
    dark seam a pixel wide, a weak falling and a strong rising edge 2.5 px
    apart, and the nearest comparable peak flipped between them frame to frame;
    an L-block edge with no contrast at the true pose found a strong edge of the
    other sign 3 px away once the pose had moved half way to it, and the fits
    that then explained more of the outline slid the track 15-23% of the
    diameter along the line of sight. Kept per sample, not per edge: along one
    edge the background changes (belt, plate, rail), and an edge's mean
    contrast fitted none of its parts.

    The contrast learnt is :attr:`vespro.edgefit.EdgeFit.sample_contrast`,
    averaged with weight ``rate`` for the new frame over the frames whose
    measurement the filter accepted; a sample is expected once it has
    ``min_frames`` such frames with the same faces of its edge seen (``side``,
    :meth:`EdgeAid.edge_side`: which faces are seen fixes the normal's
    orientation relative to them and what lies either side, so the sample
    starts again when it changes).

    Parameters
    ----------
    edge_of_sample : ndarray (S,), int
    rate : float
    min_frames : int
    """

    def __init__(self, edge_of_sample: np.ndarray, rate: float = 0.3, min_frames: int = 2):
        self.edge = np.asarray(edge_of_sample)
        self.rate = rate
        self.min_frames = min_frames
        n = len(self.edge)
        self.contrast = np.full(n, np.nan)
        self.frames = np.zeros(n, np.int64)
        self.side = np.full(n, -1, np.int64)

    def expect(self, edge_side: np.ndarray) -> np.ndarray:
        """Each sample's expected signed contrast with its edge's faces seen as ``edge_side`` (E,) (NaN: unknown)."""
        return _expect_kernel(self.frames, self.side, self.contrast, self.edge, edge_side, self.min_frames)

    def learn(self, contrast: np.ndarray, edge_side: np.ndarray) -> None:
        """A frame's sample contrasts (S,) (NaN: not seen), the edges' faces seen as ``edge_side`` (E,)."""
        _learn_kernel(self.frames, self.side, self.contrast, self.edge, edge_side, contrast, float(self.rate))


class EdgeAid:
    """Pose measurements from the model's edges in one camera image.

    Parameters
    ----------
    rig : Rig
    model : Model
    tree : BSPTree, optional
        The model's tree (self-occlusion of a non-convex part's edges).
    blur_sigma : float
        Smoothing before the gradient, px (as the initialiser's features).
    search_px : float
        Half-length of each sample's search along its normal, px.
    min_samples, min_edges : int
        Fewer samples with an edge point found, or fewer model edges among
        them, and no measurement is made (a fit to one or two edges leaves
        directions free).
    min_sigma_px : float
        Floor of the per-sample noise, px.
    max_independent_edges : int
        At most this many edges count as independent (see the module notes).
    rounds : int
        Gauss-Newton rounds (each searches the image again); the filter's
        pose is close, and each round costs 2-3 ms on the bracket.
    found_power : float
        The covariance is divided by ``f ** found_power``, ``f`` the fraction
        of the visible samples that found an edge point: a fit that explains
        half the outline it expects (a dark face on a dark belt) can sit in a
        wrong minimum its residuals do not show. Seen on a one-camera L-block
        (fresh seed 610): fits finding 48-61% of the outline, each claiming a
        3 mm position std, pulled a confirmed track 29 mm along the line of
        sight (14-17% of the diameter, published) while the filter's std
        stayed 3.3-4.5 mm; divided by ``f**2`` the same track stays within
        7% and its std grows to 5-6.5 mm. 0: off.
    spacing_px : float
        An edge's samples weigh together at most one per ``spacing_px`` of its
        projected length (see :func:`vespro.edgefit.refine_subpixel`). 0: off.
    edge_outlier_px : float
        An edge the solved step leaves more than this off on average is left
        out of the round (a faint edge found on its neighbour). 0: off.
        Measured, fitted from the true pose on one-camera views (box,
        L-block, bracket; frames 0, 10, 20, 30): with image noise (960 views,
        seeds 0-19, 40-59, 200-219, 600-619) the 90th percentile of the error
        along the line of sight fell from 2.7-3.3% of the diameter to
        2.5-3.0% and fits more than 5% off from 26 to 20; without (seeds
        40-59) from 1.2% to 0.7%. Spacing alone did as well with noise but
        left an L-block view whose dark face loses two silhouette edges
        (seed 610) 10-13 mm off where both give 0-0.7 mm. Dropping the edges
        of faces seen as strips under 2-6 px wide, or the samples within 1-3
        px of an edge's ends, removed more of the noise-free error but left
        the noisy fits worse (fewer samples).
    edge_offset_px : float
        Std of an offset common to all samples of one edge (the image edge
        as a whole off the model's), added to the covariance (see
        :meth:`vespro.edgefit.EdgeFit.covariance`). 0: off.
    near_peak_frac : float
        Each sample takes the nearest gradient peak along its normal among
        those at least this fraction of the highest, not the highest (see
        :func:`vespro.edgefit.refine_subpixel`): a face seen edge on shows
        as a line a pixel wide, both its sides edges, and the highest may be
        the far one. Box rig seed 1618 frame 30 without image noise, fitted
        from the true pose: with the highest, one silhouette edge taken 1.9 px
        out and the fit 18 mm (10.5% of the diameter) nearer along the ray,
        claiming 4.3 mm; with 0.6, 2.8%. From the true pose over 240 noisy
        views (seeds 1600-1619) fits over 5% of the diameter off 6 -> 3. On
        600 one-camera trials (``bench/init.py --rigs 1 --track 52``) the
        tracks that slid past 10% went from 5 to 2 and one more trial was
        published within the second, none lost. From the true pose over
        other view sets about even (seeds 40-59 and 600-619 with noise: p90
        along the ray 2.85% and 2.60% against 2.86% and 2.54%; 600-619 without:
        0.45% against 0.51%), and one view set worse: an L-block whose dark face
        on the dark belt leaves two silhouette edges to a neighbouring image
        edge (seed 610, frames 48-55, no noise) 0.1-7.5 mm nearer instead of
        0.0-0.7 mm. 0: the highest peak.
    contrast_ratio : (float, float) or None
        Given an :class:`EdgeContrast` (:meth:`measure`), a sample whose
        contrast is known takes only image edges of its sign between these
        multiples of its strength (no upper bound for one that saw no edge of
        its own; :func:`vespro.edgefit._normal_search`). None: the memory
        is not used. Measured on 600 one-camera trials (``bench/init.py --rigs
        1 --track 52``): the two tracks that slid past 10% (box and L-block,
        rig seed 1618) now peak at 6% and 9%, 563 published within 1 s against
        562, none wrong. Kept per edge instead (an edge's mean contrast) the
        same two held but fits of edges whose background changes along them
        lost half their outline (box 41: 0.45 found instead of 0.56) and three
        trials were published later; with an upper bound also for samples that
        saw no edge, an L-block whose samples had missed their edge by 2 px
        could not take it back and slid 15 deg to 10.05% (seed 801).
    """

    def __init__(self, rig: Rig, model: Model, tree=None, blur_sigma: float = 0.8, search_px: float = 3.0,
                 min_samples: int = 40, min_edges: int = 5, min_sigma_px: float = 0.3,
                 max_independent_edges: int = 12, rounds: int = 2, found_power: float = 2.0,
                 spacing_px: float = 2.0, edge_outlier_px: float = 1.0, edge_offset_px: float = 0.0,
                 near_peak_frac: float = 0.6, contrast_ratio: tuple[float, float] | None = (0.4, 3.0)):
        self.mf = model_features(model)
        self.tree = None if self.mf.convex else tree
        self.undistort = {c.name: Undistorter(c.intrinsics) for c in rig}
        self._grad = ScratchImages()  # per camera, its float64 gradient (read only within measure)
        self.K = {c.name: np.asarray(c.intrinsics.K, float) for c in rig}
        self.blur_sigma = blur_sigma
        self.search_px = search_px
        self.min_samples = min_samples
        self.min_edges = min_edges
        self.min_sigma_px = min_sigma_px
        self.max_independent_edges = max_independent_edges
        self.rounds = rounds
        self.found_power = found_power
        self.spacing_px = spacing_px
        self.edge_outlier_px = edge_outlier_px
        self.edge_offset_px = edge_offset_px
        self.near_peak_frac = near_peak_frac
        self.contrast_ratio = contrast_ratio
        # Per model corner, the edge sample nearest it on each sharp edge that ends there (-1: none).
        ends = []
        ev = model.edge_vertices
        for v in model.corner_vertex:
            row = []
            for e in np.flatnonzero((ev[:, 0] == v) | (ev[:, 1] == v)):
                on = np.flatnonzero(self.mf.sample_edge == e)
                if on.size:
                    row.append(on[0] if ev[e, 0] == v else on[-1])
            ends.append(row)
        width = max((len(r) for r in ends), default=0)
        self.corner_ends = np.full((len(ends), width), -1, np.int64)
        for i, r in enumerate(ends):
            self.corner_ends[i, :len(r)] = r

    def _roi(self, K, T_world_camera, T_world_object, width, height):
        """Pixel box (x0, y0, x1, y1) around the model's projection, with room for the search."""
        m = self.search_px + 8.0  # search, gradient and blur kernels, a pose a few px off
        return projection_box(K, invert_transform(T_world_camera) @ T_world_object, self.mf.vertices, m, width, height)

    def edge_side(self, T_camera_object: np.ndarray) -> np.ndarray:
        """Which of each model edge's two faces the camera sees (bit 0: the first, bit 1: the second), (E,)."""
        mf = self.mf
        return _edge_side_kernel(np.ascontiguousarray(T_camera_object, dtype=float), mf.face_normals,
                                 mf.face_offsets, mf.edge_faces)

    def corners_shown(self, contrast: EdgeContrast, T_camera_object: np.ndarray, corner_ids: np.ndarray,
                      min_frac: float) -> np.ndarray:
        """Which of the corners ``corner_ids`` can show as an image corner, by what their edges looked like.

        An image corner is where two edges with contrast meet. A corner of a dark face
        against a dark background has none there: its window holds at best a weaker
        corner response than a neighbouring feature's (a hole's rim, a nearby corner of
        the part), and the extractor, taking the nearest of the candidates within
        ``rel_quality`` of the window's best, measures that one 2-4 px off. A corner is
        dim when fewer than two of its edges' samples next to it were seen (by
        ``contrast``, learnt with the same faces of the edge seen as now) with a contrast
        of at least ``min_frac`` of the median of all the samples seen, counting a sample
        not yet learnt as seen. True where not dim (all True while nothing is learnt).
        """
        ids = np.asarray(corner_ids, np.int64)
        return _corners_shown_kernel(contrast.frames, contrast.side, contrast.contrast, contrast.edge,
                                     self.edge_side(T_camera_object), self.corner_ends, ids, float(min_frac))


    def measure(self, name: str, image: np.ndarray, T_world_camera: np.ndarray,
                T_world_object: np.ndarray, contrast: EdgeContrast | None = None,
                edge_offset_px: float | None = None) -> EdgeMeasurement | None:
        """The pose near ``T_world_object`` that fits camera ``name``'s image edges, or None.

        ``image``: the camera's image as captured, 8-bit grey (undistorted here); the
        gradient is taken in a box around the model's projection only. ``contrast``:
        what the edges looked like in this camera's last frames (the search takes
        only image edges like them; :class:`EdgeContrast`); the measurement's
        ``fit.sample_contrast[0]`` and ``edge_side`` are what to teach it when the
        measurement is accepted. ``edge_offset_px``: this call's instead of
        :attr:`edge_offset_px`.
        """
        T_wc = np.asarray(T_world_camera, float)
        if not (np.isfinite(T_wc).all() and np.isfinite(T_world_object).all()):
            return None
        K = self.K[name]
        roi = self._roi(K, T_wc, T_world_object, image.shape[1], image.shape[0])
        if roi is None:
            return None
        x0, y0, x1, y1 = roi
        img = self.undistort[name](image, roi)
        dx, dy = _gradient(img, self.blur_sigma)
        K_roi = K.copy()  # the crop is a camera whose principal point moved by (-x0, -y0)
        K_roi[0, 2] -= x0
        K_roi[1, 2] -= y0
        grad = self._grad.get(name, (2,) + dx.shape, np.float64)
        grad[0] = dx  # int16 to float64: exact
        grad[1] = dy
        view = CameraView(_GradientImage(K_roi, grad), T_wc, True)
        T_cw = invert_transform(T_wc)
        expect = None
        if contrast is not None and self.contrast_ratio is not None:
            expect = [contrast.expect(self.edge_side(T_cw @ T_world_object))]
        T, fit = refine_subpixel(T_world_object, [view], self.mf, self.tree, search_px=self.search_px, info=True,
                                 rounds=self.rounds, spacing_px=self.spacing_px,
                                 edge_outlier_px=self.edge_outlier_px, near_peak_frac=self.near_peak_frac,
                                 expect=expect, contrast_ratio=self.contrast_ratio or (0.0, np.inf))
        if fit is None or fit.n_samples < self.min_samples or fit.n_edges < self.min_edges:
            return None
        offset = self.edge_offset_px if edge_offset_px is None else edge_offset_px
        cov = fit.covariance(T[:3, :3], self.min_sigma_px, self.max_independent_edges, offset)
        if cov is None:
            return None
        return EdgeMeasurement(T, cov / max(fit.found_frac, 0.05) ** self.found_power, fit, self.edge_side(T_cw @ T))


@njit
def _corners_shown_kernel(frames, side_seen, contrast, edge, side, corner_ends, ids, min_frac):
    """:meth:`EdgeAid.corners_shown` past the faces seen (``side``, (E,)), compiled: the samples
    known, the median of their contrasts' magnitudes (NumPy's: the middle one, or the mean of
    the middle two) and each corner's count of strong or unknown end samples. Comparisons of
    the same values as the NumPy formulation's, so the same answer."""
    S = edge.shape[0]
    known = np.empty(S, np.bool_)
    mags = np.empty(S)
    m = 0
    for i in range(S):
        known[i] = frames[i] >= 1 and side_seen[i] == side[edge[i]] and np.isfinite(contrast[i])
        if known[i]:
            mags[m] = abs(contrast[i])
            m += 1
    n = ids.shape[0]
    out = np.ones(n, np.bool_)
    if m == 0 or n == 0:
        return out
    a = np.sort(mags[:m])
    med = a[m // 2] if m % 2 == 1 else (a[m // 2 - 1] + a[m // 2]) / 2.0
    level = min_frac * med
    for j in range(n):
        count = 0
        for k in range(corner_ends.shape[1]):
            e = corner_ends[ids[j], k]
            if e < 0:
                continue
            if not known[e] or abs(contrast[e]) >= level:
                count += 1
        out[j] = count >= 2
    return out


@njit
def _edge_side_kernel(T, face_normals, face_offsets, edge_faces):
    """:meth:`EdgeAid.edge_side`, compiled (the faces seen by :func:`vespro.numerics.front_face_mask`,
    the bits of :func:`vespro.imageedges.front_faces`)."""
    front = front_face_mask(T, face_normals, face_offsets)
    E = edge_faces.shape[0]
    side = np.empty(E, np.int64)
    F = front.shape[0]
    for e in range(E):
        f0, f1 = edge_faces[e, 0], edge_faces[e, 1]
        side[e] = int(front[f0 + F if f0 < 0 else f0]) + 2 * int(front[f1 + F if f1 < 0 else f1])  # (NumPy's negative index)
    return side


@njit
def _expect_kernel(frames, side_seen, contrast, edge, side, min_frames):
    """:meth:`EdgeContrast.expect`, compiled: the learnt contrast where known, else NaN."""
    out = np.empty(contrast.shape[0])
    for i in range(contrast.shape[0]):
        out[i] = contrast[i] if frames[i] >= min_frames and side_seen[i] == side[edge[i]] else np.nan
    return out


@njit
def _learn_kernel(frames, side_seen, learnt, edge, side, contrast, rate):
    """:meth:`EdgeContrast.learn`, compiled (in place): a sample seen with other faces, or for
    the first time, starts again from its contrast; one seen as before moves ``rate`` of the
    way to it (NumPy's ``a += rate * (c - a)``, the same arithmetic)."""
    for i in range(contrast.shape[0]):
        c = contrast[i]
        if not np.isfinite(c):
            continue
        s = side[edge[i]]
        if side_seen[i] != s or frames[i] == 0:
            learnt[i] = c
            frames[i] = 1
            side_seen[i] = s
        else:
            learnt[i] = learnt[i] + rate * (c - learnt[i])
            frames[i] += 1
