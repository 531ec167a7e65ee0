"""MCAP export: a tiny recording, its poses and servo histories, read back by independent readers."""

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap_ros2", reason="MCAP export needs the interop extra (pip install 'vespro[interop]')")
pytest.importorskip("rosbags", reason="MCAP export needs the interop extra (pip install 'vespro[interop]')")

from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from vespro.camera import CameraIntrinsics  # noqa: E402
from vespro.cli import main  # noqa: E402
from vespro.frames import FrameSet  # noqa: E402
from vespro.mcap_export import export_mcap  # noqa: E402
from vespro.poses import PoseRow, read_poses, write_poses  # noqa: E402
from vespro.recording import RecordingWriter  # noqa: E402
from vespro.rig import Rig, RigCamera  # noqa: E402
from vespro.se3 import exp_so3, pq_from_transform, transform_from_rt  # noqa: E402
from servo.recorder import Recorder  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
BOX = ROOT / "models" / "objects" / "box.stl"
N = 6
T0_NS = 5_000_000_000


def _run(tmp_path):
    """A recording (a fixed BGR camera, an eye-in-hand grey one missing one image), poses.csv, servo.npz."""
    rng = np.random.default_rng(0)
    K = [[500, 0, 159.5], [0, 500, 119.5], [0, 0, 1]]
    rig = Rig((
        RigCamera("a", CameraIntrinsics(320, 240, K, [0.1, -0.01, 0.001, 0.002, 0.0005]), "fixed",
                  T_world_camera=transform_from_rt(exp_so3([0.1, 0.2, 0.3]), [1, 2, 3])),
        RigCamera("h", CameraIntrinsics(160, 120, np.array(K) / [2, 2, 1]), "eye_in_hand", link="flange",
                  T_link_camera=np.eye(4)),
    ))
    images, rows = [], []
    with RecordingWriter(tmp_path / "vision" / "recording", rig, BOX, 26.0, "box") as w:
        for k in range(N):
            im = {"a": rng.integers(0, 256, (240, 320, 3), dtype=np.uint8),
                  "h": None if k == 2 else rng.integers(0, 256, (120, 160), dtype=np.uint8)}
            w.write(FrameSet(k, T0_NS + k * 38_461_538, im, {"h": transform_from_rt(exp_so3(rng.normal(size=3)),
                                                                                         rng.normal(size=3))}))
            images.append(im)
            A = rng.normal(size=(6, 6))
            status = "lost" if k == 4 else "tracking"
            T = transform_from_rt(exp_so3(rng.normal(size=3)), rng.normal(size=3))
            rows.append(PoseRow(k, k / 26.0, status, T if status == "tracking" else None, 1.5,
                                rng.normal(size=6), A @ A.T * 1e-6 if status == "tracking" else None,
                                probability=None if k == 0 else 0.25 * (k % 4)))
    write_poses(tmp_path / "vision" / "poses.csv", rows)
    (tmp_path / "vision" / "server.json").write_text(json.dumps({"t0_ns": T0_NS}))
    rec = Recorder(10)
    for i in range(10):  # 500 Hz ticks from 4 ms before frame 0: the first two precede the recording
        rec.append(t_ns=T0_NS - 4_000_000 + i * 2_000_000, q_cmd=rng.normal(size=6), qd_cmd=rng.normal(size=6),
                   q_meas=rng.normal(size=6), p_ref=rng.normal(size=3), quat_ref=[1.0, 0, 0, 0],
                   v_ref=rng.normal(size=3), status=i % 3, flags=0, compute_ns=50_000 + i)
    rec.save(tmp_path / "servo" / "servo")
    return images, rows, rec


