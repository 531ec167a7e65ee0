import cv2
import numpy as np
import pytest

from vespro import se3
from vespro.camera import CameraIntrinsics, project_points, undistort_pixels


def test_projection_matches_opencv_with_distortion():
    rng = np.random.default_rng(0)
    K = np.array([[600.0, 0.0, 321.0], [0, 590.0, 238.0], [0, 0, 1]])
    dist = np.array([-0.21, 0.09, 0.001, -0.0015, -0.02])
    intr = CameraIntrinsics(640, 480, K, dist)
    T = se3.transform_from_rt(se3.exp_so3([0.2, -0.1, 0.3]), [0.05, -0.02, 0.9])
    P = rng.uniform(-0.1, 0.1, size=(200, 3))
    uv, z = project_points(intr, T, P)
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    ref, _ = cv2.projectPoints(P, rvec, T[:3, 3], K, dist)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    assert np.all(z > 0)


def test_undistort_inverts_distortion():
    intr = CameraIntrinsics(640, 480, [[600, 0, 320], [0, 600, 240], [0, 0, 1]], [-0.2, 0.05, 0.001, 0.001, 0])
    T = np.eye(4)
    P = np.array([[x, y, 1.0] for x in np.linspace(-0.4, 0.4, 5) for y in np.linspace(-0.3, 0.3, 5)])
    uv, _ = project_points(intr, T, P)
    ideal = P[:, :2] * 600 + [320, 240]
    np.testing.assert_allclose(undistort_pixels(intr, uv), ideal, atol=1e-6)


def test_from_fovy_matches_mujoco_convention():
    intr = CameraIntrinsics.from_fovy(640, 480, 45.0)
    # The example recording (made outside the project) uses the same model.
    assert abs(intr.fy - 579.411255) < 1e-5 and intr.cx == 319.5 and intr.cy == 239.5


def test_points_behind_camera_are_nan():
    intr = CameraIntrinsics.from_fovy(64, 48, 60)
    uv, z = project_points(intr, np.eye(4), [[0, 0, -1.0], [0, 0, 1.0]])
    assert np.all(np.isnan(uv[0])) and np.all(np.isfinite(uv[1]))


def test_skew_is_rejected():
    import pytest
    with pytest.raises(ValueError, match="skew"):
        CameraIntrinsics(640, 480, [[600, 0.5, 320], [0, 600, 240], [0, 0, 1]])


def test_pinhole_projection_equals_the_numpy_formulation_bit_for_bit():
    """Without distortion the projection is compiled: the same pixels and depths as the NumPy
    code, points behind the camera, on its plane and NaN ones included; one point and a
    distorting camera go through the NumPy code."""
    from test_init_kernels import bitwise

    from vespro.camera import project_points_numpy

    if not bitwise():
        pytest.skip("this platform's BLAS accumulates otherwise than numerics.dot3")
    rng = np.random.default_rng(4)
    intr = CameraIntrinsics(640, 480, [[600.5, 0, 321.25], [0, 590.75, 238.5], [0, 0, 1]])
    for n in (0, 1, 2, 8, 300):
        T = se3.transform_from_rt(se3.exp_so3(rng.normal(size=3)), rng.normal(size=3) * 0.2 + [0, 0, 0.5])
        P = rng.normal(size=(n, 3)) * 0.3
        if n > 8:
            P[:3] = np.linalg.solve(T[:3, :3], -T[:3, 3])  # the camera centre: depth 0 (to rounding)
            P[3, 0] = np.nan
            P[4] = 0.0
        with np.errstate(all="ignore"):
            uv, z = project_points(intr, T, P)
            uv_ref, z_ref = project_points_numpy(intr, T, P)
        assert np.array_equal(uv, uv_ref, equal_nan=True) and np.array_equal(z, z_ref, equal_nan=True)
        assert uv.shape == (n, 2) and z.shape == (n,)
        if n > 8:
            assert np.isnan(uv[:4]).all() and (z[5:] < 0).any() and np.isnan(uv[5:][z[5:] < 0]).all()
