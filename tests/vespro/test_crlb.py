"""Cramér-Rao bounds: a Monte Carlo least-squares pose fit reaches the per-frame bound."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.optimize import least_squares

from vespro import crlb
from vespro.camera import CameraIntrinsics
from vespro.metrics import pose_error_vector
from vespro.model import load_model
from vespro.se3 import exp_so3, invert_transform, transform_from_rt
from vespro.toy_scene import look_at

ROOT = Path(__file__).resolve().parents[2]
INTR = CameraIntrinsics(640, 480, [[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]], [-0.1, 0.02, 0.0, 0.0, 0.0])


def _setup():
    corners = load_model(ROOT / "models/objects/lblock.stl").corners
    T_true = transform_from_rt(exp_so3([0.3, -0.2, 0.5]), [0.02, -0.01, 0.03])
    cams = [look_at([0.45, -0.45, 0.4], [0, 0, 0.03]), look_at([-0.35, -0.5, 0.45], [0, 0, 0.03])]
    return corners, T_true, cams


def _project_cv(T_wc, T_wo, P):
    """Independent projection (OpenCV) for the estimator."""
    T_co = invert_transform(T_wc) @ T_wo
    rvec, _ = cv2.Rodrigues(T_co[:3, :3])
    uv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), rvec, T_co[:3, 3].copy(), INTR.K, INTR.dist)
    return uv.reshape(-1, 2)


def _perturb(T, x):
    """Left, world-frame perturbation [dp, dtheta] (the bound's convention)."""
    return transform_from_rt(exp_so3(x[3:]) @ T[:3, :3], T[:3, 3] + x[:3])


def test_least_squares_pose_fit_reaches_the_per_frame_bound():
    corners, T_true, cams = _setup()
    sigma = 1.0
    C = crlb.frame_crlb([(INTR, T_wc, corners) for T_wc in cams], T_true, sigma)
    assert C is not None
    clean = [_project_cv(T_wc, T_true, corners) for T_wc in cams]
    rng = np.random.default_rng(0)
    n_trials = 600
    errs = np.empty((n_trials, 6))
    for k in range(n_trials):
        meas = [uv + rng.normal(0, sigma, uv.shape) for uv in clean]
        T_start = _perturb(T_true, rng.normal(0, [2e-3] * 3 + [1e-2] * 3))

        def resid(x):
            T = _perturb(T_start, x)
            return np.concatenate([(_project_cv(T_wc, T, corners) - m).ravel() for T_wc, m in zip(cams, meas)])

        sol = least_squares(resid, np.zeros(6), x_scale=[1e-3] * 3 + [1e-2] * 3, xtol=1e-12, ftol=1e-12)
        errs[k] = pose_error_vector(_perturb(T_start, sol.x), T_true)
    S = errs.T @ errs / n_trials  # the ML fit is unbiased to first order: the mean is zero
    print("empirical sqrt trace pos/rot:", np.sqrt(np.trace(S[:3, :3])), np.sqrt(np.trace(S[3:, 3:])))
    print("CRLB      sqrt trace pos/rot:", crlb.crlb_std(C))
    # 600 trials: a variance estimate has relative std sqrt(2/600) = 6 %, a trace of three less;
    # an efficient estimator (ML with Gaussian noise, small errors) sits on the bound.
    assert np.trace(S[:3, :3]) == pytest.approx(np.trace(C[:3, :3]), rel=0.10)
    assert np.trace(S[3:, 3:]) == pytest.approx(np.trace(C[3:, 3:]), rel=0.10)
    assert np.diag(S) == pytest.approx(np.diag(C), rel=0.20)


def test_information_adds_over_cameras_and_scales_with_sigma():
    corners, T_true, cams = _setup()
    I1 = crlb.frame_information([(INTR, cams[0], corners)], T_true, 1.0)
    I2 = crlb.frame_information([(INTR, cams[1], corners)], T_true, 1.0)
    I12 = crlb.frame_information([(INTR, c, corners) for c in cams], T_true, 1.0)
    np.testing.assert_allclose(I12, I1 + I2, rtol=1e-12)
    np.testing.assert_allclose(crlb.frame_information([(INTR, cams[0], corners)], T_true, 2.0), I1 / 4, rtol=1e-12)
    # Two points cannot fix a pose: no bound.
    assert crlb.frame_crlb([(INTR, cams[0], corners[:2])], T_true, 1.0) is None


def test_posterior_bound_of_a_static_object_accumulates_information():
    corners, T_true, cams = _setup()
    info = crlb.frame_information([(INTR, cams[0], corners)], T_true, 1.0)
    n = 5
    T = np.repeat(T_true[None], n, axis=0)
    t = np.arange(n) / 26.0
    P0 = np.diag([1e-4] * 3 + [1e-2] * 3 + [1e-14] * 6)  # velocities known to be zero
    pc = crlb.posterior_crlb(T, t, [info] * n, P0, q_acc=0.0, q_alpha=0.0)
    # With no motion and no process noise every frame is a repeat measurement of one pose.
    for k in range(n):
        expected = np.linalg.inv(np.linalg.inv(P0[:6, :6]) + (k + 1) * info)
        np.testing.assert_allclose(pc[k], expected, rtol=1e-4, atol=1e-16)
