"""What a servo run reports: its once-a-second status line and its statistics file.

:func:`status_line` is the line ``servo run`` prints every second (status, poses,
their age, the link, the safety record's counters); :func:`write_stats_json` the
``--stats-json`` file at the end (ticks, timing, statuses, the safety record and
the link's counters by cause), which the whole-cell demo writes too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["status_line", "write_stats_json"]

def write_stats_json(path: Path, stats, receiver, poses_used: int, period_ns: int, sigint: bool, state=None) -> dict:
    """Tick, status, safety and link statistics of a run (JSON), plus a 1 us histogram of |period error|.

    With the loop's ``state`` (:class:`servo.loop.LoopState`), ``safety`` holds
    its record (every stop, fault, late tick and rejected pose by cause, and
    the recent events with their values), ``controlled_stops`` counts the
    stops it recorded and ``poses_used`` the poses the loop took (``poses_used``
    as given otherwise).
    """
    import json

    from .events import EventKind
    from .safety import Status

    st = stats.status.astype(int)
    per = stats.period_ns[1:] - period_ns
    rs = receiver.stats()
    if state is not None:
        stops = state.record.count(EventKind.STOP)
        poses_used = state.n_used
    else:
        stops = int(np.sum((st[1:] == int(Status.STOPPING)) & (st[:-1] != int(Status.STOPPING))))
    info = {
        "ticks": int(stats.n_ticks), "overruns": int(stats.overruns),
        "compute_us_median": float(np.median(stats.compute_ns) * 1e-3) if stats.n_ticks else None,
        "compute_us_p99": float(np.percentile(stats.compute_ns, 99) * 1e-3) if stats.n_ticks else None,
        "period_error_us": {q: float(np.percentile(np.abs(per), p) * 1e-3) if per.size else None
                            for q, p in (("median", 50), ("p99", 99), ("p99.9", 99.9), ("max", 100))},
        "status_ticks": {s.name: int(np.sum(st == int(s))) for s in Status},
        "controlled_stops": stops, "sigint_stop": sigint, "poses_used": poses_used,
        "link": {"poses": rs.poses, "frames_ok": rs.frames_ok, "rejected": dict(rs.rejected),
                 "poses_rejected": dict(rs.pose_rejected), "seq_gaps": rs.seq_gaps,
                 "seq_restarts": rs.seq_restarts, "hellos": rs.hellos,
                 "connects": rs.connects, "disconnects": rs.disconnects,
                 "refusals": rs.refusals, "refusal": rs.refusal},
        "rt_warning": stats.rt_warning,
    }
    if state is not None:
        info["safety"] = {**state.record.to_dict(), "poses_rejected_by_loop": state.n_rejected,
                          "planner_held_back_ticks": state.planner.n_held_back,
                          "latched_at_end": bool(state.latched), "status_at_end": Status(state.status).name}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(info, indent=2))
    hist = np.bincount(np.clip(np.abs(per) // 1000, 0, 2000).astype(int)) if per.size else np.zeros(1)
    np.save(path.with_suffix(".period_hist_us.npy"), hist)
    return info

def status_line(state, receiver, t_ns: int) -> str:
    """The once-a-second line: status, poses, age, link, and the safety record's counters."""
    from .safety import Status

    rs = receiver.stats()
    _, age = receiver.latest(t_ns)
    age_ms = "-" if age >= 2**62 else f"{age * 1e-6:.1f}"
    link_rej = {**{k: v for k, v in rs.rejected.items() if v}, **{k: v for k, v in rs.pose_rejected.items() if v}}
    link = ",".join(f"{k}:{v}" for k, v in link_rej.items()) or "0"
    refused = f" (refused: {rs.refusal})" if rs.refusal else ""
    return (f"{Status(state.status).name:9s} | poses used {state.n_used} | age {age_ms} ms | "
            f"link {rs.state.name}{refused} rejected {link} | {state.record.summary()}")
