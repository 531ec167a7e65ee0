"""Run the tracker over a recording (the recording alone: never its ground truth)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .model import load_model
from .poses import PoseRow, write_poses
from .recording import Recording
from .tracker import InitResult, Tracker, TrackerConfig, TrackerOutput

__all__ = ["make_tracker", "track_recording", "rows_from_outputs", "parse_pose"]


def parse_pose(text: str) -> np.ndarray:
    """``"x,y,z,qw,qx,qy,qz"`` -> ``T_world_object``; raises ValueError with the reason."""
    from .se3 import transform_from_pq

    try:
        vals = np.array([float(v) for v in text.replace(" ", "").split(",")])
    except ValueError:
        raise ValueError(f"--init-pose needs 7 numbers x,y,z,qw,qx,qy,qz, got {text!r}") from None
    if vals.shape != (7,):
        raise ValueError(f"--init-pose needs 7 numbers x,y,z,qw,qx,qy,qz, got {vals.size}")
    if abs(np.linalg.norm(vals[3:]) - 1.0) > 1e-2:
        raise ValueError(f"--init-pose quaternion must be unit length, got norm {np.linalg.norm(vals[3:]):.4f}")
    return transform_from_pq(vals)


def make_tracker(rec: Recording, config: TrackerConfig = TrackerConfig(), initializer=None) -> Tracker:
    """A tracker for a recording's rig and model."""
    model = load_model(rec.model_path, name=rec.object_name)
    return Tracker(rec.rig, model, config, initializer=initializer)


def track_recording(rec: Recording, tracker: Tracker, init_pose: np.ndarray | None = None,
                    progress: bool = False) -> list[TrackerOutput]:
    """Track every frame set of a recording, in order.

    ``init_pose`` (T_world_object at frame 0), when given, starts the filter at
    the first frame, exactly as given (a symmetric part's frame included);
    otherwise the tracker's initializer decides.
    """
    outs = []
    it = range(len(rec))
    if progress:
        from tqdm import tqdm

        it = tqdm(it, unit="frame", desc=f"track {rec.path.name}")
    for i in it:
        fs = rec.frameset(i)  # images decoded here, outside the timed processing
        if i == 0 and init_pose is not None:
            tracker.start(InitResult(init_pose, given=True), fs.t_ns)
        outs.append(tracker.process(fs))
    return outs


def rows_from_outputs(rec: Recording, outs: list[TrackerOutput]) -> list[PoseRow]:
    rows = []
    for o in outs:
        rows.append(PoseRow(o.index, float(rec.t[o.index]), o.status, o.T_world_object, o.time_ms, o.velocity, o.cov6))
    return rows


def write_track(path: str | Path, rec: Recording, outs: list[TrackerOutput]) -> None:
    write_poses(path, rows_from_outputs(rec, outs))
