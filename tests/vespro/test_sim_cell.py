"""The simulated cell against independent computations.

- Markers: the rendered centroid of a small sphere at a known point lies within
  0.5 px of its projection computed from cameras.yaml (+ frames.csv for the
  eye-in-hand camera) alone, read back from a written recording.
- Ground truth: the object's silhouette in the rendered image matches the CAD
  mesh projected at the ground-truth pose.
"""

from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from vespro.camera import CameraIntrinsics, project_points
from vespro.groundtruth import read_groundtruth
from vespro.recording import Recording, RecordingWriter
from vespro.rig import Rig, RigCamera, load_rig
from vespro.se3 import invert_transform, transform_from_rt
from vespro.sim.cell import CellConfig, SimCell
from vespro.sim.motion import Conveyor, Static
from vespro.sim.record import record
from vespro.sim.rigs import CAMERAS_DIR, STANDARD_RIGS, rig_from_model
from vespro.sim.scene import CELL_XML, MODELS_DIR, PARK_POS

BOX = MODELS_DIR / "objects" / "box.stl"
HIDDEN = Static(transform_from_rt(np.eye(3), PARK_POS))

# Marker points spread over the working area (m, world).
MARKERS = np.array([
    [0.90, 0.00, 0.55], [0.80, -0.12, 0.52], [1.00, 0.12, 0.60],
    [0.85, 0.14, 0.70], [0.98, -0.10, 0.66],
])


def _hybrid_rig(distortion=None):
    rig = Rig(load_rig(CAMERAS_DIR / "fixed3.yaml").cameras + load_rig(CAMERAS_DIR / "hand.yaml").cameras)
    if distortion is None:
        return rig
    return Rig(tuple(
        RigCamera(c.name, CameraIntrinsics(c.intrinsics.width, c.intrinsics.height, c.intrinsics.K, distortion),
                  c.mount, c.T_world_camera, c.link, c.T_link_camera)
        for c in rig
    ))


def _red_blobs(img):
    """Centroids of red blobs (binary mask: no shading bias)."""
    b, g, r = [img[..., i].astype(int) for i in range(3)]
    mask = ((r - np.maximum(g, b)) > 60).astype(np.uint8)
    n, _, stats, cents = cv2.connectedComponentsWithStats(mask)
    return [cents[i] for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= 4]


@pytest.mark.parametrize("distortion", [None, (-0.2, 0.08, 0.0008, -0.0005, -0.01)], ids=["pinhole", "plumb_bob"])
def test_marker_centroids_match_projection_from_rig_file(tmp_path, distortion):
    rig = _hybrid_rig(distortion)
    cfg = CellConfig(BOX, rig, arm="watch", markers=len(MARKERS))
    with SimCell(cfg, HIDDEN) as cell, RecordingWriter(tmp_path / "rec", rig, BOX, cfg.rate_hz, "box") as w:
        cell.settle_arm()
        for i, p in enumerate(MARKERS):
            cell.set_marker(i, p)
        for _ in range(30):  # more than a second: the arm (and the hand camera) has moved
            fs = cell.next_frameset()
            w.write(fs)
    rec = Recording(tmp_path / "rec")  # from here on, only what the files say
    last = len(rec) - 1
    assert np.linalg.norm(rec.T_world_camera("hand", last)[:3, 3] - rec.T_world_camera("hand", 0)[:3, 3]) > 0.01
    for cam in rec.rig:
        img = rec.image(cam.name, last)
        T_cw = invert_transform(rec.T_world_camera(cam.name, last))
        uv, z = project_points(cam.intrinsics, T_cw, MARKERS)
        blobs = _red_blobs(img)
        errs = []
        for q in uv:
            inside = 10 < q[0] < cam.intrinsics.width - 10 and 10 < q[1] < cam.intrinsics.height - 10
            if not inside or not blobs:
                continue
            d = [np.linalg.norm(b - q) for b in blobs]
            if min(d) < 5.0:  # else hidden behind something: not this marker's blob
                errs.append(min(d))
        assert len(errs) >= 2, f"{cam.name}: too few markers seen ({len(errs)})"
        # 0.5 px: the bound; a sphere's projected centroid differs from its centre's
        # projection by ~(r/z)^2 * offset, far below it at r = 4 mm, z > 0.3 m.
        assert max(errs) < 0.5, f"{cam.name}: marker errors {np.round(errs, 3)} px"


def test_groundtruth_matches_body_pose_and_rendered_silhouette(tmp_path):
    rig = load_rig(CAMERAS_DIR / "fixed2.yaml")
    motion = Conveyor(speed=0.1, y0=-0.1)
    cfg = CellConfig(BOX, rig)
    out = record(tmp_path / "rec", cfg, motion, 8, "box")
    idx, t, T = read_groundtruth(out)
    rec = Recording(out)
    np.testing.assert_array_equal(idx, rec.index)
    np.testing.assert_allclose(t, rec.t, atol=1e-9)
    # The body pose MuJoCo had at each capture instant: the scripted pose at that time
    # (capture times are the 2 ms physics steps at or after k / 26 s).
    for k in range(len(idx)):
        assert t[k] == pytest.approx(np.ceil(k / 26.0 / 0.002 - 1e-6) * 0.002, abs=1e-9)
        np.testing.assert_allclose(T[k], motion.pose(t[k]), atol=1e-8)
    # The rendered object matches the CAD mesh projected at the ground-truth pose.
    mesh = trimesh.load(BOX)
    for cam in rig:
        img = rec.image(cam.name, 5)
        uv, _ = project_points(cam.intrinsics, invert_transform(cam.T_world_camera) @ T[5], mesh.vertices)
        pred = np.zeros(img.shape[:2], np.uint8)
        for f in mesh.faces:
            cv2.fillConvexPoly(pred, np.round(uv[f] * 16).astype(np.int32), 1, shift=4)
        grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        # The belt renders at grey ~15, the part's darkest face at ~45: threshold between.
        seen = (grey > 28).astype(np.uint8)
        x0, y0, w, h = cv2.boundingRect(pred)
        roi = (slice(max(y0 - 5, 0), y0 + h + 5), slice(max(x0 - 5, 0), x0 + w + 5))
        inter = np.sum(pred[roi] & seen[roi])
        union = np.sum(pred[roi] | seen[roi])
        assert inter / union > 0.95, f"{cam.name}: silhouette IoU {inter / union:.3f}"


