"""Frame sets handed to a worker process through shared memory (vespro.frameslot)."""

from __future__ import annotations

import pickle
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from vespro.frames import FrameSet
from vespro.frameslot import FrameSlot


def _digest(frames):
    fs = frames.frameset()
    return fs.index, fs.t_ns, {k: None if v is None else (v.shape, str(v.dtype), int(v.astype(np.int64).sum()))
                               for k, v in fs.images.items()}, sorted(fs.T_world_camera)


def _frames(rng, shape_a, index):
    return FrameSet(index, 1000 + index, {"left": rng.integers(0, 256, shape_a, dtype=np.uint8), "top": None,
                                          "hand": rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)},
                    {"hand": np.eye(4)})


def test_a_frame_set_crosses_to_a_worker_process_whole_through_a_small_handle():
    rng = np.random.default_rng(0)
    slot = FrameSlot()
    try:
        with ProcessPoolExecutor(max_workers=1) as pool:
            for index, shape in enumerate([(480, 640), (480, 640), (960, 1280)]):  # the last one grows the slot
                fs = _frames(rng, shape, index)
                handle = slot.put(fs)
                assert len(pickle.dumps(handle)) < 2000  # what crosses the queue (the images: 1-3.7 MB)
                got = pool.submit(_digest, handle).result(timeout=60)
                assert got == _digest(type("F", (), {"frameset": lambda self: fs})())
    finally:
        slot.close()
