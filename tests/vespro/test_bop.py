"""BOP interchange: a recording with tracker output survives export and import unchanged."""

import json

import cv2
import numpy as np
import pytest

from vespro.bop import export_bop, import_bop, read_results_csv
from vespro.camera import project_points
from vespro.cli import main
from vespro.groundtruth import read_groundtruth
from vespro.model import load_model
from vespro.poses import PoseRow, read_poses, write_poses
from vespro.recording import Recording
from vespro.se3 import exp_so3, invert_transform, transform_from_rt


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A short hybrid-rig recording (two fixed cameras and an eye-in-hand one) and a poses.csv."""
    d = tmp_path_factory.mktemp("bop")
    rec_path = d / "rec"
    assert main(["record", str(rec_path), "--frames", "4", "--rig", "hybrid", "--object", "box",
                 "--no-progress"]) == 0
    _, t, T_true = read_groundtruth(rec_path)
    rng = np.random.default_rng(0)
    rows = [PoseRow(0, float(t[0]), "initializing")]
    for i in range(1, len(t)):
        dT = transform_from_rt(exp_so3(rng.normal(0, 0.01, 3)), rng.normal(0, 0.002, 3))
        rows.append(PoseRow(i, float(t[i]), "tracking", T_true[i] @ dT, 1.5 + i))
    write_poses(d / "poses.csv", rows)
    return d, rec_path


def _same_pose(A, B, atol):
    np.testing.assert_allclose(A[:3, 3], B[:3, 3], atol=atol)
    np.testing.assert_allclose(A[:3, :3], B[:3, :3], atol=atol)


def test_round_trip_gives_identical_poses_rig_and_images(recorded):
    d, rec_path = recorded
    bop = d / "bop"
    assert main(["bop", "export", str(rec_path), str(bop), "--poses", str(d / "poses.csv")]) == 0
    res = import_bop(bop, d / "back")
    rec, back = Recording(rec_path), Recording(d / "back")
    _, t, T_true = read_groundtruth(rec_path)
    # In memory: only float64 arithmetic between the two (mm scaling, camera chain): ~1e-15 relative.
    for i in range(len(t)):
        _same_pose(res["T_true"][i], T_true[i], 1e-12)
    # On disk: groundtruth.csv keeps 9 decimals, poses.csv 9 significant digits.
    _, t2, T2 = read_groundtruth(d / "back")
    np.testing.assert_allclose(t2, t, atol=1e-12)
    np.testing.assert_allclose(T2, T_true, atol=2e-9)
    a, b = read_poses(d / "poses.csv"), read_poses(d / "back" / "poses.csv")
    assert [r.status == "tracking" for r in a] == [r.status == "tracking" for r in b]
    for ra, rb in zip(a, b):
        if ra.status == "tracking":
            _same_pose(rb.T_world_object, ra.T_world_object, 1e-8)
            assert rb.time_ms == pytest.approx(ra.time_ms, abs=1e-9)
    # The rig and the measured eye-in-hand poses.
    assert back.rig.names == rec.rig.names
    for c, cb in zip(rec.rig, back.rig):
        assert cb.mount == c.mount
        np.testing.assert_array_equal(cb.intrinsics.K, c.intrinsics.K)
        np.testing.assert_array_equal(cb.intrinsics.dist, c.intrinsics.dist)
        for i in range(len(rec)):
            _same_pose(back.T_world_camera(c.name, i), rec.T_world_camera(c.name, i), 2e-9)
        for i in range(len(rec)):
            assert rec.image_path(c.name, i).read_bytes() == back.image_path(c.name, i).read_bytes()
    # The model comes back in metres.
    np.testing.assert_allclose(load_model(back.model_path).vertices, load_model(rec.model_path).vertices, atol=1e-9)


def test_bop_files_follow_the_bop_conventions(recorded):
    """Project the model with OpenCV from the BOP fields alone and compare with our projection."""
    d, rec_path = recorded
    bop = d / "bop2"
    export_bop(rec_path, bop, d / "poses.csv")
    rec = Recording(rec_path)
    _, _, T_true = read_groundtruth(rec_path)
    model = load_model(rec.model_path)
    info = json.loads((bop / "models/models_info.json").read_text())["1"]
    assert info["diameter"] == pytest.approx(model.diameter * 1000)
    assert len(info["symmetries_discrete"]) == 3  # the box's three half turns (identity not listed)
    import trimesh

    V_mm = trimesh.load(str(bop / "models/obj_000001.ply"), process=False).vertices  # the raw numbers
    np.testing.assert_allclose(V_mm / 1000.0, model.vertices, atol=1e-12)
    assert info["min_z"] == pytest.approx(0.0) and info["size_x"] == pytest.approx(120.0, abs=1e-5)
    i = 2
    for k, cam in enumerate(rec.rig):
        sdir = bop / "test" / f"{k + 1:06d}"
        scam = json.loads((sdir / "scene_camera.json").read_text())[str(i)]
        sgt = json.loads((sdir / "scene_gt.json").read_text())[str(i)][0]
        K = np.array(scam["cam_K"]).reshape(3, 3)
        R = np.array(sgt["cam_R_m2c"]).reshape(3, 3)
        t_mm = np.array(sgt["cam_t_m2c"])
        uv_cv, _ = cv2.projectPoints(model.vertices * 1000.0, cv2.Rodrigues(R)[0], t_mm, K, np.array(scam["dist_coeffs"]))
        uv, _ = project_points(cam.intrinsics, invert_transform(rec.T_world_camera(cam.name, i)) @ T_true[i], model.vertices)
        np.testing.assert_allclose(uv_cv.reshape(-1, 2), uv, atol=1e-6)
        # world-to-camera: a world point (the object origin) lands where the m2c translation says
        Rw = np.array(scam["cam_R_w2c"]).reshape(3, 3)
        tw = np.array(scam["cam_t_w2c"])
        np.testing.assert_allclose(Rw @ (T_true[i][:3, 3] * 1000.0) + tw, t_mm, atol=1e-6)
        assert (sdir / "rgb" / f"{i:06d}.png").is_file() or (sdir / "gray" / f"{i:06d}.png").is_file()
    rows = read_results_csv(bop / "vespro_box-test.csv")
    assert {r["scene_id"] for r in rows} == {1, 2, 3} and {r["im_id"] for r in rows} == {1, 2, 3}


def test_import_of_a_plain_bop_dataset_without_our_extras(recorded):
    d, rec_path = recorded
    bop = d / "bop3"
    export_bop(rec_path, bop)
    (bop / "vespro.json").unlink()
    res = import_bop(bop, d / "plain", rate_hz=26.0)
    back = Recording(d / "plain")
    rec = Recording(rec_path)
    # Scenes become cameras cam1..cam3; the moving one (the hand camera) is eye-in-hand.
    assert back.rig.names == ["cam1", "cam2", "cam3"]
    assert [c.is_fixed for c in back.rig] == [c.is_fixed for c in rec.rig]
    _, _, T_true = read_groundtruth(rec_path)
    np.testing.assert_allclose(res["T_true"], T_true, atol=1e-12)
    np.testing.assert_allclose(back.t, np.arange(len(rec)) / 26.0, atol=1e-9)
    assert not (d / "plain" / "poses.csv").exists()
