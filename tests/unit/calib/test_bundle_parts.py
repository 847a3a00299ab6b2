"""The bundle adjustment's parts on synthetic data built from known poses (no images)."""

import re

import numpy as np
from scipy.spatial.transform import Rotation

from cubetrack.calib.bundle import (
    BundleAdjustmentParams,
    CubeFrame,
    group_instants,
    robust_average_corners,
    spread_instants,
    velocities,
    worse_world_fit,
)
from cubetrack.calib.solver import BodyPrior, Freedom, IntrinsicsPrior, Model, Observations, PosePrior, project, solve
from cubetrack.core.geometry import R_from_rotvec, invert_T, make_T, rotation_angle
from cubetrack.core.layout import marker_corners_m, paper_cube_layout


def look_at(position, target=(0.0, 0.0, 0.15)):
    z = np.asarray(target, float) - position
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return make_T(np.column_stack([x, np.cross(z, x), z]), position)


def test_group_instants_pairs_frames_of_different_cameras_once():
    f = lambda cam, t: CubeFrame(cam, "r", 0, t, ())
    frames = [f("a", 0.00), f("b", 0.03), f("a", 0.10), f("b", 0.30), f("c", 0.32), f("a", 0.34)]
    groups = group_instants(frames, 0.05, 2)
    assert [[x.camera for x in g] for g in groups] == [["a", "b"], ["b", "c", "a"]]


def test_velocities_of_a_constant_twist():
    t = np.linspace(0.0, 1.0, 21)
    Ts = np.array([make_T(Rotation.from_rotvec([0, 0, 0.5 * ti]).as_matrix(), [0.2 * ti, -0.1 * ti, 0.15]) for ti in t])
    v, w = velocities(t, Ts, 0.3)
    assert np.allclose(v, [0.2, -0.1, 0.0], atol=1e-9) and np.allclose(w, [0, 0, 0.5], atol=1e-9)


def test_few_instants_kept_of_a_long_drive_still_get_velocities():
    """A drive's instants (three cameras at 15 frames/s, 10 s) cut to 30: each kept instant has the
    neighbours the velocity fit needs, so a robot at 0.4 m/s is not taken for standing still. An
    even spread of single instants (0.33 s apart) leaves nearly all without (checked: fails so)."""
    f = lambda cam, t: CubeFrame(cam, "r", 0, t, ())
    frames = [f(cam, k / 15 + 0.02 * i) for k in range(150) for i, cam in enumerate("abc")]
    groups = group_instants(frames, 0.1, 2)
    assert len(groups) > 100
    times = lambda gs: np.array([g[0].time_s for g in gs])
    poses = lambda t: np.array([make_T(np.eye(3), [0.4 * ti, 0.0, 0.15]) for ti in t])
    kept = spread_instants(groups, 30, 0.3)
    assert 27 <= len(kept) <= 30 and np.ptp(times(kept)) > 9.0  # the whole drive
    v, _ = velocities(times(kept), poses(times(kept)), 0.3)
    assert np.allclose(v[:, 0], 0.4)
    single = [groups[i] for i in np.linspace(0, len(groups) - 1, 30).round().astype(int)]
    assert np.mean(velocities(times(single), poses(times(single)), 0.3)[0][:, 0] == 0.0) > 0.9
    assert spread_instants(groups, 400, 0.3) == groups  # enough room: all kept
    dense = spread_instants(groups, 100, 0.3)  # 0.1 s apart: evenly spread, no runs needed
    assert len(dense) == 100 and np.diff(times(dense)).min() > 0.05


def test_robust_average_ignores_a_bumped_frame():
    rng = np.random.default_rng(0)
    corners = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float) + rng.normal(0, 0.05, (30, 4, 2))
    corners[7] += 5.0
    mean, inliers = robust_average_corners(corners, 1.0)
    assert inliers == 29 and np.abs(mean - [[0, 0], [10, 0], [10, 10], [0, 10]]).max() < 0.05


