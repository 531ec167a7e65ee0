"""Zenoh: the pose server's stream to several subscribers (peers on loopback), and ROS 2 CDR poses."""

import socket
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh", reason="Zenoh needs the interop extra (pip install 'vespro[interop]')")

from servo.receiver import PoseReceiver  # noqa: E402
from servo.zenoh_source import parse_zenoh_url  # noqa: E402
from vespro.camera import CameraIntrinsics  # noqa: E402
from vespro.clock import SimClock  # noqa: E402
from vespro.frames import FrameSet  # noqa: E402
from vespro.model import load_model  # noqa: E402
from vespro.recording import Recording, RecordingWriter  # noqa: E402
from vespro.rig import Rig, RigCamera  # noqa: E402
from vespro.se3 import exp_so3, transform_from_rt  # noqa: E402
from vespro.server import PoseServer  # noqa: E402
from vespro.sources import ReplaySource  # noqa: E402
from vespro.tracker import InitResult, Tracker  # noqa: E402
from vespro.wire import HelloMsg, PoseMsg, PoseStatus  # noqa: E402
from vespro.zenoh_link import POSE_TYPE, ZenohPublisher, ros2_key  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
BOX = ROOT / "models" / "objects" / "box.stl"
T_START = transform_from_rt(np.eye(3), [0.0, 0.0, 0.6])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def rec_path(tmp_path_factory):
    """Twelve frame sets of one camera (noise images: what the tracker makes of them does not matter here)."""
    rng = np.random.default_rng(0)
    rig = Rig((RigCamera("a", CameraIntrinsics(160, 120, [[200, 0, 79.5], [0, 200, 59.5], [0, 0, 1]]), "fixed",
                         T_world_camera=np.eye(4)),))
    path = tmp_path_factory.mktemp("zenoh") / "rec"
    with RecordingWriter(path, rig, BOX, 26.0, "box") as w:
        for k in range(12):
            w.write(FrameSet(k, 10**9 + k * 38_461_538, {"a": rng.integers(0, 256, (120, 160), dtype=np.uint8)}))
    return path


def _until(cond, timeout_s=20.0, poll=()):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        for rx in poll:
            rx.poll()
        if cond():
            return True
        time.sleep(0.002)
    return False


def test_three_subscribers_get_every_served_pose_in_order(rec_path):
    rec = Recording(rec_path)
    clock = SimClock()
    port = _free_port()
    key = "test/vespro/pose"
    pub = ZenohPublisher(key, HelloMsg(rec.rate_hz, ("box",)), listen=[f"tcp/127.0.0.1:{port}"],
                         hello_period_s=0.1, clock_ns=clock.now_ns)
    # The servo's receiver (as `servo run --connect zenoh/...` builds it) and two more.
    rxs = [PoseReceiver(f"zenoh/{key}?connect=tcp/127.0.0.1:{port}") for _ in range(3)]
    try:
        def connected():  # heartbeats until every subscriber hears them (the simulated clock stands still)
            pub.heartbeat()
            time.sleep(0.02)
            return all(rx.stats().frames_ok > 0 for rx in rxs)

        assert _until(connected, poll=rxs), "subscribers did not connect"
        got = [[] for _ in rxs]
        fired = []

        def init(fs):  # the user's pose, once (as --init-pose)
            if fired:
                return None
            fired.append(1)
            return InitResult(T_START)

        def on_output(fs, out):  # each pose must reach all three before the next frame: in order, none lost
            seq = len(published) - 1

            def arrived():
                for rx, g in zip(rxs, got):
                    buf = []
                    rx.poll(out=buf)
                    g.extend(m for m in buf if isinstance(m, PoseMsg))
                return all(g and g[-1].seq == seq for g in got)

            assert _until(arrived), f"pose {seq} did not reach every subscriber"

        published = []

        class Recorded:  # the server's publisher, remembering what it sent
            def publish(self, msg):
                published.append(msg)
                return pub.publish(msg)

            def stats(self):
                return pub.stats()

        server = PoseServer(ReplaySource(rec, clock), Tracker(rec.rig, load_model(rec.model_path)), Recorded(),
                            clock, init, background_init=False, log=None, on_output=on_output)
        stats = server.run()
        # One pose a frame, then the source's end published once more as lost.
        assert stats.frames == len(rec) and len(published) == len(rec) + 1
        assert published[-1].status == PoseStatus.LOST

        def all_arrived():
            for rx, g in zip(rxs, got):
                buf = []
                rx.poll(out=buf)
                g.extend(m for m in buf if isinstance(m, PoseMsg))
            return all(len(g) >= len(published) for g in got)

        assert _until(all_arrived), "the last pose did not reach every subscriber"
        for g in got:
            assert [m.seq for m in g] == list(range(len(published)))
            assert all(a == b for a, b in zip(g, published))  # bit for bit: a PoseMsg compares every field exactly
        assert pub.stats().clients_connected == 1 and pub.stats().errors == 0
    finally:
        for rx in rxs:
            rx.close()
        pub.close()


