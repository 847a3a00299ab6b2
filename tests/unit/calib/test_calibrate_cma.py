"""The paper's calibration formula (eq. 1) against hand-computed values, and its quaternion signs."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cubetrack.calib.extrinsics import CumulativeMovingAverage, cma_pose, pose_spread
from cubetrack.core.errors import CalibrationError
from cubetrack.core.geometry import make_T, rotation_angle


def test_eq1_recursion_by_hand():
    cma = CumulativeMovingAverage()
    # CMA_0 = d_0 = 2; CMA_1 = 2 + (4 - 2)/2 = 3; CMA_2 = 3 + (9 - 3)/3 = 5; CMA_3 = 5 + (1 - 5)/4 = 4
    assert [float(cma.update(d)) for d in (2.0, 4.0, 9.0, 1.0)] == [2.0, 3.0, 5.0, 4.0]
    assert cma.count == 4


def test_eq1_on_vectors_equals_the_mean():
    cma = CumulativeMovingAverage()
    data = np.array([[1.0, 0.0, -2.0], [3.0, 2.0, 0.0], [2.0, 7.0, 5.0]])
    for d in data:
        out = cma.update(d)
    np.testing.assert_allclose(out, [2.0, 3.0, 1.0])  # by hand: column means


def test_cma_pose_positions_by_hand():
    Ts = [make_T(np.eye(3), p) for p in ([1.0, 2.0, 3.0], [3.0, 2.0, 1.0], [2.0, 5.0, 2.0])]
    T = cma_pose(Ts)
    np.testing.assert_allclose(T[:3, 3], [2.0, 3.0, 2.0])
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-12)


def test_cma_pose_aligns_quaternion_signs():
    # +170 deg and -170 deg about z: canonical quaternions (w >= 0) are (0,0,±0.996,0.087); a naive
    # component mean gives (0,0,0,0.087) = identity, 180 deg off. Aligned, the mean is 180 deg.
    Ts = [make_T(Rotation.from_euler("z", a, degrees=True).as_matrix(), np.zeros(3)) for a in (170, -170)]
    T = cma_pose(Ts)
    expected = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    assert rotation_angle(T[:3, :3], expected, "deg") < 1e-6


def test_cma_pose_normalises_the_mean_quaternion():
    Ts = [make_T(Rotation.from_euler("x", a, degrees=True).as_matrix(), np.zeros(3)) for a in (0, 20)]
    R = cma_pose(Ts)[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert rotation_angle(R, Rotation.from_euler("x", 10, degrees=True).as_matrix(), "deg") < 1e-6


def test_cma_pose_needs_samples():
    with pytest.raises(CalibrationError):
        cma_pose([])


def test_pose_spread_by_hand():
    ref = np.eye(4)
    Ts = [make_T(np.eye(3), [0.03, 0.0, 0.0]),
          make_T(Rotation.from_euler("z", 2, degrees=True).as_matrix(), [0.0, 0.04, 0.0])]
    spread_m, spread_deg = pose_spread(Ts, ref)
    assert spread_m == pytest.approx(np.sqrt((0.03**2 + 0.04**2) / 2))
    assert spread_deg == pytest.approx(np.sqrt(2.0**2 / 2))
