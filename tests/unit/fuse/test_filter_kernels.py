"""The filter's compiled kernels (cubetrack.fuse.filter_kernels) against the numpy model they
replace: the reprojection of cubetrack.estimate.reprojection, the calibration discount built from
its covariance, the prediction's F P Fᵀ, and one Gauss-Newton step by hand."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cubetrack.core.geometry import R_from_rotvec, invert_T, make_T
from cubetrack.estimate.reprojection import (
    CornerSet,
    moved_pose,
    perturbed,
    reprojection_jacobian_px,
    reprojection_residuals_px,
)
from cubetrack.fuse import filter_kernels as fk
from cubetrack.fuse.corner_filter import transition

SQUARE = np.array([[-0.02, -0.02, 0.0], [0.02, -0.02, 0.0], [0.02, 0.02, 0.0], [-0.02, 0.02, 0.0]])


def _camera(position: list[float]) -> np.ndarray:
    """T_cam_world of a camera at ``position`` looking at the origin (z forward)."""
    c = np.asarray(position, dtype=float)
    z = -c / np.linalg.norm(c)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    return invert_T(make_T(np.column_stack([x, np.cross(z, x), z]), c))


def _sets(rng: np.random.Generator, times: list[float]) -> list[CornerSet]:
    """Corner sets of two faces' squares from one camera, noisy, each taken at its time."""
    T_cw = _camera([1.2, -0.8, 0.9])
    out = []
    for k, t in enumerate(times):
        points = SQUARE + [0.0, 0.0, 0.02 + 0.01 * k]
        pc = (points @ T_cw[:3, :3].T) + T_cw[:3, 3]
        out.append(CornerSet("cam", t, T_cw, 800.0 + 10 * k, points,
                             pc[:, :2] / pc[:, 2:] + rng.normal(0.0, 1e-3, (4, 2)), (f"f{k}",)))
    return out


def _pose(rng: np.random.Generator) -> np.ndarray:
    return make_T(R_from_rotvec(rng.normal(0.0, 0.3, 3)), rng.normal(0.0, 0.05, 3))


def _read_only(a: np.ndarray) -> np.ndarray:
    """``a`` read-only, as the filter passes its pose and process noise (each array's writability
    is part of its numba type: the tests pass what the filter does, so they compile nothing new)."""
    a.setflags(write=False)
    return a


