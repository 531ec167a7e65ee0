"""Reading a recording's image files: the image, or why it cannot be used.

An image file is checked before it is decoded: the PNG signature, every
chunk's length and CRC up to ``IEND`` (a file cut short or damaged on disk is
caught here, by name), the size and bit depth its header gives against the
rig's. Only then does OpenCV decode it. Decoding unchecked data let libpng
print lines such as ``libpng error: Read Error`` that name no file; with the
checks first, the decoder only sees complete files whose chunks are intact.

:class:`ImageTally` counts what happened to every image a run looked at, per
camera and per reason, so that a command or a long-running server can report
it (summary lines, status line) and name a camera that gave nothing usable.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

__all__ = ["ImageRead", "read_image", "check_image", "ImageTally", "REASONS"]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

#: Why an image was not used, in report order.
REASONS = ("missing", "truncated", "unreadable", "wrong size", "wrong depth")

#: What to do about a camera whose images all failed for one reason.
HINTS = {
    "missing": "put its images in frames/<camera>/<index:06d>.png",
    "truncated": "copy or export its images again (the files end early)",
    "unreadable": "export its images again as PNG",
    "wrong size": "make image_width/image_height in cameras.yaml match the images (or the images match the rig)",
    "wrong depth": "convert its images to 8-bit grey or colour PNG",
}


@dataclass(frozen=True)
class ImageRead:
    """The outcome of reading one image file.

    Attributes
    ----------
    path : str or Path
        As the caller gave it.
    image : ndarray or None
        Grey ``(H, W)`` or BGR ``(H, W, 3)``, uint8; None when not usable.
    reason : str or None
        One of :data:`REASONS` when ``image`` is None.
    detail : str
        What exactly is wrong (empty when usable).
    grey : bool or None
        Usable files: one channel (grey) or colour.
    """

    path: str | Path
    image: np.ndarray | None
    reason: str | None = None
    detail: str = ""
    grey: bool | None = None

    def describe(self) -> str:
        """``<path>: <reason> (<detail>)``, or ``<path>: ok``."""
        if self.reason is None:
            return f"{self.path}: ok"
        return f"{self.path}: {self.reason}" + (f" ({self.detail})" if self.detail else "")


def _png_header(data: bytes) -> tuple[str | None, str, tuple[int, int, int, int] | None]:
    """Walk a PNG's chunks: ``(reason, detail, (width, height, bit_depth, colour_type))``."""
    if not data.startswith(PNG_SIGNATURE):
        if PNG_SIGNATURE.startswith(data):
            return "truncated", f"ends after {len(data)} bytes, inside the PNG signature", None
        return "unreadable", "not a PNG file (no PNG signature)", None
    view = memoryview(data)
    n = len(data)
    o = len(PNG_SIGNATURE)
    ihdr = None
    while True:
        if o + 8 > n:
            return "truncated", f"ends after {n} bytes, before the IEND chunk", ihdr
        length, ctype = struct.unpack_from(">I4s", data, o)
        end = o + 8 + length + 4
        name = ctype.decode("latin-1")
        if end > n:
            return "truncated", f"ends after {n} bytes, inside chunk {name} at byte {o}", ihdr
        crc = struct.unpack_from(">I", data, end - 4)[0]
        if zlib.crc32(view[o + 4:end - 4]) != crc:
            return "unreadable", f"damaged: CRC mismatch in chunk {name} at byte {o}", ihdr
        if ihdr is None:
            if ctype != b"IHDR" or length != 13:
                return "unreadable", "damaged: the first chunk is not IHDR", None
            ihdr = struct.unpack_from(">IIBB", data, o + 8)
        if ctype == b"IEND":
            return None, "", ihdr
        o = end


def _check(path: str | Path, width: int, height: int) -> tuple[ImageRead, bytes | None]:
    """Everything but decoding: ``(outcome, file bytes when usable so far)``."""
    try:
        with open(path, "rb") as f:  # not pathlib, which interns each part of the name
            data = f.read()
    except FileNotFoundError:
        return ImageRead(path, None, "missing", "no such file"), None
    except OSError as e:
        return ImageRead(path, None, "unreadable", e.strerror or type(e).__name__), None
    reason, detail, ihdr = _png_header(data)
    if reason is not None:
        return ImageRead(path, None, reason, detail), None
    w, h, depth, colour = ihdr
    if depth > 8:
        return ImageRead(path, None, "wrong depth", f"{depth}-bit; images must be 8-bit"), None
    if (w, h) != (width, height):
        return ImageRead(path, None, "wrong size", f"{w}x{h}, cameras.yaml gives {width}x{height}"), None
    return ImageRead(path, None, grey=colour in (0, 4)), data