def test_tracked_poses_also_go_out_as_ros2_cdr_with_the_rmw_zenoh_key():
    pytest.importorskip("mcap_ros2", reason="ROS 2 messages need the interop extra (pip install 'vespro[interop]')")
    pytest.importorskip("rosbags", reason="ROS 2 messages need the interop extra (pip install 'vespro[interop]')")
    import zenoh
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory

    from vespro.ros2 import msgdef
    from vespro.wire import zenoh_config_json5

    topic = ros2_key("vespro/pose")
    assert topic.startswith("0/vespro/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_")
    port = _free_port()
    pub = ZenohPublisher("test/vespro/pose2", HelloMsg(26.0, ("box",)), listen=[f"tcp/127.0.0.1:{port}"],
                         ros2_key=topic)
    got = []
    peer = zenoh.open(zenoh.Config.from_json5(zenoh_config_json5("peer", [], [f"tcp/127.0.0.1:{port}"])))
    try:
        peer.declare_subscriber(topic, lambda s: got.append((s.payload.to_bytes(), s.attachment.to_bytes())))
        rng = np.random.default_rng(1)
        A = rng.normal(size=(6, 6))
        cov = (A @ A.T * 1e-6).astype(np.float32)
        msgs = [PoseMsg(k, 10**9 + k, 0, 0, PoseStatus.LOST if k == 1 else PoseStatus.TRACKING,
                        rng.normal(size=3), [0.5, 0.5, 0.5, 0.5], [0, 0, 0], [0, 0, 0], cov) for k in range(3)]

        probe = PoseMsg(99, 0, 0, 0, PoseStatus.TRACKING, [9.0, 9, 9], [1.0, 0, 0, 0], [0, 0, 0], [0, 0, 0], cov)

        def ready():  # the subscription has reached the publisher: a probe gets through
            pub.publish(probe)
            time.sleep(0.05)
            return bool(got)

        assert _until(ready)
        for m in msgs:
            pub.publish(m)
        schema = Schema(id=1, name=POSE_TYPE, encoding="ros2msg", data=msgdef(POSE_TYPE).encode())
        decode = DecoderFactory().decoder_for("cdr", schema)
        poses = lambda: [(decode(p), a) for p, a in got if decode(p).pose.pose.position.x != 9.0]  # noqa: E731
        assert _until(lambda: len(poses()) == 2)
    finally:
        peer.close()
        pub.close()
    for (ros, att), m in zip(poses(), [msgs[0], msgs[2]]):  # the LOST pose is not sent
        p, o = ros.pose.pose.position, ros.pose.pose.orientation
        assert [p.x, p.y, p.z] == m.p_world_object.tolist() and [o.w, o.x, o.y, o.z] == m.q_world_object.tolist()
        np.testing.assert_array_equal(np.reshape(ros.pose.covariance, (6, 6)), m.cov.astype(np.float64))
        assert ros.header.frame_id == "world"
        # rmw_zenoh's attachment: (length-prefixed name, value) for the sequence number, the source
        # timestamp (int64 little endian) and the 16-byte publisher id.
        assert att[0] == 15 and att[1:16] == b"sequence_number" and int.from_bytes(att[16:24], "little") > 0
        assert att[24:41] == b"\x10source_timestamp" and att[49:60] == b"\x0asource_gid" and att[60] == 16
        assert len(att) == 77


