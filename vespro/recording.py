"""Recordings on disk: the format of shared/spec/recording.md, version 1.

::

    <recording>/
      meta.yaml            format, version, rate_hz, model, object
      cameras.yaml         the rig (see vespro.rig)
      model.<stl|obj|ply>  the object's CAD model, metres
      frames.csv           index,t[,<cam>.x,<cam>.y,<cam>.z,<cam>.qw,<cam>.qx,<cam>.qy,<cam>.qz ...]
      groundtruth.csv      optional; written and read by vespro.groundtruth only
      frames/<camera>/<index:06d>.png

:class:`Recording` reads everything a tracker may use and nothing else: it
never opens ``groundtruth.csv`` (see :mod:`vespro.groundtruth`, for evaluators).
:class:`RecordingWriter` writes the same layout.

Errors name the file and the field (:class:`RecordingError`). A missing or
unusable image (truncated, unreadable, of another size than the rig's, not
8-bit) is not an error: :meth:`Recording.image` returns None and counts it
per camera and reason in :attr:`Recording.images` (see
:mod:`vespro.imagecheck`), and the tracker does without that camera for that
instant. Images on disk past the last row of ``frames.csv`` (a frames.csv cut
short) are not read; :attr:`Recording.warnings` says how many there are.
"""

from __future__ import annotations

from .errors import InputError

import csv
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import yaml

from .errors import yaml_problem
from .frames import FrameSet
from .imagecheck import ImageRead, ImageTally, check_image, read_image
from .rig import Rig, RigError, load_rig, save_rig
from .se3 import pq_from_transform, transform_from_pq

__all__ = ["RecordingError", "Recording", "RecordingWriter", "AsyncRecordingWriter", "FORMAT", "VERSION",
           "MODEL_EXTS", "pose_columns"]

FORMAT = "vespro-recording"
VERSION = 1
MODEL_EXTS = (".stl", ".obj", ".ply")
POSE_FIELDS = ("x", "y", "z", "qw", "qx", "qy", "qz")


class RecordingError(InputError):
    """A recording is missing a file or has a malformed one; the message names file and field."""


def pose_columns(name: str) -> list[str]:
    """``frames.csv`` column names of an eye-in-hand camera's pose."""
    return [f"{name}.{f}" for f in POSE_FIELDS]


def _fmt(x: float) -> str:
    return f"{x:.9f}"


