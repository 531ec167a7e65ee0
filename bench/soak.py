"""Soak: the pose server killed and restarted under a running servo, for minutes.

Run from the repository root::

    python3 bench/soak.py --duration 1800 --period 300 [--recording DIR] [--servo-arg=--max-late-ticks=100]
                          [--server-arg=--init-pose=x,y,z,qw,qx,qy,qz]

``vespro serve --source replay --loop`` publishes over TCP on 127.0.0.1 and
``servo run`` follows the poses with the simulated MuJoCo arm on the wall
clock. Every ``--period`` seconds the server's process group is killed
(SIGKILL, no goodbye) and started again ``--restart-delay`` seconds later.

Reported:

- for each kill: whether the servo was tracking, the time from the kill to
  the start of its controlled stop (from the servo's own stop line, stamped on
  the same monotonic clock), against the watchdog time plus one tick (the
  bound: the last pose arrived at most then before the kill);
- for each restart: the time until the servo tracks again (the server's
  start-up, its tracker's first pose, and the servo's resume hold);
- the resident memory (VmRSS) of both processes every ``--rss-period``
  seconds: its growth after the first minute of each process's life, MB
  (the servo lives the whole run; each server lives one period);
- the servo's safety record at the end (stops by cause, late ticks,
  rejections).

The replayed recording should be long (a short one loops every few seconds and
the part jumps back at each loop), e.g. the demo's own: ``vespro demo
--lockstep --out out/demo`` then ``--recording out/demo/vision/recording``;
give the servo a core of its own (``--servo-arg=--cpu=1``, SCHED_FIFO) as a
robot controller has.

Timings depend on the machine's load: the servo's late ticks and the time to
stop are only meaningful on a machine that keeps the servo's 2 ms tick, and
the stop and resume times only where the server tracks the replayed part (a
kill while the servo is not tracking has nothing to stop: its row says so).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import print_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
WATCHDOG_S = 3 / 26  # the servo's default watchdog
TICK_S = 0.002
LINE = re.compile(r"servo run: t=(?P<t>[0-9.]+) (?P<rest>.*)")


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def start_server(args, port: int, log_path: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "vespro", "serve", "--source", "replay", "--recording", str(args.recording),
           "--loop", "--tcp", str(port), "--quiet", *args.server_arg]
    return subprocess.Popen(cmd, stdout=open(log_path, "a"), stderr=subprocess.STDOUT, cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, start_new_session=True)


def parse_servo_log(path: Path):
    """(status changes [(t, name)], stops [(t, kind, cause, value)]) from the servo's lines."""
    changes, stops = [], []
    for line in path.read_text(errors="replace").splitlines():
        m = LINE.match(line)
        if not m:
            continue
        t, rest = float(m["t"]), m["rest"].split()
        if rest[0] == "status":
            changes.append((t, rest[1]))
        elif rest[0] in ("stop", "immediate_stop", "fault"):
            stops.append((t, rest[0], rest[1], rest[3]))
    return changes, stops


def status_at(changes, t: float) -> str | None:
    st = None
    for tc, name in changes:
        if tc > t:
            break
        st = name
    return st


