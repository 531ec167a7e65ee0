"""Frame sources for the pose server: where frame sets come from.

A source yields :class:`~vespro.frames.FrameSet` objects at the capture rate,
each stamped at capture on the server's clock, and None when it has no more.

- :class:`ReplaySource`: a recording replayed at its own rate.
- :class:`SimSource`: the simulated cell, physics stepped up to each capture
  instant (real time on a :class:`~vespro.clock.WallClock`, as fast as possible
  on a :class:`~vespro.clock.SimClock`).
- :class:`CameraSource`: live fixed cameras through ``cv2.VideoCapture``.
"""

from __future__ import annotations

import sys
import time

from typing import Protocol

import numpy as np

from .clock import Clock, ns_from_s
from .frames import FrameSet
from .recording import Recording
from .rig import Rig

__all__ = ["FrameSource", "ReplaySource", "SimSource", "CameraSource"]


class FrameSource(Protocol):
    rig: Rig
    rate_hz: float

    def next(self) -> FrameSet | None:
        """Block until the next capture; None when the source is exhausted."""
        ...

    def close(self) -> None:
        ...


class ReplaySource:
    """Replay a recording at its own capture times on ``clock``.

    Frame sets are re-stamped ``t_start + t[i]`` on the clock; ``loop`` starts
    over at the end (indices keep increasing).
    """

    def __init__(self, recording: Recording, clock: Clock, loop: bool = False):
        self.recording = recording
        self.rig = recording.rig
        self.rate_hz = recording.rate_hz
        self.clock = clock
        self.loop = loop
        self._i = 0
        self._n = 0
        self._t_start = None
        self._period_ns = ns_from_s(len(recording) / recording.rate_hz)

    def next(self) -> FrameSet | None:
        rec = self.recording
        if self._i >= len(rec):
            if not self.loop:
                return None
            self._i = 0
            self._t_start += self._period_ns
        if self._t_start is None:
            self._t_start = self.clock.now_ns()
        t_cap = self._t_start + ns_from_s(rec.t[self._i] - rec.t[0])
        self.clock.sleep_until(t_cap)
        fs = rec.frameset(self._i)
        out = FrameSet(self._n, t_cap, fs.images, fs.T_world_camera)
        self._i += 1
        self._n += 1
        return out

    def close(self) -> None:
        pass


class SimSource:
    """Frames from a :class:`~vespro.sim.cell.SimCell`.

    The cell's physics runs on its own simulated clock; the server clock paces
    delivery: on a wall clock each frame set is delivered at its capture instant
    in real time, on a simulated clock immediately.
    """

    def __init__(self, cell, clock: Clock, max_frames: int | None = None):
        self.cell = cell
        self.rig = cell.config.rig
        self.rate_hz = cell.config.rate_hz
        self.clock = clock
        self.max_frames = max_frames
        self._t0 = None
        self._n = 0

    def next(self) -> FrameSet | None:
        if self.max_frames is not None and self._n >= self.max_frames:
            return None
        fs = self.cell.next_frameset()
        if self._t0 is None:
            self._t0 = self.clock.now_ns() - fs.t_ns
        t_cap = self._t0 + fs.t_ns
        self.clock.sleep_until(t_cap)
        self._n += 1
        return FrameSet(fs.index, t_cap, fs.images, fs.T_world_camera)

    def close(self) -> None:
        self.cell.close()


class CameraSource:
    """Live fixed cameras through ``cv2.VideoCapture`` (one device per rig camera).

    Frames are stamped with the clock when ``grab`` returns for the first
    camera; the grabs of all cameras are issued back to back before any
    decoding (``grab`` then ``retrieve``) to keep them as simultaneous as USB
    cameras allow. A failed read gives a missing image, not an error.
    Eye-in-hand cameras need the arm's joint state, which a live source does not
    have: they are rejected.
    """

    def __init__(self, rig: Rig, devices: list, clock: Clock, rate_hz: float = 26.0):
        import cv2

        if any(not c.is_fixed for c in rig):
            raise ValueError("the live camera source supports fixed cameras only")
        if len(devices) != len(rig):
            raise ValueError(f"need one device per rig camera: {len(rig)} cameras, {len(devices)} devices")
        self.rig = rig
        self.rate_hz = rate_hz
        self.clock = clock
        self._caps = []
        for cam, dev in zip(rig, devices):
            cap = cv2.VideoCapture(int(dev) if str(dev).isdigit() else dev)
            if not cap.isOpened():
                raise ValueError(f"camera {cam.name}: cannot open device {dev!r}")
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, cam.intrinsics.width)
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, cam.intrinsics.height)
            self._caps.append(cap)
        self._n = 0

    def next(self) -> FrameSet | None:
        ok = [cap.grab() for cap in self._caps]
        t = self.clock.now_ns()
        images = {}
        for cam, cap, g in zip(self.rig, self._caps, ok):
            img = cap.retrieve()[1] if g else None
            if img is not None and img.shape[:2] != (cam.intrinsics.height, cam.intrinsics.width):
                img = None  # never rescale silently: the intrinsics are for the rig's size
            images[cam.name] = img
        fs = FrameSet(self._n, t, images, {})
        self._n += 1
        return fs

    def close(self) -> None:
        for cap in self._caps:
            cap.release()


