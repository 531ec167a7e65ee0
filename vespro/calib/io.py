"""Files around calibration: image folders, pose CSV files, rig file updates.

Pose CSV (board placements, flange poses): a header row, then
``<key>,x,y,z,qw,qx,qy,qz`` per row, metres and a unit quaternion (scalar
first), the key an integer (the image's index) or a name (the image's stem).
"""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np

from ..camera import CameraIntrinsics
from ..rig import Rig, RigCamera, RigError, load_rig, save_rig
from ..se3 import pq_from_transform, transform_from_pq
from .errors import CalibrationError

__all__ = ["IMAGE_SUFFIXES", "list_images", "load_images", "read_pose_csv", "write_pose_csv",
           "update_rig_camera", "parse_pose"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
POSE_FIELDS = ["x", "y", "z", "qw", "qx", "qy", "qz"]


def list_images(folder: Path) -> list[Path]:
    """Image files directly in ``folder``, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CalibrationError(f"{folder}: image folder not found")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


def load_images(paths: list[Path]) -> dict[str, np.ndarray]:
    """Read images (as stored: grey or BGR), all of one size.

    Returns
    -------
    dict
        image stem -> ndarray (H, W) or (H, W, 3), uint8; in the order given.

    Raises
    ------
    CalibrationError
        No images, an unreadable file, or images of different sizes (the
        message lists the images of each size).
    """
    if not paths:
        raise CalibrationError("no images given")
    out, sizes = {}, {}
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise CalibrationError(f"{p}: cannot read the image")
        if img.dtype != np.uint8:
            img = cv2.convertScaleAbs(img, alpha=255.0 / max(1, int(img.max())))
        if img.ndim == 3 and img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        out[p.stem] = img
        sizes.setdefault((img.shape[1], img.shape[0]), []).append(p.name)
    if len(sizes) > 1:
        parts = "; ".join(f"{w}x{h}: {', '.join(names)}" for (w, h), names in sizes.items())
        raise CalibrationError(f"images of one camera must all have the same size, got {parts}")
    return out


def parse_pose(text: str, what: str = "pose") -> np.ndarray:
    """``T`` from ``"x,y,z,qw,qx,qy,qz"`` (m, unit quaternion scalar first)."""
    try:
        pq = np.array([float(v) for v in text.replace(" ", ",").split(",") if v], dtype=float)
    except ValueError:
        raise CalibrationError(f"{what}: expected 7 numbers x,y,z,qw,qx,qy,qz, got {text!r}") from None
    return _checked_pose(pq, what)


def _checked_pose(pq: np.ndarray, what: str) -> np.ndarray:
    if pq.shape != (7,) or not np.all(np.isfinite(pq)):
        raise CalibrationError(f"{what}: expected 7 finite numbers x,y,z,qw,qx,qy,qz, got {pq.tolist()}")
    n = np.linalg.norm(pq[3:])
    if abs(n - 1.0) > 1e-3:
        raise CalibrationError(f"{what}: quaternion (qw qx qy qz) must have unit norm, got norm {n:.6f}")
    return transform_from_pq(pq)


def read_pose_csv(path: Path, key: str) -> dict[str, np.ndarray]:
    """Poses from a CSV file with columns ``<key>,x,y,z,qw,qx,qy,qz``.

    Returns
    -------
    dict
        key as written (string) -> ndarray (4, 4). An integer key is also
        reachable as its zero-padded 6-digit string (the image stem).

    Raises
    ------
    CalibrationError
        Missing file or column, malformed number, non-unit quaternion,
        duplicate key; the message names the file and row.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: pose file not found")
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        cols = [key] + POSE_FIELDS
        missing = [c for c in cols if c not in (reader.fieldnames or [])]
        if missing:
            raise CalibrationError(f"{path}: missing column(s) {missing}; expected header {','.join(cols)}")
        out = {}
        for row_no, row in enumerate(reader, start=2):
            k = row[key].strip()
            try:
                pq = np.array([float(row[c]) for c in POSE_FIELDS])
            except (TypeError, ValueError):
                raise CalibrationError(f"{path}: line {row_no}: malformed number in {row}") from None
            T = _checked_pose(pq, f"{path}: line {row_no}")
            if k in out:
                raise CalibrationError(f"{path}: line {row_no}: duplicate {key} {k!r}")
            out[k] = T
    if not out:
        raise CalibrationError(f"{path}: no poses")
    return out


def lookup_pose(poses: dict[str, np.ndarray], stem: str) -> np.ndarray | None:
    """The pose of an image stem: by exact key, or by integer value (``7`` for ``000007``)."""
    if stem in poses:
        return poses[stem]
    try:
        n = int(stem)
    except ValueError:
        return None
    for k, T in poses.items():
        try:
            if int(k) == n:
                return T
        except ValueError:
            continue
    return None


def write_pose_csv(path: Path, poses: dict, key: str) -> None:
    """Write ``{key value: T (4, 4)}`` as ``<key>,x,y,z,qw,qx,qy,qz``."""
    with Path(path).open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([key] + POSE_FIELDS)
        for k, T in poses.items():
            w.writerow([k] + [f"{v:.9g}" for v in pq_from_transform(T)])


def update_rig_camera(path: Path, name: str, *, intrinsics: CameraIntrinsics | None = None,
                      T_world_camera: np.ndarray | None = None, link: str | None = None,
                      T_link_camera: np.ndarray | None = None) -> Rig:
    """Write or update one camera of a rig file, keeping the other cameras.

    Intrinsics replace the camera's; ``T_world_camera`` makes it a fixed
    camera, ``link`` + ``T_link_camera`` an eye-in-hand one. A camera not yet
    in the file needs intrinsics; when only intrinsics are known its mount is
    written as fixed at the identity pose until extrinsics or hand-eye
    calibration gives the real one.

    Returns
    -------
    Rig
        The rig as written.
    """
    path = Path(path)
    rig = load_rig(path) if path.is_file() else Rig(())
    old = rig[name] if name in rig.names else None
    intr = intrinsics if intrinsics is not None else (old.intrinsics if old else None)
    if intr is None:
        raise CalibrationError(f"{path}: camera {name!r} is not in the rig file; calibrate its intrinsics first "
                               f"(cameras in the file: {rig.names})")
    if T_world_camera is not None:
        cam = RigCamera(name, intr, "fixed", T_world_camera=T_world_camera)
    elif T_link_camera is not None:
        cam = RigCamera(name, intr, "eye_in_hand", link=link, T_link_camera=T_link_camera)
    elif old is not None:
        cam = RigCamera(name, intr, old.mount, old.T_world_camera, old.link, old.T_link_camera)
    else:
        cam = RigCamera(name, intr, "fixed", T_world_camera=np.eye(4))
    cams = [cam if c.name == name else c for c in rig]
    if old is None:
        cams.append(cam)
    new = Rig(tuple(cams))
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        save_rig(new, path)
    except RigError as e:
        raise CalibrationError(str(e)) from None
    return new
