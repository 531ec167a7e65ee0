"""The camera rig: intrinsics and mounting of every camera (``cameras.yaml``).

Format: shared/spec/recording.md. A fixed camera has ``T_world_camera``; an
eye-in-hand camera rides on a robot ``link`` at ``T_link_camera`` and its world
pose at each instant comes from the measured arm kinematics (``frames.csv``).
"""

from __future__ import annotations

from .errors import InputError, yaml_problem

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .camera import CameraIntrinsics
from .se3 import pq_from_transform, transform_from_pq

__all__ = ["RigCamera", "Rig", "RigError", "load_rig", "save_rig", "rig_from_dict", "rig_to_dict"]

MOUNTS = ("fixed", "eye_in_hand")


class RigError(InputError):
    """A rig file is missing, malformed or inconsistent; the message names file and field."""


def _ro(a):
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class RigCamera:
    """One camera of the rig.

    Attributes
    ----------
    name : str
    intrinsics : CameraIntrinsics
    mount : str
        ``"fixed"`` or ``"eye_in_hand"``.
    T_world_camera : ndarray (4, 4) or None
        Fixed cameras only.
    link : str or None
        Eye-in-hand only: the robot body the camera rides on.
    T_link_camera : ndarray (4, 4) or None
        Eye-in-hand only.
    """

    name: str
    intrinsics: CameraIntrinsics
    mount: str = "fixed"
    T_world_camera: np.ndarray | None = None
    link: str | None = None
    T_link_camera: np.ndarray | None = None

    def __post_init__(self):
        if self.mount not in MOUNTS:
            raise RigError(f"camera {self.name!r}: mount must be one of {MOUNTS}, got {self.mount!r}")
        if self.mount == "fixed":
            if self.T_world_camera is None:
                raise RigError(f"camera {self.name!r}: a fixed camera needs T_world_camera")
            object.__setattr__(self, "T_world_camera", _ro(self.T_world_camera))
        else:
            if self.T_link_camera is None or not self.link:
                raise RigError(f"camera {self.name!r}: an eye_in_hand camera needs link and T_link_camera")
            object.__setattr__(self, "T_link_camera", _ro(self.T_link_camera))

    @property
    def is_fixed(self) -> bool:
        return self.mount == "fixed"


@dataclass(frozen=True)
class Rig:
    """An ordered set of cameras with unique names."""

    cameras: tuple[RigCamera, ...]

    def __post_init__(self):
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise RigError(f"camera names must be unique, got {names}")
        object.__setattr__(self, "cameras", tuple(self.cameras))

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    @property
    def eye_in_hand(self) -> list[RigCamera]:
        return [c for c in self.cameras if not c.is_fixed]

    def __getitem__(self, name: str) -> RigCamera:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(f"no camera named {name!r} in rig {self.names}")

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self):
        return iter(self.cameras)

    def subset(self, names) -> "Rig":
        return Rig(tuple(self[n] for n in names))


def _field(d: dict, key: str, where: str) -> Any:
    if not isinstance(d, dict) or key not in d:
        raise RigError(f"{where}: missing field '{key}' (a camera needs name, image_width, image_height, "
                       "camera_matrix, mount and T_world_camera, or link and T_link_camera when eye_in_hand)"
                       if key != "cameras" else f"{where}: missing field 'cameras' (the list of the rig's cameras)")
    return d[key]


def _numbers(value, n: int, where: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=float).ravel()
    except (TypeError, ValueError):
        raise RigError(f"{where}: expected {n} numbers, got {value!r}") from None
    if a.shape != (n,):
        raise RigError(f"{where}: expected {n} numbers, got {a.size}")
    if not np.all(np.isfinite(a)):
        bad = ", ".join(f"element {i} is {v}" for i, v in enumerate(a) if not np.isfinite(v))
        raise RigError(f"{where}: {bad}; every value must be a finite number")
    return a


def _pose(value, where: str) -> np.ndarray:
    pq = _numbers(value, 7, where)
    n = np.linalg.norm(pq[3:])
    if abs(n - 1.0) > 1e-3:
        raise RigError(f"{where}: quaternion (elements 3-6, qw qx qy qz) must have unit norm, got norm {n:.6f}; "
                       "give the pose as x y z qw qx qy qz with a normalised quaternion")
    return transform_from_pq(pq)


