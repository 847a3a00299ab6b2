import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cubetrack.core.errors import EvaluationError
from cubetrack.evaluate.metrics import EvaluationParams, detection_ratio, evaluate, position_rmse_m
from cubetrack.io.trajectory import Trajectory


def gt(n=101, dt=0.01):
    t = 100.0 + np.arange(n) * dt
    p = np.column_stack([t - 100.0, np.zeros(n), np.zeros(n)])
    q = np.tile([0, 0, 0, 1.0], (n, 1))
    return Trajectory(t, p, q)


def test_position_rmse_by_hand():
    # errors 3-4-5 and 0: sqrt((25 + 0) / 2)
    est = np.array([[3.0, 4.0, 0.0], [1.0, 1.0, 1.0]])
    ref = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    assert position_rmse_m(est, ref) == pytest.approx(np.sqrt(12.5))


def test_detection_ratio_by_hand():
    # span 0..10 s; estimates every 0.1 s except a 2 s hole (4..6 s) -> 1 - 2/10
    t = np.concatenate([np.arange(0, 4.01, 0.1), np.arange(6, 10.01, 0.1)])
    assert detection_ratio(t, 0.0, 10.0, 0.5) == pytest.approx(0.8)
    # a 0.4 s hole is under the timeout: fully detected
    t2 = np.concatenate([np.arange(0, 4.01, 0.1), np.arange(4.4, 10.01, 0.1)])
    assert detection_ratio(t2, 0.0, 10.0, 0.5) == pytest.approx(1.0)
    # nothing until 3 s: the 3 s lead-in is lost
    assert detection_ratio(np.arange(3, 10.01, 0.1), 0.0, 10.0, 0.5) == pytest.approx(0.7)


def test_evaluate_uses_nearest_ground_truth_and_rotation_error():
    ref = gt()
    times = np.array([100.2, 100.5, 100.8])
    pos = np.array([[0.2, 0.01, 0.0], [0.5, 0.0, 0.02], [0.8, 0.0, 0.0]])
    q = Rotation.from_euler("z", [[2.0], [0.0], [0.0]], degrees=True).as_quat()
    r = evaluate(Trajectory(times, pos, q), ref)
    assert r.position_rmse_m == pytest.approx(np.sqrt((0.01**2 + 0.02**2) / 3))
    assert r.rotation_rmse_deg == pytest.approx(np.sqrt(4.0 / 3))
    assert r.poses_scored == 3
    assert r.detection_ratio == pytest.approx(1.0)  # every gap (0.2 s lead-in, 0.3 s) is under 0.5 s
    assert r.output_rate_hz == pytest.approx(3.0)


def test_estimates_far_from_any_ground_truth_are_not_scored():
    ref = gt(n=11, dt=0.1)  # 10 Hz ground truth
    r = evaluate(Trajectory(np.array([100.05]), np.zeros((1, 3)), np.array([[0, 0, 0, 1.0]])), ref,
                 EvaluationParams(max_time_diff_s=0.02))
    assert r.poses_scored == 0


def test_disjoint_times_are_an_error():
    with pytest.raises(EvaluationError, match="do not overlap"):
        evaluate(Trajectory(np.array([5.0]), np.zeros((1, 3)), np.array([[0, 0, 0, 1.0]])), gt())


def turning_truth(hz=10.0, yaw_deg_s=90.0, speed_m_s=1.0):
    """A ground truth sampled at ``hz`` of a cube moving along x and turning about z at constant rates."""
    t = 100.0 + np.arange(11) / hz
    p = np.column_stack([speed_m_s * (t - 100.0), np.zeros_like(t), np.full_like(t, 0.1)])
    q = Rotation.from_euler("z", yaw_deg_s * (t - 100.0)[:, None], degrees=True).as_quat()
    return Trajectory(t, p, q)


def test_truth_is_interpolated_to_each_pose_time_and_eq7_is_beside_it():
    # a perfect estimate 30 ms after a 10 Hz sample: against the interpolated truth it is exact;
    # eq. 7's nearest sample is 30 ms (3 cm, 2.7 deg) off
    times = np.array([100.13, 100.53, 100.87])
    pos = np.column_stack([times - 100.0, np.zeros(3), np.full(3, 0.1)])
    q = Rotation.from_euler("z", 90.0 * (times - 100.0)[:, None], degrees=True).as_quat()
    r = evaluate(Trajectory(times, pos, q), turning_truth(), EvaluationParams(max_time_diff_s=0.05))
    assert r.poses_scored == 3
    assert r.position_rmse_m == pytest.approx(0.0, abs=1e-9)
    assert r.rotation_rmse_deg == pytest.approx(0.0, abs=1e-6)
    assert r.position_rmse_nearest_m == pytest.approx(0.03)
    assert r.rotation_rmse_nearest_deg == pytest.approx(2.7)
    assert r.as_dict()["rotation_rmse_nearest_deg"] == pytest.approx(2.7)


def test_interpolated_rotation_is_a_slerp_not_a_blend():
    # samples 100 deg apart (1000 deg/s at 10 Hz): a component-wise quaternion blend is off by
    # several degrees between them, the slerp is exact for a constant rate
    truth = turning_truth(yaw_deg_s=1000.0)
    times = np.array([100.025, 100.05, 100.075])
    q = Rotation.from_euler("z", 1000.0 * (times - 100.0)[:, None], degrees=True).as_quat()
    pos = np.column_stack([times - 100.0, np.zeros(3), np.full(3, 0.1)])
    r = evaluate(Trajectory(times, pos, q), truth, EvaluationParams(max_time_diff_s=0.05))
    assert r.rotation_rmse_deg == pytest.approx(0.0, abs=1e-6)


def test_poses_just_outside_the_truth_take_its_end_samples():
    truth = turning_truth()
    times = np.array([99.99, 101.01])  # within max_time_diff_s of the first and last samples
    pos = truth.positions_m[[0, -1]]
    r = evaluate(Trajectory(times, pos, truth.quats_xyzw[[0, -1]]), truth)
    assert r.poses_scored == 2
    assert r.position_rmse_m == pytest.approx(0.0, abs=1e-12)
    assert r.rotation_rmse_deg == pytest.approx(0.0, abs=1e-6)
