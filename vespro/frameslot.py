"""A frame set handed to the initialisation worker process through shared memory.

The pose server's automatic start runs in a worker process. Handing it a frame
set through the executor's queue pickles every image (about a megabyte for three
640x480 cameras) on a feeder thread, which keeps the last pickle alive until the
next job: the live server's resident size then carried whole frame sets that no
one used, by amounts that changed with which job was last. A :class:`FrameSlot`
is one block of shared memory, grown to the largest frame set seen and reused:
the server copies the images into it, the worker reads them out, and what
crosses the queue is a few hundred bytes (:class:`SlotFrames`). One job at a
time uses the slot: the server writes it only when the previous job is done.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from rtkit.shm import SharedBlock

from .frames import FrameSet

__all__ = ["FrameSlot", "SlotFrames"]


@dataclass(frozen=True)
class SlotFrames:
    """A frame set whose images lie in a :class:`FrameSlot` (picklable, small)."""

    block: str
    index: int
    t_ns: int
    layout: tuple  # (camera, shape or None, dtype str, byte offset) per camera
    T_world_camera: dict = field(default_factory=dict)

    def frameset(self) -> FrameSet:
        """The frame set, its images copied out of the slot (in the worker process)."""
        buf = _attached(self.block)
        images = {}
        for name, shape, dtype, off in self.layout:
            if shape is None:
                images[name] = None
                continue
            n = int(np.prod(shape)) * np.dtype(dtype).itemsize
            images[name] = buf[off:off + n].view(dtype).reshape(shape).copy()
        return FrameSet(self.index, self.t_ns, images, dict(self.T_world_camera))


_ATTACHED: dict = {}  # the worker's read-only mapping of the server's slot (one at a time)


def _attached(name: str) -> np.ndarray:
    """The slot's bytes, mapped read-only from ``/dev/shm``: a plain mapping, so the worker
    never registers the block with the resource tracker it shares with the server (a forked
    worker that attached and unregistered it left the server's own unlink to fail there)."""
    buf = _ATTACHED.get(name)
    if buf is None:
        _ATTACHED.clear()  # the slot grew: the server made a new block
        buf = _ATTACHED[name] = np.memmap(f"/dev/shm/{name.lstrip('/')}", dtype=np.uint8, mode="r")
    return buf


class FrameSlot:
    """One frame set's images in shared memory, for a worker process (see the module)."""

    def __init__(self):
        self._block: SharedBlock | None = None

    def put(self, fs: FrameSet) -> SlotFrames:
        """Copy ``fs``'s images into the slot (growing it if they do not fit); the handle."""
        imgs = {k: None if v is None else np.ascontiguousarray(v) for k, v in fs.images.items()}
        need = sum(v.nbytes for v in imgs.values() if v is not None)
        if self._block is None or need > self._block.a.size * 8:
            self.close()
            self._block = SharedBlock(None, max(1, -(-need // 8)))
        buf = self._block.bytes
        layout, off = [], 0
        for name, v in imgs.items():
            if v is None:
                layout.append((name, None, "|u1", 0))
                continue
            buf[off:off + v.nbytes] = v.reshape(-1).view(np.uint8)
            layout.append((name, v.shape, v.dtype.str, off))
            off += v.nbytes
        return SlotFrames(self._block.name, fs.index, fs.t_ns, tuple(layout),
                          dict(fs.T_world_camera))

    def close(self) -> None:
        if self._block is not None:
            self._block.close()
            self._block = None
