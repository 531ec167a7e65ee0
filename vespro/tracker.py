"""The multi-camera pose tracker: one EKF fed by windowed corner measurements.

Per capture instant (:meth:`Tracker.process`):

1. predict the error-state EKF to the capture stamp (dt from stamps);
2. per camera with an image: ask the BSP visibility which model corners the
   camera sees at the predicted pose, and project them with their Jacobians;
3. choose a small, well-spread set of features (information-greedy by
   default, jointly over the cameras; the classic quality index as the
   alternative);
4. extract corners only in windows around the predicted positions, sized from
   each feature's predicted innovation covariance;
5. one stacked update with all cameras' measurements, outliers gated one by one;
6. decide the status with the hypothesis bank (:mod:`vespro.bank`): every pose
   hypothesis (the tracked one, the initialiser's proposals, each its own
   filter) is weighed by the image likelihood of the frame
   (:mod:`vespro.likelihood`); the most probable is published ``tracking``
   while its posterior probability is at least ``1 - wrong_lock_rate``, and
   demoted on the frame it falls below. A pose not published is never sent
   as ``tracking``.

Fixed cameras use their rig pose; eye-in-hand cameras the pose measured at that
instant (``FrameSet.T_world_camera``). The tracker never sees ground truth. It
starts from an explicit pose (:meth:`Tracker.start`) or from an
``initializer(frameset) -> InitResult | None`` hook.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from .bank import BankOptions, HypothesisBank
from .bsp import load_or_build_bsp
from .edgeaid import EdgeAid, EdgeContrast
from .ekf import PoseEKF
from .ekf import Status as EKFStatus
from .extraction import extract_corners, window_half_sizes
from .features import salient_corners
from .init.modelfeat import model_features
from .metrics import add, discrete_symmetries
from .frames import FrameSet
from .likelihood import ImageLikelihood
from .model import Model
from .projection import project_with_jacobian
from .redetect import Redetector
from .rig import Rig
from .se3 import check_transform, log_so3
from .selection import eligible_mask, select_information_joint, select_quality
from .startpose import InitResult
from .symmetry import RULES as SYMMETRY_RULES
from .symmetry import choose as choose_equivalent
from .visibility import SceneBody, VisibilityScene

__all__ = ["TrackerConfig", "CameraObservation", "TrackerOutput", "InitResult", "Tracker"]

STATUS_TRACKING = "tracking"
STATUS_INITIALIZING = "initializing"
STATUS_LOST = "lost"


@dataclass(frozen=True)
class TrackerConfig:
    """Tracker settings (one line each; the reasoning is in ``docs/design.md``).

    Attributes
    ----------
    features_per_camera : int
        Corners selected per camera and frame.
    selection : str
        ``"quality"`` (spread, view angle, border distance) or ``"information"``
        (greedy log-det of the pose information, joint over cameras).
    sigma_px : float
        Corner measurement noise std to start from, px (then learnt from the innovations).
    q_acc, q_alpha : float
        Least process noise densities, m^2/s^3 and rad^2/s^3 (raised where the motion needs it).
    gate_prob : float
        Probability of the innovation gate (chi-square, 2 dof a corner).
    robust_nis : float
        Leave-one-out NIS above which an accepted corner's variance is raised in the
        published covariance only (:func:`vespro.ekf.update`); 0: off.
    init_sigma_pos, init_sigma_rot : float
        Pose std of a start, m and rad.
    init_sigma_vel, init_sigma_angvel : float
        Velocity std of a start, m/s and rad/s.
    window_sigma : float
        Search window half-size, in std of each corner's predicted innovation.
    min_accepted : int
        Accepted corners a frame needs before it teaches the noise models.
    blind_found_fraction : float
        A camera finding fewer than this fraction of its corners is blind this frame
        (left out of the edge fits while another camera sees); the cameras together
        finding fewer, the frame is searched again with the start's velocity std. 0: off.
    max_pos_std : float
        Position std at which a hypothesis's filter has diverged and is dropped, m.
    refine_window_px : int
        Largest window half-size from which a frame is measured a second time about
        the first pass's result, px.
    edge_aid : str
        Where the part's edges are fitted too: ``"single"`` (a lone camera with corners),
        ``"always"`` or ``"off"``.
    edge_offset_px : float
        Std of a whole image edge off its model edge in the edge fits' covariance, px.
    start_edge_offset_px : float
        The same while the track is not published (the larger of the two is used), px.
    edge_aid_max_move : float
        An edge fit further than this from the filter's pose is not used, fraction of the diameter.
    dim_corner_frac : float
        Corners whose edges showed less than this fraction of the median edge contrast
        are passed over by the selection (while enough others remain); 0: off.
    adaptive_motion : bool
        Raise the process noise where the corrections exceed the predicted covariance.
    sigma_min_px, sigma_max_px : float
        Bounds of the learnt corner noise std, px.
    noise_adapt_rate : float
        Weight of each frame in the learnt noise levels (measurement and process).
    feature_noise_rate, feature_noise_max : float
        Weight of each frame in a corner's own noise factor; the largest factor.
    symmetry : str
        Which of a symmetric part's equivalent poses the tracker reports when it
        chooses: ``continuity`` or ``up`` (:mod:`vespro.symmetry`); a given start
        pose (:attr:`InitResult.given`) is kept as given.
    """

    features_per_camera: int = 8
    selection: str = "quality"
    sigma_px: float = 0.5
    q_acc: float = 0.05
    q_alpha: float = 0.5
    gate_prob: float = 0.999
    robust_nis: float = 3.0
    init_sigma_pos: float = 0.01
    init_sigma_rot: float = 0.05
    init_sigma_vel: float = 0.2
    init_sigma_angvel: float = 0.5
    window_sigma: float = 3.0
    min_accepted: int = 4
    blind_found_fraction: float = 0.5
    max_pos_std: float = 0.02
    refine_window_px: int = 12
    edge_aid: str = "single"
    edge_offset_px: float = 0.0
    start_edge_offset_px: float = 0.6
    edge_aid_max_move: float = 0.25
    dim_corner_frac: float = 0.45
    adaptive_motion: bool = True
    sigma_min_px: float = 0.15
    sigma_max_px: float = 3.0
    noise_adapt_rate: float = 0.15
    feature_noise_rate: float = 0.3
    feature_noise_max: float = 9.0
    symmetry: str = "continuity"

    def __post_init__(self):
        if self.selection not in ("information", "quality"):
            raise ValueError(f"selection must be 'information' or 'quality', got {self.selection!r}")
        if self.edge_aid not in ("single", "always", "off"):
            raise ValueError(f"edge_aid must be 'single', 'always' or 'off', got {self.edge_aid!r}")
        if self.symmetry not in SYMMETRY_RULES:
            raise ValueError(f"symmetry must be one of {', '.join(SYMMETRY_RULES)}, got {self.symmetry!r}")
        if self.features_per_camera < 3:
            raise ValueError("need at least 3 features per camera")
        for name in ("edge_offset_px", "start_edge_offset_px"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v}")


@dataclass(frozen=True)
class CameraObservation:
    """What one camera contributed in one frame (for diagnostics and overlays).

    Attributes
    ----------
    name : str
    has_image : bool
    n_visible : int
    feature_ids : ndarray (K,)
        Selected model corner indices.
    uv_pred : ndarray (K, 2)
        Their predicted pixels.
    half_size : ndarray (K,)
        Search window half-sizes, px.
    uv_meas : ndarray (K, 2)
        Measured pixels (NaN where not found).
    accepted : ndarray (K,), bool
        Used by the update (found and within the gate).
    """

    name: str
    has_image: bool
    n_visible: int = 0
    feature_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    uv_pred: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    half_size: np.ndarray = field(default_factory=lambda: np.zeros(0))
    uv_meas: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    accepted: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))


@dataclass(frozen=True)
class TrackerOutput:
    """The tracker's estimate at one capture instant.

    Attributes
    ----------
    index : int
    t_ns : int
        Capture stamp of the frame set.
    status : str
        ``tracking``, ``initializing`` or ``lost``.
    T_world_object : ndarray (4, 4) or None
        None unless tracking.
    velocity : ndarray (6,) or None
        ``[v, w]``, world frame (m/s, rad/s).
    cov6 : ndarray (6, 6) or None
        Pose covariance ``[position, orientation]``.
    observations : tuple[CameraObservation, ...]
    n_accepted : int
    mean_nis : float
    time_ms : float
        Processing time of this frame (images already decoded).
    stage_ms : dict
        Time per stage: visibility, selection, extraction, update.
    probability : float
        The posterior probability that the tracked hypothesis is the part's pose
        (:mod:`vespro.bank`); 0 when nothing is held.
    """

    index: int
    t_ns: int
    status: str
    T_world_object: np.ndarray | None = None
    velocity: np.ndarray | None = None
    cov6: np.ndarray | None = None
    observations: tuple = ()
    n_accepted: int = 0
    mean_nis: float = float("nan")
    time_ms: float = 0.0
    stage_ms: dict = field(default_factory=dict)
    probability: float = float("nan")


@dataclass(frozen=True)
class _Candidates:
    """The visible, salient corners of one camera (a filtered Visibility)."""

    indices: np.ndarray
    points: np.ndarray
    view_angle: np.ndarray
    silhouette_distance: np.ndarray

    @classmethod
    def of(cls, vis, salient: np.ndarray) -> "_Candidates":
        keep = salient[vis.indices]
        return cls(vis.indices[keep], vis.points[keep], vis.view_angle[keep], vis.silhouette_distance[keep])


@dataclass(frozen=True)
class _CameraMeasurement:
    """One camera's corners of one measurement pass: its observation, and the measured pixels
    ``z`` with their predictions ``h`` and Jacobians ``J`` at the filter's state, their
    (camera, corner) ``key``, which of the selected corners were found, and the largest
    window half-size (None arrays: the camera measured nothing)."""

    obs: CameraObservation
    z: np.ndarray | None = None
    h: np.ndarray | None = None
    J: np.ndarray | None = None
    key: np.ndarray | None = None
    found_idx: np.ndarray | None = None
    half: int = 0


#: 0.99 quantile of chi-square with 6 dof (an edge-fitted pose agreeing with the filter).
_CHI2_6_99 = 16.811893829770927


class Tracker:
    """Multi-camera model-based pose tracker deciding by a bank of pose hypotheses.

    Parameters
    ----------
    rig : Rig
    model : Model
        The tracked object's CAD model (features).
    config : TrackerConfig
    initializer : callable, optional
        ``initializer(frameset) -> InitResult | None``, called while nothing is
        published: its answer and the best other candidates of its
        ``last_report`` are proposed to the bank (:meth:`propose`). The server
        runs it in a worker instead and proposes its answers itself.
    bsp_cache_dir : path, optional
    bank_options : BankOptions
    """

    def __init__(self, rig: Rig, model: Model, config: TrackerConfig = TrackerConfig(),
                 initializer: Callable[[FrameSet], InitResult | None] | None = None, bsp_cache_dir=None,
                 bank_options: BankOptions = BankOptions()):
        self.rig = rig
        self.model = model
        self.config = config
        self.initializer = initializer
        self.tree = load_or_build_bsp(model, cache_dir=bsp_cache_dir)
        self.scene = VisibilityScene([SceneBody(model.name, model, self.tree)])
        self.salient = salient_corners(model)
        self.edge_aid = None
        if config.edge_aid != "off":
            self.edge_aid = EdgeAid(rig, model, self.tree, edge_offset_px=config.edge_offset_px)
        self.edge_updates = 0  # edge-fitted poses the filter was updated with
        self.edge_rejects = 0  # edge fits too far from the filter's pose to use
        self.dim_skipped = 0  # corner candidates passed over as dim (dim_corner_frac)
        self._contrast = {}  # camera -> EdgeContrast: what the part's edges look like, learnt per track
        # A symmetric part (a box) looks the same in several poses: the tracker picks one by
        # the rule config.symmetry where it chooses by itself (vespro.symmetry).
        self.symmetries = discrete_symmetries(model.vertices)
        self.ekf: PoseEKF | None = None  # the tracked hypothesis's filter
        self.status = STATUS_INITIALIZING
        self._t_ns: int | None = None
        self.researches = 0  # frames searched again with wider windows (the first windows missed)
        self.confirmed = False  # the tracked hypothesis is published
        self.sigma_px = config.sigma_px
        # Per (camera, corner) noise variance factor, learnt from the residuals.
        self.feature_factor = np.ones((len(rig.cameras), model.n_corners))
        self._noise_updates = 0
        self.motion_scale = np.ones(2)  # process noise factors (linear, angular), see adaptive_motion
        self.frames = 0
        self.lost_events = 0  # published tracks demoted
        self.blind_frames = 0  # frames that did without a blind camera (blind_found_fraction)
        self._start_hidden: frozenset = frozenset()  # cameras the initialiser found the part hidden from
        self.last_good = None  # (T_world_object, velocity (6,), t_ns) of the last tracking frame
        self._reseeded = True
        mf = self.edge_aid.mf if self.edge_aid is not None else model_features(model)
        self.redetector = Redetector(rig, mf, self.tree)
        self.bank = HypothesisBank(model.vertices, model.diameter, self.symmetries, ImageLikelihood(mf, self.tree),
                                   self._new_filter, bank_options)
        self._bank_report = None  # the initialiser's last report seen (its candidates are proposed)
        self._warm_up()

    def _warm_up(self) -> None:
        """Run each stage once on made-up inputs, at set-up.

        The per-frame kernels are compiled (numba): the first call in a process
        loads them from the on-disk cache (~0.3 s in all) or, on a fresh
        install, compiles them (~10-20 s, once). Doing it here keeps that out of
        the first frame. The inputs only need the real types: the model some
        diameters in front of the first camera, a bright rectangle on black.
        """
        if not self.rig.cameras:
            return
        cam = self.rig.cameras[0]
        intr = cam.intrinsics
        T_wc = cam.T_world_camera if cam.is_fixed else np.eye(4)
        T_co = np.eye(4)
        T_co[:3, 3] = [0.0, 0.0, 3.0 * self.model.diameter]
        T_wo = T_wc @ T_co
        vis = _Candidates.of(self.scene.query(0, T_wc, [T_wo], intr), self.salient)
        uv, _, _ = project_with_jacobian(intr, T_wc, T_wo, vis.points)
        select_quality(uv, vis.view_angle, vis.silhouette_distance, (intr.width, intr.height),
                       k=self.config.features_per_camera)
        img = np.zeros((intr.height, intr.width, 3), np.uint8)
        x0, y0, x1, y1 = intr.width // 4, intr.height // 4, intr.width // 2, intr.height // 2
        img[y0:y1, x0:x1] = 200
        corners = np.array([[x0, y0], [x1 - 1, y0], [x0, y1 - 1], [x1 - 1, y1 - 1]], float) - 0.5
        extract_corners(img, corners, window_half_sizes(np.tile(np.eye(2), (len(corners), 1, 1))))

    # -- starting and stopping ----------------------------------------------
    def canonical_pose(self, T_world_object: np.ndarray) -> np.ndarray:
        """Among a symmetric part's equivalent poses ``T @ S``, the one to track when the
        tracker chooses by itself, by the rule ``TrackerConfig.symmetry``
        (:func:`vespro.symmetry.choose`: continuity with the last good track, or z up).
        Parts without symmetry are returned unchanged."""
        T_last = self.last_good[0] if self.last_good is not None else None
        return choose_equivalent(T_world_object, self.symmetries, self.config.symmetry, T_last)

    def start(self, init: InitResult, t_ns: int) -> None:
        """Start (or restart) from a pose at capture time ``t_ns``: the bank then holds this
        hypothesis alone, at the user's pose exactly as given (:attr:`InitResult.given`), or
        at the equivalent :meth:`canonical_pose` chooses. Published once the frames make it
        probable, as any hypothesis."""
        T = init.T_world_object if init.given else self.canonical_pose(init.T_world_object)
        self.bank.clear()
        self._start_hidden = frozenset(init.hidden)
        self.confirmed = False
        self.status = STATUS_INITIALIZING
        self._track_filter(self.bank.add(self._filter_at(T, init.cov6, init.velocity), t_ns))

    def _track_filter(self, h) -> None:
        """Track hypothesis ``h`` with everything a frame has (it was not tracked before)."""
        self.ekf = h.ekf
        self._t_ns = h.t_ns
        self._contrast = {}
        self.motion_scale = np.ones(2)
        self.confirmed = False

    def lose(self) -> None:
        """Drop every hypothesis from outside: the frames stopped coming for longer than the
        filters can predict across (a stalled camera). A published track is ``lost`` and the
        initialiser is seeded from its last good pose; without an initialiser too."""
        if self.confirmed or (self.ekf is not None and self.initializer is None):
            self._demote()
        self.bank.clear()
        self.ekf = None

    def _demote(self) -> None:
        """The published track is no longer published: ``lost`` until found again."""
        if self.confirmed:
            self.lost_events += 1
            self._reseeded = False
        self.confirmed = False
        self.status = STATUS_LOST

    def recovery_seed(self):
        """After a loss, the last good pose, velocity and stamp (once), to seed re-initialisation."""
        if self._reseeded or self.last_good is None:
            return None
        self._reseeded = True
        return self.last_good

    # -- one frame ------------------------------------------------------------
    def process(self, fs: FrameSet) -> TrackerOutput:
        """Estimate the pose at the frame set's capture instant.

        While nothing is published the initialiser (where there is one) proposes its answer
        and its best other candidates; the most probable hypothesis is tracked with the
        corners and edges (:meth:`_track`), the others with their edge fits; all are weighed
        on the frame (:meth:`_decide`)."""
        t0 = time.perf_counter()
        self.frames += 1
        bank = self.bank
        if self.initializer is not None and not self.confirmed:
            seed = self.recovery_seed()
            if seed is not None and hasattr(self.initializer, "reseed"):
                self.initializer.reseed(seed[0], velocity=seed[1], t_ns=seed[2])
            init = self.initializer(fs)
            rep = getattr(self.initializer, "last_report", None)
            fresh = rep is not None and rep is not self._bank_report
            self.propose(init, fs.t_ns, [T for T, _ in rep.candidates] if fresh else ())
            self._bank_report = rep
        best = bank.best()
        if best is None:
            self.ekf = None
            status = STATUS_INITIALIZING if self.status != STATUS_LOST else STATUS_LOST
            return TrackerOutput(fs.index, fs.t_ns, status, time_ms=(time.perf_counter() - t0) * 1e3,
                                 probability=0.0)
        if self.ekf is not best.ekf:
            self._track_filter(best)
        self._advance_others(fs)
        out = self._track(fs)
        return replace(out, time_ms=(time.perf_counter() - t0) * 1e3)

    def _camera_pose(self, fs: FrameSet, name: str) -> np.ndarray | None:
        cam = self.rig[name]
        if cam.is_fixed:
            return cam.T_world_camera  # validated when the rig was loaded
        T = fs.T_world_camera.get(name)
        # From the frame set (a file, the arm's kinematics): checked here, as the
        # visibility query is asked not to check again.
        return None if T is None else check_transform(T, f"T_world_{name}")

    def _shown(self, name: str, T_wc: np.ndarray, T_pred: np.ndarray, vis: "_Candidates", uv: np.ndarray,
               J: np.ndarray, intr) -> tuple:
        """(vis, uv, J) less the corners this camera's edge fits found dim (``dim_corner_frac``:
        an image corner is where two edges with contrast meet), when the corners not dim fill
        the selection as all would (``features_per_camera``, or as many as are selectable)."""
        memory = self._contrast.get(name)
        if (memory is None or self.edge_aid.contrast_ratio is None or self.config.dim_corner_frac <= 0
                or vis.indices.size == 0):
            return vis, uv, J
        T_co = np.linalg.solve(T_wc, T_pred)
        keep = self.edge_aid.corners_shown(memory, T_co, vis.indices, self.config.dim_corner_frac)
        if keep.all():
            return vis, uv, J
        ok = eligible_mask(uv, (intr.width, intr.height), view_angle=vis.view_angle, J=J)
        n_shown = np.count_nonzero(ok & keep)
        if n_shown == 0 or n_shown < min(self.config.features_per_camera, np.count_nonzero(ok)):
            return vis, uv, J
        self.dim_skipped += int((~keep).sum())
        vis = _Candidates(vis.indices[keep], vis.points[keep], vis.view_angle[keep], vis.silhouette_distance[keep])
        return vis, uv[keep], J[keep]

    def _window_half_sizes(self, k: int, J: np.ndarray, corner_ids: np.ndarray, P6: np.ndarray) -> np.ndarray:
        """Search-window half-sizes (px) of camera ``k``'s corners: ``window_sigma`` std of
        their innovation ``J P6 J^T + sigma^2 f`` (f: each corner's learnt noise factor)."""
        S = (J @ P6) @ J.transpose(0, 2, 1)
        r2 = self.sigma_px**2 * self.feature_factor[k, corner_ids]
        S[:, 0, 0] += r2
        S[:, 1, 1] += r2
        return window_half_sizes(S, n_sigma=self.config.window_sigma)

    def _unambiguous(self, k: int, uv: np.ndarray, J: np.ndarray, vis: "_Candidates", P6: np.ndarray) -> np.ndarray:
        """Candidates whose search window holds no other predicted corner, as a pool to select from.

        The extractor takes the corner nearest the prediction: when the pose is
        uncertain (a start, a coast) the windows are large, and a window that
        also holds a neighbouring corner of the part (a hole's rim, a chamfer)
        may measure the neighbour. Corners whose nearest predicted neighbour lies
        outside their window are preferred; if fewer than the number to select
        are, the least crowded make up the pool. Once the windows are small
        (a few px) every candidate qualifies.
        """
        n = len(uv)
        if n <= self.config.features_per_camera:
            return np.arange(n)
        half = self._window_half_sizes(k, J, vis.indices, P6)
        diff = uv[:, None, :] - uv[None, :, :]
        d2 = np.einsum("ijk,ijk->ij", diff, diff)
        np.fill_diagonal(d2, np.inf)
        margin = np.sqrt(d2.min(axis=1)) - (half + 2.0)  # the neighbour must be clear of the window
        n_clear = int((margin > 0).sum())
        order = np.argsort(-margin, kind="stable")
        return np.sort(order[:max(n_clear, self.config.features_per_camera)])

    def _track(self, fs: FrameSet) -> TrackerOutput:
        c = self.config
        ekf = self.ekf
        stage = {"visibility": 0.0, "selection": 0.0, "extraction": 0.0, "update": 0.0}
        dt = (fs.t_ns - self._t_ns) * 1e-9
        before = ekf.snapshot()
        T_before = ekf.pose
        if dt > 0:
            ekf.q_acc, ekf.q_alpha = c.q_acc * self.motion_scale[0], c.q_alpha * self.motion_scale[1]
            ekf.predict(dt)
            self._t_ns = fs.t_ns
        if not (np.all(np.isfinite(ekf.pose)) and np.all(np.isfinite(ekf.pose_covariance))):
            return self._decide(fs, [], 0, float("nan"), stage)
        T_prior = ekf.pose  # (a copy)
        P_prior = ekf.P[:6, :6].copy()
        obs, n_found, n_acc, mean_nis, max_half, ok = self._measure_twice(fs, stage)
        n_sel = sum(int(ob.feature_ids.size) for ob in obs)
        n_cams = sum(1 for ob in obs if ob.feature_ids.size)
        missed = dt > 0 and n_found < c.blind_found_fraction * n_sel
        if missed and n_cams >= 2:
            # The windows missed most corners: the velocity is off by more than the filter
            # thinks (an unknown velocity at a start, a sudden turn). Search again about the
            # same prediction, its velocity covariance widened so that the predicted pose's
            # opens by the start's sigmas; keep whichever search accepted more corners. Only
            # where two or more cameras select corners: in wide windows one camera's corners
            # can agree with a wrong pose (depth and tilt are its weak directions), while
            # several cameras' must agree with one another too.
            kept = (ekf.snapshot(), self.sigma_px, self.feature_factor.copy(), self._noise_updates)
            ekf.restore(before)
            ekf.widen_velocity(c.init_sigma_pos / dt, c.init_sigma_rot / dt)
            ekf.predict(dt)
            again = self._measure_twice(fs, stage)
            self.researches += 1
            if again[2] > n_acc:
                obs, n_found, n_acc, mean_nis, max_half, ok = again
            else:
                snap, self.sigma_px, self.feature_factor, self._noise_updates = kept
                ekf.restore(snap)
        if self.edge_aid is not None:
            self._edge_update(fs, self._seeing(obs), stage)
        if c.adaptive_motion and ok and n_acc >= c.min_accepted and dt > 0:
            self._adapt_motion(T_prior, P_prior)
        if missed:
            self._redetect(fs, T_prior, T_before, dt, stage)
        return self._decide(fs, obs, n_acc, mean_nis, stage)

    def _redetect(self, fs: FrameSet, T_pred: np.ndarray, T_before: np.ndarray, dt: float, stage: dict) -> None:
        """The windows missed: the pose refined on the image edges about the prediction joins the
        bank as a hypothesis (:mod:`vespro.redetect`), its velocity the motion from the tracked
        filter's previous pose to it; the frame's likelihood weighs it against the tracked one."""
        t = time.perf_counter()
        poses = {cam.name: self._camera_pose(fs, cam.name) for cam in self.rig}
        T = self.redetector(fs.images, poses, T_pred)
        if T is not None:
            v = np.r_[(T[:3, 3] - T_before[:3, 3]) / dt, log_so3(T[:3, :3] @ T_before[:3, :3].T) / dt]
            self.bank.propose(T, fs.t_ns, velocity=v)
        stage["redetect"] = time.perf_counter() - t

    def _measure_twice(self, fs: FrameSet, stage: dict) -> tuple:
        """:meth:`_measure` about the filter's prediction, and again about its result in the
        cameras whose windows were wide; the filter updated once (see ``refine_window_px``)."""
        ekf = self.ekf
        saved = (ekf.snapshot(), self.sigma_px, self.feature_factor.copy(), self._noise_updates)
        result, recs = self._measure(fs, stage)
        wide = {k for k, r in recs.items() if r.half >= self.config.refine_window_px}
        if result[5] and wide:
            # Wide windows (a start, a coast, a jolt): the first pass used the corners with no
            # neighbour inside their window. Its result only places the windows of a second
            # pass (small, the full feature set) in those cameras; the filter is then updated
            # once, from its prediction, with the second pass's corners there and the first
            # pass's elsewhere: each image counts once. A camera whose windows were small
            # already measured about the prediction what it would measure about the result.
            assoc = (ekf.pose, ekf.pose_covariance)
            snap, self.sigma_px, self.feature_factor, self._noise_updates = saved
            ekf.restore(snap)
            result, _ = self._measure(fs, stage, assoc, {k: r for k, r in recs.items() if k not in wide})
        return result

    def _adapt_motion(self, T_prior: np.ndarray, P_prior: np.ndarray) -> None:
        """Scale the process noise by how far the frame corrected the prediction (``adaptive_motion``).

        The correction's position and orientation parts, each normalised by its
        predicted covariance (``P_prior``, 6x6), average at most 1 per degree of
        freedom when the motion model holds (the correction's covariance is the
        predicted one less the updated one); a larger mean raises that part's
        density, a smaller one lowers it back towards the configured one.
        """
        T = self.ekf.pose
        e = (T[:3, 3] - T_prior[:3, 3], log_so3(T[:3, :3] @ T_prior[:3, :3].T))
        rate = self.config.noise_adapt_rate
        for i, (ei, Pi) in enumerate(zip(e, (P_prior[:3, :3], P_prior[3:, 3:]))):
            try:
                ratio = float(ei @ np.linalg.solve(Pi, ei)) / 3.0
            except np.linalg.LinAlgError:
                continue
            if np.isfinite(ratio):
                ratio = min(max(ratio, 0.25), 4.0)
                self.motion_scale[i] = max(1.0, self.motion_scale[i] * (1.0 + rate * (ratio - 1.0)))

    def _edge_update(self, fs: FrameSet, obs: list, stage: dict) -> None:
        """Update the filter with the pose the part's edges fit in the image (see ``edge_aid``)."""
        t = time.perf_counter()
        c = self.config
        cams = [ob.name for ob in obs if ob.has_image and ob.feature_ids.size]
        if c.edge_aid == "single" and len(cams) != 1:
            return
        for name in cams:
            T_wc = self._camera_pose(fs, name)
            img = fs.grey(name)
            if T_wc is None or img is None:
                continue
            T = self.ekf.pose
            memory = self._contrast.get(name)
            if memory is None:
                memory = self._contrast[name] = EdgeContrast(self.edge_aid.mf.sample_edge)
            m = self.edge_aid.measure(name, img, T_wc, T, memory,
                                      None if self.confirmed else max(c.edge_offset_px, c.start_edge_offset_px))
            if m is None:
                continue
            if add(m.T_world_object, T, self.model.vertices) / self.model.diameter > c.edge_aid_max_move:
                self.edge_rejects += 1
                continue
            nis = self.ekf.update_pose(m.T_world_object, m.cov6)
            self.edge_updates += 1
            if nis <= _CHI2_6_99:
                memory.learn(m.fit.sample_contrast[0], m.edge_side)
        stage["edges"] = time.perf_counter() - t

    def _measure(self, fs: FrameSet, stage: dict, assoc: tuple | None = None, kept: dict | None = None):
        """Visibility, selection, extraction and update.

        Features are chosen and searched for around ``assoc`` = (T_world_object,
        6x6 covariance), by default the filter's prediction; the update is
        always the filter's, linearised at its own state. ``kept``: camera index ->
        :class:`_CameraMeasurement` of an earlier pass about the same prediction, used
        as it is for those cameras.

        Returns ((observations, corners found, accepted, mean NIS, largest window half-size,
        whether the update was applied), the cameras' measurements by camera index); adds
        each stage's time to ``stage``.
        """
        c = self.config
        ekf = self.ekf
        kept = kept or {}
        T_pred, P6 = (ekf.pose, ekf.pose_covariance) if assoc is None else assoc

        # Visibility and projection per camera.
        t = time.perf_counter()
        cands, per_cam = [], []
        for k, cam in enumerate(self.rig):
            img = fs.images.get(cam.name)
            T_wc = self._camera_pose(fs, cam.name)
            if img is None or T_wc is None or k in kept:
                per_cam.append(None)
                continue
            vis = _Candidates.of(self.scene.query(0, T_wc, [T_pred], cam.intrinsics, check=False), self.salient)
            if vis.indices.size == 0:
                per_cam.append((cam, img, T_wc, vis, None, None))
                continue
            uv, depth, J = project_with_jacobian(cam.intrinsics, T_wc, T_pred, vis.points)
            vis, uv, J = self._shown(cam.name, T_wc, T_pred, vis, uv, J, cam.intrinsics)
            per_cam.append((cam, img, T_wc, vis, uv, J))
            cands.append((len(per_cam) - 1, uv, J, vis))
        stage["visibility"] += time.perf_counter() - t

        # Selection.
        t = time.perf_counter()
        chosen = {}
        if cands:
            if c.selection == "information":
                picks = select_information_joint(
                    [(uv, J, vis.view_angle, (self.rig.cameras[k].intrinsics.width, self.rig.cameras[k].intrinsics.height))
                     for k, uv, J, vis in cands],
                    P6=P6, k_per_camera=c.features_per_camera, sigma_px=c.sigma_px)
                for (k, *_), sel in zip(cands, picks):
                    chosen[k] = np.asarray(sel, dtype=int)
            else:
                for k, uv, J, vis in cands:
                    intr = self.rig.cameras[k].intrinsics
                    pool = self._unambiguous(k, uv, J, vis, P6)
                    picks = np.asarray(select_quality(
                        uv[pool], vis.view_angle[pool], vis.silhouette_distance[pool], (intr.width, intr.height),
                        k=c.features_per_camera), dtype=int)
                    chosen[k] = pool[picks]
        stage["selection"] += time.perf_counter() - t

        # Windowed extraction.
        t = time.perf_counter()
        recs = {}
        for k, entry in enumerate(per_cam):
            cam = self.rig.cameras[k]
            if k in kept:
                recs[k] = kept[k]
                continue
            if entry is None:
                recs[k] = _CameraMeasurement(CameraObservation(cam.name, fs.images.get(cam.name) is not None))
                continue
            _, img, T_wc, vis, uv, J = entry
            sel = chosen.get(k, np.zeros(0, int))
            if sel.size == 0:
                recs[k] = _CameraMeasurement(CameraObservation(cam.name, True, int(vis.indices.size)))
                continue
            Jk = J[sel]
            fid = vis.indices[sel]
            half = self._window_half_sizes(k, Jk, fid, P6)
            ext = extract_corners(img, uv[sel], half)
            found = ext.found
            if assoc is None:
                h_k, J_k = uv[sel][found], Jk[found]
            elif found.any():  # predicted pixels and Jacobians at the filter's own state
                h_k, _, J_k = project_with_jacobian(cam.intrinsics, T_wc, ekf.pose, vis.points[sel][found])
            else:
                h_k, J_k = np.zeros((0, 2)), np.zeros((0, 2, 6))
            recs[k] = _CameraMeasurement(
                CameraObservation(cam.name, True, int(vis.indices.size), vis.indices[sel], uv[sel], half, ext.uv,
                                  np.zeros(sel.size, bool)),
                ext.uv[found], h_k, J_k, np.stack([np.full(int(found.sum()), k), fid[found]], axis=1),
                np.flatnonzero(found), int(half.max()))
        stage["extraction"] += time.perf_counter() - t
        obs = [recs[k].obs for k in range(len(per_cam))]
        meas = [(k, recs[k]) for k in range(len(per_cam)) if recs[k].z is not None]
        zs, hs, Js, keys = ([getattr(r, f) for _, r in meas] for f in ("z", "h", "J", "key"))
        owners = [(k, r.found_idx) for k, r in meas]
        max_half = max((r.half for r in recs.values()), default=0)

        # Update.
        t = time.perf_counter()
        n_acc, mean_nis, updated = 0, float("nan"), False
        if zs:
            z, h, Jp = np.concatenate(zs), np.concatenate(hs), np.concatenate(Js)
        else:
            z = h = np.zeros((0, 2))
            Jp = np.zeros((0, 2, 6))
        if len(z):
            key = np.concatenate(keys)
            factor = self.feature_factor[key[:, 0], key[:, 1]]
            ekf.sigma_px = self.sigma_px * np.sqrt(factor)
            res = ekf.update(z, h, Jp)
            if res.status == EKFStatus.OK:
                updated = True
                n_acc = res.n_accepted
                nis = res.nis[res.accepted]
                mean_nis = float(np.mean(nis)) if nis.size else float("nan")
                if nis.size >= c.min_accepted and np.isfinite(mean_nis):
                    # Covariance matching: E[NIS] = 2 per point when R is right.
                    # A plain running mean over the first frames (the start value is a guess),
                    # then an exponential one that follows changes.
                    self._noise_updates += 1
                    rate = max(c.noise_adapt_rate, 1.0 / (self._noise_updates + 1))
                    ratio = min(max(mean_nis / 2.0, 0.25), 4.0)
                    s2 = self.sigma_px**2 * (1.0 + rate * (ratio - 1.0))
                    self.sigma_px = float(min(max(math.sqrt(s2), c.sigma_min_px), c.sigma_max_px))  # np.clip, minus its overhead
                # Each accepted corner's own squared residual in units of the shared sigma.
                # Gated corners do not count: they are outliers (a wrong match), not noise,
                # and inflating their variance would let a drifting track accept them.
                ok = res.accepted & np.isfinite(res.nis)
                raw = np.minimum(res.nis[ok] * factor[ok] / 2.0, c.feature_noise_max)
                kk = key[ok]
                a = c.feature_noise_rate
                f = (1 - a) * self.feature_factor[kk[:, 0], kk[:, 1]] + a * raw
                self.feature_factor[kk[:, 0], kk[:, 1]] = np.clip(f, 1.0, c.feature_noise_max)
                # Mark accepted features per camera.
                offset = 0
                obs = list(obs)
                for oi, found_idx in owners:
                    acc = np.zeros(obs[oi].feature_ids.size, bool)
                    acc[found_idx] = res.accepted[offset:offset + found_idx.size]
                    offset += found_idx.size
                    obs[oi] = CameraObservation(**{**obs[oi].__dict__, "accepted": acc})
        stage["update"] += time.perf_counter() - t
        return (obs, len(z), n_acc, mean_nis, max_half, updated), recs

    def _seeing(self, obs: list) -> list:
        """The observations whose cameras get edge fits: all of them, less the blind cameras
        while another sees the part (two while the track is not published, unless the
        initialiser found the part hidden from those cameras; see ``blind_found_fraction``)."""
        c = self.config
        if c.blind_found_fraction <= 0:
            return obs
        blind = [ob.feature_ids.size >= c.min_accepted
                 and np.count_nonzero(np.isfinite(ob.uv_meas[:, 0])) < c.blind_found_fraction * ob.feature_ids.size
                 for ob in obs]
        seeing = sum(1 for ob, b in zip(obs, blind) if not b and int(ob.accepted.sum()) >= c.min_accepted)
        hidden_at_start = {ob.name for ob, b in zip(obs, blind) if b} <= self._start_hidden
        if not any(blind) or seeing < (1 if self.confirmed or hidden_at_start else 2):
            return obs
        self.blind_frames += 1
        return [ob for ob, b in zip(obs, blind) if not b]

    # -- the hypothesis bank ------------------------------------------------------
    def _new_filter(self, T_world_object: np.ndarray, cov6: np.ndarray | None = None,
                    velocity: np.ndarray | None = None) -> PoseEKF:
        """A bank hypothesis's filter: at the pose :meth:`canonical_pose` picks among its equivalents."""
        return self._filter_at(self.canonical_pose(T_world_object), cov6, velocity)

    def _filter_at(self, T_world_object: np.ndarray, cov6: np.ndarray | None = None,
                   velocity: np.ndarray | None = None) -> PoseEKF:
        """A filter started at exactly this pose, with the start's uncertainty (or ``cov6``)."""
        c = self.config
        P0 = np.diag(np.r_[np.full(3, c.init_sigma_pos**2), np.full(3, c.init_sigma_rot**2),
                           np.full(3, c.init_sigma_vel**2), np.full(3, c.init_sigma_angvel**2)])
        if cov6 is not None:
            P0[:6, :6] = cov6
        v = w = None
        if velocity is not None:
            v, w = velocity[:3], velocity[3:]
        return PoseEKF(T_world_object, P0, q_acc=c.q_acc, q_alpha=c.q_alpha,
                       sigma_px=c.sigma_px, gate_prob=c.gate_prob, v=v, w=w, robust_nis=c.robust_nis)

    def propose(self, init: InitResult | None, t_ns: int, candidates=(), frames=()) -> None:
        """An initialiser's answer on the frame set of ``t_ns`` and, beside it,
        its first ``BankOptions.proposals`` other candidate poses, as hypotheses (each merged with
        one held at the same pose). ``frames``: the frame sets captured since ``t_ns``, oldest
        first; the new hypotheses are carried through them by their edge fits (the held ones are
        at the present already).

        The candidates stand beside an answer as its rivals, never without one: the bank
        weighs the poses it holds against each other and clutter, not against poses it does
        not hold, and with the part's pose missing, the best of the rest (a face matched to
        another) would win."""
        if init is None:
            return
        bank = self.bank
        held = set(map(id, bank.hypotheses))
        bank.propose(init.T_world_object, t_ns, init.cov6, init.velocity)
        for T in list(candidates)[:bank.options.proposals]:
            bank.propose(T, t_ns)
        new = [h for h in bank.hypotheses if id(h) not in held]
        for fs in frames:
            for h in new:
                self._advance(h, fs)

    def _advance_others(self, fs: FrameSet) -> None:
        """Predict the hypotheses not tracked to the frame and update them with their edge fits."""
        for h in list(self.bank.hypotheses):
            if h.ekf is not self.ekf:
                self._advance(h, fs)

    def _advance(self, h, fs: FrameSet) -> None:
        """Predict one hypothesis to the frame and update it with its edge fits (dropped if it
        diverges)."""
        if h not in self.bank.hypotheses:
            return
        dt = (fs.t_ns - h.t_ns) * 1e-9
        if dt > 0:
            h.ekf.predict(dt)
            h.t_ns = fs.t_ns
        if self.edge_aid is not None:
            for cam in self.rig:
                img = fs.grey(cam.name)
                T_wc = self._camera_pose(fs, cam.name)
                if img is None or T_wc is None:
                    continue
                m = self.edge_aid.measure(cam.name, img, T_wc, h.ekf.pose)
                if m is not None:
                    h.ekf.update_pose(m.T_world_object, m.cov6)
        if not (np.all(np.isfinite(h.ekf.pose)) and np.all(np.isfinite(h.ekf.pose_covariance))):
            self.bank.remove(h)

    def _bank_views(self, fs: FrameSet) -> list:
        """(T_world_camera, EdgeImage) of each camera with an image, over the box that holds every
        hypothesis's projection."""
        lk = self.bank.likelihood
        views = []
        for cam in self.rig:
            img = fs.grey(cam.name)
            T_wc = self._camera_pose(fs, cam.name)
            if img is None or T_wc is None:
                continue
            K = np.asarray(cam.intrinsics.K, float)
            T_cw = np.linalg.inv(T_wc)
            boxes = [b for h in self.bank.hypotheses
                     if (b := lk.box(K, T_cw @ h.ekf.pose, img.shape[1], img.shape[0])) is not None]
            if not boxes:
                continue
            b = np.array(boxes)
            box = (int(b[:, 0].min()), int(b[:, 1].min()), int(b[:, 2].max()), int(b[:, 3].max()))
            und = self.edge_aid.undistort[cam.name](img, box) if self.edge_aid is not None else \
                img[box[1]:box[3], box[0]:box[2]]
            Kb = K.copy()
            Kb[0, 2] -= box[0]
            Kb[1, 2] -= box[1]
            views.append((T_wc, lk.edge_image(und, Kb)))
        return views

    def _decide(self, fs: FrameSet, obs: list, n_acc: int, mean_nis: float, stage: dict) -> TrackerOutput:
        """The bank's decision on a frame: every hypothesis weighed, the tracked one published
        ``tracking`` while it is the most probable and its probability is at least
        ``1 - wrong_lock_rate``; a published track whose probability falls is not published
        from that frame on (``lost``), and the initialiser looks again."""
        c = self.config
        bank = self.bank
        ekf = self.ekf
        main = next((h for h in bank.hypotheses if h.ekf is ekf), None)
        t = time.perf_counter()
        if main is not None:
            main.t_ns = self._t_ns
            P = ekf.pose_covariance
            if not (np.all(np.isfinite(ekf.pose)) and np.all(np.isfinite(P))) or \
                    float(np.sqrt(np.max(np.linalg.eigvalsh(P[:3, :3])))) > c.max_pos_std:
                bank.remove(main)  # the filter has diverged
                main = None
        bank.weigh(self._bank_views(fs))
        bank.tidy(keep=main)
        stage["bank"] = time.perf_counter() - t
        p = bank.probability(main) if main is not None else 0.0
        stage_ms = {k: v * 1e3 for k, v in stage.items()}
        if main is not None and bank.best() is main and p >= 1.0 - bank.options.wrong_lock_rate:
            self.confirmed = True
            self.status = STATUS_TRACKING
            T = ekf.pose
            vel = np.concatenate([ekf.velocity, ekf.angular_velocity])
            self.last_good = (T, vel, fs.t_ns)
            return TrackerOutput(fs.index, fs.t_ns, STATUS_TRACKING, T, vel, ekf.pose_covariance, tuple(obs),
                                 n_acc, mean_nis, stage_ms=stage_ms, probability=p)
        if self.confirmed:
            self._demote()  # at once
        if main is None:
            self.ekf = None
            if not bank.hypotheses and self.initializer is None:
                self.status = STATUS_LOST  # nothing held, and nothing here to look again
        status = STATUS_LOST if self.status == STATUS_LOST else STATUS_INITIALIZING
        return TrackerOutput(fs.index, fs.t_ns, status, observations=tuple(obs), n_accepted=n_acc,
                             mean_nis=mean_nis, stage_ms=stage_ms, probability=p)
