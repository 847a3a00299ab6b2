"""Cameras that disagree by what a calibration leaves (issue 25): near-simultaneous frames of two
cameras whose extrinsics are off by a fraction of a degree must not become velocity. Ground truth
by construction: a still cube, corners projected through the true cameras, the filter given one
camera's extrinsics turned by 0.25 deg, or one camera's focal length 2 % off."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation
from test_joint_and_filter import CAMS, INTR, LAYOUT, cube_pose, detections

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import make_T
from cubetrack.core.layout import CubeLayout
from cubetrack.core.records import CubeSighting
from cubetrack.estimate.pose import estimate_cube
from cubetrack.fuse.corner_filter import FilterParams
from cubetrack.fuse.fusion import FilterFusion, FusionParams

TURN = make_T(Rotation.from_rotvec(np.radians(0.25) * np.array([0.6, 0.0, 0.8])).as_matrix(), [0.0, 0.0, 0.0])


def sight(fusion: FilterFusion, camera: str, truth: np.ndarray, k: int, t: float, rng: np.random.Generator,
          intrinsics: CameraIntrinsics = INTR, T_world_cam: np.ndarray | None = None) -> None:
    """``camera`` (at ``CAMS[camera]`` unless ``T_world_cam`` says where it is believed to be, with the
    ``intrinsics`` it is believed to have) sees the cube at ``truth`` as frame ``k`` taken at ``t``."""
    T_world_cam = CAMS[camera] if T_world_cam is None else T_world_cam
    dets = detections(truth, CAMS[camera], rng)
    estimate = estimate_cube(dets, LAYOUT, intrinsics, T_world_cam, camera=camera, robot="bot", seq=k,
                             capture_time_s=t, arrival_time_s=t)
    fusion.add(CubeSighting(camera, "bot", k, t, t, dets, estimate, T_world_cam, intrinsics), t)


def still_cube(filter_params: FilterParams, believed: dict[str, tuple[np.ndarray, CameraIntrinsics]],
               seed: int = 3, layout: CubeLayout = LAYOUT) -> tuple[list[float], list[float]]:
    """The filter's speed (m/s) after each sighting past the first second, and its position error (m):
    a still cube seen by the two cameras of ``believed`` at 6 fps, the second 5 ms after the first,
    the corners projected through the true cameras, the filter given each camera as ``believed``
    (its T_world_cam, its intrinsics); the fusion told the body's ``layout`` (its motion)."""
    rng = np.random.default_rng(seed)
    truth = cube_pose()
    fusion = FilterFusion({"bot": layout}, FusionParams(), filter_params)
    speed, error = [], []
    for k in range(18):
        for (camera, (T_world_cam, intrinsics)), lag in zip(believed.items(), (0.0, 0.005), strict=True):
            t = k / 6.0 + lag
            sight(fusion, camera, truth, k, t, rng, intrinsics, T_world_cam)
            f = fusion.state["bot"].filter
            if t > 1.0 and f is not None:
                speed.append(float(np.linalg.norm(f.velocity_m_s)))
                error.append(float(np.linalg.norm(f.position_m - truth[:3, 3])))
    return speed, error


def speeds(filter_params: FilterParams) -> tuple[list[float], list[float]]:
    """:func:`still_cube` seen by cam1 and cam2, cam2's extrinsics off by TURN."""
    return still_cube(filter_params, {"cam1": (CAMS["cam1"], INTR), "cam2": (CAMS["cam2"] @ TURN, INTR)})


def test_disagreeing_cameras_do_not_make_a_still_cube_move():
    exact = speeds(FilterParams(camera_position_sigma_m=0.0))[0]
    speed, error = speeds(FilterParams())
    assert len(speed) == len(exact) >= 20
    # measured: median 0.014 m/s against 0.052 with the cameras taken as exact; the cube sits
    # between the two cameras' views (they disagree by ~10 mm at 2.3 m), 12 mm from either
    assert np.median(speed) < 0.025, np.median(speed)
    assert np.median(exact) > 2.5 * np.median(speed), (np.median(exact), np.median(speed))
    assert max(error) < 0.015, max(error)


