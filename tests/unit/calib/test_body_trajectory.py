"""The body calibration's continuous-time trajectory (``body_knot_s`` > 0): the solver's knots,
each corner at the pose interpolated to its time (``Observations.knot_alpha``) and the
smoothness prior on the knots' second differences.

A cube turning ever faster (40 rad/s^2: a sharp turn's start with the robot's wobble) while it
drives, seen by three unsynchronised cameras at 30 frames/s (each 11 ms after the previous one),
its corners exact at each frame's own time. No instant of two cameras has the body still, and a
constant velocity between them is wrong; the trajectory needs neither."""

import numpy as np
from calib_scene import hand_built_cube
from scenes import look_at
from scipy.spatial.transform import Rotation

from cubetrack.calib import solver
from cubetrack.calib.body import placement_errors
from cubetrack.calib.bundle import layout_with
from cubetrack.calib.solver import BodyPrior, Freedom, Model, Observations, corner_residuals_px, solve
from cubetrack.core.geometry import make_T

KNOT_S = 1 / 60
ANGULAR_ACCEL = 40.0  # rad/s^2


def _pose(t: float) -> np.ndarray:
    """The true body pose at time t (s)."""
    yaw = 0.5 * ANGULAR_ACCEL * t ** 2 + 0.3 * t
    return make_T(Rotation.from_euler("z", yaw).as_matrix(), [0.2 * t, 0.35 * t ** 2, 0.055])


def _scene(duration_s: float = 0.5):
    """(observations on knots, true model with the knots at the true poses, the true layout)."""
    layout, true_markers, truth = hand_built_cube(3)  # every marker off by about a millimetre and a degree
    T_cams = np.array([look_at([2.2 * np.cos(a), 2.2 * np.sin(a), 1.0], [0.1, 0.05, 0.3])
                       for a in np.radians([10, 130, 250])])
    K = np.tile([[520.0, 0, 320], [0, 520, 240], [0, 0, 1]], (3, 1, 1))
    times = np.arange(-KNOT_S, duration_s + 2 * KNOT_S, KNOT_S)
    model = Model(T_cams, K, np.zeros((3, 5)), np.array([_pose(t) for t in times]), true_markers,
                  np.array([m.size_m for m in truth.markers]), np.zeros(5, int), np.ones(1))
    cam, knot, alpha, marker, pixels = [], [], [], [], []
    for c in range(3):
        for t in np.arange(c * 0.011, duration_s, 1 / 30):
            T = _pose(t)
            for g, Tm in enumerate(true_markers):
                normal, centre = T[:3, :3] @ Tm[:3, 2], T[:3, :3] @ Tm[:3, 3] + T[:3, 3]
                to_camera = T_cams[c, :3, 3] - centre
                if normal @ to_camera < 0.3 * np.linalg.norm(to_camera):
                    continue
                k = int((t - times[0]) // KNOT_S)
                corners = (Tm[:3, :3] @ (solver.UNIT_CORNERS * truth.markers[g].size_m).T).T + Tm[:3, 3]
                X = corners @ T[:3, :3].T + T[:3, 3]
                px = solver.project((X - T_cams[c, :3, 3]) @ T_cams[c, :3, :3], K[c], np.zeros(5))[0]
                cam += [c] * 4
                knot += [k] * 4
                alpha += [(t - times[k]) / KNOT_S] * 4
                marker += [g] * 4
                pixels.append(px)
    n, K_ = len(cam), len(times)
    inner = np.arange(1, K_ - 1)
    obs = Observations(np.array(cam), np.array(knot), np.array(marker), np.tile(np.arange(4), n // 4),
                       np.vstack(pixels), np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)), np.zeros(K_, int), 1,
                       np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 2)), knot_alpha=np.array(alpha),
                       knot_triples=np.column_stack([inner - 1, inner, inner + 1]), knot_spacing_s=KNOT_S)
    return obs, model, truth, layout


