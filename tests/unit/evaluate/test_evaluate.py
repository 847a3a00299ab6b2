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
