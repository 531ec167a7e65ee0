"""Frame sources for the pose server: where frame sets come from.

A source yields :class:`~vespro.frames.FrameSet` objects at the capture rate,
each stamped at capture on the server's clock, and None when it has no more.

- :class:`ReplaySource`: a recording replayed at its own rate.
- :class:`SimSource`: the simulated cell, physics stepped up to each capture
  instant (real time on a :class:`~vespro.clock.WallClock`, as fast as possible
  on a :class:`~vespro.clock.SimClock`).
- :class:`CameraSource`: fixed cameras through ``cv2.VideoCapture`` (local
  cameras, video files and network streams), which may also return a
  :class:`SourceGap` when a camera stalls.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from .clock import Clock, ns_from_s
from .errors import InputError
from .frames import FrameSet
from .recording import Recording
from .rig import Rig

__all__ = ["FrameSource", "ReplaySource", "SimSource", "CameraSource", "CameraError", "SourceGap", "WorldSource",
           "is_live_device", "is_local_camera"]


class FrameSource(Protocol):
    rig: Rig
    rate_hz: float

    def next(self) -> FrameSet | SourceGap | None:
        """Block until the next capture; None when the source is exhausted; a
        :class:`SourceGap` (live sources) when no frame set came in time."""
        ...

    def close(self) -> None:
        ...


class ReplaySource:
    """Replay a recording at its own capture times on ``clock``.

    Frame sets are re-stamped ``t_start + t[i]`` on the clock; ``loop`` starts
    over at the end (indices keep increasing). ``images`` counts the images
    read, usable or not (:class:`~vespro.imagecheck.ImageTally`).
    """

    def __init__(self, recording: Recording, clock: Clock, loop: bool = False):
        self.recording = recording
        self.images = recording.images
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


@dataclass(frozen=True)
class SourceGap:
    """What a live source returns instead of a frame set when none came in time.

    Attributes
    ----------
    t_ns : int
        When the gap was noticed (source clock).
    last_ns : int
        Capture stamp of the last frame set delivered (or of the start).
    reason : str
        One line for the log: which camera, what happened.
    """

    t_ns: int
    last_ns: int
    reason: str


class CameraError(InputError):
    """A camera device that cannot be opened, or a device list that does not fit the rig."""


_STREAM_SCHEMES = ("rtsp", "rtsps", "rtp", "srt", "udp", "tcp", "rtmp", "http", "https")


def is_local_camera(spec) -> bool:
    """True for a camera on this machine (``0``, ``/dev/video0``): its size and rate can be set."""
    s = str(spec)
    return s.isdigit() or s.startswith("/dev/")


def is_live_device(spec) -> bool:
    """True for a source that delivers frames at its own pace: a local camera, or a network
    stream (``rtsp://``, ``http://``, ``udp://``, ...), whose frames come as they are sent.

    A video file is read as fast as it decodes, so the source paces it at its frame rate.
    A live source is never paced: frames it had already sent while the reader was behind
    (a stream's first second, buffered while the decoder probed it) would otherwise be held
    to a timeline that starts late, and every later frame would wait as long.
    """
    s = str(spec)
    scheme, sep, _ = s.partition("://")
    return is_local_camera(s) or (bool(sep) and scheme.lower() in _STREAM_SCHEMES)


class _Device:
    """One camera's capture: its cv2.VideoCapture (or None while down) and its end/retry state."""

    def __init__(self, name: str, spec, open_capture, size: tuple, rate_hz: float | None):
        self.name, self.spec = name, spec
        self.open_capture = open_capture
        self.size, self.rate_hz = size, rate_hz  # asked of a local camera at each (re)open
        self.cap = None
        self.frames = 0           # frames grabbed since the last (re)open
        self.retries = 0          # reopen attempts since it last ended
        self.retry_at_ns = 0
        self.backoff_s = 0.0

    def open(self) -> bool:
        cap = self.open_capture(int(self.spec) if str(self.spec).isdigit() else self.spec)
        if not cap.isOpened():
            cap.release()
            return False
        if is_local_camera(self.spec):
            import cv2

            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.size[0])
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.size[1])
            if self.rate_hz is not None:
                cap.set(cv2.CAP_PROP_FPS, self.rate_hz)
        self.cap, self.frames = cap, 0
        return True

    def release(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None


class CameraSource:
    """Fixed cameras through ``cv2.VideoCapture`` (one device per rig camera): local
    cameras, video files and network streams.

    Capture runs in its own thread (``threaded``, on a wall clock) so a device that
    stalls never blocks the server: :meth:`next` returns the next frame set, or a
    :class:`SourceGap` when none came for ``stall_s`` after one was due (the server
    publishes ``lost``), or None once the source has ended.

    Timing
        A live device (:func:`is_live_device`: a local camera or a network stream)
        paces itself: its frames are stamped when ``grab`` returns. A video file is
        paced at its frame rate (``rate_hz``, else the container's FPS): frame k is
        delivered at, and stamped, ``t0 + k / rate``. A frame that comes more than
        a period after its instant (a reader held up) starts the timeline anew from
        its arrival (counted in ``resyncs``). The grabs of all cameras are issued
        back to back before any decoding. Frame sets the server has not taken when
        a newer one is ready are dropped, newest kept (``missed``).
    End of a stream
        A device whose ``grab`` fails has ended (end of file, camera unplugged,
        stream closed): said once through ``log``. ``on_end="stop"``: the source
        ends (:meth:`next` returns None). ``on_end="retry"``: the device is
        reopened after ``retry_min_s``, doubling each failed attempt up to
        ``retry_max_s`` (a file starts over); the other cameras go on meanwhile.
    Frames with the wrong size give a missing image (the intrinsics are for the
    rig's size; never rescaled). Eye-in-hand cameras need the arm's joint state,
    which a live source does not have: they are rejected.

    Parameters
    ----------
    rig : Rig
    devices : list
        ``cv2.VideoCapture`` argument per rig camera (index, path or URL).
    clock : Clock
    rate_hz : float, optional
        Frame rate; default: the first device's FPS (``CAP_PROP_FPS``), else 26.
    on_end : {"stop", "retry"}
    stall_s : float, optional
        A gap this long after a frame was due is reported; default
        ``max(0.1, 3 / rate_hz)``.
    threaded : bool
        False: capture inline in :meth:`next` (simulated clocks; no stall reports).
    log : callable
        Receives each event line (ended, reopened, ...).
    open_capture : callable
        ``open_capture(device) -> VideoCapture-like`` (default ``cv2.VideoCapture``).
    """

    def __init__(self, rig: Rig, devices: list, clock: Clock, rate_hz: float | None = None, on_end: str = "stop",
                 stall_s: float | None = None, retry_min_s: float = 0.5, retry_max_s: float = 8.0,
                 threaded: bool = True, log: Callable[[str], None] | None = None, open_capture=None,
                 queue_frames: int = 2):
        import cv2

        if any(not c.is_fixed for c in rig):
            raise CameraError("the live camera source supports fixed cameras only: use a rig whose cameras "
                              "are all 'mount: fixed'")
        if len(devices) != len(rig):
            raise CameraError(f"need one --device per rig camera: {len(rig)} cameras "
                              f"({', '.join(rig.names)}), {len(devices)} devices")
        if on_end not in ("stop", "retry"):
            raise CameraError(f"on_end: 'stop' or 'retry', got {on_end!r}")
        self.rig = rig
        self.clock = clock
        self.on_end = on_end
        self.log = log or (lambda line: print(line, file=sys.stderr, flush=True))
        self._retry_min_s, self._retry_max_s = float(retry_min_s), float(retry_max_s)
        self._devs = [_Device(cam.name, dev, open_capture or cv2.VideoCapture,
                              (cam.intrinsics.width, cam.intrinsics.height), rate_hz) for cam, dev in zip(rig, devices)]
        for d in self._devs:
            if not d.open():
                raise CameraError(f"camera {d.name}: cannot open device {d.spec!r} (an index, a video file "
                                  "or a stream URL that cv2.VideoCapture reads)")
        fps = float(self._devs[0].cap.get(cv2.CAP_PROP_FPS) or 0.0)
        if rate_hz is None:
            rate_hz = fps if 0.0 < fps < 1000.0 else 26.0
            if not 0.0 < fps < 1000.0:
                self.log(f"camera {rig.names[0]}: the device gives no frame rate; assuming {rate_hz:g} Hz (--rate)")
        if not (rate_hz > 0.0 and math.isfinite(rate_hz)):
            raise CameraError(f"--rate must be a positive frame rate, got {rate_hz}")
        self.rate_hz = float(rate_hz)
        self.paced = not all(is_live_device(d.spec) for d in self._devs)
        self.stall_ns = ns_from_s(stall_s if stall_s is not None else max(0.1, 3.0 / self.rate_hz))
        self._period_ns = 1e9 / self.rate_hz
        self.missed = 0      # frame sets dropped: the server fell behind (newest kept)
        self.resyncs = 0     # times the timeline started anew (a frame more than a period late)
        self.ends = 0        # device ends (each said once)
        self._t0 = None
        self._k = 0
        self._n = 0
        self._last_ns = None  # stamp of the last frame set delivered
        self._next_gap_ns = 0  # a stall is reported again no sooner than this
        self._ended = False  # no more frame sets (stop after an end, or closed)
        self._threaded = bool(threaded)
        self._thread = None  # started by the first next(): nothing is read before the server asks
        self._cond = threading.Condition()
        self._queue: deque = deque()
        self._queue_frames = max(1, int(queue_frames))

    # -- the server's side ------------------------------------------------------------
    def next(self) -> FrameSet | SourceGap | None:
        """The next frame set; a :class:`SourceGap` when none came in time; None once ended."""
        if not self._threaded:
            fs = None if self._ended else self._capture()
            if fs is None:
                self._ended = True
            else:
                self._last_ns = fs.t_ns
            return fs
        if self._thread is None:
            self._last_ns = self.clock.now_ns()
            self._thread = threading.Thread(target=self._capture_loop, name="vespro-capture", daemon=True)
            self._thread.start()
        with self._cond:
            due = max(self._last_ns + int(self._period_ns) + self.stall_ns, self._next_gap_ns)
            while not self._queue and not self._ended:
                now = self.clock.now_ns()
                if now >= due:  # reported again every stall_s while it lasts
                    self._next_gap_ns = now + self.stall_ns
                    return SourceGap(now, self._last_ns, self._gap_reason())
                self._cond.wait((due - now) * 1e-9)
            if not self._queue:
                return None
            fs = self._queue.popleft()
            self._last_ns, self._next_gap_ns = fs.t_ns, 0
            return fs

    def close(self) -> None:
        with self._cond:
            self._ended = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():
                return  # blocked in a grab (a stalled stream): releasing under it is unsafe; the process ends it
        for d in self._devs:
            d.release()

    def _gap_reason(self) -> str:
        down = [d.name for d in self._devs if d.cap is None]
        if down:
            return f"camera {', '.join(down)} down (reopening)"
        return f"no frame from the cameras for {(self.clock.now_ns() - self._last_ns) * 1e-9:.1f} s (stalled)"

    # -- capture ----------------------------------------------------------------------
    def _capture_loop(self) -> None:
        while not self._ended:
            try:
                fs = self._capture()
            except Exception as e:  # a driver surprise: the source ends, and says why
                self.log(f"camera capture failed: {e!r}")
                fs = None
            with self._cond:
                if fs is None:
                    self._ended = True
                elif not self._ended:
                    self._queue.append(fs)
                    while len(self._queue) > self._queue_frames:  # the tracker fell behind: latest wins
                        self._queue.popleft()
                        self.missed += 1
                self._cond.notify_all()

    def _capture(self) -> FrameSet | None:
        """Grab, pace and stamp the next frame set; None when the source ends (``on_end="stop"``)."""
        while not self._ended:
            self._reopen_due()
            up = [d for d in self._devs if d.cap is not None]
            if not up:
                nxt = min(d.retry_at_ns for d in self._devs)
                self.clock.sleep_until(min(nxt, self.clock.now_ns() + 100_000_000))  # wakes to see close()
                continue
            ok = [d.cap.grab() for d in up]
            t_grab = self.clock.now_ns()
            for d, g in zip(up, ok):
                d.frames += bool(g)
                if not g and not self._device_ended(d, t_grab):
                    return None
            if not any(ok):
                continue
            t_cap = t_grab
            if self.paced:
                if self._t0 is None or t_grab - self._instant(self._k) > self._period_ns:
                    if self._t0 is not None:
                        self.resyncs += 1
                    self._t0, self._k = t_grab, 0  # a new timeline from this arrival
                t_cap = self._instant(self._k)
                self.clock.sleep_until(t_cap)
                self._k += 1
            images = {}
            grabbed = {d.name for d, g in zip(up, ok) if g}
            for cam, d in zip(self.rig, self._devs):
                img = None
                if d.name in grabbed:
                    d.retries, d.backoff_s = 0, 0.0
                    img = d.cap.retrieve()[1]
                    if img is not None and img.shape[:2] != (cam.intrinsics.height, cam.intrinsics.width):
                        img = None  # never rescale silently: the intrinsics are for the rig's size
                images[cam.name] = img
            fs = FrameSet(self._n, int(t_cap), images, {})
            self._n += 1
            return fs
        return None

    def _instant(self, k: int) -> int:
        return self._t0 + int(round(k * self._period_ns))

    def _device_ended(self, d: _Device, now_ns: int) -> bool:
        """A failed grab: say so once; release the device. False when the source stops here."""
        self.ends += 1
        d.release()
        if self.on_end == "stop":
            self.log(f"camera {d.name}: stream ended after {d.frames} frames (device {d.spec!r}); stopping "
                     "(--on-camera-end stop)")
            return False
        d.backoff_s = self._retry_min_s
        d.retry_at_ns = now_ns + ns_from_s(d.backoff_s)
        self.log(f"camera {d.name}: stream ended after {d.frames} frames (device {d.spec!r}); reopening in "
                 f"{d.backoff_s:g} s (--on-camera-end retry)")
        return True

    def _reopen_due(self) -> None:
        now = self.clock.now_ns()
        for d in self._devs:
            if d.cap is not None or now < d.retry_at_ns or self.on_end != "retry":
                continue
            d.retries += 1
            if d.open():
                self.log(f"camera {d.name}: device {d.spec!r} reopened (attempt {d.retries})")
                continue
            d.backoff_s = min(2.0 * d.backoff_s, self._retry_max_s)
            d.retry_at_ns = now + ns_from_s(d.backoff_s)
            self.log(f"camera {d.name}: cannot reopen device {d.spec!r} (attempt {d.retries}); next try in "
                     f"{d.backoff_s:g} s")


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
        Name of the plant's world state block (:class:`vespro.sim.world.WorldShm`).
    config : vespro.sim.cell.CellConfig
        Rig, object mesh, imaging effects (its motion and arm settings are unused).
    clock : Clock
    """

    def __init__(self, world_shm: str, config, clock: Clock, wait_start_s: float = 30.0):
        from .sim.cell import SimCell
        from .sim.motion import Static
        from .sim.world import WorldShm
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
