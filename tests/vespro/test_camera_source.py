"""The camera source: files and streams paced at their rate, ends, retries and stalls.

A fake ``cv2.VideoCapture`` stands in for the device; on a simulated clock
(inline capture) every stamp is exact, so pacing is checked on the stamps
themselves, never against the machine's speed.
"""

import time

import cv2
import numpy as np
import pytest

from vespro.clock import SimClock, WallClock
from vespro.rig import load_rig
from vespro.sim.rigs import CAMERAS_DIR
from vespro.sources import CameraError, CameraSource, SourceGap

RIG = load_rig(CAMERAS_DIR / "fixed1.yaml")
H, W = RIG["cam_left"].intrinsics.height, RIG["cam_left"].intrinsics.width


class FakeCapture:
    """A video of ``n`` frames at ``fps``; ``grab`` costs ``decode_s`` of ``clock`` time
    and, at frame ``stall_at``, blocks ``stall_s`` of wall time (a stream that stops
    then resumes). ``live``: ``grab`` waits (wall time) for each frame, ``1 / fps`` apart,
    as a camera delivers them."""

    def __init__(self, n, fps=30.0, clock=None, decode_s=0.0, stall_at=None, stall_s=0.0, opened=True,
                 slow_every=0, slow_s=0.0, live=False):
        self.n, self.fps, self.clock, self.decode_s = n, fps, clock, decode_s
        self.slow_every, self.slow_s = slow_every, slow_s
        self.stall_at, self.stall_s, self.opened = stall_at, stall_s, opened
        self.live, self._next = live, None
        self.i = 0
        self.img = np.zeros((H, W), np.uint8)

    def isOpened(self):
        return self.opened

    def set(self, prop, value):
        return True

    def get(self, prop):
        return self.fps if prop == cv2.CAP_PROP_FPS else 0.0

    def grab(self):
        if self.i >= self.n:
            return False
        if self.i == self.stall_at:
            time.sleep(self.stall_s)
        if self.live:
            now = time.monotonic()
            self._next = max(self._next or now, now)
            time.sleep(max(0.0, self._next - now))
            self._next += 1.0 / self.fps
        if self.clock is not None:
            slow = self.slow_every and self.i % self.slow_every == self.slow_every - 1
            self.clock.advance(int((self.slow_s if slow else self.decode_s) * 1e9))
        self.i += 1
        return True

    def retrieve(self):
        return True, self.img

    def release(self):
        pass


def _drain(src, limit=10_000):
    items = []
    while len(items) < limit:
        it = src.next()
        if it is None:
            break
        items.append(it)
    return items


def test_a_file_is_paced_at_its_frame_rate_and_its_end_reported_once():
    clock = SimClock(t0_ns=5_000_000_000)
    lines = []
    src = CameraSource(RIG, ["clip.mp4"], clock, threaded=False, log=lines.append,
                       open_capture=lambda dev: FakeCapture(40, fps=30.0))
    assert src.rate_hz == 30.0 and src.paced
    frames = _drain(src)
    assert len(frames) == 40 and src.next() is None and src.next() is None
    dt = np.diff([f.t_ns for f in frames])
    assert np.all(np.abs(dt - 1e9 / 30) <= 1), dt  # the stream's 30 Hz, to the rounding of a ns
    assert [f.index for f in frames] == list(range(40))
    ends = [ln for ln in lines if "ended" in ln]
    assert len(ends) == 1 and "after 40 frames" in ends[0] and "stopping" in ends[0], lines


def test_rate_option_overrides_the_container_and_a_late_frame_starts_a_new_timeline():
    """--rate paces a stream at 20 Hz whatever it says; a reader held up now and then (one
    decode in ten takes 120 ms, 2.4 periods) stamps that frame at its arrival and goes on
    at 20 Hz from there: no frame dropped, no two stamps closer than a period."""
    clock = SimClock()
    src = CameraSource(RIG, ["clip.mp4"], clock, rate_hz=20.0, threaded=False, log=lambda line: None,
                       open_capture=lambda dev: FakeCapture(60, fps=30.0, clock=clock, decode_s=0.005,
                                                            slow_every=10, slow_s=0.12))
    frames = _drain(src)
    steps = np.diff([f.t_ns for f in frames]) / 50e6
    assert len(frames) == 60 and src.missed == 0 and src.resyncs == 6
    assert np.all(steps >= 1 - 1e-7), steps
    assert np.sum(np.abs(steps - 1) < 1e-7) == 59 - 6  # 20 Hz but where a late frame restarted it


