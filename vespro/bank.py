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

Equivalent poses of a symmetric part and poses within ``merge_frac`` of the
diameter of each other (ADD over the part's symmetries) are one hypothesis:
the first keeps its filter, the scores add as probabilities. Hypotheses whose
probability falls under ``prune_prob`` are dropped, and at most
``max_hypotheses`` are kept.

The decision: the best hypothesis is published ``tracking`` while its
probability is at least ``1 - wrong_lock_rate``; when it falls below, it is
not published from that frame on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .ekf import PoseEKF
from .likelihood import ImageLikelihood, PoseLikelihood
from .metrics import add_sym

__all__ = ["BankOptions", "Hypothesis", "HypothesisBank"]


def _logsumexp(values: list) -> float:
    """``log(sum(exp(v)))`` of a few log scores, without overflow: SciPy's ``logsumexp`` to
    rounding, without its 0.1 ms of overhead a call (the bank's every frame, on a handful
    of numbers)."""
    m = max(values)
    if not math.isfinite(m):
        return m
    return m + math.log(sum(math.exp(v - m) for v in values))


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
    """

    def __init__(self, vertices: np.ndarray, diameter: float, symmetries, likelihood: ImageLikelihood,
                 make_filter: Callable[..., PoseEKF], options: BankOptions = BankOptions()):
        self.vertices = np.asarray(vertices, float)
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

    def propose(self, T_world_object: np.ndarray, t_ns: int, cov6: np.ndarray | None = None,
                velocity: np.ndarray | None = None) -> Hypothesis:
        """Add a pose (or find the hypothesis it is the same as); returns that hypothesis."""
        self.proposed += 1
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
        :class:`ImageLikelihood`); the scores end as log posterior probabilities."""
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
        """A frame's log ratio for a pose: per camera, the weighted log ratio of its lines if the
        part is in view (``p_visible``), or none (0) if something blocks it; cameras add."""
        w, q = self.options.evidence_weight, self.options.p_visible
        if q >= 1.0:
            return w * pl.log_lik
        lq, lh = math.log(q), math.log1p(-q)
        return float(sum(np.logaddexp(lq + w * c.log_lik, lh) for c in pl.cameras))

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
