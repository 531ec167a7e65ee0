"""Watch the cell in Rerun, live or from a saved ``.rrd``: an observer of the tracker's outputs.

``vespro serve|track|demo --view`` spawns (or joins) a Rerun viewer; ``--view-save
run.rrd`` writes the same stream to a file (``rerun run.rrd`` opens it). What it shows:

- each camera (``world/cameras/<name>``): its pose and frustum, its image, the
  search windows (boxes), the measured corners (green: used, orange: rejected)
  and the model's sharp edges at the estimated pose;
- the part at the estimated pose (``world/estimate``, the CAD mesh) with the
  3-sigma ellipsoid of its position covariance (``world/estimate_cov``), and,
  when the caller knows it (the simulated demo: ground truth is read only
  there), the true pose beside it (``world/truth``, grey);
- time series under ``series/``: status (2 tracking, 1 initialising, 0 lost),
  features used, tracker time, latency, error against the truth where known,
  and whatever the caller adds (the servo's status and timing in the demo).

Timelines: ``frame`` (capture index) and ``capture_time`` (s from the first frame set).

The viewer only observes: :meth:`RerunView.observe` takes the frame set and the
tracker's output (both immutable) and queues them; a process of its own does all
the work (projection, JPEG encoding, logging). Live (``block=False``) a full
queue drops the frame for the viewer, counted in ``dropped``, and the tracker
never waits; offline (``block=True``: ``vespro track``, the lockstep demo)
every frame is logged.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError

__all__ = ["RerunView", "STATUS_CODE", "add_view_options", "view_from_args", "COLORS", "merge_rrd"]

STATUS_CODE = {"tracking": 2.0, "initializing": 1.0, "lost": 0.0}
_GREEN, _ORANGE, _BLUE, _GREY = (40, 200, 60), (255, 140, 0), (60, 140, 255), (170, 170, 170)
#: Colours for callers' points (``RerunView.log_series``).
COLORS = {"green": _GREEN, "orange": _ORANGE, "blue": _BLUE, "grey": _GREY}


def add_view_options(p, join: bool = True) -> None:
    """The view's options; ``join``: also those that join a recording other processes log into."""
    g = p.add_argument_group("live view (pip install 'vespro[view]')")
    g.add_argument("--view", action="store_true", help="stream to a Rerun viewer (spawned unless one is running)")
    g.add_argument("--view-connect", metavar="URL",
                   help="stream to the Rerun viewer at URL instead (rerun+http://HOST:9876/proxy)")
    g.add_argument("--view-save", type=Path, metavar="RUN.rrd",
                   help="write the view to this file (open with: rerun RUN.rrd)")
    g.add_argument("--view-image-every", type=int, default=1, metavar="N",
                   help="log every N-th camera image (overlays and 3D every frame)")
    if not join:
        return
    g.add_argument("--view-recording-id", metavar="ID",
                   help="log into this Rerun recording (one the servo also logs into: servo run --view-recording-id)")
    g.add_argument("--view-app-id", metavar="NAME", help="Rerun application id (default: the command's name)")
    g.add_argument("--view-t0-ns", type=int, metavar="NS",
                   help="time zero of the capture_time line on the capture clock, ns (default: the first frame)")


def view_from_args(args, rig, model, block: bool, name: str = "vespro") -> "RerunView | None":
    """The view the options ask for, or None."""
    if not (args.view or args.view_connect or args.view_save):
        return None
    return RerunView(rig, model, spawn=args.view, connect=args.view_connect, save=args.view_save, block=block,
                     image_every=args.view_image_every, name=getattr(args, "view_app_id", None) or name,
                     recording_id=getattr(args, "view_recording_id", None), t0_ns=getattr(args, "view_t0_ns", None))


