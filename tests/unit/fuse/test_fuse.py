import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cubetrack.core.geometry import make_T, rotation_angle
from cubetrack.core.records import CameraEstimate, FaceObservation
from cubetrack.fuse.fusion import FusionMethod, FusionParams, LatestEstimateFusion, fuse_poses, paper_weights


def test_paper_weights_by_hand():
    areas = np.array([100.0, 400.0])
    assert paper_weights(FusionMethod.MEAN, areas).tolist() == [1.0, 1.0]
    assert paper_weights(FusionMethod.WEIGHTED, areas).tolist() == [100.0, 400.0]
    assert paper_weights(FusionMethod.GAUSSIAN, areas).tolist() == [1e4, 1.6e5]


@pytest.mark.parametrize("method,expected_x", [
    (FusionMethod.MEAN, (0.0 + 1.0) / 2),                          # eq. 2
    (FusionMethod.WEIGHTED, (100 * 0.0 + 300 * 1.0) / 400),         # eq. 4
    (FusionMethod.GAUSSIAN, (1e4 * 0.0 + 9e4 * 1.0) / 1e5),         # eq. 6 with sigma_i^2 = 1/a_i^2
])
def test_fused_position_by_hand(method, expected_x):
    p = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    Rs = np.array([np.eye(3), np.eye(3)])
    pos, _ = fuse_poses(p, Rs, paper_weights(method, np.array([100.0, 300.0])))
    assert pos[0] == pytest.approx(expected_x)


def test_rotation_is_averaged_on_the_manifold():
    Rs = Rotation.from_euler("z", [[10.0], [30.0]], degrees=True).as_matrix()
    _, R = fuse_poses(np.zeros((2, 3)), Rs, np.ones(2))
    assert rotation_angle(R, Rotation.from_euler("z", 20, degrees=True).as_matrix(), unit="deg") < 1e-6


def estimate(camera, t, x, area=100.0):
    T = make_T(np.eye(3), [x, 0, 0])
    face = FaceObservation("top", None, T, area)
    return CameraEstimate(camera, "bot", 0, t, t + 0.05, T, area, (face,), 0.1)


def test_latest_estimate_per_camera_inside_window():
    fusion = LatestEstimateFusion(FusionParams(window_s=0.2))
    fusion.fuse(estimate("cam1", 10.0, 0.0), 10.05)
    pose = fusion.fuse(estimate("cam2", 10.1, 1.0), 10.15)
    assert pose.position_m[0] == pytest.approx(0.5) and pose.cameras == ("cam1", "cam2")
    assert pose.time_s == 10.1 and pose.latency_s == pytest.approx(0.05)
    # cam1's estimate is now 0.3 s older than the newest: left out
    pose = fusion.fuse(estimate("cam2", 10.3, 2.0), 10.35)
    assert pose.position_m[0] == pytest.approx(2.0) and pose.cameras == ("cam2",)
    # cam1 replaced by its newer estimate
    pose = fusion.fuse(estimate("cam1", 10.35, 4.0), 10.4)
    assert pose.position_m[0] == pytest.approx(3.0)
