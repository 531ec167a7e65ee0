"""The pose server: tracks frames from a source and publishes every estimate.

:class:`PoseServer` runs one loop at the capture rate: take the next frame set
from the source, run the tracker, publish a POSE message (status, pose,
velocity, covariance, capture and send stamps) through a
:class:`~vespro.link.PosePublisher`. The publisher never blocks on a slow
client (latest value wins, drops counted), so the tracker is never slowed.

While no track exists the automatic initialiser runs in a background thread on
the latest frame set; meanwhile every frame is still published with status
``initializing`` (or ``lost``), at the capture rate. When the initialiser
returns a pose, the filter starts at that frame's capture stamp and is
predicted forward to the current frame.

When a live source has no frame set when one was due (a camera stalled, or
is being reopened) it returns a :class:`~vespro.sources.SourceGap`: the server
publishes ``lost`` for it, says so once, and when frames come back after a long
gap starts the filter again from its last pose. When the source ends, ``lost``
is published once more and :meth:`PoseServer.run` returns.

Once a second the server logs one line: frame rate, tracker time, vision
latency (capture to send), status (with the tracker's probability when it
states one: ``tracking p=0.998``) and link statistics. Lines of a kind that
repeats (an initialisation that finds nothing) go out at most once a second.
Statistics are kept in memory that does not grow with the run's length.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .clock import Clock
from .frames import FrameSet
from .frameslot import FrameSlot, SlotFrames
from .quantiles import LogHistogram
from .realtime import freeze_set_up, leave_realtime
from .se3 import quat_from_matrix
from .sources import SourceGap
from .throttle import LogThrottle
from .tracker import InitResult, Tracker, TrackerOutput
from .wire import PoseMsg, PoseStatus

__all__ = ["PoseServer", "ServerStats", "pose_message"]

_WORKER_INIT = None

#: Catch-up after a late initialisation: share of each capture period spent tracking the
#: queued frame sets (at least one a live frame), and the fewest that leave the queue per live
#: frame (so it drains): those beyond the share are skipped.
CATCH_UP_SHARE = 0.4
CATCH_UP_MIN = 2


def _worker_setup(factory, nice: int = 0) -> None:
    """In the initialisation worker process: build the initialiser once.

    It runs at the live loop's priority or, with ``nice`` < 0, ahead of the machine's
    other normal work (still behind real-time threads): the loop has nothing to track
    while the worker searches (it only captures and publishes ``initializing``), so
    the sooner the search ends the better; a niced worker took 5-7 s a call beside
    the rendering in the real-time demo, longer than the catch-up backlog, and on a
    machine busy with other work one call took 21 s.
    """
    global _WORKER_INIT
    # Ctrl-C reaches the whole process group: the server stops the worker (its pool's
    # shutdown), and the worker must not die mid-job with a traceback of its own.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    leave_realtime()  # free of the live loop's core and real-time class, if it had them
    if nice:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        except (OSError, AttributeError):
            pass  # not permitted: normal priority
    _WORKER_INIT = factory()
    warm_up = getattr(_WORKER_INIT, "warm_up", None)
    if warm_up is not None:
        warm_up()  # compiled kernels loaded now, not during the first search
    freeze_set_up()


def _worker_ping() -> None:
    """A no-op job: starts the worker process (and builds its initialiser) ahead of the first frame."""
    return None


def _init_call(initializer, fs: FrameSet, seed=None, pending=None) -> tuple:
    """One initialiser call (seeded first when there is a seed): ``(result, why not, candidates,
    cpu ms)``.

    ``pending``: ``(T_world_object, t_ns)`` of the tracker's provisional start, for the
    call to confirm (:meth:`vespro.tracker.Tracker.offer`). ``why not`` is the
    initialiser's reason for returning no pose (its ``last_report.reason``, e.g. an
    accidental view or an ambiguity), or "". ``candidates``: the poses it ranked besides
    its answer, best first (for the hypothesis bank: :meth:`vespro.tracker.Tracker.propose`).
    ``cpu ms``: the CPU time of the call's thread; against the wall time from submission to
    answer it tells a call that worked long from one that waited for a core.
    """
    cpu0 = time.thread_time()
    if seed is not None and hasattr(initializer, "reseed"):
        initializer.reseed(seed[0], velocity=seed[1], t_ns=seed[2])
    if pending is not None and hasattr(initializer, "await_confirmation"):
        initializer.await_confirmation(*pending)
    res = initializer(fs)
    report = getattr(initializer, "last_report", None)
    cands = tuple(T for T, _ in getattr(report, "candidates", ()))
    why = "" if res is not None or report is None else str(getattr(report, "reason", "") or "")
    return res, why, cands, (time.thread_time() - cpu0) * 1e3


def _worker_run(frames: SlotFrames, seed=None, pending=None):
    return _init_call(_WORKER_INIT, frames.frameset(), seed, pending)

_STATUS = {"tracking": PoseStatus.TRACKING, "initializing": PoseStatus.INITIALIZING, "lost": PoseStatus.LOST}


def pose_message(out: TrackerOutput, seq: int, t_send_ns: int, object_id: int = 0,
                 last_T: np.ndarray | None = None) -> PoseMsg:
    """Wire message of a tracker output.

    A frame that is not tracking still carries a pose (the last good one, or
    identity) so the message is well formed; its status tells the receiver not
    to use it. The tracker's probability goes out with every frame (NaN: not
    stated, as with the confirmation rules).
    """
    if out.status == "tracking" and out.T_world_object is not None:
        T = out.T_world_object
        vel = out.velocity if out.velocity is not None else np.zeros(6)
        cov = out.cov6 if out.cov6 is not None else np.zeros((6, 6))
    else:
        T = last_T if last_T is not None else np.eye(4)
        vel = np.zeros(6)
        cov = np.zeros((6, 6))
    return PoseMsg(seq=seq, t_capture_ns=int(out.t_ns), t_send_ns=int(t_send_ns), object_id=object_id,
                   status=_STATUS[out.status], p_world_object=T[:3, 3], q_world_object=quat_from_matrix(T[:3, :3]),
                   v_world_object=vel[:3], w_world_object=vel[3:], cov=cov,
                   probability=min(max(float(out.probability), 0.0), 1.0) if np.isfinite(out.probability) else np.nan)


@dataclass
class ServerStats:
    """Counters of a server run, in memory that does not grow with its length.

    ``tracker_ms`` and ``latency_ms`` are histograms (:class:`~vespro.quantiles.LogHistogram`:
    median, p99 within 0.5 %); ``status_counts`` counts the published statuses;
    ``source_gaps`` the times the source had no frame set when one was due (a camera
    that stalled or is being reopened): each published ``lost``.
    """

    frames: int = 0
    tracking: int = 0
    init_attempts: int = 0
    init_successes: int = 0
    publish_failures: int = 0
    tracker_errors: int = 0
    source_gaps: int = 0
    catch_up_tracked: int = 0  # old frame sets tracked to bring a late start to the present
    catch_up_skipped: int = 0  # and skipped, where the period had no room to track them
    tracker_ms: LogHistogram = field(default_factory=LogHistogram)
    latency_ms: LogHistogram = field(default_factory=LogHistogram)
    last_latency_ms: float = float("nan")  # the last frame's capture-to-publish time
    status_counts: dict = field(default_factory=dict)
    #: Per stage of the live loop, a histogram of its time per frame, ms (wall): ``capture``
    #: (the source's own work: rendering, reading a camera; not its wait for the capture
    #: instant), ``track`` (tracker and catch-up; ``track: <stage>`` its own stages,
    #: ``TrackerOutput.stage_ms``), ``backlog``, ``publish``, ``record`` (the ``on_output``
    #: hook); and once per initialisation job ``init``, from its submission to the loop
    #: taking its answer, and ``init cpu``, the CPU time it took (the rest it waited for a
    #: core). Bounded memory, whatever the uptime.
    stage_ms: dict = field(default_factory=dict)

    def add_stage(self, name: str, ms: float) -> None:
        h = self.stage_ms.get(name)
        if h is None:
            h = self.stage_ms[name] = LogHistogram()
        h.add(ms)

    def summary(self) -> dict:
        """Median and p99 of the tracker time, the latency and each stage (ms), and the status counts."""
        return {"tracker_ms_median": self.tracker_ms.quantile(0.5), "tracker_ms_p99": self.tracker_ms.quantile(0.99),
                "latency_ms_median": self.latency_ms.quantile(0.5), "latency_ms_p99": self.latency_ms.quantile(0.99),
                "statuses": dict(self.status_counts), "source_gaps": self.source_gaps,
                "catch_up": {"tracked": self.catch_up_tracked, "skipped": self.catch_up_skipped},
                "stage_ms": {k: {"median": h.quantile(0.5), "p99": h.quantile(0.99), "n": len(h)}
                             for k, h in self.stage_ms.items()}}


class PoseServer:
    """Track and publish, frame by frame.

    Parameters
    ----------
    source : FrameSource
    tracker : Tracker
        Its own ``initializer`` must be None: the server runs initialisation
        in the background itself.
    publisher : PosePublisher or None
        None: estimates are only returned/recorded (tests, offline runs).
    clock : Clock
        Stamps sends; paces nothing (the source paces).
    initializer : callable, optional
        ``initializer(frameset) -> InitResult | None``.
    background_init : bool or str
        ``"process"``: run the initialiser in a worker process built from
        ``initializer_factory`` (real time: the tracking loop keeps its rate
        while the initialiser uses another core); ``True`` or ``"thread"``: in
        a thread; False: inline (lockstep, reproducible).
    initializer_factory : callable, optional
        Picklable ``() -> initializer``, for the worker process.
    worker_nice : int
        Niceness of the initialisation worker process (negative: ahead of the
        machine's other normal work; needs the permission to raise priority).
    shedder : vespro.loadshed.LoadShedder, optional
        Watches the source's missed capture instants (its ``missed``) and lowers the
        load: the cameras it dropped are no longer captured (the source's
        ``skip_cameras``, where it has one) nor tracked; it also says which frame
        sets' images to record (the ``on_output`` hook asks it).
    log : callable, optional
        Receives the once-a-second status line.
    on_output : callable, optional
        Called with every (frameset, TrackerOutput), e.g. to record them.
    max_gap_s : float
        A source gap (:class:`~vespro.sources.SourceGap`: a camera stalled) is
        published ``lost`` while it lasts; once frames come back after a gap longer
        than this, the filter starts again from its last pose (see :meth:`_resume`).
    """

    def __init__(self, source, tracker: Tracker, publisher, clock: Clock,
                 initializer: Callable[[FrameSet], object] | None = None, background_init: bool = True,
                 log: Callable[[str], None] | None = print, on_output=None, object_id: int = 0,
                 initializer_factory=None, shedder=None, worker_nice: int = 0, max_gap_s: float = 0.5):
        self.source = source
        self.tracker = tracker
        self.tracker.initializer = None
        self._bank = getattr(tracker, "bank", None)  # decision "bank": the hypotheses the initialiser feeds
        self._blind_logged = 0  # Tracker.blind_frames at the last status line
        self.publisher = publisher
        self.clock = clock
        self.initializer = initializer
        self.background_init = background_init
        self.log = log
        self.on_output = on_output
        self.object_id = object_id
        self.shedder = shedder  # LoadShedder: missed capture deadlines lower the load (None: off)
        self._busy_ms = None  # the loop's work on the last frame set, ms
        self.stats = ServerStats()
        self.max_gap_s = float(max_gap_s)
        self._note = LogThrottle(log, clock.now_ns)  # repeated kinds of line: at most one a second
        self._gap_since: int | None = None  # stamp of the last frame set before the current source gap
        self._last_fs_ns: int | None = None
        self._stop = threading.Event()
        self._slot: FrameSlot | None = None  # the start's frames for a worker process
        if background_init == "process":
            if initializer_factory is None:
                raise ValueError("background_init='process' needs an initializer_factory")
            self._pool = ProcessPoolExecutor(max_workers=1, initializer=_worker_setup,
                                             initargs=(initializer_factory, worker_nice))
            # Start the worker now: started by the first real job, its launch stalled the live loop
            # for long enough that the frames after that job's were missing and its pose was discarded.
            self._worker_up = self._pool.submit(_worker_ping)
            # The images go through shared memory (vespro.frameslot), not the executor's queue.
            self._slot = FrameSlot()
            self._submit = lambda fs, seed, pending: self._pool.submit(_worker_run, self._slot.put(fs), seed,
                                                                       pending)
        elif background_init:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="vespro-init")
            self._submit = lambda fs, seed, pending: self._pool.submit(_init_call, self.initializer, fs, seed, pending)
        else:
            self._pool = None
        self._job: Future | None = None
        self._job_t_ns = 0
        self._job_wall = 0.0
        self._seq = 0
        self._last_T = None
        self._last_log_ns = None
        self._window: list = []
        self._window_lat: list = []  # latency (ms) of each output in _window
        # Frame sets that arrived while initialising (about 3 s): once a pose comes back for
        # an older frame, the filter is started there and caught up through these.
        self._rate = float(getattr(source, "rate_hz", 26.0))
        self._backlog: deque = deque(maxlen=max(8, int(10 * self._rate)))
        self._catching: deque | None = None  # frame sets queued for the catch-up, oldest first
        self.stale_inits = 0

    def wait_ready(self, timeout_s: float = 120.0) -> bool:
        """Wait until the initialisation worker process is up with its initialiser built.

        Building it (imports, compiled kernels, the model's features) takes a second or
        two; a first job sent before that waits for it, and its frame grows old. The
        command waits here before it starts capturing. True if ready (or no worker).
        """
        up = getattr(self, "_worker_up", None)
        if up is None:
            return True
        try:
            up.result(timeout=timeout_s)
            return True
        except Exception:  # a failed or slow start: the loop runs anyway, and says so in its log
            return False

    def stop(self) -> None:
        """Ask the loop to finish after the current frame (signal-safe)."""
        self._stop.set()

    # -- initialisation ---------------------------------------------------------
    def _searching(self) -> bool:
        """Whether the initialiser is wanted: while there is no filter, or the filter holds a
        provisional start (the initialiser confirms or replaces it: :meth:`Tracker.offer`);
        with the hypothesis bank, while nothing is published and no catch-up is under way (its
        answers are hypotheses beside those held: :meth:`Tracker.propose`)."""
        tr = self.tracker
        if self._bank is not None:  # (not while catching up: the answer would join hypotheses mid-way)
            return not tr.confirmed and self._catching is None
        return tr.ekf is None or tr.provisional

    @property
    def caught_up_frames(self) -> int:
        """Old frame sets tracked to bring a late start to the present (``ServerStats.catch_up_tracked``)."""
        return self.stats.catch_up_tracked

    @property
    def skipped_catch_up(self) -> int:
        """Queued frame sets skipped so that the catch-up's queue drains (``ServerStats.catch_up_skipped``)."""
        return self.stats.catch_up_skipped

    @property
    def kept_frames(self) -> int:
        """Frame sets kept for a catch-up: those since the initialisation call under way."""
        return len(self._backlog)

    def _holding(self) -> bool:
        """Whether the tracker holds a pose to track (a filter, or the bank's hypotheses)."""
        tr = self.tracker
        return tr.ekf is not None or (self._bank is not None and bool(self._bank.hypotheses))

    def _maybe_start(self, fs: FrameSet) -> None:
        """Run the initialiser while it is wanted (:meth:`_searching`)."""
        if not self._searching() or (self.initializer is None and self._pool is None):
            return
        if not self.background_init:
            self.stats.init_attempts += 1
            t = time.perf_counter()
            # After a loss the initialiser first tries near the last good pose.
            res, _, cands, cpu_ms = _init_call(self.initializer, fs, self.tracker.recovery_seed(),
                                               self.tracker.provisional_pose())
            self.stats.add_stage("init", (time.perf_counter() - t) * 1e3)
            self.stats.add_stage("init cpu", cpu_ms)
            if res is not None:
                self.stats.init_successes += 1
                if self._bank is not None:
                    self.tracker.propose(res, fs.t_ns, cands)
                else:
                    self._start(res, fs.t_ns)
            return
        if self._job is not None and self._job.done():
            cands = ()
            try:
                res, why, cands, cpu_ms = self._job.result()
                self.stats.add_stage("init cpu", cpu_ms)
            except Exception as e:  # an initialiser bug must not kill the server
                res, why = None, ""
                if self.log:
                    self.log(f"initialiser failed: {e!r}")
            job_t = self._job_t_ns
            self._job = None
            self.stats.add_stage("init", (time.perf_counter() - self._job_wall) * 1e3)
            if self.log:
                waited = (fs.t_ns - job_t) * 1e-9
                found = (f"no pose ({why})" if why else "no pose") if res is None else (
                    "a provisional pose" if res.provisional else "a pose") + "".join(
                    f" ({name} hidden: judged without it)" for name in res.hidden)
                self._note(found, f"initialisation on the frame of {waited:.1f} s ago: {found}")
            newer = [old for old in self._backlog if old.t_ns > job_t]
            first_after = newer[0].t_ns if newer else fs.t_ns  # this frame, when none came between
            max_gap_ns = max(2.5e9 / self._rate, 0.25e9)  # a skipped capture or two, not seconds
            if res is not None and first_after - job_t > max_gap_ns:
                # The frames right after the initialised one are gone: catching up across the
                # gap could lock onto the wrong corners. Start over on a current frame.
                self.stale_inits += 1
                res = None
                self._note("discarded", "  discarded: the frames right after it are gone (no catch-up across the gap)")
            if res is not None and self._bank is not None and self._bank.hypotheses:
                # Hypotheses are held at the present: the new ones are carried through the
                # frames since theirs and join them.
                self.stats.init_successes += 1
                self.tracker.propose(res, job_t, cands, newer)
                self._backlog.clear()
                return
            if res is not None:
                self.stats.init_successes += 1
                if self._bank is not None:
                    self.tracker.propose(res, job_t, cands)
                    self._catching = deque(newer)
                    self._backlog.clear()
                    return
                if not self._start(res, job_t):
                    return  # the provisional start confirmed (or kept): tracked on as it is
                # Catch up: the part moved while the initialiser worked. The frames that came
                # since are tracked (not published: they are old), a few per live frame, with
                # the live frames joining the queue, until the filter reaches the present.
                self._catching = deque(newer)
                self._backlog.clear()
                return
        if self._job is None:
            # The frames kept are those since the call under way: a start found on this frame
            # set is caught up from here, and nothing older is needed (a call that found no
            # pose leaves none behind).
            self._backlog.clear()
            self.stats.init_attempts += 1
            self._job_t_ns = fs.t_ns
            self._job_wall = time.perf_counter()
            self._job = self._submit(fs, self.tracker.recovery_seed(), self.tracker.provisional_pose())

    def _start(self, res, t_ns: int) -> bool:
        """Start the filter from an initialiser's pose on the frame set of ``t_ns``, or offer the
        pose to a provisional start; True when the filter was (re)started."""
        if self.tracker.ekf is not None and self.tracker.provisional:
            return self.tracker.offer(res, t_ns)
        self.tracker.start(res, t_ns)
        return True

    def _catch_up(self, fs: FrameSet) -> TrackerOutput:
        """Track queued frames, then ``fs`` once the queue is through; ``fs``'s output.

        Each live frame set joins the queue; the queue is tracked for about
        ``CATCH_UP_SHARE`` of a capture period (at least one frame set), and at least
        ``CATCH_UP_MIN`` frame sets leave it per live frame, so it drains on any
        machine: where the share holds fewer, the next queued one is skipped (the filter
        predicts across two capture periods) and the live loop keeps its rate; the live
        frame set itself, once it is all that is left, is tracked. Tracking
        two whatever they cost made a three-camera loop that renders its cameras miss
        every fourth capture instant while it caught up; tracking all of it at once
        skipped every capture meanwhile: after 8.6 s of initialisation under load, 1.3 s
        of catching up left the filter a 0.6 s gap to bridge, and a one-camera pose
        15 mm off was confirmed on the far side. While the queue lasts the live frame is
        published ``initializing``; the filter is confirmed again on the live frames once
        it is through.
        """
        q = self._catching
        q.append(fs)
        t_end = self.clock.now_ns() + int(CATCH_UP_SHARE * 1e9 / self._rate)
        n = 0
        while q and self._holding() and (n < 1 or len(q) == 1 or self.clock.now_ns() < t_end):
            f = q.popleft()
            if not q:  # the live frame set: confirmed again on live frames before publishing
                self._catching = None
                self.tracker.require_confirmation(f.t_ns)
                return self.tracker.process(f)
            self.tracker.process(f)
            self.stats.catch_up_tracked += 1
            n += 1
        while n < CATCH_UP_MIN and len(q) > 1:  # never the live frame set
            q.popleft()
            self.stats.catch_up_skipped += 1
            n += 1
        if not self._holding():  # lost (or not confirmed in time) on the way: the initialiser starts over
            self._catching = None
            return TrackerOutput(fs.index, fs.t_ns, self.tracker.status)
        return TrackerOutput(fs.index, fs.t_ns, "initializing")

    # -- the loop -------------------------------------------------------------------
    def _shed(self, fs: FrameSet) -> FrameSet:
        """Watch the deadlines (a step down is logged and applied); ``fs`` less the dropped cameras."""
        sh = self.shedder
        step = sh.observe(fs.t_ns, int(getattr(self.source, "missed", 0)), self._busy_ms)
        if step is not None:
            if hasattr(self.source, "skip_cameras"):
                self.source.skip_cameras = frozenset(sh.dropped)
            if self.log:
                self.log(f"capture deadlines kept for {sh.recover_s:.0f} s with room to spare: {step.what}"
                         if step.kind == "up" else
                         f"missed {step.missed} of the last {step.instants} capture instants: "
                         + (step.what if step.kind == "stall" else f"too slow for this load; {step.what}"))
        if sh.dropped and any(k in fs.images for k in sh.dropped):
            fs = FrameSet(fs.index, fs.t_ns, {k: (None if k in sh.dropped else v) for k, v in fs.images.items()},
                          fs.T_world_camera)
        return fs

    def step(self, fs: FrameSet) -> TrackerOutput:
        """Process and publish one frame set."""
        if self.shedder is not None:
            fs = self._shed(fs)
        s = self.stats
        capture = getattr(self.source, "last_capture_ms", None)  # the source's work on this frame set
        if capture is not None:
            s.add_stage("capture", capture)
        t0 = time.perf_counter()
        t1 = t0
        try:
            self._maybe_start(fs)
            out = self._catch_up(fs) if self._catching is not None else self.tracker.process(fs)
            t1 = time.perf_counter()
            if self._searching() and self._pool is not None and self._job is not None:
                # Kept in grey (what the tracker uses): a third of the memory.
                self._backlog.append(FrameSet(fs.index, fs.t_ns, {k: fs.grey(k) for k in fs.images},
                                              fs.T_world_camera))
            elif self._backlog:
                self._backlog.clear()  # no initialisation under way: nothing to catch up through
        except Exception as e:  # a tracker bug must not take the server down: drop the track
            s.tracker_errors += 1
            if s.tracker_errors <= 3 and self.log:
                self.log(f"tracker error on frame {fs.index}: {e!r}")
            self.tracker.ekf = None
            self.tracker.status = "lost"
            out = TrackerOutput(fs.index, fs.t_ns, "lost")
        t2 = time.perf_counter()
        if out.status == "tracking":
            self._last_T = out.T_world_object
            s.tracking += 1
        t_send = self._publish(out)
        t3 = time.perf_counter()
        s.frames += 1
        s.tracker_ms.add(out.time_ms)
        s.last_latency_ms = (t_send - fs.t_ns) * 1e-6
        s.latency_ms.add(s.last_latency_ms)
        s.status_counts[out.status] = s.status_counts.get(out.status, 0) + 1
        self._window_lat.append(s.last_latency_ms)
        if self.on_output is not None:
            self.on_output(fs, out)
        t4 = time.perf_counter()
        for name, a, b in (("track", t0, t1), ("backlog", max(t1, t0), t2), ("publish", t2, t3), ("record", t3, t4)):
            s.add_stage(name, (b - a) * 1e3)
        for name, ms in out.stage_ms.items():  # the tracker's own stages, where it tracked
            s.add_stage(f"track: {name}", ms)
        self._busy_ms = (capture or 0.0) + (t4 - t0) * 1e3  # the loop's work on this frame set (the shedder's)
        self._log_line(out)
        return out

    def _log_line(self, out: TrackerOutput) -> None:
        now = self.clock.now_ns()
        self._window.append(out)
        if self._last_log_ns is None:
            self._last_log_ns = now
            return
        if now - self._last_log_ns < 1_000_000_000:
            return
        w, self._window = self._window, []
        lat, self._window_lat = np.array(self._window_lat), []
        blind = self.tracker.blind_frames - self._blind_logged
        self._blind_logged = self.tracker.blind_frames
        dt = (now - self._last_log_ns) * 1e-9
        self._last_log_ns = now
        if not self.log:
            return
        tm = np.array([o.time_ms for o in w])
        link = ""
        if self.publisher is not None:
            st = self.publisher.stats()
            link = f" | link clients {st.clients_connected} sent {st.frames_sent} drops {st.drops} errors {st.errors}"
            link += f" refused {st.clients_refused}" if st.clients_refused else ""
        images = getattr(self.source, "images", None)  # an ImageTally: images not used, per camera and reason
        rejected = f" | {images.status()}" if images is not None and images.status() else ""
        p = w[-1].probability
        status = f"{w[-1].status} p={p:.3f}" if np.isfinite(p) else w[-1].status
        self.log(f"{len(w) / dt:5.1f} Hz | {status:12s} | tracker {np.median(tm):5.2f} ms "
                 f"(max {tm.max():5.2f}) | latency {np.median(lat):6.2f} ms | features {w[-1].n_accepted:2d}"
                 f"{f' (a camera blind in {blind} frames)' if blind else ''}{link}{rejected}")

    def gap(self, g: SourceGap) -> None:
        """No frame set came when one was due: publish ``lost`` (said once a gap)."""
        self.stats.source_gaps += 1
        if self._gap_since is None:
            self._gap_since = g.last_ns
            if self.log:
                self.log(f"source: {g.reason}; the track is published lost until frames come back")
        self._publish(TrackerOutput(-1, g.t_ns, "lost"))

    def _resume(self, fs: FrameSet) -> None:
        """The first frame set after a gap: say so; after a long one, start the filter again.

        Across more than ``max_gap_s`` the filter's velocity is no evidence (the
        stream may have paused, or lost the frames while the part moved on): a
        confirmed track is started again at its last pose with a start's
        uncertainty, published once the tracker confirms it on the new frames as
        any start; one not confirmed within ``confirm_within_s`` is dropped and the
        initialiser searches, seeded from the last good pose. On ViSP's cube
        sequence after a 2 s pause the restart tracked from the second frame;
        kept across the gap, the filter's prediction (its velocity over 2 s) lost
        the part on the first and waited for the initialiser.
        """
        waited = (fs.t_ns - (self._last_fs_ns if self._last_fs_ns is not None else self._gap_since)) * 1e-9
        self._gap_since = None
        long_gap = waited > self.max_gap_s
        tr = self.tracker
        restart = long_gap and tr.ekf is not None and tr.confirmed and not tr.provisional and self._catching is None
        if restart:
            tr.start(InitResult(tr.ekf.pose), fs.t_ns)
        elif long_gap:
            tr.lose()
        if long_gap:
            self._catching = None  # frames from before the gap: stale now
            self._backlog.clear()  # an answer for a frame before the gap is not caught up across it
        if self.log:
            self.log(f"source: frames again after {waited:.1f} s" +
                     ("; the track starts again from its last pose, to be confirmed" if restart else
                      "; the track starts over" if long_gap else ""))

    def _publish(self, out: TrackerOutput) -> int:
        """Publish ``out``; its send stamp."""
        t_send = self.clock.now_ns()
        msg = pose_message(out, self._seq, t_send, self.object_id, self._last_T)
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        if self.publisher is not None:
            try:
                self.publisher.publish(msg)
            except Exception:  # the link must never take the tracker down
                self.stats.publish_failures += 1
        return t_send

    def run(self, max_frames: int | None = None) -> ServerStats:
        """Run until the source ends, ``max_frames`` or :meth:`stop`.

        When the source ends, the track is published ``lost`` once more (nothing
        tracks it now).
        """
        try:
            while not self._stop.is_set():
                if max_frames is not None and self.stats.frames >= max_frames:
                    break
                fs = self.source.next()
                if fs is None:
                    self._publish(TrackerOutput(-1, self.clock.now_ns(), "lost"))
                    break
                if isinstance(fs, SourceGap):
                    self.gap(fs)
                    continue
                if self._gap_since is not None:
                    self._resume(fs)
                self._last_fs_ns = fs.t_ns
                self.step(fs)
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=False, cancel_futures=True)
            if self._slot is not None:
                self._slot.close()  # (a worker still reading keeps its mapping)
        return self.stats
