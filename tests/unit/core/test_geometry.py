import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cubetrack.core.geometry import (
    T_from_position_quat,
    T_from_rvec_tvec,
    invert_T,
    is_finite_pose,
    mean_rotation,
    position_quat_from_T,
    rotation_angle,
    rvec_tvec_from_T,
    shoelace_area,
    transform_points,
)


def random_T(rng):
    return T_from_position_quat(rng.normal(size=3), rng.normal(size=4))


def test_invert_and_compose():
    rng = np.random.default_rng(1)
    T = random_T(rng)
    np.testing.assert_allclose(invert_T(T) @ T, np.eye(4), atol=1e-12)
    p = rng.normal(size=(5, 3))
    np.testing.assert_allclose(transform_points(invert_T(T), transform_points(T, p)), p, atol=1e-12)


def test_rvec_round_trip_and_quaternion_sign():
    rng = np.random.default_rng(2)
    T = random_T(rng)
    np.testing.assert_allclose(T_from_rvec_tvec(*rvec_tvec_from_T(T)), T, atol=1e-12)
    _, q = position_quat_from_T(T)
    assert q[3] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)


def test_shoelace_area_by_hand():
    # a 10 x 4 rectangle, clockwise in the image, and a right triangle with legs 3 and 4
    assert shoelace_area(np.array([[0, 0], [10, 0], [10, 4], [0, 4]])) == pytest.approx(40.0)
    assert shoelace_area(np.array([[0, 0], [3, 0], [0, 4]])) == pytest.approx(6.0)


def test_shoelace_area_is_the_rolled_formula_to_the_bit():
    # the detector's areas (written to the sightings) must not change with how the next vertex is taken
    rng = np.random.default_rng(3)
    for n in (3, 4, 4, 4, 5, 9):
        p = rng.normal(300.0, 80.0, (n, 2))
        x, y = p[:, 0], p[:, 1]
        rolled = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
        assert shoelace_area(p) == rolled
        assert shoelace_area(p[::-1]) == pytest.approx(rolled, rel=1e-12)  # either direction
        assert shoelace_area(p.ravel().tolist()) == rolled  # any array-like, flat or not


def test_rotation_angle_units():
    R = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    assert rotation_angle(np.eye(3), R, unit="deg") == pytest.approx(30.0)
    assert rotation_angle(np.eye(3), R) == pytest.approx(np.pi / 6)
    tiny = Rotation.from_rotvec([3e-9, 0.0, 4e-9]).as_matrix()  # arccos of the trace would say ~2e-8
    assert rotation_angle(R, R @ tiny) == pytest.approx(5e-9, rel=1e-6)
    with pytest.raises(ValueError):
        rotation_angle(np.eye(3), R, unit="grad")


def test_mean_rotation_ignores_quaternion_sign():
    # two rotations near 180 deg about z whose quaternions straddle q / -q
    Rs = Rotation.from_euler("z", [[179.0], [-179.0]], degrees=True).as_matrix()
    m = mean_rotation(Rs)
    assert rotation_angle(m, Rotation.from_euler("z", 180, degrees=True).as_matrix(), unit="deg") < 1e-6


def test_non_finite_pose_is_detected():
    T = np.eye(4)
    assert is_finite_pose(T)
    T[0, 0] = np.nan
    assert not is_finite_pose(T)
    assert not is_finite_pose(np.diag([1.0, 1.0, -1.0, 1.0]))


def test_fast_rodrigues_matches_scipy():
    from cubetrack.core.geometry import R_from_rotvec

    rng = np.random.default_rng(5)
    for v in [*rng.normal(size=(20, 3)) * 2.0, np.zeros(3), np.array([1e-10, 0, 0]), np.array([np.pi, 0, 0])]:
        np.testing.assert_allclose(R_from_rotvec(v), Rotation.from_rotvec(v).as_matrix(), atol=1e-12)


def test_quaternion_matches_scipy_in_every_branch():
    """Shepperd's four branches: small angles, angles near pi about each axis, random ones."""
    from cubetrack.core.geometry import quat_xyzw_from_R

    rng = np.random.default_rng(6)
    axes = rng.normal(size=(30, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    vectors = [*rng.normal(size=(30, 3)), *(axes * 1e-9), *(axes * (np.pi - 1e-9)),
               *(np.eye(3) * np.pi), np.zeros(3)]
    for v in vectors:
        R = Rotation.from_rotvec(v).as_matrix()
        expected = Rotation.from_matrix(R).as_quat()
        q = quat_xyzw_from_R(R)
        assert q[3] >= 0.0
        assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-12  # q and -q: one rotation