def merge_rrd(parts: list, out) -> None:
    """Join ``.rrd`` files into ``out`` (which may be one of them) with Rerun's ``rrd merge``:
    one recording logged by several processes (same recording id) becomes one file."""
    import subprocess
    import sys

    out = Path(out)
    tmp = out.with_name(out.name + ".merging")
    r = subprocess.run([sys.executable, "-m", "rerun", "rrd", "merge", *map(str, parts), "-o", str(tmp)],
                       capture_output=True, text=True)
    if r.returncode != 0 or not tmp.exists():
        tmp.unlink(missing_ok=True)
        raise RuntimeError(f"rerun rrd merge failed: {(r.stderr or r.stdout).strip()[-300:]}")
    tmp.replace(out)


def _rr():
    try:
        import rerun as rr
    except ImportError:
        raise InputError("--view needs the 'rerun-sdk' package: pip install 'vespro[view]'") from None
    return rr


def _xyzw(R: np.ndarray) -> list:
    from .se3 import quat_from_matrix

    q = quat_from_matrix(R)
    return [q[1], q[2], q[3], q[0]]


class RerunView:
    """Logs frame sets and tracker outputs to a Rerun recording from a process of its own.

    Parameters
    ----------
    rig : Rig
    model : Model
        The tracked object's model (mesh and sharp edges).
    spawn : bool
        Stream to a viewer, spawning one if none is running.
    connect : str, optional
        Stream to the viewer at this URL.
    save : path, optional
        Write the stream to this ``.rrd`` file.
    block : bool
        True: ``observe`` waits for room in the queue (every frame logged);
        False: a frame that finds the queue full is not logged (``dropped``).
    image_every : int
        Log every n-th camera image.
    name, recording_id : str
        Rerun's application and recording ids (a given recording id: another
        process, the servo's, may log into the same recording).
    t0_ns : int, optional
        Time zero of ``capture_time`` (default: the first frame set's stamp).

    The logging (Rerun's archetypes, JPEG encoding, projections) costs about as
    much as tracking a frame; in a thread it would hold the interpreter lock
    the tracker needs, so it runs in a child process (started with "spawn": the
    caller may run threads) fed through a bounded queue; what the caller pays
    per frame is handing its references to the queue's feeder thread.
    """

    def __init__(self, rig, model, *, spawn: bool = False, connect: str | None = None, save=None,
                 block: bool = False, image_every: int = 1, max_queue: int = 16, name: str = "vespro",
                 recording_id: str | None = None, t0_ns: int | None = None):
        from rtkit.logproc import QueuedProcess  # the mechanism both sides' views share

        _rr()  # a missing package is the caller's one-line error, not the child's
        self.block = block
        opts = dict(spawn=spawn, connect=connect, save=None if save is None else str(save),
                    image_every=max(1, int(image_every)), name=name, recording_id=recording_id, t0_ns=t0_ns)
        # Wait for the process to be set up (imports, viewer connection: a second or more), so the
        # first frames are not dropped for a queue nobody reads yet.
        try:
            self._proc = QueuedProcess(_start_logger, (rig, model, opts), name="view", block=block,
                                       max_queue=max_queue, wait_ready=120)
        except RuntimeError:
            raise InputError("--view: the view process did not start (is the Rerun viewer reachable?)") from None

    @property
    def dropped(self) -> int:
        """Frames not logged because the queue was full (live)."""
        return self._proc.dropped

    # -- the caller's side (cheap, never touches its arguments) ---------------------
    def observe(self, fs, out, T_true: np.ndarray | None = None, series: dict | None = None) -> None:
        """Queue one frame set and its tracker output (``T_true``: ground truth, evaluators only)."""
        self._proc.put(("log_frame", fs, out, T_true, series))

    def log_series(self, t_ns: int, series: dict, points: dict | None = None) -> None:
        """Queue scalar series (``name -> value``) and 3D points (``entity -> ((3,), RGB)``) at capture stamp ``t_ns``."""
        self._proc.put(("log_series", t_ns, series, points))

    def close(self) -> str:
        """Log what is queued, then flush and close the stream; returns a line on what was not shown, or ""."""
        return self._proc.close("frames")

    def __enter__(self) -> "RerunView":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _start_logger(rig, model, opts: dict) -> "_Logger":
    """The view's process: off a live loop's core and real-time class (inherited from the caller),
    and niced behind the live work of normal class (the initialiser's worker): it drops frames
    rather than delay any."""
    import os

    from .realtime import leave_realtime

    leave_realtime()
    try:
        os.nice(10)
    except OSError:
        pass
    return _Logger(rig, model, **opts)