@pytest.mark.parametrize("moving, rows", [(False, False), (True, False), (True, True)])
def test_the_reprojection_kernel_is_the_numpy_model(moving: bool, rows: bool) -> None:
    """Also with each corner at its own row's instant (a rolling shutter within a face)."""
    rng = np.random.default_rng(3)
    sets = _sets(rng, [0.01, -0.02, 0.005] if moving else [0.0, 0.0, 0.0])
    if rows:
        sets = [dataclasses.replace(s, row_offsets_s=rng.normal(0.0, 1e-3, 4)) for s in sets]
    T, v, w = _pose(rng), rng.normal(0.0, 0.5, 3), rng.normal(0.0, 2.0, 3)
    motion = (0.0, v, w) if moving else ()
    r_ref, H_ref = reprojection_jacobian_px(T, sets, *motion)
    r, H = fk.reprojection(T, *fk.packed_sets(sets), 0.0, v, w, moving, True)
    np.testing.assert_allclose(r, r_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(H, H_ref, rtol=1e-10, atol=1e-9)
    r_only, _ = fk.reprojection(T, *fk.packed_sets(sets), 0.0, v, w, moving, False)
    np.testing.assert_allclose(r_only, reprojection_residuals_px(T, sets, *motion), rtol=0, atol=1e-9)


def test_a_corner_behind_the_camera_or_not_undistorted_is_a_large_residual() -> None:
    sets = _sets(np.random.default_rng(4), [0.0])
    T = make_T(np.eye(3), [3.0, -2.0, 2.25])   # past the camera (at 1.2, -0.8, 0.9, looking at the origin)
    zeros = np.zeros(3)
    r, H = fk.reprojection(T, *fk.packed_sets(sets), 0.0, zeros, zeros, False, True)
    assert (r == fk.BEHIND_PX).all() and not H.any()
    broken = CornerSet("cam", 0.0, sets[0].T_cam_world, 800.0, SQUARE, np.full((4, 2), np.nan), ("f0",))
    r, _ = fk.reprojection(np.eye(4), *fk.packed_sets([broken]), 0.0, zeros, zeros, False, False)
    np.testing.assert_array_equal(r, reprojection_residuals_px(np.eye(4), [broken]))
    assert (r == fk.BEHIND_PX).all()


def test_the_calibration_discount_is_the_covariances_inverse() -> None:
    """K = (Σ⁻¹ + H_poseᵀ W H_pose)⁻¹ with Σ built from the camera's errors and the body's wobble, not the
    closed form."""
    rng = np.random.default_rng(5)
    sets = _sets(rng, [0.0])
    T = _pose(rng)
    sigma_t, sigma_phi = 0.002, math.radians(0.1)
    info = rng.normal(size=(6, 6))
    info = info @ info.T * 1e4
    K = np.empty((6, 6))
    _, _, _, R_cw, t_cw, _, _ = fk.packed_sets(sets)
    c = invert_T(sets[0].T_cam_world)[:3, 3]
    d = T[:3, 3] - c
    D = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    A = np.vstack([D, -np.eye(3)])
    z = sets[0].T_cam_world[2, :3]   # the optical axis: a scale error moves the body along it by s x its depth
    u = np.concatenate([z * (z @ d), np.zeros(3)])
    h = T[2, 3]   # the wobble: the body rolled / pitched about the floor point below it, δp = δθ × (h z)
    wobble = np.array([[0.0, -h, 0, 1, 0, 0], [h, 0, 0, 0, 1, 0]]).T
    for sigma_s, sigma_w in ((0.0, 0.0), (0.005, 0.0), (0.005, math.radians(0.5)), (0.0, math.radians(0.5))):
        assert fk.calibration_discount(T, R_cw, t_cw, info, sigma_t, sigma_phi, sigma_s, sigma_w, K)
        sigma = (sigma_t**2 * np.diag([1.0, 1, 1, 0, 0, 0]) + sigma_phi**2 * A @ A.T + sigma_s**2 * np.outer(u, u)
                 + sigma_w**2 * wobble @ wobble.T)
        np.testing.assert_allclose(K, np.linalg.inv(np.linalg.inv(sigma) + info), rtol=1e-7, atol=1e-15)
    assert not fk.calibration_discount(T, R_cw, t_cw, info, 0.0, sigma_phi, 0.0, 0.0, K)   # the camera taken as exact


def test_the_lu_solves_and_finds_singular_matrices() -> None:
    rng = np.random.default_rng(6)
    M = rng.normal(size=(12, 12))
    out = np.empty((12, 12))
    assert fk._inverse(M, out)
    np.testing.assert_allclose(out, np.linalg.inv(M), rtol=1e-9, atol=1e-12)
    M[:, 3] = 2.0 * M[:, 7]
    assert not fk._inverse(M, out)


def test_the_prediction_kernels_are_the_constant_velocity_model() -> None:
    rng = np.random.default_rng(7)
    P = rng.normal(size=(12, 12))
    P = P @ P.T
    A, B, C = (_read_only(np.diag(rng.uniform(0.1, 1.0, 12))) for _ in range(3))
    for dt in (0.033, -0.02):
        F = transition(dt)
        expected = F @ P @ F.T + abs(dt) ** 3 / 3.0 * A + dt * dt / 2.0 * B + abs(dt) * C
        np.testing.assert_allclose(fk.predicted_covariance(P, dt, A, B, C), expected, rtol=1e-12, atol=1e-12)
        T, v, w = _read_only(_pose(rng)), rng.normal(size=3), rng.normal(0.0, 3.0, 3)
        np.testing.assert_allclose(fk.moved_pose(T, v, w, dt), moved_pose(T, v, w, dt), rtol=0, atol=1e-14)


def test_one_gauss_newton_step_is_the_normal_equations_by_hand() -> None:
    """One iteration, no calibration discount: δ = (P⁻¹ + Hᵀ W H)⁻¹ Hᵀ W (-r) with Huber weights
    times each corner's own inverse variance (both its rows); the residuals after it are at the
    moved state; the covariance is that information's inverse."""
    rng = np.random.default_rng(8)
    sets = _sets(rng, [0.004, -0.006])
    T, v, w = _read_only(_pose(rng)), rng.normal(0.0, 0.3, 3), rng.normal(0.0, 1.0, 3)
    P = np.diag(np.repeat([1e-4, 1e-3, 0.25, 4.0], 3))
    huber, inv_var = 1.5, rng.uniform(0.5, 8.0, sum(len(s.points_cube_m) for s in sets))
    status, delta, info, T_new, r_new, P_new, ok = fk.solve_update(
        T, P, 0.0, v, w, *fk.packed_sets(sets), True, 1, huber, inv_var, 0.0, 0.0, 0.0, 0.0)
    assert status == fk.OK and ok
    r, H = reprojection_jacobian_px(T, sets, 0.0, v, w)
    weights = np.minimum(huber / np.abs(r), 1.0) * np.repeat(inv_var, 2)
    expected_info = np.linalg.inv(P) + H.T @ (weights[:, None] * H)
    expected = np.linalg.solve(expected_info, H.T @ (weights * -r))
    np.testing.assert_allclose(info, expected_info, rtol=1e-9)
    np.testing.assert_allclose(delta, expected, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(T_new, perturbed(T, expected[:6]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(r_new, reprojection_residuals_px(T_new, sets, 0.0, v + delta[6:9], w + delta[9:]),
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(P_new, np.linalg.inv(expected_info), rtol=1e-7, atol=1e-15)
    singular = np.zeros((12, 12))
    assert fk.solve_update(T, singular, 0.0, v, w, *fk.packed_sets(sets), True, 1, huber, inv_var, 0.0,
                           0.0, 0.0, 0.0)[0] == fk.SINGULAR_PRIOR


def test_the_largest_eigenvalue_and_the_spread() -> None:
    rng = np.random.default_rng(9)
    for scale in (1e-8, 1e-3, 1.0):
        A = rng.normal(size=(6, 6))
        A = (A @ A.T) * scale
        expected = [np.linalg.eigvalsh(A[k:k + 3, k:k + 3]).max() for k in (0, 3)]
        assert [fk.largest_eigenvalue(A, k) for k in (0, 3)] == pytest.approx(expected, rel=1e-9)
        assert fk.spread_m(A, 0.07) == pytest.approx(math.sqrt(expected[0]) + 0.07 * math.sqrt(expected[1]), rel=1e-9)
    diagonal = np.diag([4.0, 9.0, 1.0, 2.0, 2.0, 2.0])   # no off-diagonal terms; three equal ones
    assert fk.largest_eigenvalue(diagonal, 0) == 9.0 and fk.largest_eigenvalue(diagonal, 3) == 2.0


@pytest.mark.parametrize("coefficients", [4, 5, 8, 12])
def test_the_compiled_projection_gives_opencvs_pixels_to_the_bit(coefficients: int) -> None:
    """The filter's association (estimate.match) and the detector's predicted markers
    (detect.predicted.predicted_view) project with a compiled copy of cv2.projectPoints' arithmetic,
    in its order: the same pixels to the bit, so a prediction's corners (where the edge fit starts)
    do not depend on which of the two made them. A tilted sensor (14 coefficients) still goes to OpenCV."""
    import cv2

    from cubetrack.detect.predicted import projected_px

    rng = np.random.default_rng(10 + coefficients)
    scales = np.array([0.3, 0.1, 0.01, 0.01, 0.05, 0.1, 0.05, 0.02, 0.01, 0.01, 0.01, 0.01])
    for _ in range(50):
        points = np.column_stack([rng.normal(0.0, 0.5, (24, 2)), rng.uniform(0.3, 5.0, 24)])
        K = np.array([[rng.uniform(300.0, 900.0), 0.0, 330.0], [0.0, rng.uniform(300.0, 900.0), 245.0],
                      [0.0, 0.0, 1.0]])
        dist = rng.normal(0.0, scales[:coefficients])
        expected = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
        np.testing.assert_array_equal(projected_px(points, K, dist), expected)


@pytest.mark.parametrize("angle_rad", [1e-7, 3e-3, 0.4, 2.5])   # both sides of the Taylor series' 0.01 rad
def test_the_shared_exp_kernel_is_rodrigues_and_the_left_jacobian(angle_rad: float) -> None:
    """estimate.kernels.exp_and_left_jacobian, which the filter's kernels and estimate.reprojection
    both call: [Exp(ω dt) | J_l(ω dt) dt] against core.geometry's Rodrigues and left Jacobian."""
    from cubetrack.core.geometry import so3_left_jacobian
    from cubetrack.estimate.kernels import exp_and_left_jacobian

    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    dt = 0.04
    omega = axis * angle_rad / dt
    out = np.empty((3, 6))
    exp_and_left_jacobian(float(omega[0]), float(omega[1]), float(omega[2]), dt, out)
    np.testing.assert_allclose(out[:, :3], R_from_rotvec(omega * dt), atol=1e-14)
    np.testing.assert_allclose(out[:, 3:], so3_left_jacobian(omega * dt) * dt, atol=1e-15)


@pytest.mark.parametrize("n", [6, 12])
def test_the_joint_fit_finds_scipys_soft_l1_minimum(n: int) -> None:
    """fuse.filter_kernels.joint_fit (the track start's fit) against scipy's least_squares on the
    numpy model's residuals, soft-L1 loss, one corner an outlier: the same increment, and the
    covariance from the loss-scaled Jacobian at the solution, as scipy returns it."""
    from scipy.optimize import least_squares

    from cubetrack.core.geometry import so3_left_jacobian

    rng = np.random.default_rng(11)
    sets = _sets(rng, [0.0, 0.012, 0.025])
    sets[1].normalized[2] += 6.0 / sets[1].focal_px   # a corner 6 px off
    T_init = make_T(R_from_rotvec([0.02, -0.03, 0.01]), np.array([0.004, -0.003, 0.006]))
    noise, f_scale, sigma_v, sigma_w = 0.5, 3.0, 0.5, 1.0

    def fun(x: np.ndarray) -> np.ndarray:
        T = perturbed(T_init, x[:6])
        if n == 6:
            return reprojection_residuals_px(T, sets) / noise
        r = reprojection_residuals_px(T, sets, 0.0, x[6:9], x[9:12]) / noise
        return np.concatenate([r, x[6:9] / sigma_v, x[9:12] / sigma_w])

    def jac(x: np.ndarray) -> np.ndarray:
        T = perturbed(T_init, x[:6])
        moving = (0.0, x[6:9], x[9:12]) if n == 12 else ()
        J = reprojection_jacobian_px(T, sets, *moving)[1] / noise
        J[:, 3:6] = J[:, 3:6] @ so3_left_jacobian(x[3:6])   # x[3:6] is a finite rotation increment
        return J if n == 6 else np.vstack([J, np.diag(np.repeat([1.0 / sigma_v, 1.0 / sigma_w], 3)) @ np.eye(6, 12, 6)])

    ref = least_squares(fun, np.zeros(n), jac=jac, loss="soft_l1", f_scale=f_scale, x_scale=np.full(n, 0.01),
                        ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=500)
    ok, x, covariance, f = fk.joint_fit(T_init.copy(), n, *fk.packed_sets(sets), 0.0, noise, f_scale, sigma_v, sigma_w,
                                        100)
    assert ok
    np.testing.assert_allclose(x, ref.x, rtol=0.0, atol=1e-8)   # the velocities are weakly observed: flat there
    np.testing.assert_allclose(f, ref.fun, rtol=0.0, atol=1e-8)
    np.testing.assert_allclose(covariance, np.linalg.inv(ref.jac.T @ ref.jac), rtol=1e-5, atol=1e-16)
