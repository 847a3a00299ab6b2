"""Bumped and drifting cameras (issue 27): the pose steps and drifts as asked, the frames are
rendered from the pose written as truth, and nothing moves before the start."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cubetrack.core.errors import ParamsError
from cubetrack.core.geometry import invert_T, rotation_angle, transform_points
from cubetrack.io.recording import Recording
from cubetrack.io.trajectory import read_tum
from cubetrack.simulate import SimulationParams, simulate
from cubetrack.simulate.camera_motion import DRIFT_STEP_S, plan_camera_motions
from cubetrack.simulate.render import project_points
from cubetrack.simulate.simulation import TRUE_CAMERA_POSES_DIR


def _offset(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Distance between two camera poses' positions (m) and the angle between them (deg)."""
    return (float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])),
            rotation_angle(T_a[:3, :3], T_b[:3, :3], unit="deg"))


def test_a_bump_is_a_step_of_the_asked_size_at_the_asked_time():
    rngs = [np.random.default_rng(k) for k in range(3)]
    motions = plan_camera_motions(3, (2, 2), (20.0, 30.0), 0.02, 1.0, 0, 0.0, 0.0, rngs)
    assert motions[0].still and motions[2].still and not motions[1].still
    T0 = np.eye(4)
    T0[:3, 3] = [1.0, 2.0, 1.0]
    bumped = motions[1]
    assert np.array_equal(bumped.T_world_cam(T0, 19.999), T0)
    step, turn = _offset(bumped.T_world_cam(T0, 20.0), T0)
    assert step == pytest.approx(0.02, abs=1e-12) and turn == pytest.approx(1.0, abs=1e-9)
    # the second bump starts from the first one's pose
    step2, turn2 = _offset(bumped.T_world_cam(T0, 30.0), bumped.T_world_cam(T0, 29.0))
    assert step2 == pytest.approx(0.02, abs=1e-12) and turn2 == pytest.approx(1.0, abs=1e-9)
    assert bumped.segment(25.0) == (1, 0) and bumped.segment(31.0) == (2, 0)


def test_a_drift_advances_at_its_rate_in_steps():
    rngs = [np.random.default_rng(5)]
    (motion,) = plan_camera_motions(1, (), (), 0.02, 1.0, 1, 2.0, 0.1, rngs)
    T0 = np.eye(4)
    step, turn = _offset(motion.T_world_cam(T0, 300.0), T0)
    assert step == pytest.approx(0.010, abs=1e-9)  # 2 mm/min for 5 min
    assert turn == pytest.approx(0.5, abs=1e-6)
    # constant within a step, then advancing
    assert np.array_equal(motion.T_world_cam(T0, 10.2), motion.T_world_cam(T0, 10.9))
    assert _offset(motion.T_world_cam(T0, 11.0), motion.T_world_cam(T0, 10.9))[0] == pytest.approx(
        2e-3 / 60.0 * DRIFT_STEP_S, rel=1e-9)
    assert np.array_equal(motion.T_world_cam(T0, -5.0), T0)


@pytest.mark.parametrize(("changes", "message"), [
    ({"bump_camera": (4,), "bump_at_s": (1.0,)}, "bump_camera 4"),
    ({"bump_camera": (1,), "bump_at_s": ()}, "one time per bumped camera"),
    ({"bump_camera": (1,), "bump_at_s": (40.0,)}, "within the recording"),
    ({"drift_camera": 5}, "drift_camera"),
    ({"bump_step_m": -0.01}, "bump_step_m"),
])
def test_bad_bumps_are_refused_with_a_clear_message(changes, message):
    with pytest.raises(ParamsError, match=message):
        SimulationParams(**changes)


def _world_corners(p: SimulationParams) -> np.ndarray:
    h = p.world_marker_size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@pytest.fixture(scope="module")
def bumped(tmp_path_factory):
    """A 1-camera clean session of 2 s bumped 3 cm / 1.5 deg at 1 s."""
    params = SimulationParams(cameras=1, duration_s=2.0, calibration_frames=3, seed=21, bump_camera=(1,),
                              bump_at_s=(1.0,), bump_step_m=0.03, bump_turn_deg=1.5, drop_rate=0.0)
    return simulate(params, tmp_path_factory.mktemp("bump") / "rec", workers=2)


def test_frames_are_rendered_from_the_true_pose_written_beside_them(bumped):
    """The world marker's detected corners lie where the pose in true_camera_poses/ puts them
    (within 0.5 px), and far (over 4 px) from where the unbumped pose would, after the bump only."""
    p = bumped.params
    cam = bumped.cameras[0]
    truth = read_tum(bumped.path / TRUE_CAMERA_POSES_DIR / "cam1.tum")
    capture_s = {c.seq: c.capture_host_s for c in cam.captures}
    corners_world = _world_corners(p)
    refine = cv2.aruco.DetectorParameters()
    refine.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), refine)
    errors: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
    for frame in Recording.open(bumped.path).frames("cam1"):
        gray = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
        corners, ids, _ = detector.detectMarkers(gray)
        found = [c.reshape(4, 2) for c, i in zip(corners, [] if ids is None else ids.ravel(), strict=False) if i == 0]
        if not found:
            continue  # the robot hides the world marker
        t = capture_s[frame.seq]
        row = int(np.argmin(np.abs(truth.times_s - t)))
        assert abs(truth.times_s[row] - t) < 1e-5
        T_true = bumped.T_world_cam_at("cam1", t)
        assert np.allclose(truth.positions_m[row], T_true[:3, 3], atol=2e-6)
        at_truth = np.abs(project_points(cam.intrinsics, T_true, corners_world) - found[0]).max()
        at_start = np.abs(project_points(cam.intrinsics, cam.T_world_cam, corners_world) - found[0]).max()
        errors[t - p.start_unix_s >= 1.0].append((float(at_truth), float(at_start)))
    assert len(errors[False]) >= 3 and len(errors[True]) >= 3
    assert max(e[0] for v in errors.values() for e in v) < 0.5
    assert max(e[1] for e in errors[False]) < 0.5
    assert min(e[1] for e in errors[True]) > 4.0


def test_the_calibration_recording_and_true_extrinsics_see_the_original_pose(bumped):
    cam = bumped.cameras[0]
    assert np.array_equal(cam.T_world_cam_at(-1.0), cam.T_world_cam)
    after = cam.T_world_cam_at(1.5)
    step, turn = _offset(after, cam.T_world_cam)
    assert step == pytest.approx(0.03, abs=1e-9) and turn == pytest.approx(1.5, abs=1e-6)
    # the rotation turns the camera about its optical centre: the centre moves by the translation alone
    (bump,) = cam.motion.bumps
    centre = transform_points(after @ invert_T(cam.T_world_cam), cam.T_world_cam[:3, 3][None])[0]
    assert np.allclose(centre, cam.T_world_cam[:3, 3] + bump.translation_m, atol=1e-12)


def test_still_cameras_write_no_pose_files(tmp_path):
    result = simulate(SimulationParams(cameras=1, duration_s=0.5, calibration_frames=0, seed=2), tmp_path / "rec")
    assert not (result.path / TRUE_CAMERA_POSES_DIR).exists()