class Scene:
    """Three cameras 2.2 m out (a wide-angle lens) see the paper's cube at 40 instants, and the
    world marker; every observation is the exact projection of the true model."""

    def __init__(self, seed=1, instants=40, floor_slope_deg=0.0):
        rng = np.random.default_rng(seed)
        layout = paper_cube_layout()
        self.T_cams = np.array([look_at(np.array([2.2 * np.cos(a), 2.2 * np.sin(a), 1.0]))
                                for a in np.radians([0, 120, 240])])
        self.K = np.array([[[520.0 + 3 * i, 0, 322.0 - i], [0, 518.0 + 2 * i, 238.0 + i], [0, 0, 1]] for i in range(3)])
        self.dist = np.tile([-0.3, 0.1, 0.0, 0.0, 0.0], (3, 1))
        # a hand-built cube: every marker a few mm / a degree off its nominal place, 1 % small
        self.nominal = np.array([m.T_cube_marker for m in layout.markers])
        self.T_markers = np.array([make_T(R_from_rotvec(rng.normal(0, 0.015, 3)) @ T[:3, :3],
                                          T[:3, 3] + rng.normal(0, 0.0015, 3))
                                   for T in self.nominal])
        self.sizes = np.full(5, 0.08) * (1 - rng.uniform(0.005, 0.015, 5))
        self.T_bodies = np.array([make_T(Rotation.from_euler("zx", [0.3 * k, 0.15 * np.sin(k)]).as_matrix(),
                                         [0.6 * np.sin(0.08 * k), 0.4 * np.sin(0.16 * k),
                                          0.35 + np.tan(np.radians(floor_slope_deg)) * 0.6 * np.sin(0.08 * k)])
                                  for k in range(instants)])
        true = Model(self.T_cams, self.K, self.dist, self.T_bodies, self.T_markers, self.sizes, np.zeros(5, int),
                     np.ones(1))
        self.true = true
        cam, inst, marker, corner = [], [], [], []
        for k, T_body in enumerate(self.T_bodies):
            for c, T_wc in enumerate(self.T_cams):
                T_cb = invert_T(T_wc) @ T_body
                for g, T_m in enumerate(self.T_markers):
                    centre = (T_cb @ T_m)[:3, 3]
                    if (T_cb @ T_m)[:3, 2] @ centre < -0.3 * np.linalg.norm(centre):  # faces the camera
                        cam += [c] * 4
                        inst += [k] * 4
                        marker += [g] * 4
                        corner += [0, 1, 2, 3]
        cam, inst, marker, corner = map(np.array, (cam, inst, marker, corner))
        world_points = np.tile(marker_corners_m(0.25), (3, 1))
        world_cam = np.repeat(np.arange(3), 4)
        n = len(cam)
        self.obs = Observations(cam, inst, marker, corner, np.zeros((n, 2)), np.tile(np.eye(3), (n, 1, 1)),
                                np.zeros((n, 3)), np.zeros(instants, int), 1, world_cam, world_points,
                                np.zeros((12, 2)))
        from cubetrack.calib.solver import corner_residuals_px, world_residuals_px
        self.obs = Observations(cam, inst, marker, corner, corner_residuals_px(self.obs, true), self.obs.motion_R,
                                self.obs.motion_t, self.obs.robot, 1, world_cam, world_points,
                                world_residuals_px(self.obs, true))
        self.rng = rng

    def start(self, cameras_off=True, intrinsics_off=False, body_off=False) -> Model:
        rng = self.rng
        T_cams = np.array([make_T(R_from_rotvec(rng.normal(0, 0.005, 3)) @ T[:3, :3], T[:3, 3] + rng.normal(0, 0.01, 3))
                           for T in self.T_cams]) if cameras_off else self.T_cams
        K = self.K.copy()
        if intrinsics_off:
            K[:, [0, 1], [0, 1]] *= 1.004
            K[:, :2, 2] += rng.normal(0, 2.0, (3, 2))
        dist = self.dist + ([0.006, -0.02, 0, 0, 0] if intrinsics_off else 0.0)
        bodies = np.array([make_T(R_from_rotvec(rng.normal(0, 0.01, 3)) @ T[:3, :3], T[:3, 3] + rng.normal(0, 0.005, 3))
                           for T in self.T_bodies])
        markers, sizes = (self.nominal, np.full(5, 0.08)) if body_off else (self.T_markers, self.sizes)
        return Model(T_cams, K, dist, bodies, markers, sizes, np.zeros(5, int), np.ones(1))


def _pose_errors(Ts, Ts_true):
    return (max(np.linalg.norm(T[:3, 3] - U[:3, 3]) for T, U in zip(Ts, Ts_true, strict=True)),
            max(rotation_angle(T[:3, :3], U[:3, :3], "deg") for T, U in zip(Ts, Ts_true, strict=True)))


def test_project_jacobian_matches_finite_differences():
    rng = np.random.default_rng(4)
    K = np.array([[520.0, 0, 320], [0, 515, 240], [0, 0, 1]])
    dist = np.array([-0.3, 0.1, 0.001, -0.002, 0.01])
    points = np.column_stack([rng.uniform(-0.8, 0.8, (20, 2)), rng.uniform(1.5, 3.0, 20)])
    _px, J, front = project(points, K, dist, with_jac=True)
    assert front.all() and J.shape == (20, 2, 12)
    h = 1e-6
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        numeric = (project(points + e, K, dist)[0] - project(points - e, K, dist)[0]) / (2 * h)
        assert np.allclose(J[:, :, j], numeric, rtol=1e-5, atol=1e-3)
    behind = project(np.array([[0.0, 0.0, -1.0]]), K, dist, with_jac=True)
    assert np.isnan(behind[0]).all() and not behind[2].any() and not behind[1].any()


