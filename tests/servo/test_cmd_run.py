"""``servo run`` end to end against a fake pose server: bad poses counted by reason in
``--stats-json`` and the status line, an operator stop on SIGINT."""

import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from vespro import wire
from vespro.wire import HelloMsg

from servo_helpers import WAIT_S, pose_msg

ROOT = Path(__file__).resolve().parents[2]
MS = 1_000_000


def _servo(args, **kw):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "servo", "run", *args], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, **kw)


def test_servo_run_counts_bad_poses_by_reason_and_stops_on_sigint(tmp_path):
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]
    stats = tmp_path / "stats.json"
    proc = _servo(["--connect", f"socket://127.0.0.1:{port}", "--stats-json", str(stats), "--duration", "60"])
    try:
        r, _, _ = select.select([srv], [], [], 60)  # the servo imports MuJoCo first
        assert r, "servo run did not connect"
        conn, _ = srv.accept()
        conn.sendall(b"\x00" + wire.encode(HelloMsg(26.0, ("part",))))
        p = (0.9, 0.0, 0.5)
        for seq in range(10):
            now = time.monotonic_ns()
            conn.sendall(wire.encode(pose_msg(seq, now - 40 * MS, now, p)))
            time.sleep(0.038)
        now = time.monotonic_ns()
        for msg in (pose_msg(9, now - 40 * MS, now, p),  # duplicate
                    pose_msg(3, now - 40 * MS, now, p),  # out of order
                    pose_msg(10, now + 400 * MS, now, p),  # captured 0.4 s after it was sent
                    pose_msg(11, now - 40 * MS, now, p, object_id=2)):  # not announced
            conn.sendall(wire.encode(msg))
        time.sleep(1.5)  # at least one status line after the bad poses
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=WAIT_S * 3)
        conn.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        srv.close()
    assert proc.returncode == 0, out
    info = json.loads(stats.read_text())
    assert info["link"]["poses_rejected"] == {"no_hello": 0, "unknown_object": 1, "future_stamp": 1,
                                              "duplicate": 1, "out_of_order": 1}
    assert info["sigint_stop"] and "safety" in info and info["safety"]["faults"] == {}
    assert info["poses_used"] <= 10 and info["link"]["poses"] == 10
    assert "duplicate:1" in out and "out_of_order:1" in out and "future_stamp:1" in out
    assert "status HOLD" in out and "Traceback" not in out
