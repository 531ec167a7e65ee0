"""A bank of pose hypotheses, each its own filter, weighed by the image likelihood of every frame.

Whatever proposes a pose (the initialiser, a user, a recovery) only adds a
hypothesis; what is published follows from the evidence. Each hypothesis
carries a :class:`vespro.ekf.PoseEKF` and a score: the log of its posterior
probability. Beside the hypotheses stands the null, "the part is at none of
these poses", whose lines read clutter only; a hypothesis's evidence on a
frame is its log-likelihood ratio against the null (:mod:`vespro.likelihood`).

The probabilities follow the forward recursion of a hidden Markov model: the
state is which hypothesis (or the null) is the part's pose, and between two
frames a hypothesis stops being it with probability ``switch_rate`` (its
filter slid off, the part was taken away), that mass going to the null. The
frame's evidence then multiplies each prior. The recursion bounds what a
long history can vouch for: after any number of good frames a hypothesis's
prior odds against the null are at most ``(1 - switch_rate) / switch_rate``,
so a frame whose edges a hypothesis explains worse than clutter demotes it on
that frame, however long it was published (a drifting track is not published
on its past), and a frame that explains them better restores it.

The likelihood of one frame treats its lines as independent, which they are
not: the samples along one projected edge move together when the pose is
off (a pose a little off shifts and turns a whole edge at once), so a frame's
log ratio counts the same evidence many times over. The lines already weigh
one per ``spacing_px`` (2 px) of projected edge (:mod:`vespro.likelihood`);
a pose error moves each edge's image by about two numbers (an offset and a
turn), and the parts' projected edges are 40-100 px long in the benches'
views (a one-camera box: 9 edges, 256 weighed lines), so the lines are
independent about once per 20 px of edge: one line weighed in ten.
Every frame's log ratio is therefore scaled by one constant,
``evidence_weight`` (0.1 = 2 px / 20 px: the tempered likelihood of
composite-likelihood inference). One constant for every pose and camera keeps
the ranking of the raw likelihood: a pose that explains more edge by more
evidence (a near, large projection) stays ahead of one that explains less (a
small, far copy of the part), which a weight per edge or per pose would not.

A camera's view of the part may be blocked by something the model does not
know (the arm over the belt, a hand): its lines then read the blocking body,
clutter to the model, and a right pose would lose its standing by a camera
that sees nothing of it. Each camera's evidence is therefore a mixture: its
lines' weighted log ratio with probability ``p_visible``, no evidence with
the rest, so that a blocked camera costs a pose at most ``log(1 - p_visible)``
a frame while the others decide.

Which poses are possible at all is a prior: with a working volume
(:mod:`vespro.workspace`, the stretch of conveyor or the bin the user
states), the bank holds no pose whose centre lies outside it and drops a
hypothesis whose filter leaves it. Without one, a pose anywhere in the
cameras' view is possible, and a copy of the part's outline that the
scene's straight edges draw in mid-air can be the best pose held.

Equivalent poses of a symmetric part and poses within ``merge_frac`` of the
diameter of each other (ADD over the part's symmetries) are one hypothesis:
the first keeps its filter, the scores add as probabilities. Hypotheses whose
probability falls under ``prune_prob`` are dropped, and at most
``max_hypotheses`` are kept.

An edge, too, shows or not as a whole: the lines of one model edge read one
image edge, which a face lit like its neighbour or a side face dark on a dark
background does not show at all. Each edge's evidence within a camera is
therefore a mixture as well: its lines' with probability ``p_edge``, none with
the rest, so an edge that finds nothing costs a pose at most
``log(1 - p_edge)``, and a pose cannot win by having fewer edges to miss (a
turned-over L-block, whose outline has no inner step, against the part's own
pose, whose step between faces lit alike shows nothing).

The decision weighs two things: which held pose the part is at (the bank's
probability of the tracked hypothesis) and whether the tracked filter is at
that pose closely enough to be used (:func:`accuracy_probability`: the
probability that its pose puts the part's vertices within ``pose_tolerance``
of the diameter of where they are, under its covariance). With one hypothesis
held the first is 1 whatever the filter's error; the second falls as the
filter's uncertainty grows. The covariance it is judged under is the
filter's raised to the frame's own edge fits' where these are wider
(:func:`covariance_floor`): one camera's fits repeat the same errors frame
after frame (the same view, the same edges, the same blur), so the filter's
narrowing over such frames is not knowledge, while a single frame's fit is an
honest bound on what the frame alone shows. The published probability is the
product; the best hypothesis is published ``tracking`` while it is at least
``1 - wrong_lock_rate``; when it falls below, it is not published from that
frame on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.special import gammainc

from .ekf import PoseEKF
from .likelihood import ImageLikelihood, PoseLikelihood
from .metrics import add_sym
from .se3 import skew
from .workspace import box_centre, centres_inside, check_workspace

__all__ = ["BankOptions", "Hypothesis", "HypothesisBank", "accuracy_probability", "covariance_floor",
           "displacement_metric"]


def _logsumexp(values: list) -> float:
    """``log(sum(exp(v)))`` of a few log scores, without overflow: SciPy's ``logsumexp`` to
    rounding, without its 0.1 ms of overhead a call (the bank's every frame, on a handful
    of numbers)."""
    m = max(values)
    if not math.isfinite(m):
        return m
    return m + math.log(sum(math.exp(v - m) for v in values))


def displacement_metric(T_world_object: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """A (6, 6) with ``dx' A dx`` the mean squared displacement of the vertices under a pose error
    ``dx = [dp, dtheta]`` (the filter's: ``p + dp``, ``Exp(dtheta) R``; world frame)."""
    a = np.asarray(vertices, float) @ np.asarray(T_world_object, float)[:3, :3].T  # R v, world
    # Each vertex moves by J dx = dp - [a]x dtheta; summed over the vertices, J' J is
    # [[n I, -[sum a]x], [[sum a]x, sum |a|^2 I - a a']].
    n = len(a)
    s = skew(a.sum(axis=0))
    M = np.empty((6, 6))
    M[:3, :3] = n * np.eye(3)
    M[:3, 3:], M[3:, :3] = -s, s
    M[3:, 3:] = float((a * a).sum()) * np.eye(3) - a.T @ a
    return M / n


def accuracy_probability(T_world_object: np.ndarray, cov6: np.ndarray, vertices: np.ndarray,
                         radius: float) -> float:
    """Probability that the RMS displacement of the part's vertices is at most ``radius`` (m) when
    the pose's error is Gaussian with covariance ``cov6`` ([position, orientation], the filter's).

    The squared RMS displacement is a quadratic form of the error, a weighted sum of
    chi-square variables of one degree each (weights: the eigenvalues of ``L' A L``, ``A`` the
    :func:`displacement_metric`, ``L`` a square root of ``cov6``); its law is taken as a shifted,
    scaled chi-square with the same mean, variance and skewness (Pearson's). Against sampled
    errors it is within 0.004 at the 90th percentile and 0.001 at the 99th, where the decision
    is taken, and low below the median (it understates a pose's accuracy there)."""
    C = 0.5 * (np.asarray(cov6, float) + np.asarray(cov6, float).T)
    if not np.all(np.isfinite(C)):
        return 0.0
    w, V = np.linalg.eigh(C)
    L = V * np.sqrt(np.clip(w, 0.0, None))
    lam = np.clip(np.linalg.eigvalsh(L.T @ displacement_metric(T_world_object, vertices) @ L), 0.0, None)
    c1, c2, c3 = float(lam.sum()), float(np.dot(lam, lam)), float(np.dot(lam, lam * lam))
    if c1 <= 0.0:
        return 1.0
    h, g = c2 ** 3 / c3 ** 2, c3 / c2  # Q ~ c1 - h g + g chi2(h): mean, variance and skewness
    x = radius * radius - (c1 - h * g)
    return float(gammainc(0.5 * h, 0.5 * x / g)) if x > 0.0 else 0.0


def covariance_floor(P: np.ndarray, F: np.ndarray | None) -> np.ndarray:
    """The least covariance at least ``P`` and at least ``F`` in every direction: both whitened by
    ``P``, ``F``'s eigenvalues under 1 raised to 1 (``P`` where it is the wider, ``F`` where it
    is). ``F`` None: ``P``."""
    P = 0.5 * (np.asarray(P, float) + np.asarray(P, float).T)
    if F is None:
        return P
    F = 0.5 * (np.asarray(F, float) + np.asarray(F, float).T)
    if not (np.all(np.isfinite(F)) and np.all(np.isfinite(P))):
        return P
    try:
        L = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return P
    Li = np.linalg.inv(L)
    m, V = np.linalg.eigh(Li @ F @ Li.T)
    B = L @ V
    out = (B * np.maximum(m, 1.0)) @ B.T
    return 0.5 * (out + out.T)


@dataclass(frozen=True)
class BankOptions:
    """Settings of the hypothesis bank.

    Attributes
    ----------
    wrong_lock_rate : float
        A hypothesis is published when its probability is at least one minus this.
    switch_rate : float
        Probability per frame that a hypothesis stops being the part's pose (see the module).
    evidence_weight : float
        Scale of every frame's log-likelihood ratio: independent lines per line weighed
        (``spacing_px`` over the correlation length along an edge, 2 px / 20 px).
    p_visible : float
        Probability that a camera's view of the part is not blocked by something the model
        does not know (a camera that finds none of the part's edges costs a pose at most
        ``log(1 - p_visible)``).
    p_edge : float
        Probability that a visible model edge shows in the image at all (an edge that finds
        nothing costs a pose at most ``log(1 - p_edge)``).
    pose_tolerance : float
        A pose is right when the part's vertices are within this fraction of the diameter
        (RMS) of where they are: the decision's accuracy term (the wrong-lock bound of the benches).
    new_prior : float
        Prior probability of a proposed pose against the hypotheses already held
        (its score starts at the log of this plus the best current score, at most 0).
    merge_frac : float
        Hypotheses closer than this (ADD over the symmetries / diameter) are one.
    prune_prob : float
        Hypotheses under this probability are dropped.
    max_hypotheses : int
    proposals : int
        Candidates of each initialiser call proposed besides its answer.
    """

    wrong_lock_rate: float = 0.01
    switch_rate: float = 0.01
    evidence_weight: float = 0.1
    p_visible: float = 0.95
    p_edge: float = 0.9
    pose_tolerance: float = 0.1
    new_prior: float = 0.1
    merge_frac: float = 0.05
    prune_prob: float = 1e-4
    max_hypotheses: int = 5
    proposals: int = 3

    def __post_init__(self):
        if not 0 < self.wrong_lock_rate < 1:
            raise ValueError(f"wrong_lock_rate must be in (0, 1), got {self.wrong_lock_rate}")
        if not 0 < self.switch_rate < 1:
            raise ValueError(f"switch_rate must be in (0, 1), got {self.switch_rate}")
        if not self.evidence_weight > 0:
            raise ValueError(f"evidence_weight must be > 0, got {self.evidence_weight}")
        if not 0 < self.p_visible <= 1:
            raise ValueError(f"p_visible must be in (0, 1], got {self.p_visible}")
        if not 0 < self.p_edge <= 1:
            raise ValueError(f"p_edge must be in (0, 1], got {self.p_edge}")
        if not self.pose_tolerance > 0:
            raise ValueError(f"pose_tolerance must be > 0, got {self.pose_tolerance}")
        if self.max_hypotheses < 1:
            raise ValueError(f"max_hypotheses must be >= 1, got {self.max_hypotheses}")


@dataclass(eq=False)
class Hypothesis:
    """One pose hypothesis: its filter, score (log posterior probability) and last evidence."""

    ekf: PoseEKF
    score: float
    t_ns: int  # the filter's stamp
    frames: int = 0
    last: PoseLikelihood | None = None
    last_log_lik: float = 0.0  # this frame's log ratio times evidence_weight


class HypothesisBank:
    """Pose hypotheses of one part and their probabilities.

    Parameters
    ----------
    vertices : ndarray, shape (V, 3)
        The part's vertices (ADD), object frame, m.
    diameter : float
        m.
    symmetries : list of ndarray (4, 4)
        The part's symmetries (identity first).
    likelihood : ImageLikelihood
    make_filter : callable
        ``make_filter(T_world_object, cov6 or None, velocity (6,) or None) -> PoseEKF``.
    options : BankOptions
    workspace : tuple of 6 float or None
        The working volume the part's centre lies in (:mod:`vespro.workspace`), or None.
    """

    def __init__(self, vertices: np.ndarray, diameter: float, symmetries, likelihood: ImageLikelihood,
                 make_filter: Callable[..., PoseEKF], options: BankOptions = BankOptions(),
                 workspace: tuple | None = None):
        self.vertices = np.asarray(vertices, float)
        self.workspace = None if workspace is None else check_workspace(workspace)
        self.centre = box_centre(self.vertices)
        self.outside = 0  # poses refused or hypotheses dropped for lying outside the working volume
        self.diameter = float(diameter)
        self.symmetries = list(symmetries)
        self.likelihood = likelihood
        self.make_filter = make_filter
        self.options = options
        self.hypotheses: list[Hypothesis] = []
        self.null_score = 0.0
        self.proposed = 0
        self.merged = 0
        self.pruned = 0

    def clear(self) -> None:
        self.hypotheses = []
        self.null_score = 0.0

    def _same(self, T_a: np.ndarray, T_b: np.ndarray) -> bool:
        return add_sym(T_a, T_b, self.vertices, self.symmetries) < self.options.merge_frac * self.diameter

    def inside(self, T_world_object: np.ndarray) -> bool:
        """Whether the pose puts the part's centre in the working volume (always, without one)."""
        T = np.asarray(T_world_object, float)
        return bool(centres_inside(T[:3, :3], T[:3, 3], self.centre, self.workspace)[0])

    def propose(self, T_world_object: np.ndarray, t_ns: int, cov6: np.ndarray | None = None,
                velocity: np.ndarray | None = None) -> Hypothesis | None:
        """Add a pose (or find the hypothesis it is the same as); returns that hypothesis, or None
        for a pose outside the working volume."""
        self.proposed += 1
        if not self.inside(T_world_object):
            self.outside += 1
            return None
        for h in self.hypotheses:
            if self._same(h.ekf.pose, T_world_object):
                self.merged += 1
                return h
        best = max((h.score for h in self.hypotheses), default=0.0)
        h = Hypothesis(self.make_filter(T_world_object, cov6, velocity),
                       min(max(best, self.null_score), 0.0) + math.log(self.options.new_prior), t_ns)
        self.hypotheses.append(h)
        return h

    def add(self, ekf: PoseEKF, t_ns: int, score: float = 0.0) -> Hypothesis:
        """Hold an existing filter as a hypothesis (a pose given by the user)."""
        h = Hypothesis(ekf, score, t_ns)
        self.hypotheses.append(h)
        return h

    def remove(self, h: Hypothesis) -> None:
        if h in self.hypotheses:
            self.hypotheses.remove(h)

    def weigh(self, views) -> None:
        """One step of the forward recursion: every hypothesis's prior (``switch_rate`` of its
        probability passed to the null), then the frame's evidence (``views`` as for
        :class:`ImageLikelihood`); the scores end as log posterior probabilities. A hypothesis
        whose filter left the working volume is dropped first."""
        if self.workspace is not None:
            kept = [h for h in self.hypotheses if self.inside(h.ekf.pose)]
            self.outside += len(self.hypotheses) - len(kept)
            self.hypotheses = kept
        if not self.hypotheses:
            self.null_score = 0.0
            return
        eps = self.options.switch_rate
        p = self.probabilities()
        p_null = max(1.0 - float(p.sum()), 0.0)
        self.null_score = math.log(max(p_null + eps * float(p.sum()), 1e-300))
        for h, ph in zip(self.hypotheses, p):
            pl = self.likelihood(h.ekf.pose, views)
            h.last = pl
            h.last_log_lik = self.evidence(pl)
            h.score = math.log(max((1.0 - eps) * float(ph), 1e-300)) + h.last_log_lik
            h.frames += 1
        norm = _logsumexp([self.null_score] + [h.score for h in self.hypotheses])
        self.null_score -= norm
        for h in self.hypotheses:
            h.score -= norm

    def evidence(self, pl: PoseLikelihood) -> float:
        """A frame's log ratio for a pose: per camera, if the part is in view (``p_visible``), the
        sum over its edges of each edge's weighted log ratio if the edge shows (``p_edge``) or none
        (0) if not; none if something blocks the camera; cameras add."""
        o = self.options
        w, q = o.evidence_weight, o.p_visible
        total = 0.0
        for c in pl.cameras:
            if o.p_edge >= 1.0:
                ll = w * c.log_lik
            else:
                e = np.asarray(c.edge_log_lik, float)
                if c.edge_region_log_lik is not None:
                    e = e + c.edge_region_log_lik
                ll = float(np.logaddexp(math.log(o.p_edge) + w * e, math.log1p(-o.p_edge)).sum())
            total += ll if q >= 1.0 else float(np.logaddexp(math.log(q) + ll, math.log1p(-q)))
        return total

    def accuracy(self, T_world_object: np.ndarray, cov6: np.ndarray) -> float:
        """Probability that a filter at ``T_world_object`` with covariance ``cov6`` puts the part
        within ``pose_tolerance`` (see :func:`accuracy_probability`)."""
        return accuracy_probability(T_world_object, cov6, self.vertices, self.options.pose_tolerance * self.diameter)

    def probabilities(self) -> np.ndarray:
        """Each hypothesis's probability (the null takes the rest), in the order held."""
        if not self.hypotheses:
            return np.zeros(0)
        s = np.array([self.null_score] + [h.score for h in self.hypotheses])
        w = np.exp(s - s.max())
        return (w / w.sum())[1:]

    def probability(self, h: Hypothesis) -> float:
        p = self.probabilities()
        return float(p[self.hypotheses.index(h)]) if h in self.hypotheses else 0.0

    def best(self) -> Hypothesis | None:
        return max(self.hypotheses, key=lambda h: h.score, default=None)

    def tidy(self, keep: Hypothesis | None = None) -> None:
        """Merge near-duplicates (the scores add as probabilities), drop the improbable and the
        surplus; ``keep`` (the tracked one) is never dropped while it is the best."""
        o = self.options
        hs = sorted(self.hypotheses, key=lambda h: -h.score)
        out: list[Hypothesis] = []
        for h in hs:
            twin = next((k for k in out if self._same(k.ekf.pose, h.ekf.pose)), None)
            if twin is None:
                out.append(h)
            else:
                twin.score = float(np.logaddexp(twin.score, h.score))
                self.merged += 1
        self.hypotheses = out
        p = self.probabilities()
        best = self.best()
        kept = [h for h, ph in zip(out, p) if ph >= o.prune_prob or h is best or h is keep]
        kept = kept[:o.max_hypotheses]
        self.pruned += len(out) - len(kept)
        self.hypotheses = kept