def test_solver_jacobian_matches_finite_differences():
    """The analytic sparse Jacobian of every block (cameras, intrinsics, bodies, heights, the floor's
    tilt, scale, markers, priors) against central differences at the start of a solve and at a
    point away from it (a tilted floor)."""
    from cubetrack.calib import solver

    scene = Scene(instants=6)
    start = scene.start(intrinsics_off=True, body_off=True)
    free = Freedom(camera_prior=PosePrior(scene.T_cams, 0.01, 0.01),
                   intrinsics=IntrinsicsPrior(scene.K, scene.dist, 0.005, 3.0, 0.01, 0.03),
                   body=BodyPrior(scene.nominal, np.full(5, 0.08), 0.003, 0.03, 0.02), free_scale=True,
                   height_sigma_m=0.002, upright_sigma_rad=0.02, floor_tilt_sigma_rad=0.01)
    captured = {}

    def capture(fun, x0, jac, **_kw):
        captured.update(fun=fun, jac=jac, x0=x0)
        return type("R", (), {"x": x0})

    original = solver.least_squares
    solver.least_squares = capture
    try:
        solver.solve(scene.obs, start, free)
    finally:
        solver.least_squares = original
    fun, x0 = captured["fun"], captured["x0"]
    h = 1e-7

    def jacobians(x):
        return captured["jac"](x).toarray(), np.column_stack([(fun(x + h * e) - fun(x - h * e)) / (2 * h)
                                                              for e in np.eye(len(x))])

    J, numeric = jacobians(x0)
    # the pose priors' rotation part is linearised at the prior (the start here is 0.3 deg off)
    assert np.abs(J - numeric).max() < 2e-3 * np.abs(numeric).max()
    assert (np.abs(J - numeric) < 1e-4 * np.abs(numeric).max() + 1e-3)[:2 * len(scene.obs.cam)].all()
    # the ground rows (after the corners and world points: heights, upright, the floor's tilt prior) on a
    # floor tilted by 0.5 and -0.3 degrees, where the slopes enter the heights' and uprights' Jacobians
    L = solver._columns(scene.obs, start, free)
    x = x0.copy()
    x[L.slopes:L.slopes + 2] = np.radians([0.5, -0.3])
    J, numeric = jacobians(x)
    first = 2 * (len(scene.obs.cam) + len(scene.obs.world_cam))
    ground = slice(first, first + 3 * len(scene.T_bodies) + 2)
    assert np.abs(J - numeric)[ground].max() < 1e-5 * np.abs(numeric[ground]).max()


def test_bundle_adjustment_recovers_cameras_from_exact_corners():
    """Starting 1 cm / 0.3 deg off, cube and world-marker corners give the true camera poses."""
    scene = Scene()
    model = solve(scene.obs, scene.start(), Freedom(max_nfev=100))
    pos, rot = _pose_errors(model.T_cams, scene.T_cams)
    assert pos < 1e-5 and rot < 1e-4


def test_a_floor_that_slopes_is_not_read_as_the_worlds_tilt():
    """The cube driven on a floor sloping 1 deg along x (exact corners): held at one height on a
    level floor the refined world turns toward that slope against the world marker; with the
    floor's tilt held only loosely (floor_tilt_sigma_rad 5 deg) the world marker keeps the world
    level; with the refinement's default (``[bundle_adjustment] floor_tilt_sigma_deg``, 1 deg: as
    steep as this floor) the world keeps under a fifth of the level floor's turn (about a tenth here:
    the prior against this scene's world-marker corners)."""
    scene = Scene(floor_slope_deg=1.0)
    start = scene.start()

    def world_tilt_deg(model):
        R = np.array([T[:3, :3] @ U[:3, :3].T for T, U in zip(model.T_cams, scene.T_cams, strict=True)])
        return np.degrees(np.linalg.norm(Rotation.from_matrix(R).mean().as_rotvec()[:2]))

    level = solve(scene.obs, start, Freedom(height_sigma_m=0.002, max_nfev=100))
    tilted = solve(scene.obs, start, Freedom(height_sigma_m=0.002, floor_tilt_sigma_rad=np.radians(5.0), max_nfev=100))
    sigma_rad = np.radians(BundleAdjustmentParams().floor_tilt_sigma_deg)
    default = solve(scene.obs, start, Freedom(height_sigma_m=0.002, floor_tilt_sigma_rad=sigma_rad, max_nfev=100))
    turns = world_tilt_deg(level), world_tilt_deg(tilted), world_tilt_deg(default)
    assert turns[0] > 0.5 and turns[1] < 0.05 and turns[2] < 0.2 * turns[0], turns


