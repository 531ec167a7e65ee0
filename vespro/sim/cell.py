"""The simulated cell: MuJoCo physics at 500 Hz, camera capture at 26 Hz.

:class:`SimCell` owns the MuJoCo model and data, moves the object (and the
occluder) along scripted motions, drives the arm, steps physics on a
:class:`~vespro.clock.SimClock`, and captures :class:`~vespro.frames.FrameSet`
objects at the capture rate. Eye-in-hand camera poses in a frame set come from
the arm's measured joint positions (jointpos sensors, optional encoder noise)
through forward kinematics on a private copy of the model, as a real cell
computes them.

Ground truth (:meth:`SimCell.true_object_pose`) is a separate call, for the
recording writer's ``groundtruth.csv`` and evaluators only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import mujoco  # MUJOCO_GL is defaulted to egl by the vespro package, imported first
import numpy as np

from ..clock import NS_PER_S, SimClock, ns_from_s
from ..frames import FrameSet
from ..memory import ScratchImages
from ..rig import Rig
from ..se3 import log_so3, matrix_from_quat, quat_from_matrix, transform_from_rt
from .imaging import ImageEffects, ImagePipeline
from .motion import Motion
from .scene import PARK_POS, WORK_POINT, SceneSpec, build_cell

__all__ = ["CellConfig", "OccluderSweep", "CameraDropout", "SimCell", "ARM_MODES"]

ARM_MODES = ("home", "watch")


@dataclass(frozen=True)
class OccluderSweep:
    """A paddle that passes between a fixed camera and the working area.

    Between ``t_start`` and ``t_start + duration`` (s) the paddle moves across
    the camera's line of sight to the working area, at ``fraction`` of the
    distance from the camera, from ``-half_travel`` to ``+half_travel`` (m)
    along the camera's x axis; parked out of sight otherwise.
    """

    camera: str
    t_start: float
    duration: float = 1.5
    fraction: float = 0.4
    half_travel: float = 0.3


@dataclass(frozen=True)
class CameraDropout:
    """No image from ``camera`` for captures in ``[t_start, t_end)`` (s)."""

    camera: str
    t_start: float
    t_end: float


@dataclass(frozen=True)
class CellConfig:
    """Set-up of a simulated cell run.

    Attributes
    ----------
    object_mesh : Path
        CAD model of the tracked object (metres).
    rig : Rig
        The cameras (names, intrinsics, mounting).
    rate_hz : float
        Capture rate.
    effects : ImageEffects
        Image degradations applied to every camera.
    arm : str
        ``"home"`` (arm parked) or ``"watch"`` (the flange hovers above the
        working area looking down, drifting slowly, so the eye-in-hand camera
        sees the object from a moving viewpoint).
    encoder_noise : float
        Std of the joint sensors' noise, rad.
    occluders : tuple[OccluderSweep, ...]
    dropouts : tuple[CameraDropout, ...]
    markers : int
        Number of marker spheres (tests).
    seed : int
    scene_extras : tuple of callables
        Passed to :class:`~vespro.sim.scene.SceneSpec` ``extras``.
    render_samples : int
        Render multisampling (see :class:`~vespro.sim.scene.SceneSpec`).
    supersample : int
        Render samples per pixel and axis, averaged into each pixel (see
        :class:`~vespro.sim.scene.SceneSpec`); render time grows with its square.
    mono : bool
        Monochrome cameras: 8-bit grey images instead of BGR.
    clutter : int
        Textured background items (:mod:`vespro.sim.clutter`; placed by ``seed``).
    distractors : tuple of Distractor
        Other objects in view (:mod:`vespro.sim.distractors`).
    textured_part : bool
        Grey patterns on the part's faces.
    """

    object_mesh: Path
    rig: Rig
    rate_hz: float = 26.0
    effects: ImageEffects = field(default_factory=ImageEffects)
    arm: str = "home"
    encoder_noise: float = 0.0
    occluders: tuple = ()
    dropouts: tuple = ()
    markers: int = 0
    seed: int = 0
    scene_extras: tuple = ()
    render_samples: int = 4
    supersample: int = 1
    mono: bool = False
    clutter: int = 0
    distractors: tuple = ()
    textured_part: bool = False

    def __post_init__(self):
        if self.arm not in ARM_MODES:
            raise ValueError(f"arm mode must be one of {ARM_MODES}, got {self.arm!r}")
        if not (0 < self.rate_hz <= 500):
            raise ValueError(f"capture rate must be in (0, 500] Hz, got {self.rate_hz}")
        for o in self.occluders:
            if o.camera not in self.rig.names or not self.rig[o.camera].is_fixed:
                raise ValueError(f"occluder camera {o.camera!r} must be a fixed camera of the rig {self.rig.names}")
        for d in self.dropouts:
            if d.camera not in self.rig.names:
                raise ValueError(f"dropout camera {d.camera!r} is not in the rig {self.rig.names}")


class SimCell:
    """The cell, stepped in lockstep with a simulated clock.

    Parameters
    ----------
    config : CellConfig
    motion : Motion
        The object's trajectory.
    clock : SimClock, optional
        Advanced by one physics step per :meth:`step`.
    """

    def __init__(self, config: CellConfig, motion: Motion, clock: SimClock | None = None):
        self.config = config
        self.motion = motion
        self.clock = clock or SimClock()
        self.model, info = build_cell(SceneSpec(Path(config.object_mesh), config.rig, markers=config.markers,
                                                extras=tuple(config.scene_extras),
                                                render_samples=config.render_samples,
                                                supersample=config.supersample, clutter=config.clutter,
                                                clutter_seed=config.seed,
                                                distractors=tuple(config.distractors),
                                                textured_part=config.textured_part))
        self.data = mujoco.MjData(self.model)
        home = self.model.key("home").id
        mujoco.mj_resetDataKeyframe(self.model, self.data, home)
        self._q_home = self.data.qpos[:6].copy()
        self._fk = mujoco.MjData(self.model)  # private data for forward kinematics
        self.dt_ns = ns_from_s(self.model.opt.timestep)
        self.rng = np.random.default_rng(config.seed)
        self._render_info = info["render"]
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}
        self._rgb = ScratchImages()  # the renders as read and turned over (see _render_rgb)
        self._pipelines = {}
        for cam in config.rig:
            rintr, mj_name = self._render_info[cam.name]
            self._pipelines[cam.name] = ImagePipeline(cam.intrinsics, rintr, config.effects, mono=config.mono,
                                                    supersample=config.supersample)
            key = (rintr.height, rintr.width)
            if key not in self._renderers:
                r = mujoco.Renderer(self.model, rintr.height, rintr.width)
                r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
                r.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
                self._renderers[key] = r
        self._obj_mocap = self.model.body("object").mocapid[0]
        self._occ_mocap = self.model.body("occluder").mocapid[0]
        self._distractor_mocap = [self.model.body(d.name).mocapid[0] for d in config.distractors]
        self._flange = self.model.body("flange").id
        self._arm_target_q = self._q_home.copy()
        self._next_capture = 0
        self._t0_ns = self.clock.now_ns()
        self._apply_scripts()
        mujoco.mj_forward(self.model, self.data)

    # -- scripted bodies ---------------------------------------------------
    @property
    def t(self) -> float:
        """Simulated time since the start, s."""
        return (self.clock.now_ns() - self._t0_ns) / NS_PER_S

    def _set_mocap(self, mocap_id: int, T: np.ndarray) -> None:
        self.data.mocap_pos[mocap_id] = T[:3, 3]
        self.data.mocap_quat[mocap_id] = quat_from_matrix(T[:3, :3])

    def _occluder_pose(self, t: float) -> np.ndarray | None:
        for o in self.config.occluders:
            if o.t_start <= t < o.t_start + o.duration:
                T_wc = self.config.rig[o.camera].T_world_camera
                c = T_wc[:3, 3]
                target = self.motion.pose(t)[:3, 3]
                s = -o.half_travel + 2 * o.half_travel * (t - o.t_start) / o.duration
                p = c + o.fraction * (target - c) + s * T_wc[:3, 0]
                # Paddle's thin axis (y) along the line of sight.
                y = (target - c) / np.linalg.norm(target - c)
                x = T_wc[:3, 0] - y * (T_wc[:3, 0] @ y)
                x /= np.linalg.norm(x)
                return transform_from_rt(np.column_stack([x, y, np.cross(x, y)]), p)
        return None

    def _apply_scripts(self) -> None:
        t = self.t
        self._set_mocap(self._obj_mocap, self.motion.pose(t))
        T_occ = self._occluder_pose(t)
        if T_occ is None:
            self.data.mocap_pos[self._occ_mocap] = PARK_POS + [1.0, 0, 0]
        else:
            self._set_mocap(self._occ_mocap, T_occ)
        for d, m in zip(self.config.distractors, self._distractor_mocap):
            self._set_mocap(m, d.pose(t))
        self.data.ctrl[:6] = self._arm_target_q

    # -- arm ---------------------------------------------------------------
    def _watch_target(self, t: float) -> np.ndarray:
        """Flange pose for the "watch" mode: looking down at the working area."""
        p = WORK_POINT + [-0.065 + 0.04 * np.sin(0.5 * t), 0.05 * np.sin(0.37 * t), 0.55 + 0.03 * np.sin(0.23 * t)]
        R = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # z down, x along world y
        tilt = 0.12 * np.sin(0.3 * t)
        c, s = np.cos(tilt), np.sin(tilt)
        R = np.array([[1, 0, 0], [0, c, -s], [0, s, c]]) @ R
        return transform_from_rt(R, p)

    def solve_ik(self, T_world_flange: np.ndarray, q0: np.ndarray, iters: int = 60) -> np.ndarray:
        """Joint positions putting the flange at a pose (damped least squares).

        A simulator utility for scripting the arm (the servo side has its own
        CLIK); uses the private kinematics data.
        """
        m, d = self.model, self._fk
        q = np.array(q0, dtype=float)
        jacp = np.zeros((3, m.nv))
        jacr = np.zeros((3, m.nv))
        lo, hi = m.jnt_range[:6, 0], m.jnt_range[:6, 1]
        for _ in range(iters):
            d.qpos[:6] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            ep = T_world_flange[:3, 3] - d.xpos[self._flange]
            R = d.xmat[self._flange].reshape(3, 3)
            Re = T_world_flange[:3, :3] @ R.T
            er = log_so3(Re)
            e = np.concatenate([ep, er])
            if np.linalg.norm(ep) < 1e-6 and np.linalg.norm(er) < 1e-5:
                break
            mujoco.mj_jacBody(m, d, jacp, jacr, self._flange)
            J = np.vstack([jacp[:, :6], jacr[:, :6]])
            dq = J.T @ np.linalg.solve(J @ J.T + 1e-4 * np.eye(6), e)
            q = np.clip(q + dq, lo, hi)
        return q

    def measured_joints(self) -> np.ndarray:
        """Joint positions as the arm's sensors report them (rad, shape (6,))."""
        q = self.data.sensordata[:6].copy()
        if self.config.encoder_noise > 0:
            q += self.rng.normal(0.0, self.config.encoder_noise, 6)
        return q

    def link_pose(self, link: str, q: np.ndarray) -> np.ndarray:
        """``T_world_link`` by forward kinematics of joint positions ``q``."""
        d = self._fk
        d.qpos[:6] = q
        mujoco.mj_kinematics(self.model, d)
        b = self.model.body(link).id
        return transform_from_rt(d.xmat[b].reshape(3, 3).copy(), d.xpos[b].copy())

    # -- stepping and capture ---------------------------------------------
    def step(self) -> None:
        """One physics step (2 ms) and one clock tick."""
        self.clock.advance(self.dt_ns)
        self._apply_scripts()
        mujoco.mj_step(self.model, self.data)

    def capture_due(self) -> bool:
        return self.t >= self._next_capture / self.config.rate_hz - 1e-9

    def capture(self) -> FrameSet:
        """Render every camera now; returns the frame set (no ground truth)."""
        mujoco.mj_forward(self.model, self.data)  # positions consistent with qpos and scripts
        fs = self.render_frameset(self._next_capture, self.clock.now_ns(), self.t)
        self._next_capture += 1
        if self.config.arm == "watch":
            self._arm_target_q = self.solve_ik(self._watch_target(self.t + 1.0 / self.config.rate_hz),
                                               self.data.qpos[:6])
        return fs

    def render_frameset(self, index: int, t_ns: int, t: float, skip=()) -> FrameSet:
        """Render every camera from the current (forwarded) state.

        ``t`` (s since the start) decides camera dropouts; ``t_ns`` stamps the set. Cameras
        named in ``skip`` are not rendered (their images None).
        """
        q_meas = self.measured_joints()
        images, poses = {}, {}
        for cam in self.config.rig:
            if not cam.is_fixed:
                poses[cam.name] = self.link_pose(cam.link, q_meas) @ cam.T_link_camera
            if cam.name in skip or any(d.camera == cam.name and d.t_start <= t < d.t_end
                                       for d in self.config.dropouts):
                images[cam.name] = None
                continue
            rintr, mj_name = self._render_info[cam.name]
            r = self._renderers[(rintr.height, rintr.width)]
            r.update_scene(self.data, camera=mj_name)
            r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
            # The cell's walls hide the sky from every camera: not drawing it saves ~1.6 ms a view.
            r.scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = False
            rgb = self._render_rgb(r, (rintr.height, rintr.width))
            images[cam.name] = self._pipelines[cam.name].apply(rgb, self.rng)
        return FrameSet(index, t_ns, images, poses)

    def _render_rgb(self, r: "mujoco.Renderer", key: tuple) -> np.ndarray:
        """The renderer's RGB image of size ``key`` (height, width), in a buffer reused frame after
        frame (the pipeline reads it at once).

        MuJoCo's ``Renderer.render`` turns OpenGL's bottom-up rows over in place through a
        temporary copy of the image: a fresh block each frame, which in a live server is a
        fresh mapping whose pages fault in (:mod:`vespro.memory`). Here the rows are read
        into one buffer and turned over into another; where this MuJoCo's renderer does not
        have the parts read here, its own ``render``.
        """
        raw, rgb = (self._rgb.get(name, key + (3,), np.uint8) for name in ("read", "rgb"))
        ctx, rect, gl = (getattr(r, a, None) for a in ("_mjr_context", "_rect", "_gl_context"))
        if ctx is None or rect is None or gl is None:
            return r.render(out=rgb)
        gl.make_current()
        mujoco.mjr_render(rect, r.scene, ctx)
        mujoco.mjr_readPixels(raw, None, rect, ctx)
        return cv2.flip(raw, 0, dst=rgb)  # bottom-up rows to top-down, as render() gives them

    def set_world(self, q: np.ndarray, T_world_object: np.ndarray) -> None:
        """Put the arm and the object in a given state (a world simulated elsewhere)."""
        self.data.qpos[:6] = q
        self.data.qvel[:] = 0.0
        self._set_mocap(self._obj_mocap, T_world_object)
        self.data.mocap_pos[self._occ_mocap] = PARK_POS + [1.0, 0, 0]
        mujoco.mj_forward(self.model, self.data)

    def next_frameset(self) -> FrameSet:
        """Step physics to the next capture instant and capture."""
        while not self.capture_due():
            self.step()
        return self.capture()

    def settle_arm(self, seconds: float = 1.0) -> None:
        """Move the arm to its scripted start and let it settle, before time 0.

        Runs physics on a throwaway clock so the capture timeline is unchanged.
        """
        if self.config.arm == "watch":
            self._arm_target_q = self.solve_ik(self._watch_target(0.0), self._q_home)
            self.data.qpos[:6] = self._arm_target_q
            self.data.qvel[:] = 0
        self.data.ctrl[:6] = self._arm_target_q
        for _ in range(int(seconds / self.model.opt.timestep)):
            mujoco.mj_step(self.model, self.data)
        self.data.time = 0.0
        mujoco.mj_forward(self.model, self.data)

    # -- ground truth (evaluators only) -----------------------------------
    def true_object_pose(self) -> np.ndarray:
        """MuJoCo's pose of the object body now: ``T_world_object``."""
        b = self.model.body("object").id
        return transform_from_rt(matrix_from_quat(self.data.xquat[b]), self.data.xpos[b].copy())

    def true_distractor_poses(self) -> dict[str, np.ndarray]:
        """MuJoCo's pose of every distractor body now: ``{name: T_world_distractor}``."""
        out = {}
        for d in self.config.distractors:
            b = self.model.body(d.name).id
            out[d.name] = transform_from_rt(matrix_from_quat(self.data.xquat[b]), self.data.xpos[b].copy())
        return out

    def true_camera_pose(self, name: str) -> np.ndarray:
        """The render camera's true ``T_world_camera`` (optical frame) now."""
        _, mj_name = self._render_info[name]
        c = self.model.camera(mj_name).id
        T_gl = transform_from_rt(self.data.cam_xmat[c].reshape(3, 3).copy(), self.data.cam_xpos[c].copy())
        return T_gl @ np.diag([1.0, -1.0, -1.0, 1.0])

    def set_marker(self, i: int, p_world: np.ndarray) -> None:
        """Place marker sphere ``i`` (tests)."""
        self.data.mocap_pos[self.model.body(f"marker_{i}").mocapid[0]] = p_world

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
