"""A virtual object stream for virtual mode and tests: a part on a conveyor.

Poses are "captured" at ``rate_hz`` and become available ``latency_s`` later,
as the vision side's would; ``latest(now_ns)`` is the
:class:`~servo.loop.SampleSource` interface the loop polls.
"""

from __future__ import annotations

import numpy as np

from .target import SampleStatus, TargetSample

__all__ = ["ConveyorTarget"]


class ConveyorTarget:
    """Object moving at constant velocity; sampled, delayed, optionally noisy.

    Parameters
    ----------
    p0 : (3,) m          object position at ``t0_ns``, world
    velocity : (3,) m/s  constant, world
    quat : (4,)          constant orientation (w, x, y, z)
    rate_hz : float      capture rate
    latency_s : float    capture-to-availability delay
    noise_std_m : float  white position noise on each sample
    gaps_s : list of (start, end)
        Capture-time intervals (s after t0) without any sample (stream loss).
    velocity_known : bool
        Samples carry the true velocity (the tracker's estimate); else zero.
    """

    def __init__(
        self,
        p0=(0.9, -0.3, 0.5),
        velocity=(0.0, 0.1, 0.0),
        quat=(1.0, 0.0, 0.0, 0.0),
        rate_hz: float = 26.0,
        latency_s: float = 0.040,
        t0_ns: int = 0,
        noise_std_m: float = 0.0,
        gaps_s=(),
        velocity_known: bool = True,
        seed: int = 0,
    ):
        self.p0 = np.asarray(p0, float)
        self.velocity = np.asarray(velocity, float)
        self.quat = np.asarray(quat, float)
        self.period_ns = int(round(1e9 / rate_hz))
        self.latency_ns = int(round(latency_s * 1e9))
        self.t0_ns = int(t0_ns)
        self.noise = float(noise_std_m)
        self.gaps_ns = [(int(a * 1e9), int(b * 1e9)) for a, b in gaps_s]
        self.velocity_known = velocity_known
        self.rng = np.random.default_rng(seed)
        self._k = None
        self._sample = None

    def position(self, t_ns: int) -> np.ndarray:
        """True object position at ``t_ns``, (3,), m."""
        return self.p0 + self.velocity * ((t_ns - self.t0_ns) * 1e-9)

    def latest(self, now_ns: int):
        """(newest available sample or None, its age ns)."""
        k = (now_ns - self.latency_ns - self.t0_ns) // self.period_ns
        # step back over capture times inside a gap
        while k >= 0:
            tc = k * self.period_ns
            if not any(a <= tc < b for a, b in self.gaps_ns):
                break
            k -= 1
        if k < 0:
            return None, 0
        if k != self._k:
            t_cap = self.t0_ns + k * self.period_ns
            p = self.position(t_cap)
            if self.noise > 0:
                p = p + self.rng.normal(0.0, self.noise, 3)
            v = self.velocity if self.velocity_known else np.zeros(3)
            self._sample = TargetSample(
                t_cap, p, self.quat, v, np.zeros(3), np.eye(6) * max(self.noise, 1e-4) ** 2, SampleStatus.OK, k
            )
            self._k = k
        return self._sample, now_ns - self._sample.t_capture_ns
