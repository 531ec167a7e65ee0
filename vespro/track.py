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
    """``"x,y,z,qw,qx,qy,qz"``, or a file holding it, -> ``T_world_object``.

    In a file the numbers may be split by commas, spaces or new lines; text
    after ``#`` is a comment.

    Raises
    ------
    InputError
        The reason, naming the file if one was given.
    """
    from .errors import InputError
    from .se3 import transform_from_pq

    what = "--init-pose"
    path = Path(text.strip())
    if path.is_file():
        what = f"--init-pose file {path}"
        try:
            text = path.read_text(errors="replace")
        except OSError as e:
            raise InputError(f"{what}: cannot read ({e.strerror or e})") from None
        text = ",".join(line.split("#", 1)[0] for line in text.splitlines())
    elif not any(c.isdigit() for c in text) or "/" in text or text.endswith(".txt"):
        raise InputError(f"--init-pose: {text!r} is neither 7 numbers x,y,z,qw,qx,qy,qz nor an existing file")
    try:
        vals = np.array([float(v) for v in text.replace(" ", ",").replace("\t", ",").split(",") if v.strip()])
    except ValueError:
        raise InputError(f"{what} needs 7 numbers x,y,z,qw,qx,qy,qz, got {text.strip()!r}") from None
    if vals.shape != (7,):
        raise InputError(f"{what} needs 7 numbers x,y,z,qw,qx,qy,qz, got {vals.size}")
    if not np.all(np.isfinite(vals)):
        raise InputError(f"{what} needs finite numbers, got {vals.tolist()}")
    if abs(np.linalg.norm(vals[3:]) - 1.0) > 1e-2:
        raise InputError(f"{what}: quaternion must be unit length, got norm {np.linalg.norm(vals[3:]):.4f}")
    return transform_from_pq(vals)


def make_tracker(rec: Recording, config: TrackerConfig = TrackerConfig(), initializer=None,
                 unit: str = "m", workspace: tuple | None = None) -> Tracker:
    """A tracker for a recording's rig and model (the model file drawn in ``unit``; ``workspace``:
    the cell's working volume, :mod:`vespro.workspace`)."""
    model = load_model(rec.model_path, unit=unit, name=rec.object_name)
    return Tracker(rec.rig, model, config, initializer=initializer, workspace=workspace)


def track_recording(rec: Recording, tracker: Tracker, init_pose: np.ndarray | None = None,
                    progress: bool = False, on_output=None) -> list[TrackerOutput]:
    """Track every frame set of a recording, in order.

    ``init_pose`` (T_world_object at frame 0), when given, starts the filter at
    the first frame, exactly as given (a symmetric part's frame included);
    otherwise the tracker's initializer decides.
    ``on_output(frameset, output)``, when given, observes each frame (a viewer).
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
        if on_output is not None:
            on_output(fs, outs[-1])
    return outs


def rows_from_outputs(rec: Recording, outs: list[TrackerOutput]) -> list[PoseRow]:
    rows = []
    for o in outs:
        rows.append(PoseRow(o.index, float(rec.t[o.index]), o.status, o.T_world_object, o.time_ms, o.velocity, o.cov6,
                            o.probability))
    return rows


def write_track(path: str | Path, rec: Recording, outs: list[TrackerOutput]) -> None:
    write_poses(path, rows_from_outputs(rec, outs))