def growth_after(samples, t0: float, skip_s: float = 60.0):
    """RSS growth (MB) from the first sample ``skip_s`` after ``t0`` to the last, and the span max - min."""
    a = [(t, r) for t, r in samples if t - t0 >= skip_s and r is not None]
    if len(a) < 2:
        return None, None
    r = np.array([x[1] for x in a])
    return float(r[-1] - r[0]), float(r.max() - r.min())


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--duration", type=float, default=1800.0, help="soak length, s")
    p.add_argument("--period", type=float, default=300.0, help="kill the server every this many seconds")
    p.add_argument("--restart-delay", type=float, default=1.0, help="restart the server this long after the kill, s")
    p.add_argument("--recording", type=Path, default=ROOT.parent / "shared" / "data" / "example_box2",
                   help="recording the server replays in a loop")
    p.add_argument("--port", type=int, default=5587, help="TCP port of the server on 127.0.0.1")
    p.add_argument("--rss-period", type=float, default=5.0, help="memory sampling period, s")
    p.add_argument("--out", type=Path, default=ROOT / "out" / "soak", help="logs and the servo's stats")
    p.add_argument("--servo-arg", action="append", default=[],
                   help="extra argument for servo run (repeatable), e.g. --servo-arg=--max-late-ticks=100")
    p.add_argument("--server-arg", action="append", default=[],
                   help="extra argument for vespro serve (repeatable), e.g. --server-arg=--init-pose=x,y,z,qw,qx,qy,qz")
    args = p.parse_args()
    if not (args.recording / "meta.yaml").exists():
        print(f"soak: {args.recording}: not a recording (no meta.yaml); give one with --recording", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    port = args.port
    server_log, servo_log = args.out / "server.log", args.out / "servo.log"
    for f in (server_log, servo_log):
        f.write_text("")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t_start = time.monotonic()
    server = start_server(args, port, server_log)
    servo = subprocess.Popen([sys.executable, "-m", "servo", "run", "--connect", f"socket://127.0.0.1:{port}",
                              "--duration", str(args.duration), "--stats-json", str(args.out / "servo_stats.json"),
                              *args.servo_arg],
                             stdout=open(servo_log, "w"), stderr=subprocess.STDOUT, cwd=ROOT, env=env,
                             start_new_session=True)
    servers = [(server.pid, t_start)]
    kills, restarts = [], []
    rss = {"servo": [], "server": {}}
    t_next_kill = t_start + args.period
    t_next_rss = t_start
    try:
        while servo.poll() is None:
            now = time.monotonic()
            if now >= t_next_rss:
                t_next_rss += args.rss_period
                rss["servo"].append((now, rss_mb(servo.pid)))
                rss["server"].setdefault(server.pid, []).append((now, rss_mb(server.pid)))
            if now >= t_next_kill and now - t_start < args.duration - 5.0:
                t_next_kill += args.period
                os.killpg(server.pid, signal.SIGKILL)
                kills.append(time.monotonic())
                server.wait()
                time.sleep(args.restart_delay)
                server = start_server(args, port, server_log)
                restarts.append(time.monotonic())
                servers.append((server.pid, restarts[-1]))
            time.sleep(0.05)
    finally:
        for proc in (server, servo):
            if proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGINT if proc is servo else signal.SIGKILL)
                    proc.wait(timeout=20)
                except (ProcessLookupError, subprocess.TimeoutExpired):
                    os.killpg(proc.pid, signal.SIGKILL)

    changes, stops = parse_servo_log(servo_log)
    bound = WATCHDOG_S + TICK_S
    rows = []
    for i, tk in enumerate(kills):
        tracking = status_at(changes, tk) == "TRACKING"
        after = [s for s in stops if s[0] >= tk - 0.5]
        stop = after[0] if after else None
        dt_stop = None if stop is None else stop[0] - tk
        tr = restarts[i]
        resumed = [t for t, name in changes if t > tr and name == "TRACKING"]
        rows.append([i + 1, round(tk - t_start, 1), "yes" if tracking else "no",
                     "-" if stop is None else f"{stop[2]}", "-" if dt_stop is None else dt_stop * 1e3,
                     bound * 1e3, "-" if dt_stop is None else ("yes" if dt_stop <= bound else "NO"),
                     "-" if not resumed else resumed[0] - tr])
    print(f"soak: {time.monotonic() - t_start:.0f} s, server killed every {args.period:.0f} s "
          f"(restarted {args.restart_delay:.1f} s later), recording {args.recording.name}, "
          f"servo args {' '.join(args.servo_arg) or '(defaults)'}")
    print_table(["kill", "t_s", "tracking", "stop cause", "stop_after_ms", "bound_ms", "within", "resume_after_s"],
                rows, title="kills and restarts")
    mem = []
    g, span = growth_after(rss["servo"], t_start)
    first = next((r for _, r in rss["servo"] if r is not None), None)
    mem.append(["servo (whole run)", first, g, span])
    for pid, t0 in servers:
        g, span = growth_after(rss["server"].get(pid, []), t0)
        first = next((r for _, r in rss["server"].get(pid, []) if r is not None), None)
        mem.append([f"server pid {pid}", first, "-" if g is None else g, "-" if span is None else span])
    print_table(["process", "rss_first_mb", "growth_after_1min_mb", "span_after_1min_mb"], mem, title="memory")
    stats_path = args.out / "servo_stats.json"
    if stats_path.exists():
        s = json.loads(stats_path.read_text())
        saf = s.get("safety", {})
        print(f"servo: {s['ticks']} ticks, {s['overruns']} overruns, stops {saf.get('stops')}, "
              f"faults {saf.get('faults')}, late ticks {saf.get('late_ticks')} (longest "
              f"{saf.get('late_tick_max_s', 0) * 1e3:.1f} ms), rejected {saf.get('rejected')}, "
              f"link {s['link']['connects']} connects, poses rejected {s['link']['poses_rejected']}")
    (args.out / "soak.json").write_text(json.dumps({"kills": kills, "restarts": restarts, "t_start": t_start,
                                                    "rows": rows, "memory": mem}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