def check_image(path: str | Path, width: int, height: int) -> ImageRead:
    """The checks of :func:`read_image` without decoding (``image`` stays None).

    For copying files: a usable file has ``reason`` None; ``grey`` tells grey
    from colour.
    """
    return _check(path, width, height)[0]


def read_image(path: str | Path, width: int, height: int) -> ImageRead:
    """Read an 8-bit PNG of ``width`` x ``height`` pixels; never raises for a bad file.

    Returns an :class:`ImageRead` whose ``image`` is None when the file is
    missing, truncated, unreadable (not a PNG, damaged), of another size, or
    not 8-bit; ``reason`` and ``detail`` say which. Colour images come back
    BGR (an alpha channel is dropped), grey ones as they are.
    """
    res, data = _check(path, width, height)
    if data is None:
        return res
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        return ImageRead(path, None, "unreadable", "the PNG decoder refused it")
    if img.dtype != np.uint8:
        return ImageRead(path, None, "wrong depth", f"decoded as {img.dtype}; images must be 8-bit")
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    elif img.ndim == 3 and img.shape[2] != 3:
        return ImageRead(path, None, "wrong depth", f"{img.shape[2]} channels; images must be grey or colour")
    return ImageRead(path, img, grey=img.ndim == 2)


class ImageTally:
    """Counts of the images a run read, per camera: usable, and not used per reason.

    Counts grow with every read (an image read twice counts twice); a
    reader that reads each frame once (a tracking run, a server) gets the
    figures of its input. Keeps the first rejection of each reason per camera
    as an example for the report.
    """

    def __init__(self, cameras):
        self.cameras = list(cameras)
        self.usable = {c: 0 for c in self.cameras}
        self.rejected = {c: {} for c in self.cameras}
        self._first: dict[tuple[str, str], ImageRead] = {}

    def note(self, camera: str, res: ImageRead) -> None:
        """Count one read of ``camera``'s image."""
        if res.reason is None:
            self.usable[camera] += 1
            return
        r = self.rejected[camera]
        r[res.reason] = r.get(res.reason, 0) + 1
        self._first.setdefault((camera, res.reason), res)

    def n_rejected(self, camera: str) -> int:
        return sum(self.rejected[camera].values())

    def n_read(self, camera: str) -> int:
        return self.usable[camera] + self.n_rejected(camera)

    def dead(self) -> list[str]:
        """Cameras that were read and never gave a usable image."""
        return [c for c in self.cameras if self.n_read(c) and not self.usable[c]]

    def _counts(self, camera: str) -> str:
        r = self.rejected[camera]
        return ", ".join(f"{k} {r[k]}" for k in REASONS if k in r)

    def status(self) -> str:
        """Short text for a status line (empty when every image was usable)."""
        parts = [f"{c} {self.n_rejected(c)} ({self._counts(c)})" for c in self.cameras if self.rejected[c]]
        return ("images not used: " + "; ".join(parts)) if parts else ""

    def report(self) -> list[str]:
        """One line per camera with images not used, then a warning per camera that gave none.

        Each line gives the counts per reason and the first file of each
        reason with what is wrong with it.
        """
        lines = []
        for c in self.cameras:
            if not self.rejected[c]:
                continue
            first = "; ".join(self._first[(c, k)].describe() for k in REASONS if (c, k) in self._first)
            lines.append(f"camera '{c}': {self.n_rejected(c)} of {self.n_read(c)} images not used "
                         f"({self._counts(c)}); first: {first}")
        for c in self.dead():
            main = max(self.rejected[c], key=lambda k: self.rejected[c][k])
            lines.append(f"warning: camera '{c}' gave no usable image in the whole run; {HINTS[main]}")
        return lines

    def as_dict(self) -> dict:
        """``{camera: {"usable": n, <reason>: n, ...}}`` (for JSON summaries)."""
        return {c: {"usable": self.usable[c], **self.rejected[c]} for c in self.cameras}
