"""The standard rig files in ``cameras/``, exported from the cell's MuJoCo cameras.

:func:`rig_path` finds one by name (or takes a rig file's path), as the commands do.

``python -m vespro.sim.rigs`` rewrites them; a test checks they still match
``models/cell.xml`` and ``models/arm.xml``. Intrinsics come from each MuJoCo
camera's ``fovy`` and the resolution (square pixels, centred principal point);
extrinsics are converted from MuJoCo's camera frame (-z forward, y up) to the
OpenCV optical frame.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from ..camera import CameraIntrinsics
from ..rig import Rig, RigCamera, save_rig
from ..se3 import matrix_from_quat, transform_from_rt
from .scene import CELL_XML, T_CAMERA_GL

__all__ = ["STANDARD_RIGS", "CAMERAS_DIR", "rig_path", "rig_from_model", "write_standard_rigs"]

CAMERAS_DIR = Path(__file__).resolve().parents[2] / "cameras"

#: file stem -> MuJoCo camera names.
STANDARD_RIGS = {
    "fixed1": ["cam_left"],
    "fixed2": ["cam_left", "cam_right"],
    "fixed3": ["cam_left", "cam_right", "cam_top"],
    "hand": ["hand"],
    "hybrid": ["cam_left", "cam_right", "hand"],
}


def rig_path(name_or_path: str) -> Path:
    """A rig file: an existing path, or a standard rig name in ``cameras/``."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    q = CAMERAS_DIR / f"{name_or_path}.yaml"
    if q.is_file():
        return q
    names = sorted(x.stem for x in CAMERAS_DIR.glob("*.yaml"))
    raise ValueError(f"no rig {name_or_path!r}; standard rigs: {', '.join(names)} (or give a cameras.yaml path)")


def rig_from_model(model: mujoco.MjModel, names: list[str], width: int = 640, height: int = 480) -> Rig:
    """A rig of the named MuJoCo cameras at a resolution.

    Cameras on the world body are fixed; cameras on another body are
    eye-in-hand on that body (``link``).
    """
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    cams = []
    for name in names:
        c = model.camera(name)
        intr = CameraIntrinsics.from_fovy(width, height, float(c.fovy[0]))
        body = int(c.bodyid[0])
        if body == 0:
            T_gl = transform_from_rt(data.cam_xmat[c.id].reshape(3, 3).copy(), data.cam_xpos[c.id].copy())
            cams.append(RigCamera(name, intr, "fixed", T_world_camera=T_gl @ T_CAMERA_GL))
        else:
            T_gl = transform_from_rt(matrix_from_quat(c.quat), np.array(c.pos))
            link = model.body(body).name
            cams.append(RigCamera(name, intr, "eye_in_hand", link=link, T_link_camera=T_gl @ T_CAMERA_GL))
    return Rig(tuple(cams))


def write_standard_rigs(out_dir: Path = CAMERAS_DIR, width: int = 640, height: int = 480) -> list[Path]:
    model = mujoco.MjModel.from_xml_path(str(CELL_XML))
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for stem, names in STANDARD_RIGS.items():
        p = out_dir / f"{stem}.yaml"
        save_rig(rig_from_model(model, names, width, height), p)
        paths.append(p)
    return paths


if __name__ == "__main__":
    for p in write_standard_rigs():
        print(p)