@pytest.mark.parametrize("retry_max_s, waits", [(8.0, [0.5, 1.0, 2.0, 4.0]), (1.0, [0.5, 1.0, 1.0, 1.0])])
def test_retry_reopens_with_bounded_backoff_and_reports_each_end_once(retry_max_s, waits):
    """A file that ends is reopened after 0.5 s, doubling per failed attempt up to the
    cap; the frames after a successful reopen start a new timeline on the same rate."""
    clock = SimClock()
    opens = []

    def open_capture(dev):
        opens.append(clock.now_ns())
        return FakeCapture(5, fps=25.0, opened=len(opens) == 1 or len(opens) >= 5)  # 3 failed reopens

    lines = []
    src = CameraSource(RIG, ["clip.mp4"], clock, on_end="retry", retry_max_s=retry_max_s, threaded=False,
                       log=lines.append, open_capture=open_capture)
    frames = [src.next() for _ in range(10)]
    assert all(f is not None and not isinstance(f, SourceGap) for f in frames)
    gaps = np.diff(opens) * 1e-9
    t_end = frames[4].t_ns  # the end was found right after the fifth frame
    assert (opens[1] - t_end) * 1e-9 == pytest.approx(0.5, abs=1e-3)
    assert gaps[1:] == pytest.approx(waits[1:], abs=1e-3)  # doubling, capped
    assert sum("ended" in ln for ln in lines) == 1 and sum("cannot reopen" in ln for ln in lines) == 3
    assert sum("reopened" in ln for ln in lines) == 1
    assert np.all(np.abs(np.diff([f.t_ns for f in frames[5:]]) - 40e6) <= 1)  # 25 Hz again


def test_a_stalled_stream_is_reported_while_it_lasts_then_resumes_on_a_new_timeline():
    """The capture thread blocks 0.6 s in the middle of a 50 Hz camera: the source returns
    gaps (each ``stall_s`` apart, not at full speed) between the frames before and after,
    then the frames again, the first stamped at its arrival."""
    src = CameraSource(RIG, ["/dev/video9"], WallClock(), rate_hz=50.0, stall_s=0.1, log=lambda line: None,
                       open_capture=lambda dev: FakeCapture(20, fps=50.0, stall_at=10, stall_s=0.6, live=True))
    items = _drain(src)
    src.close()
    frames = [it for it in items if not isinstance(it, SourceGap)]
    assert [f.index for f in frames] == list(range(20))
    i10 = next(k for k, it in enumerate(items) if it is frames[10])
    i9 = items.index(frames[9])
    stall = items[i9 + 1:i10]
    assert stall and all(isinstance(g, SourceGap) and g.last_ns == frames[9].t_ns for g in stall)
    assert len(stall) <= 0.6 / 0.1 + 2  # reported every stall_s, not in a tight loop
    assert all(b.t_ns - a.t_ns >= 0.1e9 for a, b in zip(stall, stall[1:]))
    assert frames[10].t_ns - frames[9].t_ns >= 0.6e9  # the stall is in the stamps, not hidden


class BufferedStream(FakeCapture):
    """A live network stream on a simulated clock: frame i is sent at ``sent[i]`` and ``grab``
    waits for it; frames sent before the reader asked are already buffered (no wait)."""

    def __init__(self, sent_ns, clock):
        super().__init__(len(sent_ns), fps=30.0)
        self.sent_ns, self.clock = list(sent_ns), clock

    def grab(self):
        if self.i >= self.n:
            return False
        self.clock.advance(max(0, self.sent_ns[self.i] - self.clock.now_ns()))
        self.i += 1
        return True


@pytest.mark.parametrize("url", ["rtsp://192.168.0.20/stream1", "http://cam.local/video.mjpg", "udp://@:5000"])
def test_a_network_stream_is_taken_as_it_comes_never_held_to_a_late_timeline(url):
    """A 30 Hz stream whose first 10 frames were buffered while the reader opened it (sent
    before it asked): they are taken at once, and every later frame is stamped when it
    arrives, not held to a timeline started at the first read (which would delay every
    frame by the 10 buffered periods for as long as the stream runs)."""
    clock = SimClock(t0_ns=10**9)
    period = int(1e9 / 30)
    sent = [10**9 - (10 - i) * period for i in range(10)] + [10**9 + k * period for k in range(1, 41)]
    src = CameraSource(RIG, [url], clock, rate_hz=30.0, threaded=False, log=lambda line: None,
                       open_capture=lambda dev: BufferedStream(sent, clock))
    frames = _drain(src)
    assert [f.index for f in frames] == list(range(50)) and not src.paced
    stamps = [f.t_ns for f in frames]
    assert stamps[:10] == [10**9] * 10  # buffered: read at once, on arrival
    assert stamps[10:] == sent[10:]     # live: each stamped as it came
    # The premise: a file's reader paces the same arrivals, and then lags by the buffer.
    clock = SimClock(t0_ns=10**9)
    paced = CameraSource(RIG, ["cube.mp4"], clock, rate_hz=30.0, threaded=False, log=lambda line: None,
                         open_capture=lambda dev: BufferedStream(sent, clock))
    lag = np.array([f.t_ns for f in _drain(paced)][10:]) - np.array(sent[10:])
    assert paced.paced and np.all(lag >= 9 * period)


def test_bad_devices_are_a_one_line_input_error():
    with pytest.raises(CameraError, match="one --device per rig camera"):
        CameraSource(RIG, ["a.mp4", "b.mp4"], SimClock(), open_capture=lambda d: FakeCapture(1))
    with pytest.raises(CameraError, match="cannot open device 'missing.mp4'"):
        CameraSource(RIG, ["missing.mp4"], SimClock(), open_capture=lambda d: FakeCapture(1, opened=False))
