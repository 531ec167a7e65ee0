"""Board geometry and detection against independent truth.

- Synthetic: the printable board image warped by a known homography; detected
  corners must land where the homography sends the known corner positions
  (orientation included: a chessboard turned by 180 deg must be renumbered).
- Simulator: boards rendered in the MuJoCo cell; corners detected in the
  rendered (distorted) images must match the projection of the board's known
  corners through the rig (the texture maps exactly onto the board geometry).
"""

import cv2
import numpy as np
import pytest

from vespro.calib import CalibrationError
from vespro.calib.board import BoardSpec, board_image, detect_board, require_unambiguous
from vespro.camera import CameraIntrinsics, project_points
from vespro.rig import Rig, RigCamera, load_rig
from vespro.se3 import exp_so3, transform_from_rt
from vespro.sim.board import board_extra, set_board_pose
from vespro.sim.rigs import CAMERAS_DIR

DIST = (-0.22, 0.09, 0.0006, -0.0004, -0.015)
PX = 40  # texture pixels per square in the synthetic images
MARGIN = 30


def _warped(spec, H_img_tex, size=(800, 600)):
    tex = board_image(spec, PX, MARGIN)
    return cv2.warpPerspective(tex, H_img_tex, size, flags=cv2.INTER_AREA, borderValue=128)


def _expected(spec, H_img_tex):
    # Board metres -> texture pixels: pixel edges on square boundaries, so the
    # corner at x metres is at texture coordinate x/s*PX + MARGIN - 0.5 (pixel centres).
    tex = spec.P_board[:, :2] / spec.square_size * PX + MARGIN - 0.5
    return cv2.perspectiveTransform(tex.reshape(-1, 1, 2), H_img_tex).reshape(-1, 2)


def _homography(turn: float):
    c, s = np.cos(turn), np.sin(turn)
    H = np.array([[0.9 * c, -0.9 * s, 0.0], [0.9 * s, 0.9 * c, 0.0], [0.0, 0.0, 1.0]])
    H[:2, 2] = [400, 300] - H[:2, :2] @ [250, 180]
    P = np.array([[1.0, 0.05, 0.0], [0.02, 1.0, 0.0], [1e-4, 5e-5, 1.0]])
    return P @ H


@pytest.mark.parametrize("kind", ["chessboard", "charuco"])
@pytest.mark.parametrize("turn_deg", [0.0, 180.0, 25.0, -150.0])
def test_detection_matches_homography_truth(kind, turn_deg):
    spec = BoardSpec(kind, 9, 6, 0.035, 0.026 if kind == "charuco" else None)
    H = _homography(np.deg2rad(turn_deg))
    det = detect_board(_warped(spec, H), spec)
    assert det is not None
    assert len(det) >= 0.9 * spec.n_corners
    d = det.uv - _expected(spec, H)[det.ids]
    err = np.linalg.norm(d, axis=1)
    # A wrong numbering (the 180-deg turn) is off by whole squares (> 30 px); the
    # warp's bilinear resampling of a 40 px/square texture leaves < 0.25 px noise.
    assert err.max() < 0.25, err.max()
    assert np.linalg.norm(d.mean(0)) < 0.05


def test_no_board_and_symmetric_board():
    spec = BoardSpec("chessboard", 9, 6, 0.035, None)
    assert detect_board(np.full((480, 640), 200, np.uint8), spec) is None
    assert detect_board(np.full((480, 640), 200, np.uint8), BoardSpec()) is None
    sym = BoardSpec("chessboard", 8, 6, 0.035, None)
    assert sym.symmetric and not spec.symmetric and not BoardSpec().symmetric
    with pytest.raises(CalibrationError, match="180"):
        require_unambiguous(sym, "extrinsic calibration")


def test_board_spec_validation():
    with pytest.raises(ValueError, match="marker size"):
        BoardSpec("charuco", 9, 6, 0.03, 0.04)
    with pytest.raises(ValueError, match="dictionary"):
        BoardSpec("charuco", 9, 6, 0.03, 0.02, "DICT_NOPE")
    with pytest.raises(ValueError, match="markers"):
        BoardSpec("charuco", 20, 20, 0.03, 0.02, "DICT_4X4_50")


@pytest.mark.parametrize("kind", ["chessboard", "charuco"])
def test_sim_texture_maps_onto_board_geometry(kind):
    """Rendered corners vs the rig's projection of the known corners (< 0.2 px)."""
    from vespro.sim.cell import CellConfig, SimCell
    from vespro.sim.motion import Static
    from vespro.sim.scene import MODELS_DIR, PARK_POS

    spec = BoardSpec(kind, 9, 6, 0.035, 0.026 if kind == "charuco" else None)
    base = load_rig(CAMERAS_DIR / "fixed1.yaml")["cam_left"]
    intr = CameraIntrinsics(640, 480, base.intrinsics.K, DIST)
    rig = Rig((RigCamera("cam_left", intr, "fixed", T_world_camera=base.T_world_camera),))
    cfg = CellConfig(MODELS_DIR / "objects" / "box.stl", rig, scene_extras=(board_extra(spec),))
    W, H = spec.size
    errs, means = [], []
    with SimCell(cfg, Static(transform_from_rt(np.eye(3), PARK_POS))) as cell:
        # Poses chosen by hand: centre, off-centre (strong distortion), tilted both ways.
        for rv, t in [([0, 0, 0], [0, 0, 0.6]), ([0.5, 0, 0.2], [0.1, 0.07, 0.55]), ([0, -0.6, 0], [-0.1, -0.08, 0.6])]:
            R = exp_so3(rv)
            T_cb = transform_from_rt(R, np.array(t) - R @ [W / 2, H / 2, 0])
            set_board_pose(cell, base.T_world_camera @ T_cb)
            img = cell.capture().images["cam_left"]
            det = detect_board(img, spec)
            assert det is not None and len(det) >= 0.8 * spec.n_corners
            uv, _ = project_points(intr, T_cb, spec.P_board[det.ids])
            errs.append(np.linalg.norm(det.uv - uv, axis=1))
            means.append(np.linalg.norm((det.uv - uv).mean(0)))
    errs = np.concatenate(errs)
    # Rendering (texture filtering, multisampling, remap) leaves ~0.07 px RMS noise;
    # a half-texel or a flipped-v texture mapping error would be >= 0.3 px everywhere.
    assert errs.max() < 0.25, errs.max()
    assert np.sqrt(np.mean(errs ** 2)) < 0.12
    assert max(means) < 0.05