class _Logger:
    """The Rerun logging itself (in the view's process)."""

    def __init__(self, rig, model, *, spawn: bool, connect: str | None, save: str | None, image_every: int,
                 name: str, recording_id: str | None, t0_ns: int | None):
        rr = _rr()
        self.rr = rr
        self.rig = rig
        self.model = model
        self.image_every = image_every
        self.rec = rr.RecordingStream(name, recording_id=recording_id)
        if save is not None:
            self.rec.save(save)
        if connect:
            self.rec.connect_grpc(connect)
        elif spawn:
            self.rec.spawn(connect=True)
        self._t0_ns = t0_ns
        self._mesh_shown = self._truth_shown = False
        self.rec.send_blueprint(self._blueprint())
        self._static()

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()

    def _blueprint(self):
        """The cell in 3D beside the cameras' images, the series below, on the capture-time line
        (the servo's series, at its own ticks, line up with the frames there)."""
        import rerun.blueprint as rrb

        cams = [rrb.Spatial2DView(origin=f"world/cameras/{c.name}/image", name=c.name) for c in self.rig]
        series = [("tracking", ["series/status", "series/features_used"]),
                  ("time, ms", ["series/tracker_ms", "series/latency_ms"]),
                  ("error against the truth (mm, deg)", ["series/error_mm", "series/error_deg"]),
                  ("servo", ["series/servo_status", "series/servo_error_mm", "series/servo_target_error_mm"]),
                  ("servo loop, us", ["series/servo_compute_us", "series/servo_period_error_us"])]
        return rrb.Blueprint(
            rrb.Vertical(
                rrb.Horizontal(rrb.Spatial3DView(origin="world", name="cell"), rrb.Grid(*cams), column_shares=[2, 3]),
                rrb.Horizontal(*[rrb.TimeSeriesView(origin="series", contents=c, name=n) for n, c in series],
                               rrb.TextLogView(origin="servo/events", name="servo events")),
                row_shares=[3, 2]),
            rrb.TimePanel(timeline="capture_time"), collapse_panels=True)

    def _static(self) -> None:
        rr, rec = self.rr, self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for cam in self.rig:
            intr = cam.intrinsics
            path = f"world/cameras/{cam.name}"
            rec.log(f"{path}/image", rr.Pinhole(image_from_camera=intr.K, resolution=[intr.width, intr.height],
                                                camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.1),
                    static=True)
            if cam.is_fixed:
                T = cam.T_world_camera
                rec.log(path, rr.Transform3D(translation=T[:3, 3], quaternion=rr.Quaternion(xyzw=_xyzw(T[:3, :3]))),
                        static=True)
        rec.log("series/status", rr.SeriesLines(names="status (2 tracking, 1 initialising, 0 lost)"), static=True)

    def _time(self, t_ns: int, index: int | None = None) -> None:
        if self._t0_ns is None:
            self._t0_ns = int(t_ns)
        if index is not None:
            self.rec.set_time("frame", sequence=int(index))
        self.rec.set_time("capture_time", duration=(int(t_ns) - self._t0_ns) * 1e-9)

    def log_series(self, t_ns, series, points) -> None:
        rr, rec = self.rr, self.rec
        rec.reset_time()
        self._time(t_ns)
        for name, v in (series or {}).items():
            rec.log(f"series/{name}", rr.Scalars(float(v)))
        for name, (p, color) in (points or {}).items():
            rec.log(f"world/{name}", rr.Points3D([p], radii=0.006, colors=[color]))

    def log_frame(self, fs, out, T_true, series) -> None:
        import cv2

        from .camera import project_points
        from .se3 import invert_transform

        rr, rec = self.rr, self.rec
        self._time(fs.t_ns, fs.index)
        T_est = out.T_world_object if out.status == "tracking" else None
        obs = {o.name: o for o in out.observations}
        edges = self.model.edge_points.reshape(-1, 3)
        for cam in self.rig:
            path = f"world/cameras/{cam.name}"
            T_wc = cam.T_world_camera if cam.is_fixed else fs.T_world_camera.get(cam.name)
            if T_wc is None:
                continue
            if not cam.is_fixed:
                rec.log(path, rr.Transform3D(translation=T_wc[:3, 3], quaternion=rr.Quaternion(xyzw=_xyzw(T_wc[:3, :3]))))
            img = fs.images.get(cam.name)
            if img is not None and fs.index % self.image_every == 0:
                ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
                if ok:
                    rec.log(f"{path}/image", rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg"))
            o = obs.get(cam.name)
            if o is not None and len(o.uv_pred):
                half = np.repeat(o.half_size[:, None], 2, 1)
                rec.log(f"{path}/image/windows", rr.Boxes2D(centers=o.uv_pred, half_sizes=half, colors=[_BLUE]))
                found = np.all(np.isfinite(o.uv_meas), axis=1)
                colors = np.where(o.accepted[found, None], _GREEN, _ORANGE)
                rec.log(f"{path}/image/corners", rr.Points2D(o.uv_meas[found], colors=colors, radii=2.0))
            else:
                rec.log(f"{path}/image/windows", rr.Clear(recursive=False))
                rec.log(f"{path}/image/corners", rr.Clear(recursive=False))
            if T_est is not None:
                uv, z = project_points(cam.intrinsics, invert_transform(T_wc) @ T_est, edges)
                strips = uv.reshape(-1, 2, 2)
                keep = np.all(np.isfinite(strips), axis=(1, 2))
                rec.log(f"{path}/image/model", rr.LineStrips2D(strips[keep], colors=[_GREEN], radii=0.8))
            else:
                rec.log(f"{path}/image/model", rr.Clear(recursive=False))
        if T_est is not None:
            rec.log("world/estimate", rr.Transform3D(translation=T_est[:3, 3],
                                                     quaternion=rr.Quaternion(xyzw=_xyzw(T_est[:3, :3]))))
            if not self._mesh_shown:
                m = self.model
                rec.log("world/estimate/mesh", rr.Mesh3D(vertex_positions=m.vertices, triangle_indices=m.triangles,
                                                         albedo_factor=[*_GREEN, 200]))
                self._mesh_shown = True
            if out.cov6 is not None:
                w, V = np.linalg.eigh(np.asarray(out.cov6, dtype=float)[:3, :3])
                if np.linalg.det(V) < 0:
                    V[:, 0] = -V[:, 0]
                rec.log("world/estimate_cov", rr.Ellipsoids3D(
                    centers=[T_est[:3, 3]], half_sizes=[3.0 * np.sqrt(np.clip(w, 0.0, None))],
                    quaternions=[rr.Quaternion(xyzw=_xyzw(V))], colors=[_GREEN], fill_mode="MajorWireframe"))
        else:
            rec.log("world/estimate", rr.Clear(recursive=True))
            rec.log("world/estimate_cov", rr.Clear(recursive=False))
            self._mesh_shown = False
        if T_true is not None:
            if not self._truth_shown:
                m = self.model
                rec.log("world/truth/mesh", rr.Mesh3D(vertex_positions=m.vertices, triangle_indices=m.triangles,
                                                      albedo_factor=[*_GREY, 110]), static=True)
                self._truth_shown = True
            rec.log("world/truth", rr.Transform3D(translation=T_true[:3, 3],
                                                  quaternion=rr.Quaternion(xyzw=_xyzw(T_true[:3, :3]))))
        s = {"status": STATUS_CODE[out.status], "features_used": out.n_accepted, "tracker_ms": out.time_ms}
        if T_est is not None and T_true is not None:
            from .se3 import pose_error

            e_pos, e_rot = pose_error(T_est, T_true)
            s["error_mm"] = e_pos * 1e3
            s["error_deg"] = np.rad2deg(e_rot)
        s.update(series or {})
        for name, v in s.items():
            rec.log(f"series/{name}", rr.Scalars(float(v)))
