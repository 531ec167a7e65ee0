"""Scripted motions of the tracked object: pure functions of time.

Each motion maps time ``t`` (s) to ``T_world_object`` (4x4). They drive the
object's mocap body in the simulator; they are never seen by the tracker.

- :class:`Static`: a fixed pose.
- :class:`Conveyor`: resting on the belt, carried along world +y at a settable
  speed, optionally stopping smoothly at a given time.
- :class:`Sinusoid`: free 6-DoF motion, smooth sinusoids of settable amplitude
  and speed about a centre pose.
- :class:`RandomSmooth`: random smooth 6-DoF motion, a seeded sum of
  band-limited sinusoids.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..se3 import exp_so3, transform_from_rt
from .scene import BELT_CENTER_X, BELT_TOP_Z, WORK_POINT

__all__ = ["Motion", "Static", "Conveyor", "Sinusoid", "RandomSmooth", "make_motion", "MOTION_KINDS"]


class Motion:
    """A trajectory of the object: ``pose(t) -> T_world_object``."""

    def pose(self, t: float) -> np.ndarray:
        raise NotImplementedError


@dataclass(frozen=True)
class Static(Motion):
    T_world_object: np.ndarray

    def pose(self, t: float) -> np.ndarray:
        return np.array(self.T_world_object, dtype=float)


@dataclass(frozen=True)
class Conveyor(Motion):
    """A part resting on the belt, carried along +y.

    Attributes
    ----------
    speed : float
        Belt speed, m/s.
    y0 : float
        Position along the belt at t = 0, m.
    x_offset : float
        Lateral offset from the belt's centre line, m.
    yaw : float
        Rotation of the part about the vertical, rad.
    stop_time : float or None
        Time at which the belt starts decelerating to rest (s).
    stop_decel : float
        Deceleration of the stopping belt, m/s^2.
    """

    speed: float = 0.1
    y0: float = -0.25
    x_offset: float = 0.0
    yaw: float = 0.4
    stop_time: float | None = None
    stop_decel: float = 0.2

    def travel(self, t: float) -> float:
        if self.stop_time is None or t <= self.stop_time:
            return self.speed * t
        t_brake = self.speed / self.stop_decel
        dt = min(t - self.stop_time, t_brake)
        return self.speed * self.stop_time + self.speed * dt - 0.5 * self.stop_decel * dt * dt

    def pose(self, t: float) -> np.ndarray:
        p = [BELT_CENTER_X + self.x_offset, self.y0 + self.travel(t), BELT_TOP_Z]
        return transform_from_rt(exp_so3([0.0, 0.0, self.yaw]), p)


def _default_center() -> np.ndarray:
    return transform_from_rt(exp_so3([0.35, -0.25, 0.6]), WORK_POINT + [0.0, 0.0, 0.08])


@dataclass(frozen=True)
class Sinusoid(Motion):
    """Free 6-DoF sinusoidal motion about a centre pose.

    Position ``c + a_p * sin(2 pi f t + phase)`` per axis; orientation
    ``R_c @ Exp(a_r * sin(2 pi f' t + phase'))`` (rotation vector in the object
    frame). ``speed`` scales every frequency.

    Attributes
    ----------
    amplitude : float
        Position amplitude per axis, m.
    rot_amplitude : float
        Rotation amplitude per axis, rad.
    speed : float
        Frequency scale (1.0: periods of 4-7 s, the "slow" motion).
    """

    amplitude: float = 0.05
    rot_amplitude: float = 0.3
    speed: float = 1.0
    center: np.ndarray = field(default_factory=_default_center)

    _FREQ = np.array([0.25, 0.19, 0.15, 0.21, 0.17, 0.23])
    _PHASE = np.array([0.0, 1.3, 2.1, 0.7, 2.9, 1.9])

    def pose(self, t: float) -> np.ndarray:
        s = np.sin(2 * np.pi * self._FREQ * self.speed * t + self._PHASE)
        dp = self.amplitude * s[:3]
        dr = self.rot_amplitude * s[3:]
        c = np.asarray(self.center)
        return transform_from_rt(c[:3, :3] @ exp_so3(dr), c[:3, 3] + dp)


@dataclass(frozen=True)
class RandomSmooth(Motion):
    """Random smooth 6-DoF motion: a seeded sum of sinusoids per axis.

    Frequencies are drawn in ``[0.05, 0.4] * speed`` Hz, amplitudes scaled so that
    each axis has standard deviation ``amplitude`` (m) or ``rot_amplitude`` (rad).
    """

    amplitude: float = 0.05
    rot_amplitude: float = 0.3
    speed: float = 1.0
    seed: int = 0
    n_terms: int = 4
    center: np.ndarray = field(default_factory=_default_center)

    def __post_init__(self):
        rng = np.random.default_rng(self.seed)
        f = rng.uniform(0.05, 0.4, (6, self.n_terms)) * self.speed
        ph = rng.uniform(0, 2 * np.pi, (6, self.n_terms))
        a = rng.uniform(0.5, 1.0, (6, self.n_terms))
        a /= np.sqrt(0.5 * np.sum(a * a, axis=1, keepdims=True))  # unit std per axis
        object.__setattr__(self, "_f", f)
        object.__setattr__(self, "_ph", ph)
        object.__setattr__(self, "_a", a)

    def pose(self, t: float) -> np.ndarray:
        s = np.sum(self._a * np.sin(2 * np.pi * self._f * t + self._ph), axis=1)
        dp = self.amplitude * s[:3]
        dr = self.rot_amplitude * s[3:]
        c = np.asarray(self.center)
        return transform_from_rt(c[:3, :3] @ exp_so3(dr), c[:3, 3] + dp)


MOTION_KINDS = ("conveyor", "sinusoid", "random", "static")


def make_motion(kind: str, *, speed: float | None = None, amplitude: float | None = None,
                rot_amplitude: float | None = None, seed: int = 0, stop_time: float | None = None,
                y0: float | None = None) -> Motion:
    """Motion from a command-line description.

    ``speed`` is the belt speed (m/s) for ``conveyor`` and the frequency scale
    for the free motions.
    """
    if kind == "conveyor":
        kw = {}
        if speed is not None:
            kw["speed"] = speed
        if y0 is not None:
            kw["y0"] = y0
        return Conveyor(stop_time=stop_time, **kw)
    kw = {k: v for k, v in dict(speed=speed, amplitude=amplitude, rot_amplitude=rot_amplitude).items() if v is not None}
    if kind == "sinusoid":
        return Sinusoid(**kw)
    if kind == "random":
        return RandomSmooth(seed=seed, **kw)
    if kind == "static":
        return Static(_default_center())
    raise ValueError(f"unknown motion {kind!r}; choose one of {MOTION_KINDS}")