class Recording:
    """A recording opened for reading (tracker side).

    Parameters
    ----------
    path : str or Path
        The recording folder.

    Attributes
    ----------
    path : Path
    meta : dict
        Parsed ``meta.yaml``.
    rig : Rig
    model_path : Path
    rate_hz : float
    object_name : str
    index : ndarray, shape (N,), int
    t : ndarray, shape (N,), float
        Capture times, s.
    images : ImageTally
        Per camera, how many images read so far were usable, and how many
        not, per reason.
    missing : dict[str, int]
        Per camera, how many images were missing or not usable so far.
    warnings : list of str
        Things a user should know that do not stop a run (one line each,
        naming the file): images past the end of ``frames.csv``.

    Raises
    ------
    RecordingError
        Missing folder or required file, or a malformed field.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_dir():
            raise RecordingError(f"{self.path}: recording folder not found")
        self.meta = self._read_meta()
        try:
            self.rig: Rig = load_rig(self.path / "cameras.yaml")
        except RigError as e:
            raise RecordingError(str(e)) from None
        self.model_path = self._model_path()
        self.index, self.t, self._eih = self._read_frames()
        self._frames_dir = os.path.join(os.fspath(self.path), "frames")
        self.images = ImageTally(self.rig.names)
        self.warnings: list[str] = self._images_past_end()

    @property
    def missing(self) -> dict[str, int]:
        return {c: self.images.n_rejected(c) for c in self.rig.names}

    # -- parsing -----------------------------------------------------------
    def _read_meta(self) -> dict:
        p = self.path / "meta.yaml"
        if not p.is_file():
            raise RecordingError(f"{p}: missing (every recording needs meta.yaml)")
        try:
            meta = yaml.safe_load(p.read_text())
        except yaml.YAMLError as e:
            raise RecordingError(f"{p}: not valid YAML: {yaml_problem(e)}; fix the syntax there") from None
        if not isinstance(meta, dict):
            raise RecordingError(f"{p}: expected a mapping of fields, got {type(meta).__name__}")
        for key in ("format", "version", "rate_hz", "model"):
            if key not in meta:
                raise RecordingError(f"{p}: missing field '{key}'")
        if meta["format"] != FORMAT:
            raise RecordingError(f"{p}: field 'format' must be '{FORMAT}', got {meta['format']!r}")
        if meta["version"] != VERSION:
            raise RecordingError(f"{p}: field 'version': this reader knows version {VERSION}, got {meta['version']!r}")
        rate = meta["rate_hz"]
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not np.isfinite(rate) or rate <= 0:
            raise RecordingError(f"{p}: field 'rate_hz' must be a positive number, got {rate!r}")
        if not isinstance(meta["model"], str) or not meta["model"]:
            raise RecordingError(f"{p}: field 'model' must be a file name, got {meta['model']!r}")
        return meta

    def _model_path(self) -> Path:
        rel = self.meta["model"]
        p = (self.path / rel)
        if Path(rel).is_absolute() or ".." in Path(rel).parts:
            raise RecordingError(f"{self.path / 'meta.yaml'}: field 'model' must be a path inside the recording, got {rel!r}")
        if p.suffix.lower() not in MODEL_EXTS:
            raise RecordingError(f"{self.path / 'meta.yaml'}: field 'model': {rel!r} is not one of {MODEL_EXTS}")
        if not p.is_file():
            raise RecordingError(f"{p}: model file named by meta.yaml field 'model' is missing")
        return p

    def _read_frames(self):
        p = self.path / "frames.csv"
        if not p.is_file():
            raise RecordingError(f"{p}: missing (every recording needs frames.csv)")
        with open(p, newline="") as f:
            rows = list(csv.reader(f))
        if not rows:
            raise RecordingError(f"{p}: empty (expected a header row 'index,t,...')")
        header = [h.strip() for h in rows[0]]
        if header[:2] != ["index", "t"]:
            raise RecordingError(f"{p}: header must start with 'index,t', got {','.join(header[:2])!r}")
        col = {h: i for i, h in enumerate(header)}
        eih_cols = {}
        for cam in self.rig.eye_in_hand:
            names = pose_columns(cam.name)
            missing = [n for n in names if n not in col]
            if missing:
                raise RecordingError(f"{p}: eye_in_hand camera '{cam.name}' needs column(s) {', '.join(missing)}")
            eih_cols[cam.name] = [col[n] for n in names]
        body = [r for r in rows[1:] if r and any(x.strip() for x in r)]
        if not body:
            raise RecordingError(f"{p}: no frames (only a header)")
        n = len(body)
        index = np.empty(n, dtype=np.int64)
        t = np.empty(n)
        eih = {name: np.empty((n, 4, 4)) for name in eih_cols}
        for k, r in enumerate(body):
            line = k + 2
            if len(r) < len(header):
                raise RecordingError(f"{p}: line {line}: expected {len(header)} fields, got {len(r)}")
            try:
                index[k] = int(r[0])
            except ValueError:
                raise RecordingError(f"{p}: line {line}: field 'index' is not an integer: {r[0]!r}") from None
            if index[k] != k:
                what = (f"the row of index {k} is missing" if index[k] == k + 1 else
                        f"the rows of indices {k}-{index[k] - 1} are missing" if index[k] > k else
                        f"index {index[k]} comes again or out of order")
                raise RecordingError(f"{p}: line {line}: field 'index' is {index[k]} where {k} was due: {what} "
                                     "(indices start at 0 and increase by one, one row per capture instant; "
                                     "an instant without images still has its row)")
            try:
                t[k] = float(r[1])
            except ValueError:
                raise RecordingError(f"{p}: line {line}: field 't' is not a number: {r[1]!r}") from None
            if not np.isfinite(t[k]) or (k > 0 and t[k] < t[k - 1]):
                raise RecordingError(f"{p}: line {line}: field 't' must be finite and non-decreasing, got {r[1]!r}"
                                     + (f" after {t[k - 1]:.9g}" if k > 0 else "")
                                     + ": times are seconds since the first capture, in capture order")
            for name, cols in eih_cols.items():
                try:
                    pq = np.array([float(r[c]) for c in cols])
                except ValueError:
                    raise RecordingError(f"{p}: line {line}: pose of camera '{name}' has a non-number") from None
                if not np.all(np.isfinite(pq)):
                    bad = [header[c] for c, v in zip(cols, pq) if not np.isfinite(v)]
                    raise RecordingError(f"{p}: line {line}: field(s) {', '.join(bad)} not finite: the eye_in_hand "
                                         f"camera '{name}' needs the arm's measured pose at every row")
                if abs(np.linalg.norm(pq[3:]) - 1.0) > 1e-3:
                    raise RecordingError(f"{p}: line {line}: pose of camera '{name}': quaternion "
                                         f"{name}.qw..{name}.qz must have unit norm, got {np.linalg.norm(pq[3:]):.6f}")
                eih[name][k] = transform_from_pq(pq)
        for a in eih.values():
            a.setflags(write=False)
        return index, t, eih

    # -- access --------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.index)

    @property
    def rate_hz(self) -> float:
        return float(self.meta["rate_hz"])

    @property
    def object_name(self) -> str:
        return str(self.meta.get("object", self.model_path.stem))

    def image_path(self, camera: str, index: int) -> Path:
        return Path(self._image_file(camera, index))

    def _image_file(self, camera: str, index: int) -> str:
        # A plain string, built without pathlib: pathlib interns every part of a
        # path (CPython's sys.intern), so a server replaying for hours would
        # churn the interned-string table with a new name per frame, and that
        # table is rebuilt larger, never smaller, as the churn fills it.
        return f"{self._frames_dir}{os.sep}{camera}{os.sep}{index:06d}.png"

    def image(self, camera: str, index: int) -> np.ndarray | None:
        """The image of ``camera`` at ``index`` (grey or BGR uint8), or None if missing or unusable.

        Unusable: truncated, unreadable, not 8-bit, or of another size than
        the rig's (never rescaled silently). Every read is counted in
        :attr:`images`.
        """
        intr = self.rig[camera].intrinsics
        res = read_image(self._image_file(camera, index), intr.width, intr.height)
        self.images.note(camera, res)
        return res.image

    def check_image(self, camera: str, index: int) -> ImageRead:
        """:meth:`image`'s checks without decoding (for copying files); counted in :attr:`images`."""
        intr = self.rig[camera].intrinsics
        res = check_image(self._image_file(camera, index), intr.width, intr.height)
        self.images.note(camera, res)
        return res

    def _images_past_end(self) -> list[str]:
        """A warning when the image folders hold indices past the last row of frames.csv."""
        n = len(self.index)
        extra = {}
        for c in self.rig.names:
            d = self.path / "frames" / c
            if not d.is_dir():
                continue
            past = [int(f.stem) for f in d.iterdir() if f.suffix == ".png" and f.stem.isdigit() and int(f.stem) >= n]
            if past:
                extra[c] = (len(past), max(past))
        if not extra:
            return []
        counts = ", ".join(f"frames/{c} {k} (up to index {m})" for c, (k, m) in extra.items())
        return [f"{self.path / 'frames.csv'}: lists {n} frames (indices 0-{n - 1}) but the image folders hold "
                f"images past its end: {counts}; only the {n} listed frames are used (a frames.csv cut short?): "
                "add their rows to frames.csv to use them"]

    def T_world_camera(self, camera: str, index: int) -> np.ndarray:
        """Camera pose at ``index``: the rig's for fixed cameras, frames.csv's for eye-in-hand."""
        cam = self.rig[camera]
        return cam.T_world_camera if cam.is_fixed else self._eih[camera][index]

    def frameset(self, index: int) -> FrameSet:
        """All cameras' frames at ``index`` (images decoded now)."""
        images = {c.name: self.image(c.name, index) for c in self.rig}
        poses = {name: a[index] for name, a in self._eih.items()}
        return FrameSet(int(index), int(round(self.t[index] * 1e9)), images, poses)

    def __iter__(self):
        for i in range(len(self)):
            yield self.frameset(i)


