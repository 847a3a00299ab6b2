"""Cameras that disagree by what a calibration leaves (issue 25): near-simultaneous frames of two
cameras whose extrinsics are off by a fraction of a degree must not become velocity. Ground truth
by construction: a still cube, corners projected through the true cameras, the filter given one
camera's extrinsics turned by 0.25 deg."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from test_joint_and_filter import CAMS, INTR, LAYOUT, cube_pose, detections

from cubetrack.core.geometry import make_T
from cubetrack.core.records import CubeSighting
from cubetrack.estimate.pose import estimate_cube
from cubetrack.fuse.corner_filter import FilterParams
from cubetrack.fuse.fusion import FilterFusion, FusionParams

TURN = make_T(Rotation.from_rotvec(np.radians(0.25) * np.array([0.6, 0.0, 0.8])).as_matrix(), [0.0, 0.0, 0.0])


def speeds(filter_params: FilterParams) -> tuple[list[float], list[float]]:
    """The filter's speed (m/s) after each sighting past the first second, and its position error (m):
    cam1 and cam2 each at 6 fps, cam2 5 ms after cam1, cam2's extrinsics off by TURN."""
    rng = np.random.default_rng(3)
    truth = cube_pose()
    believed = {"cam1": CAMS["cam1"], "cam2": CAMS["cam2"] @ TURN}
    fusion = FilterFusion({"bot": LAYOUT}, FusionParams(), filter_params)
    speed, error = [], []
    for k in range(18):
        for camera, lag in (("cam1", 0.0), ("cam2", 0.005)):
            t = k / 6.0 + lag
            dets = detections(truth, CAMS[camera], rng)
            estimate = estimate_cube(dets, LAYOUT, INTR, believed[camera], camera=camera, robot="bot", seq=k,
                                     capture_time_s=t, arrival_time_s=t)
            fusion.add(CubeSighting(camera, "bot", k, t, t, dets, estimate, believed[camera], INTR), t)
            f = fusion.state["bot"].filter
            if t > 1.0 and f is not None:
                speed.append(float(np.linalg.norm(f.velocity_m_s)))
                error.append(float(np.linalg.norm(f.position_m - truth[:3, 3])))
    return speed, error


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
            dets = detections(cube_pose(), CAMS[camera], rng)
            estimate = estimate_cube(dets, LAYOUT, INTR, CAMS[camera], camera=camera, robot="bot", seq=k,
                                     capture_time_s=t, arrival_time_s=t)
            fusion.add(CubeSighting(camera, "bot", k, t, t, dets, estimate, CAMS[camera], INTR), t)
    t = 12 / 7.5
    moved = cube_pose(y=-0.11)   # 9 cm across cam1 in one frame: beyond the association gate, within reacquire_m
    dets = detections(moved, CAMS["cam1"], rng)
    fusion.add(CubeSighting("cam1", "bot", 12, t, t, dets, None, CAMS["cam1"], INTR), t)
    assert fusion.stats["re-acquired sighting"] == 1, dict(fusion.stats)
    assert seen and all(p is settings for p in seen)
