"""The corner-level estimators on synthetic corners: joint fit resolves flips, the filter gates
outliers and follows motion. Ground truth by construction (exact projections plus noise)."""

import dataclasses

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import invert_T, make_T, rotation_angle, shoelace_area
from cubetrack.core.layout import paper_cube_layout
from cubetrack.core.records import Detection
from cubetrack.estimate import reprojection
from cubetrack.estimate.match import match_faces
from cubetrack.estimate.pose import marker_pose
from cubetrack.estimate.reprojection import CornerSet
from cubetrack.fuse.corner_filter import FilterParams, PoseFilter
from cubetrack.fuse.multi_view_fit import solve_joint

K = np.array([[520.0, 0, 319.5], [0, 520.0, 239.5], [0, 0, 1]])
INTR = CameraIntrinsics(640, 480, K, np.zeros(5), "cam")
LAYOUT = paper_cube_layout()


def look_at(eye, target=(0.0, 0.0, 0.17)):
    """T_world_cam of a camera at ``eye`` looking at ``target`` (optical z forward, y down)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return make_T(np.column_stack([x, np.cross(z, x), z]), eye)


CAMS = {"cam1": look_at([2.2, -0.6, 1.0]), "cam2": look_at([-1.4, 1.8, 1.0]), "cam3": look_at([-1.0, -2.0, 1.2])}


def cube_pose(x=0.1, y=-0.2, yaw_deg=30.0):
    return make_T(Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix(), [x, y, 0.305])


def detections(T_world_cube, T_world_cam, rng, noise_px=0.2, faces=None):
    """Noisy detections of every cube face the camera sees (or of ``faces``)."""
    T_cam_cube = invert_T(T_world_cam) @ T_world_cube
    out = []
    for m in LAYOUT.markers:
        T = T_cam_cube @ m.T_cube_marker
        if faces is not None and m.face not in faces:
            continue
        if -T[:3, 2] @ T[:3, 3] / np.linalg.norm(T[:3, 3]) < 0.2:
            continue
        rvec, _ = cv2.Rodrigues(T_cam_cube[:3, :3])
        px, _ = cv2.projectPoints(m.corners_cube_m(), rvec, T_cam_cube[:3, 3], K, None)
        px = px.reshape(4, 2) + rng.normal(0, noise_px, (4, 2))
        out.append(Detection(m.marker_id, px, shoelace_area(px), "DICT_4X4_50"))
    return tuple(out)


def corner_set(T_world_cube, camera, rng, t=0.0, **kw):
    dets = detections(T_world_cube, CAMS[camera], rng, **kw)
    return matched(dets, T_world_cube, camera, t)


def matched(dets, T_world_cube, camera, t, gate_px=10.0):
    """The corner set of ``dets`` matched to the faces where ``T_world_cube`` puts them."""
    matches = match_faces(dets, LAYOUT, INTR, CAMS[camera], T_world_cube, gate_px=gate_px)
    return reprojection.corner_set(matches, INTR, CAMS[camera], camera, t)


def test_association_tells_same_id_faces_apart_by_the_predicted_pose():
    rng = np.random.default_rng(0)
    truth = cube_pose()
    s = corner_set(truth, "cam1", rng)
    assert len(s.faces) >= 2 and len(set(s.faces)) == len(s.faces)
    # the same detections against a prediction turned by 90 degrees match other faces, or none
    turned = truth @ make_T(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [0, 0, 0])
    other = matched(detections(truth, CAMS["cam1"], rng), turned, "cam1", 0.0)
    assert other is None or other.faces != s.faces


def test_joint_fit_over_cameras_resolves_a_flipped_single_face_start():
    rng = np.random.default_rng(1)
    truth = cube_pose(yaw_deg=10.0)
    # a lone, small, nearly fronto-parallel face: take IPPE's *other* solution as a bad start
    dets = detections(truth, CAMS["cam1"], rng, faces=("front",))
    mp = marker_pose(dets[0], 0.08, INTR)
    assert mp is not None and mp.T_cam_marker_alt is not None
    front = next(m for m in LAYOUT.markers if m.face == "front")
    candidates = [CAMS["cam1"] @ T @ invert_T(front.T_cube_marker) for T in (mp.T_cam_marker, mp.T_cam_marker_alt)]
    start = max(candidates, key=lambda T: rotation_angle(T[:3, :3], truth[:3, :3]))
    assert rotation_angle(start[:3, :3], truth[:3, :3], "deg") > 5.0  # the start really is flipped
    sets = [corner_set(truth, c, rng) for c in CAMS]
    sol = solve_joint(sets, start, 0.0)
    assert sol is not None
    assert rotation_angle(sol.T_world_cube[:3, :3], truth[:3, :3], "deg") < 0.5
    assert np.linalg.norm(sol.T_world_cube[:3, 3] - truth[:3, 3]) < 0.003


def test_joint_fit_estimates_velocity_from_sightings_spread_in_time():
    rng = np.random.default_rng(2)
    v_true = np.array([0.25, -0.1, 0.0])
    T0 = cube_pose()
    sets = []
    for cam, t in [("cam1", -0.2), ("cam2", -0.13), ("cam3", -0.07), ("cam1", 0.0)]:
        T = make_T(T0[:3, :3], T0[:3, 3] + v_true * t)
        sets.append(corner_set(T, cam, rng, t=t))
    sol = solve_joint(sets, cube_pose(x=0.12, y=-0.18), 0.0, velocity_sigma=(0.5, 1.0))
    assert np.linalg.norm(sol.T_world_cube[:3, 3] - T0[:3, 3]) < 0.003
    assert np.linalg.norm(sol.velocity_m_s - v_true) < 0.05


def test_a_joint_fit_capped_at_few_steps_finds_the_full_fits_solution_and_covariance():
    """solve_joint(iterations=N) (the camera watcher's fits): the same pose, velocities and
    covariance as the uncapped fit (itself checked against scipy's trust-region solver in
    test_filter_kernels), with an outlier corner the soft-L1 loss must discount."""
    rng = np.random.default_rng(5)
    v_true = np.array([0.2, 0.05, 0.0])
    T0 = cube_pose()
    sets = []
    for cam, t in [("cam1", -0.1), ("cam2", -0.05), ("cam3", 0.0)]:
        sets.append(corner_set(make_T(T0[:3, :3], T0[:3, 3] + v_true * t), cam, rng, t=t))
    sets[1].normalized[0] += 8.0 / sets[1].focal_px  # one corner 8 px off
    start = cube_pose(x=0.105, y=-0.21)  # about 2 cm off, as a camera's own estimate after a bump
    trf = solve_joint(sets, start, 0.0, velocity_sigma=(1.0, 4.0))
    gn = solve_joint(sets, start, 0.0, velocity_sigma=(1.0, 4.0), iterations=30)
    assert np.linalg.norm(gn.T_world_cube[:3, 3] - trf.T_world_cube[:3, 3]) < 1e-5
    assert rotation_angle(gn.T_world_cube[:3, :3], trf.T_world_cube[:3, :3], "deg") < 1e-3
    assert np.allclose(gn.velocity_m_s, trf.velocity_m_s, atol=1e-4)
    assert np.allclose(gn.covariance, trf.covariance, rtol=1e-3, atol=1e-12) and gn.rms_px == pytest.approx(trf.rms_px)


def test_the_camera_refit_falls_back_to_the_trust_region_solver_where_gauss_newton_gives_up(monkeypatch):
    """refit_camera (the camera watcher's resection) by robust_gauss_newton; from a start it would
    run off from (turned 25 deg), or with too few steps to converge, that gives up (None) and the
    trust-region solver finds the same camera pose."""
    from cubetrack.fuse import camera_watch
    from cubetrack.fuse.multi_view_fit import robust_gauss_newton

    rng = np.random.default_rng(4)
    T_cam = CAMS["cam1"]
    X = np.column_stack([rng.uniform(-0.6, 0.6, 60), rng.uniform(-0.6, 0.6, 60), rng.uniform(0.2, 0.4, 60)])
    in_cam = (X - T_cam[:3, 3]) @ T_cam[:3, :3]
    uv = in_cam[:, :2] / in_cam[:, 2:] + rng.normal(0, 0.3 / INTR.K[0, 0], (60, 2))
    told = []
    monkeypatch.setattr(camera_watch, "robust_gauss_newton",
                        lambda *a: told.append(robust_gauss_newton(*a)) or told[-1])
    near = make_T(Rotation.from_euler("z", 1.0, degrees=True).as_matrix() @ T_cam[:3, :3], T_cam[:3, 3] + 0.02)
    far = make_T(Rotation.from_euler("xz", [20.0, 15.0], degrees=True).as_matrix() @ T_cam[:3, :3], T_cam[:3, 3])
    fits = [camera_watch.refit_camera(X, uv, INTR.K[0, 0], start) for start in (near, far)]
    monkeypatch.setattr(camera_watch, "FIT_ITERATIONS", 1)
    fits.append(camera_watch.refit_camera(X, uv, INTR.K[0, 0], near))
    assert told[0] is not None and told[1:] == [None, None]
    for fit in fits:
        assert np.linalg.norm(fit.T_world_cam[:3, 3] - T_cam[:3, 3]) < 0.005
        assert rotation_angle(fit.T_world_cam[:3, :3], T_cam[:3, :3], "deg") < 0.1


def started_filter(truth, t=0.0):
    cov = np.diag([1e-4] * 3 + [1e-4] * 3)
    return PoseFilter(FilterParams(), t, truth, cov)


def test_filter_follows_constant_velocity_motion():
    rng = np.random.default_rng(3)
    v = np.array([0.2, 0.1, 0.0])
    T0 = cube_pose()
    f = started_filter(T0)
    cams = list(CAMS)
    for k in range(1, 60):
        t = k / 22.5
        truth = make_T(T0[:3, :3], T0[:3, 3] + v * t)
        f.predict(t)
        s = matched(detections(truth, CAMS[cams[k % 3]], rng), f.T_world_cube, cams[k % 3], t)
        assert f.update([s]).accepted
    assert np.linalg.norm(f.position_m - truth[:3, 3]) < 0.002
    assert np.linalg.norm(f.velocity_m_s - v) < 0.03


def test_filter_drops_a_bad_face_and_rejects_a_garbage_sighting():
    rng = np.random.default_rng(4)
    truth = cube_pose()
    f = started_filter(truth)
    good = corner_set(truth, "cam1", rng)
    assert len(good.faces) >= 2
    bad = good.normalized.copy()
    bad[:4] += 25.0 / 520.0  # the first face's corners 25 px off: a misread marker
    result = f.update([CornerSet(good.camera, 0.0, good.T_cam_world, good.focal_px, good.points_cube_m, bad,
                                 good.faces)])
    assert result.accepted and result.points == 4 * (len(good.faces) - 1)
    assert np.linalg.norm(f.position_m - truth[:3, 3]) < 0.003
    before = f.T_world_cube.copy()
    garbage = CornerSet("cam2", 0.0, invert_T(CAMS["cam2"]), 520.0, LAYOUT.markers[0].corners_cube_m(),
                        rng.uniform(-0.3, 0.3, (4, 2)), ("top",))
    assert not f.update([garbage]).accepted
    np.testing.assert_array_equal(f.T_world_cube, before)  # a rejected sighting changes nothing


@pytest.mark.parametrize("bad", [{"accel_noise": 0.0}, {"iterations": 0}, {"gate_rms_px": -1.0}])
def test_filter_params_are_checked(bad):
    with pytest.raises(ValueError):
        FilterParams(**bad)


def test_analytic_jacobian_matches_finite_differences():
    from cubetrack.estimate.reprojection import perturbed, reprojection_jacobian_px, reprojection_residuals_px

    rng = np.random.default_rng(6)
    T = cube_pose()
    sets = [corner_set(T, c, rng) for c in CAMS]
    r, J = reprojection_jacobian_px(T, sets)
    zero = np.zeros(3)
    np.testing.assert_allclose(r, reprojection_residuals_px(T, sets, 0.0, zero, zero), atol=1e-9)
    eps = 1e-7
    for k in range(6):
        step = np.zeros(6)
        step[k] = eps
        numeric = (reprojection_residuals_px(perturbed(T, step), sets, 0.0, zero, zero) - r) / eps
        np.testing.assert_allclose(J[:, k], numeric, rtol=1e-4, atol=1e-3)


def test_motion_jacobian_matches_finite_differences():
    """The joint fit's Jacobian: pose increment, linear and angular velocity of a moving cube."""
    from cubetrack.estimate.reprojection import (
        moved_pose,
        perturbed,
        reprojection_jacobian_px,
        reprojection_residuals_px,
    )

    rng = np.random.default_rng(7)
    T = cube_pose()
    v, w = np.array([0.2, -0.1, 0.0]), np.array([0.1, 0.3, -1.5])
    sets = [corner_set(moved_pose(T, v, w, t), c, rng, t=t) for c, t in zip(CAMS, (-0.08, 0.0, 0.11), strict=True)]
    sets[2] = dataclasses.replace(sets[2], row_offsets_s=rng.normal(0.0, 0.01, len(sets[2].points_cube_m)))  # rows
    r, J = reprojection_jacobian_px(T, sets, 0.0, v, w)
    assert J.shape == (len(r), 12)
    np.testing.assert_allclose(r, reprojection_residuals_px(T, sets, 0.0, v, w), atol=1e-9)
    eps = 1e-7
    for k in range(12):
        step = np.zeros(12)
        step[k] = eps
        numeric = (reprojection_residuals_px(perturbed(T, step[:6]), sets, 0.0, v + step[6:9], w + step[9:])
                   - r) / eps
        np.testing.assert_allclose(J[:, k], numeric, rtol=1e-4, atol=1e-3)


def test_so3_left_jacobian_chains_a_finite_rotation_increment():
    from cubetrack.core.geometry import R_from_rotvec, so3_left_jacobian

    rng = np.random.default_rng(8)
    for v in (rng.normal(size=3), np.array([1e-9, 0.0, 2e-9]), np.array([0.0, 3.0, 0.0])):
        e = rng.normal(size=3) * 1e-6
        np.testing.assert_allclose(R_from_rotvec(v + e), R_from_rotvec(so3_left_jacobian(v) @ e) @ R_from_rotvec(v),
                                   atol=1e-11)


def test_turning_is_less_certain_than_tilting_over_a_prediction():
    """Robots turn sharply about the world's z axis and tilt little: the process noise says so
    (yaw_accel_noise vs angular_accel_noise), in the world frame whatever the cube's heading."""
    heading = cube_pose(yaw_deg=60.0)
    turning = [0.0, 0.0, 3.0]  # rad/s: a sharp turn, so the turning noise applies
    f = PoseFilter(FilterParams(angular_accel_noise=0.5, yaw_accel_noise=10.0), 0.0, heading, np.eye(12) * 1e-6,
                   angular_velocity_rad_s=turning)
    f.predict(0.2)
    tilt, yaw = f.P[3, 3], f.P[5, 5]
    assert tilt == pytest.approx(f.P[4, 4]) and yaw > 100 * (tilt - 1e-6) > 0
    same = PoseFilter(FilterParams(angular_accel_noise=2.0, yaw_accel_noise=2.0), 0.0, heading, np.eye(12) * 1e-6,
                      angular_velocity_rad_s=turning)
    same.predict(0.2)
    assert same.P[3, 3] == pytest.approx(same.P[5, 5])


def yaw_variance_after(f, dt):
    """The yaw variance a prediction over ``dt`` adds beyond what the covariance carried in."""
    before = f.P[5, 5] + dt * dt * f.P[11, 11] + 2 * dt * f.P[5, 11]
    f.predict(f.time_s + dt)
    return f.P[5, 5] - before


def test_the_turning_noise_holds_for_turn_hold_s_after_a_sharp_turn():
    params = FilterParams(yaw_accel_noise=10.0, steady_yaw_accel_noise=3.0, sharp_turn_rad_s=2.0, turn_hold_s=1.0)
    dt = 0.05
    steady, turning = 3.0**2 * dt**3 / 3, 10.0**2 * dt**3 / 3
    f = PoseFilter(params, 0.0, cube_pose(), np.eye(12) * 1e-6, angular_velocity_rad_s=[0.0, 0.0, 1.5])
    assert yaw_variance_after(f, dt) == pytest.approx(steady)  # 1.5 rad/s is no sharp turn
    g = PoseFilter(params, 0.0, cube_pose(), np.eye(12) * 1e-6, angular_velocity_rad_s=[0.0, 0.0, -2.5])
    assert yaw_variance_after(g, dt) == pytest.approx(turning)
    g.angular_velocity_rad_s = np.zeros(3)  # the turn ended at 0 s: the turning noise holds until 1 s
    g.predict(0.96)
    assert yaw_variance_after(g, dt) == pytest.approx(turning)
    assert yaw_variance_after(g, dt) == pytest.approx(steady)


def track_yaw_errors(params, yaw_deg_at, seconds=6.0, seed=11, noise_px=0.3, single_face=False, rate_hz=22.5,
                     manoeuvre=None):
    """Yaw errors (rad) of a filter fed single-camera sightings at ``rate_hz`` of a cube turning as
    ``yaw_deg_at(t)`` on the spot (``single_face``: only the largest face of each camera frame,
    as in most sightings of the realistic preset), and whether every sighting was accepted;
    ``manoeuvre``: a list to which each sighting appends whether the manoeuvre's noise is on after it."""
    rng = np.random.default_rng(seed)
    truth_at = lambda t: cube_pose(yaw_deg=yaw_deg_at(t))
    f = PoseFilter(params, 0.0, truth_at(0.0), np.diag([1e-6] * 3 + [1e-5] * 3))
    cams, errors, accepted = list(CAMS), [], True
    for k in range(1, int(seconds * rate_hz)):
        t = k / rate_hz
        f.predict(t)
        dets = detections(truth_at(t), CAMS[cams[k % 3]], rng, noise_px=noise_px)
        if single_face:
            dets = (max(dets, key=lambda d: d.area_px2),)
        s = matched(dets, f.T_world_cube, cams[k % 3], t)
        accepted &= f.update([s]).accepted
        errors.append(rotation_angle(f.R_world_cube, truth_at(t)[:3, :3]))
        if manoeuvre is not None:
            manoeuvre.append(f.time_s <= f.manoeuvre_until_s)
    return np.array(errors), accepted


def ramped_turn(start_s, rate_deg_s, hold_s, yaw_accel_rad_s2=8.0, yaw0_deg=30.0):
    """A turn on the spot a wheeled robot can drive: from ``start_s`` the yaw rate ramps up to
    ``rate_deg_s`` at ``yaw_accel_rad_s2`` (the simulator's sharp path: 2 x 1 m/s^2 / 0.25 m wheel
    track), holds for ``hold_s`` and ramps down again. Returns (yaw in degrees at t, the stop)."""
    accel = np.degrees(yaw_accel_rad_s2)
    ramp = rate_deg_s / accel
    stop = start_s + 2 * ramp + hold_s

    def yaw_deg_at(t):
        up, down = np.clip(t - start_s, 0.0, ramp), np.clip(t - (stop - ramp), 0.0, ramp)
        steady = np.clip(t - start_s - ramp, 0.0, hold_s)
        return yaw0_deg + 0.5 * accel * up**2 + rate_deg_s * (steady + down) - 0.5 * accel * down**2

    return yaw_deg_at, stop


def test_ramped_turn_is_continuous_and_turns_at_the_rate_asked():
    yaw, stop = ramped_turn(1.0, 200.0, 0.6)
    t = np.arange(0.0, stop + 0.5, 1e-3)
    y = np.array([yaw(x) for x in t])
    rate = np.gradient(y, t)
    assert np.max(np.abs(np.diff(y))) < 0.25 and rate.max() == pytest.approx(200.0, abs=0.5)
    assert np.max(np.abs(np.gradient(rate, t))) < np.degrees(8.0) * 1.01  # the yaw rate ramps, never steps
    assert yaw(stop + 1.0) - yaw(0.0) == pytest.approx(200.0 * (0.6 + 200.0 / np.degrees(8.0)))


def test_a_robot_that_turns_gently_gets_the_steady_noise_and_a_smoother_heading():
    """A gentle weave (at most 0.8 rad/s): the steady yaw noise averages more sightings than the
    turning noise would, whose level a fixed model needs for the sharp turns of other robots."""
    weave = lambda t: 30.0 + 15.0 * np.sin(3.0 * t)  # (deg; 0.79 rad/s at most)
    adaptive, ok = track_yaw_errors(FilterParams(), weave)
    fixed, ok_fixed = track_yaw_errors(FilterParams(steady_yaw_accel_noise=FilterParams().yaw_accel_noise), weave)
    assert ok and ok_fixed
    rms = lambda e: float(np.sqrt(np.mean(e[20:] ** 2)))  # (after the start)
    assert rms(adaptive) < 0.97 * rms(fixed)  # 0.95-0.96 over seeds 11-13 (the same filter: 1.0)


def test_the_turning_noise_follows_a_drivable_sharp_turn_and_its_stop():
    """Still, a turn on the spot at 200 deg/s whose rate ramps at 8 rad/s^2 (as a wheeled robot
    drives it), still again; one face per sighting: the turn switches to the turning noise, which
    follows the turn closer than the steady noise alone, and holds for turn_hold_s, so the
    ramp down to the stop is followed closer than if it fell back to the steady noise at once (the
    manoeuvre's noise off: the turn rule on its own)."""
    turn, stop = ramped_turn(1.0, 200.0, 0.6)
    t = np.arange(1, int((stop + 1.0) * 22.5)) / 22.5
    turning, stopping = (t > 1.0) & (t < stop), (t >= stop - 0.3) & (t < stop + 0.4)
    run = lambda **kw: track_yaw_errors(FilterParams(**{"manoeuvre_z2": 0.0, **kw}), turn, seconds=stop + 1.0,
                                        noise_px=0.1, single_face=True)
    adaptive, ok = run()
    steady, _ = run(yaw_accel_noise=FilterParams().steady_yaw_accel_noise)
    no_hold, _ = run(turn_hold_s=0.01)
    assert ok
    rms = lambda e, m: float(np.sqrt(np.mean(e[m] ** 2)))
    assert np.degrees(rms(adaptive, turning)) < 1.2  # 0.83
    assert rms(adaptive, turning) < 0.9 * rms(steady, turning)  # 0.82-0.85 over seeds 11-16
    assert rms(adaptive, stopping) < 0.93 * rms(no_hold, stopping)  # 0.80-0.93 over seeds 11-14


def test_the_manoeuvre_noise_follows_a_turn_onset_and_stays_off_while_still():
    """The yaw lags a turn's onset (its rate ramping at 8 rad/s^2) before the yaw rate reaches a sharp turn's: its
    corrections lean one way, the manoeuvre's noise switches on and follows the ramp up closer than the turn rule
    alone; while the cube stands still the corrections are noise and it stays off."""
    turn, stop = ramped_turn(3.0, 200.0, 0.6)
    t = np.arange(1, int((stop + 1.0) * 22.5)) / 22.5
    still, ramp_up = (t > 1.5) & (t < 3.0), (t >= 3.0) & (t < 3.0 + 200.0 / np.degrees(8.0))
    on: list[bool] = []
    run = lambda z2, flags=None: track_yaw_errors(FilterParams(manoeuvre_z2=z2), turn, seconds=stop + 1.0,
                                                  noise_px=0.1, single_face=True, manoeuvre=flags)
    adaptive, ok = run(FilterParams().manoeuvre_z2, on)
    rule_only, _ = run(0.0)
    assert ok
    on = np.array(on)
    assert on[ramp_up].any() and on[still].mean() < 0.2  # 0 over seeds 11-17 but 16 (0.53: a false alarm, held)
    rms = lambda e: float(np.sqrt(np.mean(e[ramp_up] ** 2)))
    assert rms(adaptive) < 0.9 * rms(rule_only)  # 0.62-0.78 over seeds 11-17


def test_the_manoeuvre_noise_needs_sightings_close_enough_to_show_a_trend():
    """Sightings 0.2 s apart (5 Hz) put fewer than manoeuvre_min_samples corrections in the short mean: the
    manoeuvre's noise never switches on, whatever they say."""
    turn, stop = ramped_turn(3.0, 200.0, 0.6)
    on: list[bool] = []
    track_yaw_errors(FilterParams(), turn, seconds=stop + 1.0, noise_px=0.1, rate_hz=5.0, manoeuvre=on)
    assert len(on) > 10 and not any(on)
