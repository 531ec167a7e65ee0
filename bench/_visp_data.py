"""ViSP's public model-based tracking data (Debian ``visp-images-data``) read into our types.

``mbt/cube``: 218 grey 640x480 frames of an 84 mm cube, its ``.cao`` model, its camera
(``cube.xml``, no distortion) and the start pose ``cube.0.pos`` (cMo: translation, then
theta-u). The camera is put at the world origin, so ``T_world_object`` = cMo.
Also the inverse: ``.cao`` models and tracker settings (with the camera) written from our meshes and rigs, so
that ViSP's tracker can run on our recordings.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vespro.camera import CameraIntrinsics
from vespro.frames import FrameSet
from vespro.model import Model, model_from_arrays
from vespro.rig import Rig, RigCamera

VISP_MBT = Path("/usr/share/visp-images-data/ViSP-images/mbt")
RATE_HZ = 30.0  # the sequence's nominal rate (it carries no stamps)


def _numbers(line: str) -> list[float]:
    return [float(v) for v in line.split("#")[0].split()]


def read_cao(path: Path) -> tuple[np.ndarray, list[list[int]]]:
    """Points and point-indexed faces of a ``.cao`` model (version 1; lines, cylinders and
    circles are not read: the cube has none)."""
    rows = [r for r in (_numbers(x) for x in path.read_text().splitlines() if not x.startswith("V1")) if r]
    n = int(rows[0][0])
    pts = np.array(rows[1:1 + n], float)
    i = 1 + n
    n_lines = int(rows[i][0])
    i += 1 + n_lines
    n_face_lines = int(rows[i][0])
    i += 1 + n_face_lines
    n_faces = int(rows[i][0])
    faces = [[int(v) for v in rows[i + 1 + k][1:1 + int(rows[i + 1 + k][0])]] for k in range(n_faces)]
    return pts, faces


def model_from_cao(path: Path, name: str = "cube") -> Model:
    """A triangle model of a ``.cao`` solid (faces fanned into triangles, outward normals)."""
    pts, faces = read_cao(path)
    tris = [[f[0], f[j], f[j + 1]] for f in faces for j in range(1, len(f) - 1)]
    tris = np.array(tris, int)
    # Outward: each triangle's normal away from the solid's centre.
    c = pts.mean(axis=0)
    a, b, d = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    flip = np.einsum("ij,ij->i", np.cross(b - a, d - a), a - c) < 0
    tris[flip] = tris[flip][:, [0, 2, 1]]
    return model_from_arrays(pts, tris, name=name, source=str(path))


def intrinsics_from_xml(path: Path, width: int, height: int) -> CameraIntrinsics:
    cam = ET.parse(path).getroot().find("camera")
    px, py, u0, v0 = (float(cam.find(k).text) for k in ("px", "py", "u0", "v0"))
    return CameraIntrinsics(width, height, np.array([[px, 0, u0], [0, py, v0], [0, 0, 1.0]]))


def pose_from_pos(path: Path) -> np.ndarray:
    """cMo of a ViSP ``.pos`` file (tx ty tz, theta-u)."""
    v = np.array([float(x) for x in path.read_text().split()])
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(v[3:6])[0]
    T[:3, 3] = v[:3]
    return T


@dataclass
class Sequence:
    """A one-camera sequence in our types (camera ``cam0`` at the world origin)."""

    rig: Rig
    model: Model
    frames: list[Path]
    T_start: np.ndarray  # T_world_object at frame 0

    def frameset(self, i: int) -> FrameSet:
        img = cv2.imread(str(self.frames[i]), cv2.IMREAD_GRAYSCALE)
        return FrameSet(i, int(round(i * 1e9 / RATE_HZ)), {"cam0": img})

    def __len__(self) -> int:
        return len(self.frames)


def visp_cube() -> Sequence | None:
    """ViSP's cube sequence, or None where ``visp-images-data`` is not installed."""
    d = VISP_MBT
    frames = sorted((d / "cube").glob("image*.pgm"))
    if not frames:
        return None
    h, w = cv2.imread(str(frames[0]), cv2.IMREAD_GRAYSCALE).shape
    cam = RigCamera("cam0", intrinsics_from_xml(d / "cube.xml", w, h), "fixed", np.eye(4))
    return Sequence(Rig((cam,)), model_from_cao(d / "cube.cao"), frames, pose_from_pos(d / "cube.0.pos"))


def write_cao(model: Model, path: Path) -> None:
    """Our model as a ``.cao``: one point-face per planar face, its outer loop (ViSP tracks
    every polygon side as an edge, so triangles would add their diagonals). Each loop starts
    at a convex vertex: ViSP takes a polygon's normal from its first three points."""
    V = np.asarray(model.vertices)
    faces = []
    for f in model.faces:
        loop = np.asarray(f.loops[0])
        if len(f.loops) > 1:
            raise ValueError(f"{model.name}: a face with a hole has no .cao point-face")
        P = V[loop]
        turn = np.cross(P - np.roll(P, 1, axis=0), np.roll(P, -1, axis=0) - P) @ f.normal
        faces.append(np.roll(loop, -int(np.argmax(turn))))
    lines = ["V1", "# 3D points", str(len(V))]
    lines += [f"{x:.9g} {y:.9g} {z:.9g}" for x, y, z in V]
    lines += ["# 3D lines", "0", "# faces from lines", "0", "# faces from points", str(len(faces))]
    lines += [f"{len(lp)} " + " ".join(str(int(i)) for i in lp) for lp in faces]
    lines += ["# cylinders", "0", "# circles", "0", ""]
    path.write_text("\n".join(lines))


def write_tracker_xml(intr: CameraIntrinsics, path: Path) -> None:
    """A ViSP tracker settings file for one camera: moving edges and KLT as in ViSP's cube
    example (``cube.xml``), this camera's intrinsics (ViSP's tracker model has no distortion:
    our recordings' cameras have none)."""
    path.write_text(f"""<?xml version="1.0"?>
<conf>
  <ecm>
    <mask><size>5</size><nb_mask>180</nb_mask></mask>
    <range><tracking>7</tracking></range>
    <contrast><edge_threshold>5000</edge_threshold><mu1>0.5</mu1><mu2>0.5</mu2></contrast>
    <sample><step>4</step></sample>
  </ecm>
  <klt>
    <mask_border>5</mask_border><max_features>300</max_features><window_size>5</window_size>
    <quality>0.01</quality><min_distance>5</min_distance><harris>0.01</harris>
    <size_block>3</size_block><pyramid_lvl>3</pyramid_lvl>
  </klt>
  <camera><u0>{intr.cx:.9g}</u0><v0>{intr.cy:.9g}</v0><px>{intr.fx:.9g}</px><py>{intr.fy:.9g}</py></camera>
  <face>
    <angle_appear>65</angle_appear><angle_disappear>75</angle_disappear>
    <near_clipping>0.05</near_clipping><far_clipping>5.0</far_clipping><fov_clipping>1</fov_clipping>
  </face>
</conf>
""")