def _perturbed(model: Model, layout) -> Model:
    """The start: knots 3 mm and 0.5 deg off, markers at the nominal layout."""
    rng = np.random.default_rng(5)
    knots = np.array([make_T(Rotation.from_rotvec(np.radians(rng.normal(0, 0.5, 3))).as_matrix() @ T[:3, :3],
                             T[:3, 3] + rng.normal(0, 3e-3, 3)) for T in model.T_bodies])
    return model.replace(T_bodies=knots, T_body_markers=np.array([m.T_cube_marker for m in layout.markers]),
                         sizes_m=np.array([m.size_m for m in layout.markers]))


def _free(layout) -> Freedom:
    """Markers free, held by a loose prior (the half second of frames is a short calibration)."""
    return Freedom(cameras=False, body=BodyPrior(np.array([m.T_cube_marker for m in layout.markers]),
                                                 np.array([m.size_m for m in layout.markers]), 0.02,
                                                 np.radians(20.0), 0.1), max_nfev=80)


def test_interpolated_corners_are_exact_on_the_knots():
    """With the knots at the true poses every corner lands within the interpolation's error of
    its pixel (the turn's acceleration over one knot spacing: a few hundredths of a pixel)."""
    obs, model, _truth, _layout = _scene()
    r = corner_residuals_px(obs, model)
    assert np.abs(r).max() < 0.05, np.abs(r).max()
    moved = model.replace(T_bodies=model.T_bodies[np.r_[1:len(model.T_bodies), 0]])  # one knot late
    assert np.abs(corner_residuals_px(obs, moved)).max() > 1.0


def test_trajectory_recovers_every_marker_from_unsynchronised_frames():
    obs, model, truth, layout = _scene()
    solved = solve(obs, _perturbed(model, layout), _free(layout))
    errors = placement_errors(layout_with(layout, solved.T_body_markers, solved.sizes_m), truth)
    before = placement_errors(layout, truth)
    for face, (pos_m, rot_deg, size_m) in errors.items():
        assert pos_m < 0.1e-3 and rot_deg < 0.03 and abs(size_m) < 0.05e-3, (face, errors[face], before[face])
    # the same frames, each moved to its knot's time as if the body stood still there (no
    # trajectory): the turn between the cameras' frames shows as marker errors
    still = Observations(obs.cam, obs.inst, obs.marker, obs.corner, obs.pixels, obs.motion_R, obs.motion_t,
                         obs.robot, 1, obs.world_cam, obs.world_points, obs.world_pixels)
    stiff = solve(still, _perturbed(model, layout), _free(layout))
    worst = max(placement_errors(layout_with(layout, stiff.T_body_markers, stiff.sizes_m), truth).values(),
                key=lambda e: e[1])
    assert worst[1] > 3 * max(e[1] for e in errors.values()), (worst, errors)


def test_trajectory_jacobian_matches_finite_differences(monkeypatch):
    """The interpolated corners' and the smoothness prior's analytic Jacobian against central
    differences, at a start away from the solution (first order in the knot step: within 1 %)."""
    obs, model, _truth, layout = _scene(0.2)
    problems = []
    monkeypatch.setattr(solver, "levenberg_marquardt", lambda evaluate, x0, *_a: problems.append((evaluate, x0)) or x0)
    solve(obs, _perturbed(model, layout), _free(layout))
    evaluate, x0 = problems[0]
    x = x0 + np.random.default_rng(1).normal(0, 1e-3, len(x0))
    J = evaluate(x, True)[1].toarray()
    h = 1e-7
    numeric = np.column_stack([(evaluate(x + h * e, False)[0] - evaluate(x - h * e, False)[0]) / (2 * h)
                               for e in np.eye(len(x))])
    scale = np.abs(numeric).max()
    assert np.abs(J - numeric).max() < 0.01 * scale, np.abs(J - numeric).max() / scale
    assert np.abs(numeric[:, ::6]).max() > 0  # the knots' columns are exercised
