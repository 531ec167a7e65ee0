"""Hand-eye solvers on synthetic motions with a known X (A X = X B exactly)."""

import numpy as np
import pytest

from vespro.calib.axxb import NUMPY_METHODS, hand_eye, robot_world_hand_eye
from vespro.se3 import exp_so3, invert_transform, pose_error, transform_from_rt


def _views(X, n, rng, noise=0.0):
    T_base_board = transform_from_rt(exp_so3([0.1, -0.2, 0.3]), [0.9, 0.0, 0.5])
    G = [transform_from_rt(exp_so3(rng.normal(size=3) * 0.5), rng.normal(size=3) * 0.2 + [0.8, 0, 0.9])
         for _ in range(n)]
    C = []
    for g in G:
        c = invert_transform(g @ X) @ T_base_board
        if noise:
            c = c @ transform_from_rt(exp_so3(rng.normal(size=3) * noise), rng.normal(size=3) * noise * 0.3)
        C.append(c)
    return G, C


@pytest.mark.parametrize("method", sorted(NUMPY_METHODS))
def test_exact_motions_give_x(method):
    rng = np.random.default_rng(0)
    X = transform_from_rt(exp_so3([0.3, -1.1, 0.7]), [0.06, -0.02, 0.05])
    G, C = _views(X, 8, rng)
    dp, da = pose_error(hand_eye(method, G, C, use_opencv=False), X)
    assert dp < 1e-9 and da < 1e-9


@pytest.mark.parametrize("method", ["park", "daniilidis"])
def test_noisy_motions_close_and_half_turn(method):
    """Park and Daniilidis stay accurate with noise, also for a camera turned by
    180 deg about its axis (the standard hand camera's mounting)."""
    rng = np.random.default_rng(1)
    X = transform_from_rt(exp_so3([0.0, 0.0, np.pi]), [0.065, 0.0, 0.056])
    G, C = _views(X, 15, rng, noise=1e-3)
    dp, da = pose_error(hand_eye(method, G, C, use_opencv=False), X)
    assert dp < 2e-3 and np.rad2deg(da) < 0.2


def test_robot_world_shah_exact_and_noisy():
    rng = np.random.default_rng(2)
    X = transform_from_rt(exp_so3([0.0, 0.0, np.pi]), [0.065, 0.0, 0.056])
    Y = transform_from_rt(exp_so3([0.1, -0.2, 0.3]), [0.9, 0.0, 0.5])  # _views' board pose
    G, C = _views(X, 10, rng)
    Xe, Ye = robot_world_hand_eye(G, C, use_opencv=False)
    for est, true in ((Xe, X), (Ye, Y)):
        dp, da = pose_error(est, true)
        assert dp < 1e-9 and da < 1e-9
    G, C = _views(X, 15, rng, noise=1e-3)
    dp, da = pose_error(robot_world_hand_eye(G, C, use_opencv=False)[0], X)
    assert dp < 3e-3 and np.rad2deg(da) < 0.2


def test_tsai_singular_at_half_turn():
    """Tsai's modified Rodrigues parameter tan(theta/2) is infinite at 180 deg, the
    standard hand camera's mounting: exact motions still give a wrong X there
    (why hand-eye scores every method and keeps the most consistent)."""
    rng = np.random.default_rng(1)
    X = transform_from_rt(exp_so3([0.0, 0.0, np.pi]), [0.065, 0.0, 0.056])
    G, C = _views(X, 15, rng)
    _, da = pose_error(hand_eye("tsai", G, C, use_opencv=False), X)
    assert np.rad2deg(da) > 10.0
    _, da = pose_error(hand_eye("park", G, C, use_opencv=False), X)
    assert da < 1e-9
