import cv2
import numpy as np
import pytest

from vespro import se3
from vespro.camera import CameraIntrinsics, project_points
from vespro.projection import apply_pose_error, project_with_jacobian, refine_pose_gauss_newton

K = np.array([[600.0, 0.0, 321.0], [0.0, 590.0, 238.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.21, 0.09, 0.001, -0.0015, -0.02])


def _scene(seed=0, n=50):
    rng = np.random.default_rng(seed)
    T_wc = se3.transform_from_rt(se3.exp_so3(rng.normal(0, 0.3, 3)), rng.normal(0, 0.2, 3))
    # object about 0.8 m in front of the camera, arbitrary orientation
    p_c = np.array([0.05, -0.03, 0.8])
    T_co = se3.transform_from_rt(se3.exp_so3(rng.normal(0, 1.0, 3)), p_c)
    T_wo = T_wc @ T_co
    P = rng.uniform(-0.1, 0.1, size=(n, 3))
    return T_wc, T_wo, P


@pytest.mark.parametrize("dist", [np.zeros(5), DIST])
def test_uv_matches_opencv(dist):
    intr = CameraIntrinsics(640, 480, K, dist)
    T_wc, T_wo, P = _scene()
    uv, depth, J = project_with_jacobian(intr, T_wc, T_wo, P)
    T_co = se3.invert_transform(T_wc) @ T_wo
    rvec, _ = cv2.Rodrigues(T_co[:3, :3])
    ref, _ = cv2.projectPoints(P, rvec, T_co[:3, 3], K, dist)
    # same double-precision formula evaluated in another order: 1e-9 px
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(depth, se3.transform_points(T_co, P)[:, 2], atol=1e-12)
    assert J.shape == (len(P), 2, 6)


@pytest.mark.parametrize("dist", [np.zeros(5), DIST])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jacobian_matches_central_differences(dist, seed):
    intr = CameraIntrinsics(640, 480, K, dist)
    T_wc, T_wo, P = _scene(seed)
    _, _, J = project_with_jacobian(intr, T_wc, T_wo, P)
    h = 1e-6
    J_fd = np.empty_like(J)
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        up, _, _ = project_with_jacobian(intr, T_wc, apply_pose_error(T_wo, d), P)
        um, _, _ = project_with_jacobian(intr, T_wc, apply_pose_error(T_wo, -d), P)
        J_fd[:, :, k] = (up - um) / (2 * h)
    # central differences: truncation O(h^2 * u''') ~1e-9 px, rounding ~1e-16*400/1e-6 ~ 1e-7;
    # J entries are ~1e2..1e3 px/unit, so 1e-5 relative is still a sharp test.
    np.testing.assert_allclose(J, J_fd, rtol=1e-5, atol=1e-4)


def test_jacobian_convention_is_left_world_rotation_about_object_origin():
    # A pure rotation about world z through the object origin leaves the
    # projection of the object origin unchanged: the dtheta columns vanish there.
    intr = CameraIntrinsics(640, 480, K)
    T_wc, T_wo, _ = _scene(3)
    _, _, J = project_with_jacobian(intr, T_wc, T_wo, np.zeros((1, 3)))
    np.testing.assert_allclose(J[0, :, 3:], 0.0, atol=1e-9)
    # ...whereas dp moves it
    assert np.abs(J[0, :, :3]).max() > 100


def test_vectorised_matches_per_point_loop_and_camera_module():
    intr = CameraIntrinsics(640, 480, K, DIST)
    T_wc, T_wo, P = _scene(4, n=20)
    uv, depth, J = project_with_jacobian(intr, T_wc, T_wo, P)
    for i in range(len(P)):
        u1, d1, J1 = project_with_jacobian(intr, T_wc, T_wo, P[i : i + 1])
        np.testing.assert_allclose(u1[0], uv[i], atol=1e-10)
        np.testing.assert_allclose(J1[0], J[i], rtol=1e-13, atol=1e-12)
    uv2, _ = project_points(intr, se3.invert_transform(T_wc) @ T_wo, P)
    np.testing.assert_allclose(uv, uv2, atol=1e-9)


def test_behind_camera_is_nan_and_shapes_checked():
    intr = CameraIntrinsics(640, 480, K)
    uv, depth, J = project_with_jacobian(intr, np.eye(4), np.eye(4), np.array([[0, 0, -1.0], [0, 0, 1.0]]))
    assert np.all(np.isnan(uv[0])) and np.all(np.isnan(J[0]))
    assert np.all(np.isfinite(uv[1])) and np.all(np.isfinite(J[1]))
    assert depth[0] == -1.0
    with pytest.raises(ValueError, match=r"\(5, 2\)"):
        project_with_jacobian(intr, np.eye(4), np.eye(4), np.zeros((5, 2)))
    with pytest.raises(ValueError, match="T_world_camera"):
        project_with_jacobian(intr, np.eye(3), np.eye(4), np.zeros((5, 3)))


def test_gauss_newton_recovers_pose_from_two_cameras():
    intr = CameraIntrinsics(640, 480, K, DIST)
    rng = np.random.default_rng(5)
    T_wc1 = se3.transform_from_rt(np.eye(3), [0, 0, -0.8])
    T_wc2 = se3.transform_from_rt(se3.exp_so3([0, -0.5, 0]), [0.4, 0, -0.7])
    T_wo = se3.transform_from_rt(se3.exp_so3([0.1, 0.2, 0.3]), [0.01, 0.02, 0.0])
    P = rng.uniform(-0.05, 0.05, (8, 3))
    cams = [(intr, T_wc1), (intr, T_wc2)]
    z = [project_with_jacobian(intr, T, T_wo, P)[0] for _, T in cams]
    T0 = apply_pose_error(T_wo, [0.02, -0.01, 0.01, 0.05, -0.05, 0.08])
    T_est, _ = refine_pose_gauss_newton(cams, z, [P, P], T0)
    dp, da = se3.pose_error(T_est, T_wo)
    assert dp < 1e-9 and da < 1e-9


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_vec3 = st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).map(np.array)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(rv_c=_vec3, rv_o=_vec3, t=_vec3, pts=st.lists(_vec3, min_size=1, max_size=6))
def test_jacobian_property_any_pose(rv_c, rv_o, t, pts):
    # any camera / object orientation, object 0.5-1.5 m in front of the camera
    intr = CameraIntrinsics(640, 480, K, DIST)
    T_wc = se3.transform_from_rt(se3.exp_so3(2.0 * rv_c), 0.3 * t)
    T_co = se3.transform_from_rt(se3.exp_so3(3.0 * rv_o), [0.1 * t[0], 0.1 * t[1], 1.0 + 0.5 * t[2]])
    T_wo = T_wc @ T_co
    P = 0.1 * np.array(pts)
    uv, depth, J = project_with_jacobian(intr, T_wc, T_wo, P)
    assert np.all(depth > 0.3)
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        up = project_with_jacobian(intr, T_wc, apply_pose_error(T_wo, d), P)[0]
        um = project_with_jacobian(intr, T_wc, apply_pose_error(T_wo, -d), P)[0]
        np.testing.assert_allclose(J[:, :, k], (up - um) / (2 * h), rtol=1e-5, atol=1e-3)
