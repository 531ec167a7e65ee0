"""The servo's series in a Rerun recording, logged from a process of its own.

``servo run --view-connect URL`` streams to a Rerun viewer, ``--view-save
FILE.rrd`` writes a file; with ``--view-recording-id ID`` (and the same
``--view-app-id``) the servo joins the recording another process logs into
(the pose server's view, :mod:`vespro.viewer`), so a viewer shows one
recording. Two processes cannot write one file: each saves its own with the
same recording id and ``rerun rrd merge`` joins them (``vespro demo`` does).

What it logs, on the ``capture_time`` line (s from ``t0_ns`` on the loop's
clock, the pose server's line when both are given the same ``t0_ns``):

- ``world/arm/tcp`` (orange): the measured end effector (the forward
  kinematics of the measured joints), ``world/arm/target`` (blue): the
  stand-off target the planner follows (none before the first pose),
  ``world/arm/reference`` (grey): the planner's reference;
- ``series/servo_status`` (``servo.safety.Status``: 0 tracking, 1 hold,
  2 stopping, 3 stopped, 4 finished), ``series/servo_target_error_mm`` (the
  end effector to its target), ``series/servo_compute_us`` and
  ``series/servo_period_error_us`` (the largest in each logged interval),
  ``series/servo_overruns`` (so far), ``series/servo_poses_used``;
- ``servo/events``: every stop, fault and status change as a text line.

The 500 Hz loop pays a few attribute reads per tick and, every ``every``-th
tick (50 Hz by default), one small tuple put on a bounded queue without
waiting (a full queue drops the sample, counted); the Rerun logging and the
kinematics run in the view's process. The process and the queue's feeder
thread are started before the loop raises its priority, so neither inherits
the loop's core or real-time class.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["ServoView", "add_view_options", "view_from_args", "ViewUnavailable"]

_ORANGE, _BLUE, _GREY = (255, 140, 0), (60, 140, 255), (170, 170, 170)


class ViewUnavailable(RuntimeError):
    """The view cannot start (rerun-sdk missing, viewer unreachable): one line for the user."""


def add_view_options(p) -> None:
    g = p.add_argument_group("Rerun view (pip install 'vespro[view]')")
    g.add_argument("--view-connect", metavar="URL",
                   help="stream the servo's series to the Rerun viewer at URL (rerun+http://HOST:9876/proxy)")
    g.add_argument("--view-save", type=Path, metavar="FILE.rrd", help="write the servo's series to this file")
    g.add_argument("--view-recording-id", metavar="ID",
                   help="log into this recording (the id the pose server's view uses: one recording in the viewer)")
    g.add_argument("--view-app-id", default="vespro servo", metavar="NAME",
                   help="Rerun application id (the pose server's, to join its recording)")
    g.add_argument("--view-t0-ns", type=int, metavar="NS",
                   help="time zero of the capture_time line on the loop's clock, ns (default: the first tick)")
    g.add_argument("--view-every", type=int, default=10, metavar="N",
                   help="log every N-th tick (10: 50 Hz)")


def view_from_args(args, model_path, site) -> "ServoView | None":
    """The view the options ask for, or None (raises :class:`ViewUnavailable`)."""
    if not (args.view_connect or args.view_save):
        return None
    if args.view_every < 1:
        raise ViewUnavailable("--view-every: expected a number of ticks >= 1")
    return ServoView(model_path, site, connect=args.view_connect, save=args.view_save,
                     recording_id=args.view_recording_id, application_id=args.view_app_id, t0_ns=args.view_t0_ns,
                     every=args.view_every)


def _rr():
    try:
        import rerun as rr
    except ImportError:
        raise ViewUnavailable("the view needs the 'rerun-sdk' package: pip install 'vespro[view]'") from None
    return rr


def _check_rr() -> None:
    """A missing package is the user's one-line error (checked without importing it here)."""
    import importlib.util

    if importlib.util.find_spec("rerun") is None:
        _rr()