def test_serve_publishes_on_zenoh_beside_tcp(rec_path, capsys):
    """``vespro serve --zenoh`` (in this process: the command's wiring, not its start-up time)."""
    import threading

    from vespro.cli import main

    port, zport = _free_port(), _free_port()
    key = "test/vespro/serve"
    rx = PoseReceiver(f"zenoh/{key}?connect=tcp/127.0.0.1:{zport}")
    seqs, stop = [], threading.Event()

    def listen():
        while not stop.is_set():
            buf = []
            rx.poll(out=buf)
            seqs.extend(m.seq for m in buf if isinstance(m, PoseMsg))
            time.sleep(0.002)

    t = threading.Thread(target=listen, daemon=True)
    t.start()
    try:
        rc = main(["serve", "--source", "replay", "--recording", str(rec_path), "--loop", "--init-pose",
                   "0,0,0.6,1,0,0,0", "--tcp", str(port), "--zenoh", key, "--zenoh-listen",
                   f"tcp/127.0.0.1:{zport}", "--frames", "60", "--quiet"])
        time.sleep(0.2)
    finally:
        stop.set()
        t.join()
        rx.close()
    assert rc == 0
    assert f"zenoh key {key}" in capsys.readouterr().out
    # The subscriber joins while the server runs: from its first pose on, every one, in order.
    assert len(seqs) >= 20 and seqs == list(range(seqs[0], 60))


def test_zenoh_urls_parse_and_bad_ones_are_refused():
    o = parse_zenoh_url("zenoh/vespro/pose")
    assert o["key"] == "vespro/pose" and o["connect"] == ["tcp/127.0.0.1:7447"] and o["listen"] == []
    o = parse_zenoh_url("zenoh/a/**?connect=tcp/10.0.0.1:7447,tcp/10.0.0.2:7447&mode=client")
    assert o["key"] == "a/**" and o["mode"] == "client" and len(o["connect"]) == 2
    for bad in ("zenoh/", "zenoh/k?mode=router", "zenoh/k?port=3"):
        with pytest.raises(ValueError):
            parse_zenoh_url(bad)


def test_servo_run_refuses_a_bad_zenoh_url_in_one_line(capsys):
    from servo.cli import main as servo_main

    assert servo_main(["run", "--connect", "zenoh/vespro/pose?mode=router", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "--connect" in err and "mode must be peer or client" in err and err.count("\n") == 1


def test_the_documented_router_config_carries_the_poses_between_clients():
    """docs/zenoh/router.json5 (on loopback here): the server and the servo each connect to the router only."""
    import json

    import zenoh

    port = _free_port()
    conf = zenoh.Config.from_file(str(ROOT / "docs" / "zenoh" / "router.json5"))
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    router = zenoh.open(conf)
    pub = ZenohPublisher("cell/pose", HelloMsg(26.0, ("box",)), listen=[], connect=[f"tcp/127.0.0.1:{port}"])
    rx = PoseReceiver(f"zenoh/cell/pose?connect=tcp/127.0.0.1:{port}&mode=client")
    try:
        assert _until(lambda: pub.heartbeat() is not None and rx.stats().frames_ok > 0, poll=[rx])
        sent = [PoseMsg(k, 1, 0, 0, PoseStatus.TRACKING, [0.0, 0, k], [1.0, 0, 0, 0], [0, 0, 0], [0, 0, 0],
                        np.eye(6)) for k in range(20)]
        got = []

        def arrived(k):
            buf = []
            rx.poll(out=buf)
            got.extend(m for m in buf if isinstance(m, PoseMsg))
            return len(got) == k + 1

        for k, m in enumerate(sent):
            pub.publish(m)
            assert _until(lambda: arrived(k)), f"pose {k} did not arrive"
        assert [m.seq for m in got] == list(range(20))
        assert [m.p_world_object[2] for m in got] == list(range(20))
    finally:
        rx.close()
        pub.close()
        router.close()
