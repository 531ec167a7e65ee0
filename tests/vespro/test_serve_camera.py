"""``vespro serve --source camera`` on a video file: paced at the file's rate, the end
of the stream handled as ``--on-camera-end`` says, every pose over TCP to a client."""

import socket
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from servo.receiver import PoseReceiver
from vespro.groundtruth import read_groundtruth
from vespro.recording import Recording
from vespro.rig import load_rig
from vespro.se3 import pq_from_transform
from vespro.sim.cell import CellConfig
from vespro.sim.imaging import ImageEffects
from vespro.sim.motion import Conveyor
from vespro.sim.record import record
from vespro.sim.rigs import CAMERAS_DIR
from vespro.sim.scene import MODELS_DIR
from vespro.wire import PoseMsg, PoseStatus

FPS = 30.0
N_FRAMES = 45


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """A rendered box on the belt seen by one fixed camera, as a 30 fps mp4; its rig, mesh
    and the first frame's pose (the user's --init-pose)."""
    tmp = tmp_path_factory.mktemp("cam")
    cfg = CellConfig(MODELS_DIR / "objects" / "box.stl", load_rig(CAMERAS_DIR / "fixed1.yaml"),
                     effects=ImageEffects(noise_px=0.3), rate_hz=FPS)
    rec = Recording(record(tmp / "rec", cfg, Conveyor(speed=0.05, y0=-0.1), N_FRAMES, "box"))
    name = rec.rig.names[0]
    h, w = rec.rig[name].intrinsics.height, rec.rig[name].intrinsics.width
    path = tmp / "clip.mp4"
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (w, h))
    assert out.isOpened()
    for i in range(len(rec)):
        img = rec.frameset(i).images[name]
        out.write(img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    out.release()
    _, _, T = read_groundtruth(rec.path)
    return path, rec.path / "cameras.yaml", rec.model_path, ",".join(f"{v:.9f}" for v in pq_from_transform(T[0]))


def _serve(video, *extra):
    """Run the server on the video with a client connected; (exit code, output, messages)."""
    path, rig, mesh, pose = video
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "vespro", "serve", "--source", "camera", "--device", str(path),
                             "--rig", str(rig), "--model", str(mesh), "--init-pose", pose, "--tcp", str(port),
                             *extra], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rx = PoseReceiver(f"socket://127.0.0.1:{port}", backoff_min_s=0.01, backoff_max_s=0.02)
    msgs, deadline = [], time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            got = []
            rx.poll(out=got)
            msgs += [m for m in got if isinstance(m, PoseMsg)]
            if proc.poll() is not None and rx.stats().disconnects:
                break
            time.sleep(0.002)
        out, _ = proc.communicate(timeout=30)
    finally:
        rx.close()
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, out, msgs


def _paced(stamps_ns, period_ns):
    """Stamps a period apart (more where a frame set was dropped or a late one restarted
    the timeline), never closer: the stream's rate, not as fast as it decodes."""
    steps = np.diff(stamps_ns)
    return np.all(steps >= period_ns - 1e3) and abs(np.median(steps) - period_ns) <= 1e3


def test_a_video_is_paced_at_its_rate_and_the_server_stops_at_its_end(video):
    code, out, msgs = _serve(video, "--on-camera-end", "stop")
    assert code == 0 and "Traceback" not in out, out
    assert out.count("stream ended after 45 frames") == 1 and "stopping" in out, out
    assert "stopped after" in out
    # Frames' own poses; a stall report (published lost at the instant the stall is noticed, as on a
    # heavily loaded machine) is stamped off the stream's grid.
    frames = [m for m in msgs if m.t_capture_ns != msgs[-1].t_capture_ns and m.status != PoseStatus.LOST]
    assert len(frames) >= 20, out  # the client joined within the first half of the clip
    assert _paced([m.t_capture_ns for m in frames], 1e9 / FPS)  # the file's 30 Hz
    assert msgs[-1].status == PoseStatus.LOST  # at the end: nothing tracks the part any more
    assert sum(m.status == PoseStatus.TRACKING for m in msgs) >= 10, out


def test_retry_reopens_the_ended_stream_and_publishes_lost_meanwhile(video, kept_publisher):
    """In process (the same code as the command): the file ends, is reopened after the
    0.5 s backoff and starts over; the camera down meanwhile is published lost, said once."""
    from vespro.clock import WallClock
    from vespro.model import load_model
    from vespro.server import PoseServer
    from vespro.sources import CameraSource
    from vespro.track import parse_pose
    from vespro.tracker import InitResult, Tracker

    path, rig_path, mesh, pose = video
    clock, lines = WallClock(), []
    src = CameraSource(load_rig(rig_path), [str(path)], clock, on_end="retry", log=lines.append)
    pub = kept_publisher
    fired = []

    def init(fs):
        if fired:
            return None
        fired.append(1)
        return InitResult(parse_pose(pose))

    server = PoseServer(src, Tracker(src.rig, load_model(mesh)), pub, clock, init, background_init=False,
                        log=lines.append)
    server.run(max_frames=N_FRAMES + 5)
    src.close()
    ends = sum("stream ended after 45 frames" in ln for ln in lines)  # 2 if frames were dropped behind
    assert ends >= 1 and ends == sum("reopening in 0.5 s" in ln for ln in lines), "\n".join(lines)
    assert sum("reopened" in ln for ln in lines) == ends, lines
    again = [float(ln.split("frames again after ")[1].split(" s")[0]) for ln in lines if "frames again after" in ln]
    assert again and max(again) >= 0.5, lines  # back after the first backoff
    assert sum("down (reopening); the track is published lost" in ln for ln in lines) == ends, lines  # once each
    assert server.stats.source_gaps >= 1 and any(m.status == PoseStatus.LOST for m in pub.msgs)