class RecordingWriter:
    """Write a recording in the spec's layout.

    Parameters
    ----------
    path : Path
        Folder to create (must not exist or be empty, unless ``overwrite``).
    rig : Rig
    model_src : Path
        CAD file to copy in as ``model.<ext>``.
    rate_hz : float
    object_name : str
    overwrite : bool
    """

    def __init__(self, path: str | Path, rig: Rig, model_src: str | Path, rate_hz: float, object_name: str,
                 overwrite: bool = False, extra_meta: dict | None = None, png_compression: int = 3,
                 defer_png: bool = False):
        self.path = Path(path)
        # defer_png: keep images as raw arrays in a spool folder while recording (0.4 ms an image
        # instead of 3-8 ms of PNG encoding) and encode them on close: for live loops whose CPU
        # is short while they run. Until close the folder is not a complete recording.
        self._spool = self.path / ".spool" if defer_png else None
        # Run-length strategy: on rendered and camera frames (large flat areas) it is smaller
        # than zlib's default strategy at levels 1-3 and about a fifth cheaper to encode.
        self._png = [cv2.IMWRITE_PNG_COMPRESSION, int(png_compression), cv2.IMWRITE_PNG_STRATEGY,
                     cv2.IMWRITE_PNG_STRATEGY_RLE]
        if self.path.exists() and any(self.path.iterdir()):
            if not overwrite:
                raise FileExistsError(f"{self.path}: exists and is not empty (use overwrite)")
            shutil.rmtree(self.path)
        self.path.mkdir(parents=True, exist_ok=True)
        self.rig = rig
        model_src = Path(model_src)
        ext = model_src.suffix.lower()
        if ext not in MODEL_EXTS:
            raise ValueError(f"{model_src}: model must be one of {MODEL_EXTS}")
        shutil.copyfile(model_src, self.path / f"model{ext}")
        meta = {"format": FORMAT, "version": VERSION, "rate_hz": float(rate_hz), "model": f"model{ext}",
                "object": object_name}
        meta.update(extra_meta or {})
        (self.path / "meta.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
        save_rig(rig, self.path / "cameras.yaml")
        for c in rig:
            (self.path / "frames" / c.name).mkdir(parents=True, exist_ok=True)
            if self._spool is not None:
                (self._spool / c.name).mkdir(parents=True, exist_ok=True)
        self._eih = [c.name for c in rig.eye_in_hand]
        self._frames = open(self.path / "frames.csv", "w", newline="")
        self._csv = csv.writer(self._frames, lineterminator="\n")
        self._csv.writerow(["index", "t"] + [c for n in self._eih for c in pose_columns(n)])
        self._next = 0
        self._t0_ns: int | None = None

    def write(self, fs: FrameSet) -> None:
        """Append one frame set (indices must follow 0, 1, 2, ...)."""
        if fs.index != self._next:
            raise ValueError(f"frame set index {fs.index} out of order (expected {self._next})")
        if self._t0_ns is None:
            self._t0_ns = fs.t_ns
        for c in self.rig:
            img = fs.images.get(c.name)
            if img is not None:
                if self._spool is not None:
                    np.save(self._spool / c.name / f"{fs.index:06d}.npy", img)
                elif not cv2.imwrite(str(self.path / "frames" / c.name / f"{fs.index:06d}.png"), img, self._png):
                    raise OSError(f"could not write image of camera {c.name} at index {fs.index}")
        row = [str(fs.index), _fmt((fs.t_ns - self._t0_ns) * 1e-9)]
        for name in self._eih:
            row += [_fmt(v) for v in pq_from_transform(fs.T_world_camera[name])]
        self._csv.writerow(row)
        self._next += 1

    @property
    def t0_ns(self) -> int | None:
        """Stamp of frame 0 (times in frames.csv are relative to it)."""
        return self._t0_ns

    def close(self) -> None:
        if not self._frames.closed:
            self._frames.close()
        if self._spool is not None and self._spool.exists():
            self._encode_spool()

    def _encode_spool(self) -> None:
        """PNG-encode the spooled images into ``frames/`` (two threads: OpenCV releases the GIL)."""
        from concurrent.futures import ThreadPoolExecutor

        def encode(src: Path) -> None:
            dst = self.path / "frames" / src.parent.name / (src.stem + ".png")
            if not cv2.imwrite(str(dst), np.load(src), self._png):
                raise OSError(f"could not write {dst}")
            src.unlink()

        with ThreadPoolExecutor(max_workers=2) as ex:
            list(ex.map(encode, sorted(self._spool.glob("*/*.npy"))))
        shutil.rmtree(self._spool)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class AsyncRecordingWriter:
    """A :class:`RecordingWriter` fed through a queue by a background thread.

    For live loops (the pose server): ``write`` returns at once; PNG encoding
    (OpenCV releases the interpreter lock while encoding) happens on the writer
    thread. Frame sets the queue has no room for are dropped and counted: a
    recording must never slow the tracker down. The recording stays valid: its
    indices must be consecutive, so the writer fills a gap with frame sets whose
    images are all missing (as the spec allows), stamped between their
    neighbours and carrying the next frame set's eye-in-hand poses (unused:
    without images no tracker looks at them).
    """

    def __init__(self, *args, max_queue: int = 64, thread_setup=None, **kwargs):
        import queue
        import threading

        self._thread_setup = thread_setup  # called first on the writer thread (its scheduling)
        kwargs.setdefault("png_compression", 1)
        self.writer = RecordingWriter(*args, **kwargs)
        self.dropped = 0
        self._q = queue.Queue(maxsize=max_queue)
        self._thread = threading.Thread(target=self._run, name="vespro-recording", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        if self._thread_setup is not None:
            self._thread_setup()
        last_t = None
        while True:
            fs = self._q.get()
            if fs is None:
                return
            gap = fs.index - self.writer._next
            for j in range(gap):
                i = self.writer._next
                t = fs.t_ns if last_t is None else last_t + (fs.t_ns - last_t) * (j + 1) // (gap + 1)
                self.writer.write(FrameSet(i, t, {k: None for k in fs.images}, fs.T_world_camera))
            self.writer.write(fs)
            last_t = fs.t_ns

    def write(self, fs: FrameSet) -> None:
        """Queue a frame set (indices increasing; gaps allowed); never blocks."""
        import queue

        try:
            self._q.put_nowait(fs)
        except queue.Full:
            self.dropped += 1

    @property
    def t0_ns(self) -> int | None:
        return self.writer.t0_ns

    def close(self) -> None:
        self._q.put(None)
        self._thread.join()
        self.writer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