def test_mcap_holds_every_frame_and_round_trips_pose_and_covariance(tmp_path):
    images, rows, servo = _run(tmp_path)
    out = tmp_path / "run.mcap"
    assert main(["export", "mcap", str(tmp_path / "vision" / "recording"), "--poses",
                 str(tmp_path / "vision" / "poses.csv"), "--servo", str(tmp_path / "servo"), "-o", str(out)]) == 0
    msgs = {}
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, message, ros in reader.iter_decoded_messages(log_time_order=True):
            msgs.setdefault(channel.topic, []).append((schema.name, message.log_time, ros))
    tracked = [r for r in rows if r.status == "tracking"]
    count = {t: len(v) for t, v in msgs.items()}
    assert count == {
        "/a/image_raw": N, "/a/camera_info": N, "/h/image_raw": N - 1, "/h/camera_info": N - 1,
        "/tf_static": 1, "/tf": N, "/vespro/status": N, "/vespro/probability": N - 1, "/vespro/pose": len(tracked),
        "/vespro/velocity": len(tracked),
        **{t: 8 for t in ("/servo/joint_states", "/servo/joint_command", "/servo/reference",
                          "/servo/reference_velocity", "/servo/status", "/servo/flags", "/servo/compute_time")},
    }
    # Images: bytes, encoding and stamps (the recording's t).
    rec_t = [k * 38_461_538 for k in range(N)]
    for k, (name, t, im) in enumerate(msgs["/a/image_raw"]):
        assert name == "sensor_msgs/msg/Image" and im.encoding == "bgr8" and t == rec_t[k]
        assert im.header.stamp.sec * 10**9 + im.header.stamp.nanosec == t
        np.testing.assert_array_equal(np.frombuffer(bytes(im.data), np.uint8).reshape(240, 320, 3), images[k]["a"])
    assert msgs["/h/image_raw"][0][2].encoding == "mono8"
    info = msgs["/a/camera_info"][0][2]
    assert info.distortion_model == "plumb_bob" and list(info.d) == [0.1, -0.01, 0.001, 0.002, 0.0005]
    assert list(info.k) == [500, 0, 159.5, 0, 500, 119.5, 0, 0, 1] and list(info.p)[3] == 0.0
    # Pose and covariance exactly as read from poses.csv (float64 all the way).
    back = read_poses(tmp_path / "vision" / "poses.csv")
    for (name, t, m), r in zip(msgs["/vespro/pose"], [b for b in back if b.status == "tracking"]):
        assert name == "geometry_msgs/msg/PoseWithCovarianceStamped" and m.header.frame_id == "world"
        pq = pq_from_transform(r.T_world_object)
        p, o = m.pose.pose.position, m.pose.pose.orientation
        assert [p.x, p.y, p.z, o.w, o.x, o.y, o.z] == pq.tolist()
        assert list(m.pose.covariance) == r.cov.reshape(36).tolist()
        assert t == rec_t[r.index]
    # The probability where poses.csv states one (not on frame 0).
    assert [(t, m.data) for _, t, m in msgs["/vespro/probability"]] == [(rec_t[k], 0.25 * (k % 4)) for k in range(1, N)]
    # Servo ticks on the recording's time line; the two before frame 0 are left out.
    js = msgs["/servo/joint_states"]
    assert [t for _, t, _ in js] == [i * 2_000_000 for i in range(8)]
    np.testing.assert_array_equal(js[0][2].position, servo.data["q_meas"][2])
    assert list(js[0][2].name) == ["j1", "j2", "j3", "j4", "j5", "j6"]
    # The part on /tf only where tracked, the eye-in-hand camera always.
    tf = [sorted(x.child_frame_id for x in m.transforms) for _, _, m in msgs["/tf"]]
    assert tf[4] == ["h"] and all(f == ["box", "h"] for i, f in enumerate(tf) if i != 4)


def test_rosbags_reads_the_same_messages(tmp_path):
    """A second reader with its own CDR decoder and msg parser (rosbags) agrees."""
    from rosbags.highlevel import AnyReader

    _, rows, _ = _run(tmp_path)
    out = tmp_path / "run.mcap"
    export_mcap(tmp_path / "vision" / "recording", out, poses=tmp_path / "vision" / "poses.csv")
    covs = []
    with AnyReader([out]) as reader:
        conns = [c for c in reader.connections if c.topic == "/vespro/pose"]
        for conn, t, raw in reader.messages(connections=conns):
            covs.append(reader.deserialize(raw, conn.msgtype).pose.covariance)
    tracked = [r for r in read_poses(tmp_path / "vision" / "poses.csv") if r.status == "tracking"]
    assert len(covs) == len(tracked)
    for c, r in zip(covs, tracked):
        np.testing.assert_array_equal(np.asarray(c).reshape(6, 6), r.cov)


def test_bad_inputs_are_one_line_errors(tmp_path, capsys):
    _run(tmp_path)
    rec = str(tmp_path / "vision" / "recording")
    assert main(["export", "mcap", rec, "--servo", str(tmp_path / "nowhere"), "-o", str(tmp_path / "x.mcap")]) == 2
    assert "servo.npz: missing" in capsys.readouterr().err
    (tmp_path / "vision" / "server.json").write_text("{}")
    assert main(["export", "mcap", rec, "--servo", str(tmp_path / "servo"), "-o", str(tmp_path / "x.mcap")]) == 2
    assert "--servo-t0-ns" in capsys.readouterr().err
    rows = [PoseRow(N + 3, 0.0, "lost")]
    write_poses(tmp_path / "other.csv", rows)
    assert main(["export", "mcap", rec, "--poses", str(tmp_path / "other.csv"), "-o", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert "not a frame" in err and err.count("\n") == 1