class WorldSource:
    """Camera frames of a world simulated in another process (the demo's plant).

    At each capture instant (the plant's start time plus ``k / rate``, on the
    wall clock) it reads the world state from shared memory and renders every
    rig camera from it, with the simulator's imaging pipeline. If processing
    fell behind, the capture instants it missed are skipped (counted in
    ``missed``), as a real camera's frames would be dropped. Returns None once the
    plant has stopped.

    Parameters
    ----------
    world_shm : str
        Name of the plant's :class:`vespro.sim.plant.WorldShm`.
    config : vespro.sim.cell.CellConfig
        Rig, object mesh, imaging effects (its motion and arm settings are unused).
    clock : Clock
    """

    def __init__(self, world_shm: str, config, clock: Clock, wait_start_s: float = 30.0):
        from .sim.cell import SimCell
        from .sim.motion import Static
        from .sim.plant import WorldShm
        from .se3 import transform_from_pq

        self._pq = transform_from_pq
        self.world = WorldShm(world_shm)
        self.cell = SimCell(config, Static(np.eye(4)))
        self.rig = config.rig
        self.rate_hz = config.rate_hz
        self.clock = clock
        self.missed = 0
        self.last_capture_ms = 0.0  # rendering time of the last capture, ms
        self.skip_cameras: frozenset = frozenset()  # cameras not rendered (their images None)
        self._k = 0
        self._wait_start_s = float(wait_start_s)
        # One throwaway render now: the first one builds the imaging pipeline's noise banks
        # (~0.2 s for three cameras), which on the first live capture stalled the loop for
        # the next five captures.
        self.cell.render_frameset(0, 0, 0.0)

    def wait_start(self) -> bool:
        """Wait (up to ``wait_start_s``) for the plant to start; False if it did not."""
        t_end = self.clock.now_ns() + int(self._wait_start_s * 1e9)
        while self.world.t0_ns == 0 and self.clock.now_ns() < t_end:
            self.clock.sleep_until(self.clock.now_ns() + 5_000_000)
        return self.world.t0_ns != 0

    def next(self) -> FrameSet | None:
        """The next capture (waits for the plant's start first); None once the plant has stopped."""
        if self.world.t0_ns == 0 and not self.wait_start():
            print(f"world source: the plant did not start within {self._wait_start_s:.0f} s", file=sys.stderr)
            return None
        period = 1e9 / self.rate_hz
        t0 = self.world.t0_ns
        while True:
            now = self.clock.now_ns()
            k_now = int((now - t0) // period)
            if k_now > self._k:  # fell behind: drop the missed captures
                self.missed += k_now - self._k
                self._k = k_now + 1
            t_cap = t0 + int(round(self._k * period))
            self.clock.sleep_until(t_cap)
            if self.world.finished:
                return None
            fs = self.render_now()
            if fs is not None:
                return fs
            # A torn read under heavy load: skip this capture, not the rest of the run.
            self.missed += 1
            self._k += 1

    def render_now(self) -> FrameSet | None:
        """Render the world as it is now, as capture index ``k`` (lockstep drivers call this)."""
        t = time.perf_counter()
        state = self.world.read()
        if state is None:
            return None
        t_ns, q, pq, _ = state
        self.cell.set_world(q, self._pq(pq))
        fs = self.cell.render_frameset(self._k, t_ns, (t_ns - self.world.t0_ns) * 1e-9, skip=self.skip_cameras)
        self._k += 1
        self.last_capture_ms = (time.perf_counter() - t) * 1e3
        return fs

    def close(self) -> None:
        self.cell.close()
        self.world.close()