def rig_from_dict(data: dict, source: str = "cameras.yaml") -> Rig:
    """Build a rig from parsed YAML; errors name ``source`` and the field."""
    cams = _field(data, "cameras", source)
    if not isinstance(cams, list) or not cams:
        raise RigError(f"{source}: 'cameras' must be a non-empty list")
    out = []
    for i, c in enumerate(cams):
        where = f"{source}: cameras[{i}]"
        name = str(_field(c, "name", where))
        where = f"{source}: camera '{name}'"
        w = _field(c, "image_width", where)
        h = _field(c, "image_height", where)
        if not isinstance(w, int) or not isinstance(h, int) or w <= 0 or h <= 0:
            raise RigError(f"{where}: image_width/image_height must be positive integers, got {w!r}x{h!r}")
        K = _numbers(_field(c, "camera_matrix", where), 9, f"{where}: camera_matrix").reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise RigError(f"{where}: camera_matrix: focal lengths fx (element 0) and fy (element 4) must be positive, "
                           f"got fx={K[0, 0]:g}, fy={K[1, 1]:g} (pixels); copy the matrix K of the camera's "
                           "calibration, row-major")
        model = c.get("distortion_model", "plumb_bob")
        if model != "plumb_bob":
            raise RigError(f"{where}: distortion_model {model!r} is not supported (only plumb_bob)")
        dist = _numbers(c.get("distortion_coefficients", [0] * 5), 5, f"{where}: distortion_coefficients")
        try:
            intr = CameraIntrinsics(w, h, K, dist)
        except ValueError as e:
            raise RigError(f"{where}: camera_matrix: {e}") from None
        mount = c.get("mount", "fixed")
        if mount == "fixed":
            T = _pose(_field(c, "T_world_camera", where), f"{where}: T_world_camera")
            out.append(RigCamera(name, intr, "fixed", T_world_camera=T))
        elif mount == "eye_in_hand":
            link = str(_field(c, "link", where))
            T = _pose(_field(c, "T_link_camera", where), f"{where}: T_link_camera")
            out.append(RigCamera(name, intr, "eye_in_hand", link=link, T_link_camera=T))
        else:
            raise RigError(f"{where}: mount must be 'fixed' (a camera standing in the cell, with T_world_camera) "
                           f"or 'eye_in_hand' (on the robot, with link and T_link_camera), got {mount!r}")
    try:
        return Rig(tuple(out))
    except RigError as e:
        raise RigError(f"{source}: {e}") from None


def load_rig(path: str | Path) -> Rig:
    """Read a ``cameras.yaml`` rig file.

    Raises
    ------
    RigError
        Missing file, YAML syntax error, missing or malformed field; the message
        names the file and the field.
    """
    path = Path(path)
    if not path.is_file():
        raise RigError(f"{path}: rig file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise RigError(f"{path}: not valid YAML: {yaml_problem(e)}; fix the syntax there") from None
    return rig_from_dict(data, str(path))


def _fmt(a) -> list[float]:
    return [float(f"{x:.9g}") for x in np.asarray(a).ravel()]


def rig_to_dict(rig: Rig) -> dict:
    cams = []
    for c in rig:
        d = {
            "name": c.name,
            "image_width": c.intrinsics.width,
            "image_height": c.intrinsics.height,
            "camera_matrix": _fmt(c.intrinsics.K),
            "distortion_model": "plumb_bob",
            "distortion_coefficients": _fmt(c.intrinsics.dist),
            "mount": c.mount,
        }
        if c.is_fixed:
            d["T_world_camera"] = _fmt(pq_from_transform(c.T_world_camera))
        else:
            d["link"] = c.link
            d["T_link_camera"] = _fmt(pq_from_transform(c.T_link_camera))
        cams.append(d)
    return {"cameras": cams}


class _FlowListDumper(yaml.SafeDumper):
    pass


def _repr_list(dumper, data):
    if all(isinstance(x, (int, float)) for x in data):
        return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=True)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data)


_FlowListDumper.add_representer(list, _repr_list)


def dump_yaml(data: dict) -> str:
    """YAML with number lists in flow style, as in the spec's examples."""
    return yaml.dump(data, Dumper=_FlowListDumper, sort_keys=False)


def save_rig(rig: Rig, path: str | Path) -> None:
    """Write a ``cameras.yaml`` rig file."""
    Path(path).write_text(dump_yaml(rig_to_dict(rig)))