def test_standard_rig_files_match_the_mujoco_cameras():
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(CELL_XML))
    for stem, names in STANDARD_RIGS.items():
        committed = load_rig(CAMERAS_DIR / f"{stem}.yaml")
        fresh = rig_from_model(model, names)
        assert committed.names == fresh.names
        for a, b in zip(committed, fresh):
            np.testing.assert_allclose(a.intrinsics.K, b.intrinsics.K, atol=1e-5)
            Ta = a.T_world_camera if a.is_fixed else a.T_link_camera
            Tb = b.T_world_camera if b.is_fixed else b.T_link_camera
            np.testing.assert_allclose(Ta, Tb, atol=1e-7)


def test_dropout_and_occluder(tmp_path):
    from vespro.sim.cell import CameraDropout, OccluderSweep

    rig = load_rig(CAMERAS_DIR / "fixed2.yaml")
    cfg = CellConfig(BOX, rig, dropouts=(CameraDropout("cam_right", 0.1, 0.2),),
                     occluders=(OccluderSweep("cam_left", 0.0, 0.4),))
    out = record(tmp_path / "rec", cfg, Conveyor(y0=0.0), 8, "box")
    rec = Recording(out)
    for k in range(len(rec)):
        present = rec.image("cam_right", k) is not None
        assert present == (not 0.1 <= rec.t[k] < 0.2)
    # Mid-sweep the paddle (blue) covers the middle of cam_left's view of the part.
    img = rec.image("cam_left", 5)
    b, g, r = [img[..., i].astype(int) for i in range(3)]
    assert np.mean((b - r) > 40) > 0.05


def test_bad_config_is_rejected():
    rig = load_rig(CAMERAS_DIR / "fixed2.yaml")
    with pytest.raises(ValueError, match="arm mode"):
        CellConfig(BOX, rig, arm="dance")
    from vespro.sim.cell import OccluderSweep

    with pytest.raises(ValueError, match="occluder camera"):
        CellConfig(BOX, rig, occluders=(OccluderSweep("nope", 0.0),))
    with pytest.raises(ValueError, match="mesh not found"):
        SimCell(CellConfig(Path("/nonexistent.stl"), rig), HIDDEN)


def test_floor_tiles_draw_the_texture_checker():
    """The geometric floor (the default, cheaper to rasterise) looks like the textured one it replaces."""
    import mujoco

    from vespro.sim.scene import SceneSpec, build_cell

    rig = load_rig(CAMERAS_DIR / "fixed2.yaml")
    images = {}
    for tiles in (False, True):
        model, info = build_cell(SceneSpec(MODELS_DIR / "objects" / "box.stl", rig, render_samples=0,
                                           floor_tiles=tiles))
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        r = mujoco.Renderer(model, 480, 640)
        r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        views = []
        for cam in rig:
            r.update_scene(data, camera=info["render"][cam.name][1])
            views.append(r.render().astype(int))
        r.close()
        images[tiles] = np.stack(views)
        floor_tex = model.mat_texid[model.material("floor_mat").id]
        assert (floor_tex < 0).all() == tiles  # no texture sampled with tiles
    diff = np.abs(images[True] - images[False]).max(axis=-1)
    assert diff.mean() < 1.0
    assert (diff > 8).mean() < 0.01  # only along the checks' edges (texture filtering vs geometry)
    # ...and the checker is there: the floor is not one flat grey.
    floor = images[True][0][300:, :].reshape(-1, 3)
    assert len(np.unique(floor // 8, axis=0)) > 2


def test_the_cell_reads_its_renders_as_mujocos_renderer_gives_them():
    """The cell reads each render into buffers of its own (no fresh image a frame); the image
    is MuJoCo's ``Renderer.render`` of the same scene to the bit, frame after frame."""
    import mujoco

    rig = _hybrid_rig()
    cfg = CellConfig(BOX, rig)
    with SimCell(cfg, Conveyor(y0=-0.1)) as cell:
        for _ in range(2):
            cell.next_frameset()
            for cam in rig:
                rintr, mj_name = cell._render_info[cam.name]
                r = cell._renderers[(rintr.height, rintr.width)]
                r.update_scene(cell.data, camera=mj_name)
                r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
                r.scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = False
                ours = cell._render_rgb(r, (rintr.height, rintr.width)).copy()
                assert np.array_equal(ours, r.render())
                assert ours.std() > 5  # a scene, not a blank buffer
