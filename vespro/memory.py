"""Memory of a long-running process that churns images: freed image buffers go back to the system,
and the intermediate images of each frame are kept from frame to frame (:class:`ScratchImages`).

The pose server allocates and frees image-sized arrays every frame (a frame
set's images, the grey copies kept while a start is searched for, the
gradients of the windows). glibc's allocator serves a block over its mmap
threshold (128 KiB by default) from a mapping of its own and unmaps it when
freed, but it raises the threshold to the size of every such block freed
(up to 32 MiB), so that after the first frame the images come from the heap
instead. Freed there, they stay in the process under any block still held
above them: a hundred 640x480 images made, the newest kept, leave 29 MB
resident; replaying the demo's recording, the server's heap stepped up by
2.7 MB after four minutes with nothing live behind it.

Fixing the threshold (``mallopt(M_MMAP_THRESHOLD)``, which also turns the
adjustment off) keeps every image in a mapping of its own, returned whole
when freed: the resident size follows what is live (0.4 MB for the hundred
images above; no heap step in the replay). The cost is a mapping and its page
faults per image allocation, tens of microseconds per frame set.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math

import numpy as np

__all__ = ["ScratchImages", "return_freed_images"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def return_freed_images(threshold_bytes: int = 128 * 1024) -> str | None:
    """Blocks of ``threshold_bytes`` or more each in a mapping of its own, for the life of the
    process (glibc); returns why not where the C library does not offer it, else None."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return f"the C library ({name}) has no mallopt: freed image memory may stay with the process"
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes)) and mallopt(_M_TRIM_THRESHOLD, 2 * int(threshold_bytes))
    return None if ok else "mallopt refused the thresholds: freed image memory may stay with the process"


class ScratchImages:
    """Image-sized intermediate arrays kept from frame to frame, by name.

    With the thresholds fixed (:func:`return_freed_images`) every fresh image-sized block
    is a mapping of its own whose pages fault in when first written: in a live server a
    three-camera simulated frame set took 42 ms of CPU instead of 24, and a part seen close
    up by one camera faulted a thousand pages a frame into its edge fit's gradient. What a
    step overwrites every frame and reads only within it lives here instead.
    :meth:`get` returns a C-contiguous view of the given shape on a block that only grows
    (a window's crop may change size from frame to frame); the view is valid until the next
    :meth:`get` of the same name.
    """

    def __init__(self):
        self._blocks: dict = {}

    def get(self, name, shape, dtype) -> np.ndarray:
        shape = tuple(int(n) for n in shape)
        dtype = np.dtype(dtype)
        size = math.prod(shape)
        b = self._blocks.get((name, dtype))
        if b is None or b.size < size:
            b = self._blocks[(name, dtype)] = np.empty(size, dtype)
        return b[:size].reshape(shape)

