"""ViSP data in vespro's terms: camera ``.xml``, ``.pos`` poses, tutorial folders.

ViSP's model-based tracker tutorials keep, in one folder, an image sequence
(``cube/image0000.pgm`` ...), the model ``cube.cao`` (metres), the camera in
``cube.xml`` and often a start pose ``cube.0.pos``. ``import_visp`` turns such
a folder into a recording (``shared/spec/recording.md``, version 1) with one
fixed camera ``cam0`` whose frame is the world frame, so ViSP's ``cMo``
(T_camera_object) is the object's world pose.

Camera model: ViSP projects ``u = u0 + px * x * (1 + kud * r^2)``,
``v = v0 + py * y * (1 + kud * r^2)`` (``x, y`` normalised, ``r^2 = x^2 + y^2``),
which is OpenCV's plumb_bob with ``k1 = kud`` and the other coefficients zero:
the mapping is exact for projection. ``kdu`` (ViSP's approximate inverse) is
not used; OpenCV inverts ``k1`` iteratively.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import CameraIntrinsics
from .errors import InputError
from .se3 import exp_so3, transform_from_rt

__all__ = ["VispError", "VispCamera", "read_visp_camera", "read_visp_pose", "image_sequence", "import_visp"]

#: Image files ViSP's readers take, in the order we look for them.
IMAGE_SUFFIXES = (".pgm", ".ppm", ".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class VispError(InputError):
    """A ViSP file or folder that cannot be used; the message names it."""


@dataclass(frozen=True)
class VispCamera:
    """ViSP camera parameters (pixels); ``kud`` is None for the model without distortion."""

    px: float
    py: float
    u0: float
    v0: float
    kud: float | None = None
    kdu: float | None = None
    width: int | None = None
    height: int | None = None

    def intrinsics(self, width: int, height: int) -> CameraIntrinsics:
        """OpenCV intrinsics: K from px, py, u0, v0; plumb_bob ``[kud, 0, 0, 0, 0]``."""
        K = np.array([[self.px, 0.0, self.u0], [0.0, self.py, self.v0], [0.0, 0.0, 1.0]])
        return CameraIntrinsics(width, height, K, [self.kud or 0.0, 0.0, 0.0, 0.0, 0.0])


def _number(el, tag: str, where: str, required: bool = True):
    node = el.find(tag)
    if node is None or node.text is None or not node.text.strip():
        if required:
            raise VispError(f"{where}: no <{tag}> value")
        return None
    try:
        v = float(node.text.strip())
    except ValueError:
        raise VispError(f"{where}: <{tag}> must be a number, got {node.text.strip()!r}") from None
    if not np.isfinite(v):
        raise VispError(f"{where}: <{tag}> must be finite, got {v}")
    return v


def read_visp_camera(path) -> tuple[VispCamera, str]:
    """Camera parameters from a ViSP ``.xml`` file.

    Two layouts are read: the tracker settings file (``<conf><camera>`` with
    ``u0 v0 px py``) and ``vpXmlParserCamera``'s file (``<root><camera>`` with
    ``image_width``, ``image_height`` and ``<model>`` entries of type
    ``perspectiveProjWithoutDistortion`` / ``perspectiveProjWithDistortion``).
    When both models are given the one with distortion is taken: it describes
    the raw images.

    Returns
    -------
    VispCamera
    note : str
        Which model was taken (one line, for the user).

    Raises
    ------
    VispError
        Missing or malformed file, missing or non-numeric field, a focal
        length that is not positive.
    """
    import xml.etree.ElementTree as ET

    path = Path(path)
    if not path.is_file():
        raise VispError(f"{path}: no such camera file")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise VispError(f"{path}: not a well-formed XML file ({e})") from None
    cam = root if root.tag == "camera" else root.find("camera")
    if cam is None:
        raise VispError(f"{path}: no <camera> element (expected a ViSP camera or tracker settings file)")
    width = _number(cam, "image_width", str(path), required=False)
    height = _number(cam, "image_height", str(path), required=False)
    models = {}
    for m in cam.findall("model"):
        kind = (m.findtext("type") or "").strip()
        models[kind] = m
    if models:
        with_d = models.get("perspectiveProjWithDistortion")
        m = with_d if with_d is not None else models.get("perspectiveProjWithoutDistortion")
        if m is None:
            raise VispError(f"{path}: <model> <type> must be perspectiveProjWithDistortion or "
                            f"perspectiveProjWithoutDistortion, got {sorted(models)}")
        where = f"{path}: <model> {(m.findtext('type') or '').strip()}"
    else:
        m, where = cam, f"{path}: <camera>"
    vals = {k: _number(m, k, where) for k in ("px", "py", "u0", "v0")}
    kud = _number(m, "kud", where, required=False)
    kdu = _number(m, "kdu", where, required=False)
    if vals["px"] <= 0 or vals["py"] <= 0:
        raise VispError(f"{where}: focal lengths px, py must be positive, got {vals['px']}, {vals['py']}")
    c = VispCamera(**vals, kud=kud, kdu=kdu, width=None if width is None else int(width),
                   height=None if height is None else int(height))
    if kud is None:
        note = f"camera {path.name}: px={c.px:g} py={c.py:g} u0={c.u0:g} v0={c.v0:g}, no distortion"
    else:
        note = (f"camera {path.name}: the model with distortion (kud={kud:g} -> plumb_bob k1, exact for projection; "
                f"kdu unused)")
    return c, note


def read_visp_pose(path) -> np.ndarray:
    """``T_camera_object`` (ViSP's cMo) from a ``.pos`` file.

    The file holds six numbers, translation (m) then theta-u rotation vector
    (rad), separated by white space; text after ``#`` is a comment.

    Raises
    ------
    VispError
        Missing file, fewer or more than six numbers, non-numeric text.
    """
    path = Path(path)
    if not path.is_file():
        raise VispError(f"{path}: no such pose file")
    vals = []
    for k, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        for tok in line.split("#", 1)[0].split():
            try:
                vals.append(float(tok))
            except ValueError:
                raise VispError(f"{path}:{k}: expected a number, got {tok!r}") from None
    if len(vals) != 6 or not np.all(np.isfinite(vals)):
        raise VispError(f"{path}: expected 6 finite numbers (tx ty tz, then theta-u in rad), got {vals}")
    return transform_from_rt(exp_so3(vals[3:]), vals[:3])


def image_sequence(folder) -> list[Path]:
    """Image files of a sequence folder, in the order of the number in their names.

    Raises
    ------
    VispError
        Missing folder, no image files.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise VispError(f"{folder}: no such image folder")
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    if not files:
        raise VispError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")

    def key(p: Path):
        nums = re.findall(r"\d+", p.stem)
        return (int(nums[-1]) if nums else -1, p.name)

    return sorted(files, key=key)


def _read_image(path: Path, shape) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise VispError(f"{path}: cannot read the image (unreadable or truncated)")
    if img.dtype != np.uint8:
        raise VispError(f"{path}: {img.dtype} image; recordings take 8-bit grey or colour images")
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if shape is not None and img.shape[:2] != shape:
        raise VispError(f"{path}: image size {img.shape[1]}x{img.shape[0]} differs from the first image's "
                        f"{shape[1]}x{shape[0]}")
    return img


def _pick_name(folder: Path) -> str:
    names = sorted(p.stem for p in folder.glob("*.cao"))
    if len(names) == 1:
        return names[0]
    if not names:
        raise VispError(f"{folder}: no .cao model in the folder")
    raise VispError(f"{folder}: holds several models ({', '.join(names)}): choose one with --name")


def import_visp(folder, out=None, name: str | None = None, rate_hz: float = 30.0, images=None, camera=None,
                pose=None, frames: int | None = None, unit: str = "m", overwrite: bool = False,
                progress=None) -> dict:
    """Write a ViSP tutorial folder as a recording.

    Parameters
    ----------
    folder : str or Path
        Holds ``NAME.cao``, ``NAME.xml``, optionally ``NAME.0.pos``, and the
        image sequence folder ``NAME/``.
    out : str or Path, optional
        Recording folder to create (default ``out/NAME``).
    name : str, optional
        The sequence; defaults to the folder's only ``.cao`` stem.
    rate_hz : float
        Capture rate to stamp the frames with (ViSP sequences carry none), Hz.
    images, camera, pose : str or Path, optional
        Override ``NAME/``, ``NAME.xml`` and ``NAME.0.pos``.
    frames : int, optional
        Import only the first ``frames`` images.
    unit : str
        Unit of the ``.cao`` (ViSP models are in metres).
    overwrite : bool
        Replace a non-empty ``out``.
    progress : callable, optional
        Wraps the image iterator (e.g. tqdm).

    Returns
    -------
    dict
        ``recording`` (Path), ``frames`` (int), ``init_pose`` (Path or None),
        ``T_world_object`` (4x4 or None), ``notes`` (list of str).

    Raises
    ------
    VispError, ModelError
        Bad input, one line naming the file.
    FileExistsError
        ``out`` exists, is not empty and ``overwrite`` is False.
    """
    from .frames import FrameSet
    from .model import load_model, model_file_in_metres
    from .recording import RecordingWriter
    from .rig import Rig, RigCamera
    from .se3 import pq_from_transform

    folder = Path(folder)
    if not folder.is_dir():
        raise VispError(f"{folder}: no such folder")
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise VispError(f"--rate must be a positive number of Hz, got {rate_hz}")
    name = name or _pick_name(folder)
    cao = folder / f"{name}.cao"
    if not cao.is_file():
        raise VispError(f"{cao}: no such model (give the sequence name with --name)")
    if not images and not (folder / name).is_dir():
        raise VispError(f"{folder / name}: no such image folder (the sequence NAME/ next to NAME.cao; "
                        f"give another with --images)")
    seq = image_sequence(Path(images) if images else folder / name)
    if frames is not None:
        if frames <= 0:
            raise VispError(f"--frames must be positive, got {frames}")
        seq = seq[:frames]
    vcam, cam_note = read_visp_camera(Path(camera) if camera else folder / f"{name}.xml")
    notes = [cam_note]
    pose_path = Path(pose) if pose else folder / f"{name}.0.pos"
    T_co = read_visp_pose(pose_path) if (pose or pose_path.is_file()) else None
    if (folder / f"{name}.init").is_file():
        notes.append(f"{name}.init (3D points for ViSP's click start) is not used: the start pose comes from "
                     f"{pose_path.name}" + ("" if T_co is not None else " (missing) or the automatic start"))

    first = _read_image(seq[0], None)
    h, w = first.shape[:2]
    if vcam.width is not None and (vcam.width, vcam.height) != (w, h):
        raise VispError(f"camera file: image_width x image_height {vcam.width}x{vcam.height} differs from the "
                        f"images' {w}x{h} ({seq[0]})")
    try:
        intr = vcam.intrinsics(w, h)
    except ValueError as e:
        raise VispError(f"camera file: {e}") from None
    model_file = model_file_in_metres(cao, unit)
    model = load_model(model_file, name=name)
    if T_co is not None:
        depth = (np.c_[model.vertices, np.ones(len(model.vertices))] @ T_co.T)[:, 2]
        if np.any(depth <= 0):
            notes.append(f"{pose_path.name}: part of the model lies behind the camera at this pose; check the pose")
    rig = Rig((RigCamera("cam0", intr, "fixed", T_world_camera=np.eye(4)),))
    out = Path(out) if out is not None else Path("out") / name
    writer = RecordingWriter(out, rig, model_file, rate_hz, name, overwrite=overwrite,
                             extra_meta={"source": f"ViSP folder {folder.resolve()}"})
    it = enumerate(seq)
    if progress is not None:
        it = progress(it, total=len(seq))
    with writer:
        for i, p in it:
            img = first if i == 0 else _read_image(p, (h, w))
            writer.write(FrameSet(i, int(round(i * 1e9 / rate_hz)), {"cam0": img}))
    init_path = None
    if T_co is not None:
        init_path = out / "init_pose.txt"
        pq = pq_from_transform(T_co)
        init_path.write_text(f"# T_world_object at frame 0 (world = camera cam0), from {pose_path.name} "
                             f"(ViSP cMo): x,y,z,qw,qx,qy,qz\n" + ",".join(f"{v:.9f}" for v in pq) + "\n")
    return {"recording": out, "frames": len(seq), "init_pose": init_path, "T_world_object": T_co, "notes": notes}