def test_re_acquisition_finds_the_cameras_own_pose_with_the_estimator_settings(monkeypatch):
    """A sighting the prediction does not explain is re-examined against its camera's own cube
    pose, made with the tracker's [estimator] settings (issue 25: they were lost there)."""
    import cubetrack.fuse.fusion as fusion_module
    from cubetrack.estimate.params import EstimatorParams

    seen = []
    original = fusion_module.estimate_cube

    def spy(*args, **kwargs):
        seen.append(kwargs.get("params"))
        return original(*args, **kwargs)

    monkeypatch.setattr(fusion_module, "estimate_cube", spy)
    settings = EstimatorParams(use_upright_prior=False, max_reprojection_error_px=2.5)
    fusion = FilterFusion({"bot": LAYOUT}, FusionParams(), FilterParams(), settings)
    rng = np.random.default_rng(4)
    for k in range(12):   # a still cube: the track starts and settles
        for camera in ("cam1", "cam2"):
            t = k / 7.5 + (0.01 if camera == "cam2" else 0.0)
            sight(fusion, camera, cube_pose(), k, t, rng)
    t = 12 / 7.5
    moved = cube_pose(y=-0.11)   # 9 cm across cam1 in one frame: beyond the association gate, within reacquire_m
    dets = detections(moved, CAMS["cam1"], rng)
    fusion.add(CubeSighting("cam1", "bot", 12, t, t, dets, None, CAMS["cam1"], INTR), t)
    assert fusion.stats["re-acquired sighting"] == 1, dict(fusion.stats)
    assert seen and all(p is settings for p in seen)
    # the track goes on with the prediction's velocities and their covariance, not a start's spreads
    # (init_velocity_sigma 0.5 m/s, 3 rad/s), which would let the next frame of a camera that disagrees, a few ms
    # later, become velocity (issue 25, tenth round); the re-acquiring update informs the pose only
    predicted = fusion.history["bot"][-1].before.filter.copy()
    predicted.predict(t)
    after = fusion.state["bot"].filter.P
    assert np.allclose(after[6:, 6:], predicted.P[6:, 6:]), (np.sqrt(after.diagonal()[6:]),
                                                            np.sqrt(predicted.P.diagonal()[6:]))
    assert np.sqrt(after.diagonal()[6:9]).max() < 0.3, np.sqrt(after.diagonal()[6:9])


def focal_errors(filter_params: FilterParams, seed: int) -> list[float]:
    """:func:`still_cube`'s position errors (m) seen by cam1 and cam3 (about 110 deg apart), the filter
    given cam1's focal length 2 % too long, so cam1's own depth of the cube is 2 % (~45 mm) too far."""
    K = INTR.K.copy()
    K[:2, :2] *= 1.02
    believed = {"cam1": (CAMS["cam1"], dataclasses.replace(INTR, K=K)), "cam3": (CAMS["cam3"], INTR)}
    return still_cube(filter_params, believed, seed)[1]


def test_a_cameras_scale_error_is_not_taken_as_its_depth():
    """With the scale term (camera_scale_sigma) a camera's depth of the body is trusted less than its view
    across, so the other camera's view across fixes the depth: measured, median error 3.59 / 3.57 mm
    (seeds 3 / 4) against 3.74 / 3.91 mm without it (3.49 / 3.39 against 3.97 / 3.75 before each corner got
    its own noise, issue 26: this scene's small oblique faces, modules of 0.7-1.4 px, now count less, and
    with them the depth they gave)."""
    medians = []
    for seed in (3, 4):
        scaled, plain = focal_errors(FilterParams(), seed), focal_errors(FilterParams(camera_scale_sigma=0.0), seed)
        assert len(scaled) == len(plain) >= 20
        medians.append((np.median(scaled), np.median(plain)))
    scaled_m, plain_m = np.sum(medians, axis=0)
    assert scaled_m < 0.95 * plain_m, medians


def wobbling_cube(filter_params: FilterParams, seed: int) -> tuple[float, float]:
    """The filter's median speed (m/s) and RMS position error (m) past the first second: a cube at rest on a robot
    that wobbles (each instant rolled and pitched 0.5 deg std about the floor point below it, independent from
    instant to instant, as a 3-12 Hz vibration is at 7.5 fps), seen by three cameras 0 / 4 / 9 ms apart."""
    rng = np.random.default_rng(seed)
    rest = cube_pose()
    floor = make_T(np.eye(3), [rest[0, 3], rest[1, 3], 0.0])
    fusion = FilterFusion({"bot": LAYOUT}, FusionParams(), filter_params)
    speed, error = [], []
    for k in range(30):
        tilt = make_T(Rotation.from_rotvec(np.radians(0.5) * np.append(rng.normal(size=2), 0.0)).as_matrix(), [0, 0, 0])
        truth = floor @ tilt @ np.linalg.inv(floor) @ rest
        for camera, lag in (("cam1", 0.0), ("cam2", 0.004), ("cam3", 0.009)):
            t = k / 7.5 + lag
            sight(fusion, camera, truth, k, t, rng)
            f = fusion.state["bot"].filter
            if t > 1.0 and f is not None:
                speed.append(float(np.linalg.norm(f.velocity_m_s)))
                error.append(float(np.linalg.norm(f.position_m - truth[:3, 3])))
    return float(np.median(speed)), float(np.sqrt(np.mean(np.square(error))))


def test_a_robots_wobble_is_not_taken_as_its_motion():
    """With the wobble term (wobble_sigma_deg, issue 25 eleventh round) each frame's roll and pitch about the
    floor is trusted less, so a wobble faster than the motion model follows moves the velocity less: measured
    (seeds 3 / 4) median speed 34 / 32 mm/s against 39 / 38 without it, RMS error 3.31 / 3.83 mm against
    3.45 / 4.09 (with 40 instants and seed 5 as well, the median error is ~0.1 mm worse: the wobble is not
    followed)."""
    for seed in (3, 4):
        without = wobbling_cube(FilterParams(), seed)
        with_term = wobbling_cube(FilterParams(wobble_sigma_deg=0.5), seed)
        assert with_term[0] < 0.92 * without[0], (with_term, without)
        assert with_term[1] < without[1], (with_term, without)