def test_bundle_adjustment_recovers_intrinsics_from_exact_corners():
    """Camera matrices off by 0.4 % in focal length and 2 px, k1/k2 off by 0.006/0.02: with
    (almost) no priors the solve returns the true intrinsics and cameras; k2 is the least sure."""
    scene = Scene(seed=2, instants=60)
    start = scene.start(intrinsics_off=True)
    free = Freedom(intrinsics=IntrinsicsPrior(start.K, start.dist, 1.0, 1000.0, 10.0, 10.0), max_nfev=200)
    model = solve(scene.obs, start, free)
    assert np.abs(model.K - scene.K).max() < 0.02, model.K - scene.K
    assert np.abs(model.dist[:, 0] - scene.dist[:, 0]).max() < 2e-3
    assert np.abs(model.dist[:, 1] - scene.dist[:, 1]).max() < 0.015
    pos, rot = _pose_errors(model.T_cams, scene.T_cams)
    assert pos < 5e-5 and rot < 3e-3


def test_bundle_adjustment_recovers_the_markers_on_the_body():
    """The cube as built (markers mm / 1 deg off, 1 % small) from the nominal start: each marker's
    pose relative to the others and its size within 10 µm / 0.001 deg (the body frame itself is
    only weakly held, by the markers' loose priors)."""
    scene = Scene(seed=3)
    start = scene.start(cameras_off=False, body_off=True)
    free = Freedom(cameras=False, body=BodyPrior(scene.nominal, np.full(5, 0.08), 1.0, 1.0, 1.0), max_nfev=100)
    model = solve(scene.obs, start, free)
    relative = np.array([invert_T(model.T_body_markers[0]) @ T for T in model.T_body_markers])
    true_relative = np.array([invert_T(scene.T_markers[0]) @ T for T in scene.T_markers])
    pos, rot = _pose_errors(relative, true_relative)
    assert pos < 1e-5 and rot < 1e-3
    assert np.abs(model.sizes_m - scene.sizes).max() < 1e-6


def test_rolling_shutter_moves_each_corner_to_its_rows_time():
    """With a readout, a corner on row v is moved by the body's velocity over
    (frame time - instant time) + (v - (H - 1) / 2) readout / H; with none (camera_info's default),
    over the frame's offset alone."""
    from cubetrack.calib.bundle import FrameCorners, Instant, Refinement
    from cubetrack.core.cameras import CameraIntrinsics

    lens = CameraIntrinsics(640, 480, np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]]), np.zeros(5))
    corners = np.array([[[100.0, 0.0], [120.0, 0.0], [120.0, 239.5], [100.0, 479.0]]])
    frame = FrameCorners("cam", 10.02, np.array([0]), corners)
    instant = Instant("r", 10.0, (), (frame,), np.eye(4))
    layout = paper_cube_layout()
    v = np.array([[0.5, -0.2, 0.0]])
    for readout_s, row_dt in ((0.03, 0.03 / 480 * (corners[0, :, 1] - 239.5)), (None, np.zeros(4))):
        ref = Refinement.start([instant], ["cam"], {"cam": np.eye(4)}, {"cam": lens}, {"r": layout},
                               BundleAdjustmentParams(), None if readout_s is None else {"cam": readout_s})
        ref.vel = v
        obs = ref.observations()
        assert np.allclose(obs.motion_t, v * (0.02 + row_dt)[:, None], atol=1e-12), readout_s


def test_a_refinement_that_fits_the_world_marker_worse_than_its_noise_is_named():
    """Issue 26: the refinement never leaves the cameras worse than the world marker left them.
    Cube markers 5 % larger in the model than as built pull every camera out; the refined poses
    then reproject the world marker 0.8 px off where the world-marker calibration (here the true
    poses) fits it exactly: beyond its corners' 0.5 px noise, so each camera is named. The cube
    as built (the true sizes) passes."""
    scene = Scene()
    cameras = ["cam1", "cam2", "cam3"]
    exact = solve(scene.obs, scene.start(), Freedom(max_nfev=100))
    assert worse_world_fit(scene.obs, scene.true, exact, cameras, 0.5) == []
    start = scene.start()
    too_big = solve(scene.obs, start.replace(sizes_m=1.05 * start.sizes_m), Freedom(max_nfev=100))
    named = worse_world_fit(scene.obs, scene.true, too_big, cameras, 0.5)
    assert [line.split("'")[0] for line in named] == cameras, named
    assert all(re.search(r"reprojects 0\.8\d px off after refinement, 0\.00 px before", line) for line in named)
