"""What a recorded pose-server run leaves for evaluation (``vespro serve --record DIR``, the demo).

``DIR/recording`` (the frames as served, written while the server runs), and at the end
``DIR/poses.csv`` (its outputs, times from the first frame set), ``DIR/outputs.pkl`` (the
outputs themselves) and ``DIR/server.json`` (the run's counts and timings, the image
report, the load shedder's steps, the link's counters).
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path

from .poses import PoseRow, write_poses

__all__ = ["save_run"]


def save_run(folder: Path, writer, outputs, stats, link_stats, source, shedder=None) -> None:
    """Close the recording writer; write ``folder``'s poses.csv, outputs.pkl and server.json."""
    writer.close()
    t0 = writer.t0_ns or 0
    write_poses(folder / "poses.csv", [
        PoseRow(o.index, (o.t_ns - t0) * 1e-9, o.status, o.T_world_object, o.time_ms, o.velocity, o.cov6)
        for o in outputs])
    with open(folder / "outputs.pkl", "wb") as f:
        pickle.dump(outputs, f)
    info = {
        # The capture stamp of frame set 0 (the recording's t = 0) on the clock the servo shares.
        "t0_ns": writer.t0_ns,
        "frames": stats.frames, "tracking": stats.tracking, "init_attempts": stats.init_attempts,
        "init_successes": stats.init_successes, "recording_dropped": writer.dropped,
        "missed_captures": getattr(source, "missed", 0),
        **stats.summary(),
        "images": source.images.as_dict() if getattr(source, "images", None) is not None else None,
        "capture_instants": stats.frames + getattr(source, "missed", 0),
        # Steps the load shedder took (vespro.loadshed): when (s from the first frame set), what.
        "load_steps": [] if shedder is None else [
            {"t_s": (st.t_ns - (writer.t0_ns or st.t_ns)) * 1e-9, "kind": st.kind, "what": st.what,
             "missed": st.missed, "instants": st.instants} for st in shedder.steps],
        "link": {"frames_published": link_stats.frames_published, "frames_sent": link_stats.frames_sent,
                 "drops": link_stats.drops, "clients_accepted": link_stats.clients_accepted,
                 "errors": link_stats.errors},
    }
    (folder / "server.json").write_text(json.dumps(info, indent=2))