def test_a_free_body_is_tracked_with_half_the_calibration_term_and_no_wobble():
    """A body whose layout says motion = "free" (hand-held, issue 25 twelfth round) gets the three camera
    sigmas times free_body_term_scale (0.5), no wobble and its height's acceleration noise as accel_noise; a floor body
    (the default) the term as set and vertical_accel_noise."""
    believed = {"cam1": (CAMS["cam1"], INTR), "cam2": (CAMS["cam2"] @ TURN, INTR)}
    free = dataclasses.replace(LAYOUT, motion="free")
    halved = FilterParams(camera_position_sigma_m=0.001, camera_rotation_sigma_deg=0.05, camera_scale_sigma=0.0025,
                          vertical_accel_noise=0.5)
    as_free = still_cube(FilterParams(wobble_sigma_deg=0.5), believed, layout=free)
    assert as_free == still_cube(halved, believed)  # the same arithmetic, to the bit
    assert still_cube(FilterParams(), believed) != as_free
    assert still_cube(FilterParams(free_body_term_scale=1.0), believed, layout=free) == still_cube(
        FilterParams(vertical_accel_noise=0.5), believed)



def lone_camera_errors(filter_params: FilterParams, seed: int, layout: CubeLayout = LAYOUT) -> list[float]:
    """The position errors (m) after each of cam1's sightings past the first: a still cube seen by cam1 and
    cam3 (true cameras) at 6 fps for 1 s, then by cam1 alone for 0.5 s, the filter given cam1's focal length
    2 % too long (its depth ~45 mm too far; issue 27: one camera's markers carrying the pose along its ray)."""
    rng = np.random.default_rng(seed)
    truth = cube_pose()
    K = INTR.K.copy()
    K[:2, :2] *= 1.02
    believed = {"cam1": dataclasses.replace(INTR, K=K), "cam3": INTR}
    fusion = FilterFusion({"bot": layout}, FusionParams(), filter_params)
    errors = []
    for k in range(9):
        for camera, lag in (("cam1", 0.0), ("cam3", 0.005))[: 2 if k < 6 else 1]:
            t = k / 6.0 + lag
            sight(fusion, camera, truth, k, t, rng, believed[camera])
            if camera == "cam1" and k > 1:
                errors.append(float(np.linalg.norm(fusion.state["bot"].filter.position_m - truth[:3, 3])))
    return errors


def test_a_floor_robots_height_pins_a_lone_cameras_depth():
    """With the vertical acceleration noise of a floor body low, the height the two cameras fix holds cam1's
    ray (it looks down at the cube, 18 deg) against cam1's biased depth, with cam3 and without; a free body
    (hand-held) is not held so: the setting does not touch it. Measured: mean error over cam1's sightings
    25.0 / 23.3 mm (seeds 3 / 4) with the height's noise as accel_noise (0.5), 15.9 / 15.2 mm at the default 0.05."""
    loose = FilterParams(vertical_accel_noise=FilterParams().accel_noise)  # the height as free as the rest
    errors = [(np.mean(lone_camera_errors(loose, seed)), np.mean(lone_camera_errors(FilterParams(), seed)))
              for seed in (3, 4)]
    assert all(held < 0.75 * free_height for free_height, held in errors), errors
    free = dataclasses.replace(LAYOUT, motion="free")
    assert lone_camera_errors(FilterParams(), 3, free) == lone_camera_errors(loose, 3, free)


def start_nees(seed: int, partner: str) -> float:
    """The squared position error of a track's start over the covariance it claims (its NEES, 3
    degrees of freedom): a still cube seen by cam1 and ``partner`` at 6 fps, both cameras' focal
    lengths believed 2 % long (each puts the cube too far along its own ray)."""
    rng = np.random.default_rng(seed)
    truth = cube_pose()
    K = INTR.K.copy()
    K[:2, :2] *= 1.02
    believed = dataclasses.replace(INTR, K=K)
    fusion = FilterFusion({"bot": LAYOUT}, FusionParams(), FilterParams())
    for k in range(3):
        for camera, lag in (("cam1", 0.0), (partner, 0.005)):
            t = k / 6.0 + lag
            sight(fusion, camera, truth, k, t, rng, believed)
            f = fusion.state["bot"].filter
            if f is not None:
                error = f.position_m - truth[:3, 3]
                return float(error @ np.linalg.solve(f.P[:3, :3], error))
    raise AssertionError("no track start")


def test_a_track_start_claims_the_uncertainty_its_cameras_leave():
    """A start is as sure of its pose as the filter's own updates from the same frames would be
    (each corner's noise and its camera's calibration term), not as the joint fit of the corners'
    noise alone (issue 27: a start from a few far markers claimed a centimetre's depth too little)."""
    nees = [start_nees(seed, partner) for seed in range(4) for partner in ("cam2", "cam3")]
    # measured: mean 2.1 (max 3.2); the joint fit's own covariance: mean 10.3 (7.2-14.9)
    assert np.mean(nees) < 4.0, nees