class ServoView:
    """Queues the loop's state every ``every`` ticks to a process that logs it to Rerun.

    Parameters
    ----------
    model_path, site
        The arm's model and TCP site (``LoopConfig``), for the forward kinematics.
    connect : str, optional
        Stream to the viewer at this URL.
    save : path, optional
        Write the stream to this ``.rrd`` file.
    recording_id, application_id : str
        The Rerun recording to log into (another process's, to share it).
    t0_ns : int, optional
        Time zero of ``capture_time`` on the loop's clock (default: the first tick logged).
    every : int
        Log every n-th tick.

    The loop does not wait for the process to be set up (seconds on a machine
    busy with real-time work): the queue holds the first samples meanwhile, and
    a failure to set up is reported by :meth:`close`.
    """

    def __init__(self, model_path, site: str, *, connect: str | None = None, save=None,
                 recording_id: str | None = None, application_id: str = "vespro servo", t0_ns: int | None = None,
                 every: int = 10, max_queue: int = 1024):
        from rtkit.logproc import QueuedProcess  # the mechanism both sides' views share

        _check_rr()
        self.every = max(1, int(every))
        self._k = 0
        self._t_prev = None
        self._per_max = 0
        self._comp_max = 0
        opts = dict(model_path=str(model_path), site=site, connect=connect, save=None if save is None else str(save),
                    recording_id=recording_id, application_id=application_id, t0_ns=t0_ns)
        self._proc = QueuedProcess(_Logger, (opts,), name="servo view", max_queue=max_queue)

    @property
    def dropped(self) -> int:
        """Samples not logged because the queue was full."""
        return self._proc.dropped

    def tick(self, t_ns: int, out, state, q_meas, compute_ns: int, overruns: int, period_ns: int) -> None:
        """Called after each tick (outside its timed part): cheap except every ``every``-th tick."""
        if self._t_prev is not None:
            e = abs(t_ns - self._t_prev - period_ns)
            if e > self._per_max:
                self._per_max = e
        self._t_prev = t_ns
        if compute_ns > self._comp_max:
            self._comp_max = compute_ns
        self._k += 1
        if self._k % self.every:
            return
        pl = state.planner
        tgt = pl.tgt_p.tolist() if pl.have_sample else None
        self._proc.put(("log_tick", t_ns, int(out.status), q_meas.tolist(), out.ref.p.tolist(), tgt,
                        self._comp_max * 1e-3, self._per_max * 1e-3, overruns, state.n_used))
        self._per_max = self._comp_max = 0

    def event(self, t_ns: int, text: str, level: str = "INFO") -> None:
        """A text line (a stop, a fault, a status change) at ``t_ns``."""
        self._proc.put(("log_event", t_ns, text, level))

    def close(self) -> str:
        """Log what is queued, flush, close; returns a line on what was not logged, or ""."""
        return self._proc.close("samples")


class _Logger:
    """The Rerun logging itself (in the view's process)."""

    def __init__(self, opts: dict):
        import os

        try:
            os.nice(10)  # behind the loop and the cell's live work
        except OSError:
            pass
        self._setup(**opts)

    def _setup(self, model_path: str, site: str, connect, save, recording_id, application_id, t0_ns) -> None:
        from .kinematics import ArmKinematics

        rr = _rr()
        self.rr = rr
        self.kin = ArmKinematics(model_path, site)
        self.rec = rr.RecordingStream(application_id, recording_id=recording_id)
        if save is not None:
            self.rec.save(save)
        if connect:
            self.rec.connect_grpc(connect)
        self.t0_ns = t0_ns
        self.rec.log("series/servo_status", rr.SeriesLines(
            names="servo status (0 tracking, 1 hold, 2 stopping, 3 stopped, 4 finished)"), static=True)

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()

    def _time(self, t_ns: int) -> None:
        if self.t0_ns is None:
            self.t0_ns = int(t_ns)
        self.rec.set_time("capture_time", duration=(int(t_ns) - self.t0_ns) * 1e-9)

    def log_tick(self, t_ns, status, q, ref, tgt, compute_us, period_err_us, overruns, poses_used) -> None:
        import numpy as np

        rr, rec = self.rr, self.rec
        self._time(t_ns)
        self.kin.update(np.asarray(q, dtype=float), jacobian=False)
        tcp = self.kin.p.copy()
        rec.log("world/arm/tcp", rr.Points3D([tcp], radii=0.006, colors=[_ORANGE]))
        rec.log("world/arm/reference", rr.Points3D([ref], radii=0.003, colors=[_GREY]))
        series = {"servo_status": status, "servo_compute_us": compute_us, "servo_period_error_us": period_err_us,
                  "servo_overruns": overruns, "servo_poses_used": poses_used}
        if tgt is not None:
            rec.log("world/arm/target", rr.Points3D([tgt], radii=0.006, colors=[_BLUE]))
            series["servo_target_error_mm"] = 1e3 * float(np.linalg.norm(tcp - np.asarray(tgt)))
        for name, v in series.items():
            rec.log(f"series/{name}", rr.Scalars(float(v)))

    def log_event(self, t_ns, text, level) -> None:
        self._time(t_ns)
        self.rec.log("servo/events", self.rr.TextLog(text, level=level))
