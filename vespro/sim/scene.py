"""Build the simulated cell for a given object and camera rig.

``models/cell.xml`` holds the static cell (arm, conveyor, table, lights and the
reference cameras). At run time this module adds, with MuJoCo's ``MjSpec``:

- the tracked object as a mocap body named ``object`` with the CAD mesh
  (object frame = body frame; MuJoCo re-centres the mesh inside the geom, not
  the body, so the body pose is the CAD frame's pose);
- an occluder paddle (mocap body ``occluder``), parked out of sight;
- optionally a cluttered, textured background (:mod:`vespro.sim.clutter`),
  distractors (mocap bodies ``distractor_<i>``, :mod:`vespro.sim.distractors`)
  and a texture on the part's faces;
- one render camera per rig camera, named ``rig_<name>``: fixed cameras in the
  world at ``T_world_camera``, eye-in-hand cameras on their ``link`` body at
  ``T_link_camera``. MuJoCo cameras look along -z with y up (``camera_gl``);
  ``R_camera_camera_gl = diag(1, -1, -1)`` converts, here and nowhere else.

The render camera is an ideal centred pinhole; :mod:`vespro.sim.imaging` maps its
image to the rig camera's intrinsics and distortion.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from ..camera import CameraIntrinsics
from ..rig import Rig, RigCamera
from ..se3 import quat_from_matrix

__all__ = ["MODELS_DIR", "CELL_XML", "T_CAMERA_GL", "WATCHED_VOLUME", "render_intrinsics", "SceneSpec", "build_cell"]

MODELS_DIR = Path(__file__).resolve().parents[2] / "models"
CELL_XML = MODELS_DIR / "cell.xml"

#: ``T_camera_camera_gl``: from MuJoCo's camera frame to the OpenCV optical frame.
T_CAMERA_GL = np.diag([1.0, -1.0, -1.0, 1.0])

#: Where parked mocap bodies wait (below the floor, out of every view).
PARK_POS = np.array([0.0, 0.0, -5.0])

BELT_TOP_Z = 0.50
BELT_CENTER_X = 0.90

#: The working volume of the simulated cell (:mod:`vespro.workspace`), as its user would state it:
#: the stretch of conveyor the cameras watch, from 10 cm under its belt's top to 30 cm over it;
#: world, m.
WATCHED_VOLUME = (BELT_CENTER_X - 0.3, -0.7, BELT_TOP_Z - 0.1, BELT_CENTER_X + 0.3, 0.7, BELT_TOP_Z + 0.3)
WORK_POINT = np.array([0.90, 0.0, 0.55])


def render_intrinsics(intr: CameraIntrinsics, margin: float = 1.0,
                      supersample: int = 1) -> tuple[CameraIntrinsics, float]:
    """The centred square-pixel pinhole MuJoCo renders for a rig camera.

    Parameters
    ----------
    intr : CameraIntrinsics
        The rig camera (any focal lengths, principal point, distortion).
    margin : float
        Extra field of view factor (>= 1).
    supersample : int
        Render this many times finer than the rig camera's pixels (each rig
        pixel then averages ``supersample**2`` render samples, see
        :class:`~vespro.sim.imaging.ImagePipeline`).

    Returns
    -------
    render : CameraIntrinsics
        Centred pinhole, focal length = ``supersample * max(fx, fy)`` (no loss
        of sampling density), sized to cover every pixel of the rig image once
        undistorted.
    fovy_deg : float
        MuJoCo ``fovy`` of that render camera.
    """
    ss = int(supersample)
    if ss < 1:
        raise ValueError(f"supersample must be an integer >= 1, got {supersample}")
    if ss == 1 and not intr.has_distortion and abs(intr.fx - intr.fy) < 1e-6 * intr.fx \
            and abs(intr.cx - (intr.width - 1) / 2) < 1e-6 and abs(intr.cy - (intr.height - 1) / 2) < 1e-6:
        fovy = float(np.rad2deg(2 * np.arctan(0.5 * intr.height / intr.fy)))
        return intr, fovy
    from ..camera import undistort_pixels

    w, h = intr.width, intr.height
    # Undistort a dense border of the rig image: its extent bounds what must be rendered.
    s = np.linspace(0, 1, 64)
    border = np.concatenate([
        np.stack([s * (w - 1), np.zeros_like(s)], 1), np.stack([s * (w - 1), np.full_like(s, h - 1)], 1),
        np.stack([np.zeros_like(s), s * (h - 1)], 1), np.stack([np.full_like(s, w - 1), s * (h - 1)], 1),
    ])
    ideal = undistort_pixels(intr, border)
    xn = (ideal[:, 0] - intr.cx) / intr.fx
    yn = (ideal[:, 1] - intr.cy) / intr.fy
    f = ss * max(intr.fx, intr.fy)
    half_w = margin * f * np.max(np.abs(xn)) + 2.0 * ss
    half_h = margin * f * np.max(np.abs(yn)) + 2.0 * ss
    rw, rh = int(np.ceil(2 * half_w)), int(np.ceil(2 * half_h))
    K = np.array([[f, 0, (rw - 1) / 2], [0, f, (rh - 1) / 2], [0, 0, 1]])
    fovy = float(np.rad2deg(2 * np.arctan(0.5 * rh / f)))
    return CameraIntrinsics(rw, rh, K), fovy


@dataclass(frozen=True)
class SceneSpec:
    """What goes into the cell.

    Attributes
    ----------
    object_mesh : Path
        CAD file of the tracked object, metres.
    rig : Rig
        Cameras to add as render cameras.
    object_rgba : tuple
        Object colour (light metal grey against the dark belt by default).
    markers : int
        Number of small marker spheres (mocap bodies ``marker_<i>``) for tests.
    occluder_size : tuple
        Half-sizes (m) of the occluder paddle box.
    render_samples : int
        Multisampling of the offscreen renders (anti-aliasing): 4 for accuracy,
        0 where render time matters most (a real-time demo, with a slight blur
        standing in for the pixel integration of a real sensor).
    supersample : int
        Render each camera this many times finer (per axis) than its pixels; the
        image pipeline averages the samples of each pixel, as a sensor
        integrates light over its area (multisampling only smooths geometry
        edges: a texture is sampled once per render pixel).
    extras : tuple of callables
        Each is called as ``f(spec: mujoco.MjSpec)`` before compiling, to add
        bodies of its own (a calibration board, a second part...).
    clutter : int
        Number of textured background items (:func:`vespro.sim.clutter.add_clutter`).
    clutter_seed : int
        Their sizes, places and textures.
    distractors : tuple of Distractor
        Other objects in view (:mod:`vespro.sim.distractors`).
    textured_part : bool
        Grey patterns printed on the part's faces (the silhouette is unchanged).
    floor_tiles : bool
        Draw the floor's checker as geometry (flat tiles on a plain floor) instead
        of a texture: the same pattern, but a CPU rasteriser spends about half of a
        view's render time sampling the texture (4-5 ms a 640x480 view here).
    """

    object_mesh: Path
    rig: Rig
    object_rgba: tuple = (0.60, 0.62, 0.66, 1.0)
    markers: int = 0
    marker_radius: float = 0.004
    occluder_size: tuple = (0.12, 0.012, 0.16)
    extras: tuple = ()
    render_samples: int = 4
    floor_tiles: bool = True
    supersample: int = 1
    clutter: int = 0
    clutter_seed: int = 0
    distractors: tuple = ()
    textured_part: bool = False


# The floor's checker (models/cell.xml: 512 px builtin checker, 8 repeats over the 8 m plane).
FLOOR_CHECK_M = 0.5
FLOOR_RGB = ((0.42, 0.44, 0.46), (0.36, 0.38, 0.40))
FLOOR_TILES_HALF_EXTENT = 4.0


def _floor_as_tiles(s: mujoco.MjSpec) -> None:
    """Replace the floor texture by its checker drawn as thin tiles (same squares, same greys)."""
    mat = s.material("floor_mat")
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = ""
    mat.rgba = [*FLOOR_RGB[0], 1.0]
    dark = s.add_material(name="floor_tile_mat")
    dark.rgba = [*FLOOR_RGB[1], 1.0]
    dark.specular, dark.shininess, dark.reflectance = mat.specular, mat.shininess, 0.0
    # One flat mesh of all the dark squares, 1 mm above the floor: one draw call (as separate
    # geoms, the 128 tiles cost more render time than the texture they replace).
    n = int(round(2 * FLOOR_TILES_HALF_EXTENT / FLOOR_CHECK_M))
    verts, faces = [], []
    for i in range(n):
        for j in range(n):
            if (i + j) % 2:
                continue
            x0 = -FLOOR_TILES_HALF_EXTENT + i * FLOOR_CHECK_M
            y0 = -FLOOR_TILES_HALF_EXTENT + j * FLOOR_CHECK_M
            k = len(verts)
            verts += [(x0, y0, 0.001), (x0 + FLOOR_CHECK_M, y0, 0.001),
                      (x0 + FLOOR_CHECK_M, y0 + FLOOR_CHECK_M, 0.001), (x0, y0 + FLOOR_CHECK_M, 0.001)]
            faces += [(k, k + 1, k + 2), (k, k + 2, k + 3)]
    mesh = s.add_mesh(name="floor_tiles_mesh")
    mesh.uservert = np.asarray(verts, float).ravel().tolist()
    mesh.userface = np.asarray(faces, int).ravel().tolist()
    mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
    s.worldbody.add_geom(name="floor_tiles", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="floor_tiles_mesh",
                         material="floor_tile_mat", contype=0, conaffinity=0)

def _camera_pose_gl(cam: RigCamera) -> tuple[np.ndarray, np.ndarray]:
    T = cam.T_world_camera if cam.is_fixed else cam.T_link_camera
    T_gl = T @ T_CAMERA_GL
    return T_gl[:3, 3].copy(), quat_from_matrix(T_gl[:3, :3])


def build_cell(spec: SceneSpec) -> tuple[mujoco.MjModel, dict]:
    """Compile the cell with the object, occluder, markers and rig cameras.

    Returns
    -------
    model : mujoco.MjModel
    info : dict
        ``render``: {camera name: (render CameraIntrinsics, MuJoCo camera name)}.

    Raises
    ------
    ValueError
        An eye-in-hand camera names a link that is not a body of the cell, or the
        object mesh is missing.
    """
    mesh_path = Path(spec.object_mesh).resolve()
    if not mesh_path.is_file():
        raise ValueError(f"object mesh not found: {mesh_path}")
    s = mujoco.MjSpec.from_file(str(CELL_XML))
    if spec.textured_part:
        from .textures import add_texture, grey_pattern, planar_uv_mesh

        v, f, uv = planar_uv_mesh(mesh_path)
        mesh = s.add_mesh(name="object_mesh")
        mesh.uservert = v.ravel().tolist()
        mesh.userface = f.ravel().tolist()
        mesh.usertexcoord = uv.ravel().tolist()
        mesh.userfacetexcoord = f.ravel().tolist()
        rng = np.random.default_rng([spec.clutter_seed, 5281])
        mat = s.material(add_texture(s, "object", grey_pattern(rng, mean=float(np.mean(spec.object_rgba[:3])),
                                                                spread=0.3), per_metre=8.0))
        mat.texuniform = False
    else:
        s.add_mesh(name="object_mesh", file=str(mesh_path))
        mat = s.add_material(name="object_mat")
        mat.rgba = list(spec.object_rgba)
    mat.specular = 0.35
    mat.shininess = 0.4

    wb = s.worldbody
    obj = wb.add_body(name="object", mocap=True, pos=PARK_POS.tolist())
    obj.add_geom(
        name="object_geom", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="object_mesh",
        material=mat.name, contype=0, conaffinity=0, group=2,
    )
    occ = wb.add_body(name="occluder", mocap=True, pos=(PARK_POS + [1.0, 0, 0]).tolist())
    occ.add_geom(
        name="occluder_geom", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(spec.occluder_size),
        rgba=[0.20, 0.30, 0.55, 1.0], contype=0, conaffinity=0, group=2,
    )
    if spec.markers:
        mmat = s.add_material(name="marker_mat")
        mmat.rgba = [1.0, 0.0, 0.0, 1.0]
        mmat.emission = 1.0  # uniformly bright: its image centroid has no shading bias
        mmat.specular = 0.0
    for i in range(spec.markers):
        mk = wb.add_body(name=f"marker_{i}", mocap=True, pos=(PARK_POS + [0, 0.1 * (i + 1), 0]).tolist())
        mk.add_geom(
            type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[spec.marker_radius, 0, 0],
            material="marker_mat", contype=0, conaffinity=0, group=2,
        )

    if spec.floor_tiles:
        _floor_as_tiles(s)
    if spec.clutter:
        from .clutter import add_clutter

        add_clutter(s, spec.clutter, spec.clutter_seed, spec.rig)
    if spec.distractors:
        from .distractors import add_distractors

        add_distractors(s, spec.distractors, spec.object_rgba)
    for extra in spec.extras:
        extra(s)

    render = {}
    for cam in spec.rig:
        rintr, fovy = render_intrinsics(cam.intrinsics, supersample=spec.supersample)
        pos, quat = _camera_pose_gl(cam)
        if cam.is_fixed:
            parent = wb
        else:
            parent = s.body(cam.link)
            if parent is None:
                raise ValueError(f"camera {cam.name!r}: link {cam.link!r} is not a body of the cell")
        mj_name = f"rig_{cam.name}"
        parent.add_camera(name=mj_name, pos=pos.tolist(), quat=quat.tolist(), fovy=fovy)
        render[cam.name] = (rintr, mj_name)

    # The offscreen buffer as large as the largest render, no larger: with
    # multisampling a larger buffer costs render time on a CPU rasteriser.
    if render:
        s.visual.global_.offwidth = max(r.width for r, _ in render.values())
        s.visual.global_.offheight = max(r.height for r, _ in render.values())
    s.visual.quality.offsamples = int(spec.render_samples)
    model = s.compile()
    return model, {"render": render}
