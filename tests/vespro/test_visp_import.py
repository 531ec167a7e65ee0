"""``vespro import visp``: ViSP camera, pose and tutorial folders in, a recording out."""

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from test_cao import CUBE
from vespro.cli import main
from vespro.recording import Recording
from vespro.track import parse_pose
from vespro.visp import read_visp_camera, read_visp_pose

VISP_MBT = Path("/usr/share/visp-images-data/ViSP-images/mbt")

CUBE_CAO = CUBE  # ViSP's tutorial cube, as a .cao


# vpXmlParserCamera's layout, both models; the importer takes the one with distortion.
CAMERA_XML = """<?xml version="1.0"?>
<root>
  <camera>
    <name>Camera</name>
    <image_width>64</image_width>
    <image_height>48</image_height>
    <model>
      <type>perspectiveProjWithoutDistortion</type>
      <px>100.5</px> <py>101.5</py> <u0>31.5</u0> <v0>23.5</v0>
    </model>
    <model>
      <type>perspectiveProjWithDistortion</type>
      <px>99.0</px> <py>100.0</py> <u0>32.0</u0> <v0>24.0</v0>
      <kud>-0.21</kud> <kdu>0.22</kdu>
    </model>
  </camera>
</root>
"""

POS = "0.01 -0.02 0.5  # translation, m\n0.3\n-0.2\n0.1\n"


@pytest.fixture
def visp_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("VESPRO_MODEL_CACHE", str(tmp_path / "cache"))
    d = tmp_path / "mbt"
    (d / "cube").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(d / "cube" / f"image{i:04d}.pgm"), rng.integers(0, 256, (48, 64), dtype=np.uint8))
    (d / "cube.cao").write_text(CUBE_CAO)
    (d / "cube.xml").write_text(CAMERA_XML)
    (d / "cube.0.pos").write_text(POS)
    return d


def test_pose_file_is_translation_then_theta_u(tmp_path):
    p = tmp_path / "a.pos"
    p.write_text(POS)
    T = read_visp_pose(p)
    R_cv, _ = cv2.Rodrigues(np.array([0.3, -0.2, 0.1]))  # independent theta-u -> matrix
    np.testing.assert_allclose(T[:3, :3], R_cv, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [0.01, -0.02, 0.5])


def test_distortion_maps_to_plumb_bob_k1_exactly(visp_folder):
    cam, note = read_visp_camera(visp_folder / "cube.xml")
    assert (cam.px, cam.kud, cam.width) == (99.0, -0.21, 64) and "kud" in note
    intr = cam.intrinsics(64, 48)
    P = np.array([[0.05, -0.03, 0.4], [-0.1, 0.08, 0.5]])
    uv_cv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), intr.K, intr.dist)
    # ViSP's projection with distortion, by hand: u = u0 + px x (1 + kud r^2).
    x, y = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
    f = 1 + cam.kud * (x * x + y * y)
    np.testing.assert_allclose(uv_cv[:, 0], np.c_[cam.u0 + cam.px * x * f, cam.v0 + cam.py * y * f], atol=1e-9)


