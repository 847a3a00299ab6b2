"""The solver's time-dependent corner noise (Freedom.motion_noise_px_per_s, calibrate-body's
``body_motion_noise_px_per_s``): a corner seen away from its instant's time counts less, since the
constant-velocity motion between an instant's frames misses turns and vibration. Exact corners
of three cameras; the third camera's frame is 80 ms from the instant and its corners carry an
unmodelled 2 px motion error."""

import numpy as np
from scipy.spatial.transform import Rotation

from cubetrack.calib import solver
from cubetrack.calib.solver import Freedom, Model, Observations, corner_residuals_px, solve
from cubetrack.core.geometry import make_T
from cubetrack.core.layout import paper_cube_layout


def _look_at(position, target=(0.0, 0.0, 0.35)):
    z = np.asarray(target) - position
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return make_T(np.column_stack([x, np.cross(z, x), z]), position)


def _scene(dt_s: float, error_px: float):
    layout = paper_cube_layout()
    T_cams = np.array([_look_at(np.array([2.2 * np.cos(a), 2.2 * np.sin(a), 1.0])) for a in np.radians([10, 130, 250])])
    K = np.tile([[520.0, 0, 320], [0, 520, 240], [0, 0, 1]], (3, 1, 1))
    T_body = make_T(Rotation.from_euler("z", 35, degrees=True).as_matrix(), [0.1, -0.05, 0.35])
    true = Model(T_cams, K, np.zeros((3, 5)), T_body[None], np.array([m.T_cube_marker for m in layout.markers]),
                 np.array([m.size_m for m in layout.markers]), np.zeros(5, int), np.ones(1))
    cam = np.repeat([0, 0, 0, 1, 1, 1, 2, 2, 2], 4)          # each camera: top and two side faces
    marker = np.repeat([0, 1, 2, 0, 3, 4, 0, 2, 4], 4)
    n = len(cam)
    blank = Observations(cam, np.zeros(n, int), marker, np.tile(np.arange(4), 9), np.zeros((n, 2)),
                         np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)), np.zeros(1, int), 1,
                         np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 2)))
    pixels = corner_residuals_px(blank, true)
    assert np.isfinite(pixels).all()
    pixels[cam == 2, 0] += error_px
    dt = np.where(cam == 2, dt_s, 0.0)
    obs = Observations(cam, blank.inst, marker, blank.corner, pixels, blank.motion_R, blank.motion_t, blank.robot,
                       1, blank.world_cam, blank.world_points, blank.world_pixels, dt)
    start = true.replace(T_bodies=make_T(true.T_bodies[0, :3, :3], true.T_bodies[0, :3, 3] + 0.004)[None])
    return obs, start, T_body


def _position_error_m(motion_noise: float) -> float:
    obs, start, T_body = _scene(0.08, 2.0)
    model = solve(obs, start, Freedom(cameras=False, motion_noise_px_per_s=motion_noise, max_nfev=100))
    return float(np.linalg.norm(model.T_bodies[0, :3, 3] - T_body[:3, 3]))


def test_late_corners_count_less_with_motion_noise():
    without, with_noise = _position_error_m(0.0), _position_error_m(25.0)
    assert without > 2e-3          # the late camera's 2 px pull the body by 5 mm
    assert with_noise < 0.25 * without, (without, with_noise)


def test_motion_noise_scales_residuals_and_jacobian_alike(monkeypatch):
    """Residuals and Jacobian rows of a late corner are divided by the same grown noise."""
    obs, start, _ = _scene(0.08, 2.0)
    problems = []
    monkeypatch.setattr(solver, "least_squares", lambda fun, x0, jac, **_kw: problems.append(
        (fun(x0), jac(x0).toarray())) or type("Result", (), {"x": x0}))
    solve(obs, start, Freedom(cameras=False, motion_noise_px_per_s=25.0))
    solve(obs, start, Freedom(cameras=False))
    (r_noise, J_noise), (r_plain, J_plain) = problems
    late = np.repeat(obs.cam == 2, 2)
    factor = np.hypot(0.5, 25.0 * 0.08) / 0.5
    assert np.allclose(r_noise[~late], r_plain[~late]) and np.allclose(J_noise[~late], J_plain[~late])
    assert np.allclose(r_noise[late] * factor, r_plain[late]) and np.allclose(J_noise[late] * factor, J_plain[late])
