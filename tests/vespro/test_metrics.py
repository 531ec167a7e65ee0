"""Metrics against hand-computed cases."""

import numpy as np
import pytest

from vespro import metrics
from vespro.camera import CameraIntrinsics
from vespro.poses import PoseRow, read_poses, write_poses
from vespro.se3 import exp_so3, transform_from_rt

CUBE = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * 0.05


def test_known_offset_gives_known_add_mssd_mspd():
    T = transform_from_rt(np.eye(3), [0, 0, 1.0])
    Te = transform_from_rt(np.eye(3), [0.003, 0.004, 1.0])  # 5 mm sideways
    assert metrics.add(Te, T, CUBE) == pytest.approx(0.005)
    assert metrics.mssd(Te, T, CUBE) == pytest.approx(0.005)
    intr = CameraIntrinsics(640, 480, [[600, 0, 320], [0, 600, 240], [0, 0, 1]])
    # A 5 mm lateral shift seen at depths 0.95 and 1.05 m: the nearest points move most.
    assert metrics.mspd(Te, T, CUBE, intr) == pytest.approx(600 * 0.005 / 0.95, rel=1e-9)
    assert metrics.position_errors(Te[None], T[None])[0] == pytest.approx(0.005)


def test_symmetric_box_rotated_180_has_zero_add_s_but_large_add():
    box = np.array([[x, y, z] for x in (-0.06, 0.06) for y in (-0.04, 0.04) for z in (-0.03, 0.03)])
    T = transform_from_rt(exp_so3([0.2, 0.1, -0.3]), [0.1, 0, 1])
    flip = transform_from_rt(exp_so3([0, 0, np.pi]), [0, 0, 0])
    Te = T @ flip
    assert metrics.add_s(Te, T, box) == pytest.approx(0.0, abs=1e-12)
    assert metrics.add(Te, T, box) > 0.05
    assert metrics.mssd(Te, T, box, symmetries=[np.eye(4), flip]) == pytest.approx(0.0, abs=1e-12)
    assert metrics.add_sym(Te, T, box, [np.eye(4), flip]) == pytest.approx(0.0, abs=1e-12)
    moved = Te.copy()
    moved[:3, 3] += [0.003, 0.004, 0.0]  # 5 mm: ADD to the nearest equivalent, not ADD-S
    assert metrics.add_sym(moved, T, box, [np.eye(4), flip]) == pytest.approx(0.005)
    assert metrics.add_sym(Te, T, box, [np.eye(4)]) == pytest.approx(metrics.add(Te, T, box))
    assert metrics.rotation_errors(Te[None], T[None])[0] == pytest.approx(np.pi)


def test_nees_of_a_known_error():
    T = np.eye(4)
    Te = transform_from_rt(exp_so3([0, 0, -0.01]), [0.002, 0, 0])
    P = np.diag([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4])
    # error = [-0.002, 0, 0, 0, 0, 0.01]: 4e-6/1e-6 + 1e-4/1e-4 = 5
    assert metrics.nees(Te, T, P) == pytest.approx(5.0)
    lo, hi = metrics.nees_band(6)
    assert lo == pytest.approx(1.2373, abs=1e-3) and hi == pytest.approx(14.449, abs=1e-3)


def test_recall():
    assert metrics.recall([0.1, 0.2, 0.3, 0.4], [0.25, 0.5]) == pytest.approx((0.5 + 1.0) / 2)


def test_poses_csv_roundtrip(tmp_path):
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    rows = [
        PoseRow(0, 0.0, "initializing"),
        PoseRow(1, 0.04, "tracking", transform_from_rt(exp_so3([0.1, 0.2, 0.3]), [1, 2, 3]), 1.25,
                rng.normal(size=6), A @ A.T, 0.9987),
        PoseRow(2, 0.08, "lost", None, 0.5),
    ]
    write_poses(tmp_path / "p.csv", rows)
    back = read_poses(tmp_path / "p.csv")
    assert [r.status for r in back] == ["initializing", "tracking", "lost"]
    np.testing.assert_allclose(back[1].T_world_object, rows[1].T_world_object, atol=1e-8)
    np.testing.assert_allclose(back[1].cov, rows[1].cov, rtol=1e-8)
    np.testing.assert_allclose(back[1].velocity, rows[1].velocity, rtol=1e-8)
    assert back[2].time_ms == 0.5 and back[0].T_world_object is None
    assert back[1].probability == 0.9987 and back[2].probability is None  # (written to 6 digits)


def test_poses_csv_minimal_columns_and_errors(tmp_path):
    p = tmp_path / "p.csv"
    p.write_text("index,t,x,y,z,qw,qx,qy,qz,status,extra\n0,0,1,2,3,1,0,0,0,tracking,zz\n")
    assert read_poses(p)[0].T_world_object[0, 3] == 1.0
    p.write_text("index,t,x,y,z,qw,qx,qy,qz,status\n0,0,,,,,,,,tracking\n")
    with pytest.raises(ValueError, match="line 2: status 'tracking' needs a pose"):
        read_poses(p)
    p.write_text("index,t,status\n")
    with pytest.raises(ValueError, match="missing column"):
        read_poses(p)


def test_add_equals_the_numpy_formulation_bit_for_bit():
    """The compiled ADD against NumPy's, from 2 to 1000 points (pairwise sums past 8 and 128),
    and one point, float32 points and a NaN pose through the NumPy code."""
    from test_init_kernels import bitwise

    from vespro.metrics import add, add_numpy
    from vespro.se3 import exp_so3, transform_from_rt

    if not bitwise():
        pytest.skip("this platform's BLAS accumulates otherwise than numerics.dot3")
    rng = np.random.default_rng(17)
    for n in (1, 2, 7, 8, 9, 12, 100, 129, 1000):
        for _ in range(40):
            P = rng.normal(size=(n, 3)) * 0.1
            Ta = transform_from_rt(exp_so3(rng.normal(size=3)), rng.normal(size=3))
            Tb = Ta @ transform_from_rt(exp_so3(rng.normal(size=3) * 1e-3), rng.normal(size=3) * 1e-3)
            assert add(Ta, Tb, P) == add_numpy(Ta, Tb, P)
    assert add(Ta, Tb, P.astype(np.float32)) == add_numpy(Ta, Tb, P.astype(np.float32))
    Tn = Ta.copy()
    Tn[0, 3] = np.nan
    assert np.isnan(add(Tn, Tb, P)) and np.isnan(add_numpy(Tn, Tb, P))
