"""Make a recording from a simulated scenario."""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path

from ..groundtruth import DistractorWriter, GroundTruthWriter
from ..recording import RecordingWriter
from .cell import CellConfig, SimCell
from .motion import Motion

__all__ = ["record"]


def record(out: str | Path, config: CellConfig, motion: Motion, n_frames: int, object_name: str,
           overwrite: bool = False, progress: bool = False, extra_meta: dict | None = None) -> Path:
    """Simulate the cell and write ``n_frames`` capture instants as a recording.

    Ground truth goes to ``groundtruth.csv`` only (its own writer), and the
    distractors' true poses, when there are any, to ``distractors.csv``; the
    frames, rig and measured eye-in-hand poses go where the tracker reads them.

    Returns
    -------
    Path
        The recording folder.
    """
    if n_frames < 1:
        raise ValueError(f"need at least one frame, got {n_frames}")
    out = Path(out)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_frames, unit="frame", desc=f"record {out.name}")
    with SimCell(config, motion) as cell, \
            RecordingWriter(out, config.rig, config.object_mesh, config.rate_hz, object_name,
                            overwrite=overwrite, extra_meta=extra_meta) as writer, \
            GroundTruthWriter(out) as gt, ExitStack() as stack:
        dw = stack.enter_context(DistractorWriter(out)) if config.distractors else None
        kinds = {d.name: d for d in config.distractors}
        cell.settle_arm()
        for _ in range(n_frames):
            fs = cell.next_frameset()
            writer.write(fs)
            t = (fs.t_ns - writer.t0_ns) * 1e-9
            gt.write(fs.index, t, cell.true_object_pose())
            if dw is not None:
                for name, T in cell.true_distractor_poses().items():
                    d = kinds[name]
                    dw.write(fs.index, t, name, d.kind, T, T[:3, :3] @ d.center + T[:3, 3])
            if bar:
                bar.update(1)
    if bar:
        bar.close()
    return out
