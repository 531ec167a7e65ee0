"""The Rerun view: a short track saved with --view-save, read back with Rerun's own reader."""

from collections import defaultdict

import numpy as np
import pytest

rr = pytest.importorskip("rerun", reason="the live view needs the view extra (pip install 'vespro[view]')")

from rerun.chunk import RrdReader  # noqa: E402

from vespro.cli import main  # noqa: E402
from vespro.groundtruth import read_groundtruth  # noqa: E402
from vespro.rig import load_rig  # noqa: E402
from vespro.se3 import pq_from_transform  # noqa: E402
from vespro.sim.cell import CellConfig  # noqa: E402
from vespro.sim.motion import Conveyor  # noqa: E402
from vespro.sim.record import record  # noqa: E402
from vespro.sim.rigs import CAMERAS_DIR  # noqa: E402
from vespro.sim.scene import MODELS_DIR  # noqa: E402

N = 8


def rrd_rows(path) -> dict:
    """entity path -> {frame index (None: static): {column: value}}, the columns logged at that frame."""
    rows = defaultdict(dict)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        cols = [c for c in batch.schema.names if c not in ("capture_time", "log_time")]
        data = {c: batch.column(c).to_pylist() for c in cols}
        frames = data.pop("frame", None) or [None] * batch.num_rows
        for k, f in enumerate(frames):
            rows[chunk.entity_path].setdefault(f, {}).update({c: v[k] for c, v in data.items() if v[k] is not None})
    return rows


def _col(row: dict, suffix: str):
    (value,) = [v for c, v in row.items() if c.endswith(suffix)]
    return value


@pytest.fixture(scope="module")
def rec_path(tmp_path_factory):
    cfg = CellConfig(MODELS_DIR / "objects" / "box.stl", load_rig(CAMERAS_DIR / "fixed2.yaml"))
    return record(tmp_path_factory.mktemp("view") / "rec", cfg, Conveyor(speed=0.1, y0=-0.2), N, "box")


def test_view_save_of_a_track_holds_images_pose_and_series_for_every_frame(rec_path, tmp_path):
    _, _, T = read_groundtruth(rec_path)
    pose = ",".join(f"{v:.9f}" for v in pq_from_transform(T[0]))
    rrd = tmp_path / "run.rrd"
    out = tmp_path / "poses.csv"
    assert main(["track", str(rec_path), "--init-pose", pose, "-o", str(out), "--no-progress",
                 "--view-save", str(rrd)]) == 0
    rows = rrd_rows(rrd)
    frames = set(range(N))
    for cam in ("cam_left", "cam_right"):
        images = rows[f"/world/cameras/{cam}/image"]
        assert set(images) >= frames  # an image of every camera at every frame
        assert all(_col(images[f], "EncodedImage:blob") for f in frames)
        assert set(rows[f"/world/cameras/{cam}/image/corners"]) >= frames
        assert None in rows[f"/world/cameras/{cam}"]  # the fixed camera's pose, once (static)
    from vespro.poses import read_poses
    from vespro.viewer import STATUS_CODE

    poses = read_poses(out)
    est = rows["/world/estimate"]
    assert sum(r.status == "tracking" for r in poses) >= N - 2
    for r in poses:  # the 3D pose logged is the tracker's, at every frame it tracked
        if r.status == "tracking":
            t = np.asarray(_col(est[r.index], "Transform3D:translation"), dtype=float).ravel()
            np.testing.assert_allclose(t, r.T_world_object[:3, 3], atol=1e-6)  # float32 in Rerun: 1 um at 1 m
            assert _col(rows["/world/estimate_cov"][r.index], "Ellipsoids3D:half_sizes")
            assert _col(rows["/world/cameras/cam_left/image/model"][r.index], "LineStrips2D:strips")
        else:
            assert _col(est[r.index], "Clear:is_recursive")
        assert _col(rows["/series/status"][r.index], "Scalars:scalars") == [STATUS_CODE[r.status]]
    for name in ("features_used", "tracker_ms"):
        assert set(rows[f"/series/{name}"]) >= frames
    assert "/world/truth" not in rows  # tracking never shows ground truth


def test_view_save_of_a_lockstep_demo_shows_estimate_truth_and_servo(tmp_path):
    """The demo (an evaluator) adds the true pose, the arm and the servo's series to the view."""
    from vespro.demo import DemoConfig, run_demo
    from vespro.poses import read_poses
    from vespro.recording import Recording

    rrd = tmp_path / "demo.rrd"
    run_demo(DemoConfig(out=tmp_path / "demo", object="box", cameras="fixed", duration=0.4, lockstep=True,
                        video=False, view_save=rrd), log=lambda m: None)
    rows = rrd_rows(rrd)
    rec = Recording(tmp_path / "demo" / "vision" / "recording")
    poses = read_poses(tmp_path / "demo" / "vision" / "poses.csv")
    frames = set(range(len(rec)))
    assert len(frames) >= 10 and len(poses) == len(frames)
    for cam in rec.rig.names:
        assert set(rows[f"/world/cameras/{cam}/image"]) >= frames
    assert set(rows["/world/truth"]) == frames and set(rows["/series/status"]) >= frames
    tracked = [r for r in poses if r.status == "tracking"]
    assert len(tracked) >= len(frames) - 2
    for r in tracked:
        t = np.asarray(_col(rows["/world/estimate"][r.index], "Transform3D:translation"), dtype=float).ravel()
        np.testing.assert_allclose(t, r.T_world_object[:3, 3], atol=1e-6)  # float32 in Rerun
        err = _col(rows["/series/error_mm"][r.index], "Scalars:scalars")[0]
        assert 0.0 < err < 5.0  # the estimate beside the truth, a millimetre or so apart
    # The servo's series and the arm, at 50 Hz of cell time (on the capture_time timeline only).
    assert len(_col(rows["/series/servo_status"][None], "Scalars:scalars")) >= 1
    assert "/world/arm/tcp" in rows and "/world/arm/target" in rows