def test_folder_becomes_a_recording_with_its_start_pose(visp_folder, tmp_path, capsys):
    out = tmp_path / "rec"
    assert main(["import", "visp", str(visp_folder), "-o", str(out), "--rate", "25", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    rec = Recording(out)
    assert len(rec) == 3 and rec.rig.names == ["cam0"] and rec.object_name == "cube"
    np.testing.assert_allclose(rec.t, [0, 0.04, 0.08])
    cam = rec.rig["cam0"]
    np.testing.assert_allclose(cam.T_world_camera, np.eye(4))
    np.testing.assert_allclose(cam.intrinsics.K, [[99, 0, 32], [0, 100, 24], [0, 0, 1]])
    np.testing.assert_allclose(cam.intrinsics.dist, [-0.21, 0, 0, 0, 0])
    src = cv2.imread(str(visp_folder / "cube" / "image0002.pgm"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(rec.image("cam0", 2), src)
    # World = camera: the start pose is ViSP's cMo, written where --init-pose takes it.
    np.testing.assert_allclose(parse_pose(str(out / "init_pose.txt")), read_visp_pose(visp_folder / "cube.0.pos"),
                               atol=1e-8)
    assert f"vespro track {out} --init-pose {out / 'init_pose.txt'}" in printed
    from vespro.model import load_model

    m = load_model(rec.model_path)
    assert abs(m.volume - 0.084**3) < 1e-9 and m.n_corners == 8


def _break(folder: Path, what: str) -> list[str]:
    extra = []
    if what == "no folder":
        folder = folder / "nowhere"
    elif what == "no images":
        for p in (folder / "cube").iterdir():
            p.unlink()
    elif what == "bad xml":
        (folder / "cube.xml").write_text("<root><camera><px>1</px>")
    elif what == "xml field":
        (folder / "cube.xml").write_text(CAMERA_XML.replace("<py>100.0</py>", "<py>abc</py>"))
    elif what == "negative focal":
        (folder / "cube.xml").write_text(CAMERA_XML.replace("<px>99.0</px>", "<px>-99.0</px>"))
    elif what == "bad pos":
        (folder / "cube.0.pos").write_text("0.1 0.2 0.3\n")
    elif what == "bad cao":
        (folder / "cube.cao").write_text(CUBE_CAO.replace("4 1 5 6 2", "4 1 5 6 12"))
    elif what == "16-bit image":
        cv2.imwrite(str(folder / "cube" / "image0001.pgm"), np.zeros((48, 64), np.uint16))
    elif what == "size":
        cv2.imwrite(str(folder / "cube" / "image0001.pgm"), np.zeros((40, 64), np.uint8))
    elif what == "two models":
        (folder / "other.cao").write_text(CUBE_CAO)
    elif what == "exists":
        extra = ["-o", str(folder)]
    return ["import", "visp", str(folder), "--no-progress", *extra]


@pytest.mark.parametrize("what, match", [
    ("no folder", r"nowhere: no such folder"),
    ("no images", r"cube: no images"),
    ("bad xml", r"cube.xml: not a well-formed XML file"),
    ("xml field", r"cube.xml: <model> perspectiveProjWithDistortion: <py> must be a number, got 'abc'"),
    ("negative focal", r"cube.xml: .*focal lengths px, py must be positive"),
    ("bad pos", r"cube.0.pos: expected 6 finite numbers"),
    ("bad cao", r"cube.cao:19: point index 12 out of range"),
    ("16-bit image", r"image0001.pgm: uint16 image"),
    ("size", r"image0001.pgm: image size 64x40 differs"),
    ("two models", r"holds several models \(cube, other\): choose one with --name"),
    ("exists", r"exists and is not empty.*--overwrite"),
])
def test_bad_input_gives_one_line_and_exit_2(visp_folder, tmp_path, capsys, monkeypatch, what, match):
    monkeypatch.chdir(tmp_path)
    assert main(_break(visp_folder, what)) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1, err
    assert re.search(match, err), err


def _add_s(C, Ta, Tb):
    """Mean distance from each model corner at Ta to the nearest corner at Tb (blind to the cube's symmetry)."""
    A = C @ Ta[:3, :3].T + Ta[:3, 3]
    B = C @ Tb[:3, :3].T + Tb[:3, 3]
    return float(np.mean(np.min(np.linalg.norm(A[:, None] - B[None], axis=2), axis=1)))


def _edge_gradient(img, model, intr, T_camera_object):
    """Median image gradient along the model's edges facing the camera, sampled at 30 points each."""
    from vespro.camera import project_points

    g = cv2.GaussianBlur(img.astype(np.float32), (3, 3), 0)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    c = np.linalg.inv(T_camera_object)[:3, 3]
    s = np.linspace(0.1, 0.9, 30)[:, None]
    vals = []
    for (a, b), faces in zip(model.edge_vertices, model.edge_faces):
        if any(model.face_normals[f] @ (c - model.vertices[a]) > 0 for f in faces):
            uv, _ = project_points(intr, T_camera_object, model.vertices[a] * (1 - s) + model.vertices[b] * s)
            u = np.clip(np.round(uv).astype(int), 0, [img.shape[1] - 1, img.shape[0] - 1])
            vals.append(mag[u[:, 1], u[:, 0]])
    return float(np.median(np.concatenate(vals))), float(np.median(mag))


@pytest.mark.skipif(not (VISP_MBT / "cube").is_dir(), reason="visp-images-data is not installed")
def test_visp_cube_imports_and_tracks_from_the_converted_start_pose(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("VESPRO_MODEL_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "cube"
    assert main(["import", "visp", str(VISP_MBT), "--name", "cube", "-o", str(out), "--frames", "30",
                 "--no-progress"]) == 0
    assert main(["track", str(out), "--init-pose", str(out / "init_pose.txt"), "-o", str(out / "poses.csv"),
                 "--no-progress"]) == 0
    assert "30 frames" in capsys.readouterr().out
    from vespro.model import load_model
    from vespro.poses import read_poses

    rec = Recording(out)
    model = load_model(rec.model_path)
    rows = read_poses(out / "poses.csv")
    T0 = parse_pose(str(out / "init_pose.txt"))
    tracked = [r for r in rows if r.status == "tracking"]
    # The filter confirms a given start over a few frames, then holds on to the cube.
    assert len(tracked) >= 25 and all(r.status == "tracking" for r in rows[5:])
    # The cube stands still in these frames. ViSP's start pose sits 6.6-6.9 mm (corner-set
    # distance) from where the edges put it (its edge gradient, below, is a third of the
    # tracked pose's): a few mm either way of that, and no drift from frame to frame.
    d0 = [_add_s(model.corners, r.T_world_object, T0) for r in tracked]
    assert max(d0) < 0.010, d0
    steps = [_add_s(model.corners, a.T_world_object, b.T_world_object) for a, b in zip(tracked, tracked[1:])]
    assert max(steps) < 0.001, steps
    # The projected edges land on image edges: far above the image's typical gradient, and
    # well above the same edges moved 4 mm sideways.
    intr = rec.rig["cam0"].intrinsics
    for r in (tracked[0], tracked[-1]):
        img = rec.image("cam0", r.index)
        on, typical = _edge_gradient(img, model, intr, r.T_world_object)
        T_off = r.T_world_object.copy()
        T_off[:3, 3] += [0.004, 0.004, 0.0]
        off, _ = _edge_gradient(img, model, intr, T_off)
        assert on > 10 * typical and on > 2.5 * off, (on, typical, off)
