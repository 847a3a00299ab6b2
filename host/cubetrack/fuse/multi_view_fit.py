"""A multi-camera fit of one body pose (and optionally its velocities) over every matched corner.

The paper fuses per-marker poses; each of those is a monocular estimate of a small marker, weak
in depth and prone to planar flips. Here the unknown is the body pose itself and the residual is
the reprojection error of every matched corner in every camera (see
:mod:`cubetrack.estimate.reprojection`; compiled: :func:`cubetrack.fuse.filter_kernels.reprojection`), with a
robust loss. Used to start a track from sightings
of several cameras.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from cubetrack.core.geometry import so3_left_jacobian
from cubetrack.estimate.reprojection import CornerSet, perturbed
from cubetrack.fuse.filter_kernels import packed_sets, reprojection


@dataclass(frozen=True, slots=True, eq=False)
class JointSolution:
    """A solved cube pose at the reference time: ``T_world_cube``, the world-frame velocities
    (zero unless estimated), the covariance of ``[δp, δθ]`` or, with velocities,
    ``[δp, δθ, v, ω]`` (m, rad, m/s, rad/s), the RMS corner residual (px) and the fraction of
    corner coordinates within ``3 f_scale`` of their reprojection."""

    T_world_cube: np.ndarray
    velocity_m_s: np.ndarray
    angular_velocity_rad_s: np.ndarray
    covariance: np.ndarray
    rms_px: float
    inlier_fraction: float
    points: int


def robust_least_squares(residuals: Callable[[np.ndarray], np.ndarray], jacobian: Callable[[np.ndarray], np.ndarray],
                         x_scale: np.ndarray, f_scale: float, max_nfev: int
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A soft-L1 least-squares fit of increments started at zero (``residuals`` in units of their
    noise): the solution, its covariance ``(JᵀJ)⁻¹`` and the residuals there; None when the fit
    fails or its information is singular."""
    try:
        result = least_squares(residuals, np.zeros(len(x_scale)), jac=jacobian, method="trf", loss="soft_l1",
                               f_scale=f_scale, x_scale=x_scale, max_nfev=max_nfev)
    except (ValueError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(result.x)):
        return None
    J = np.asarray(result.jac)  # of residuals in units of their noise: J^T J is the information
    try:
        covariance = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    return result.x, covariance, np.asarray(result.fun)


MAX_STEP_RAD = 0.2  # robust_gauss_newton gives up on a step turning more than this (rad) ...
MAX_STEP_M = 0.2  # ... or moving more than this (m)


def robust_gauss_newton(residuals: Callable[[np.ndarray], np.ndarray], jacobian: Callable[[np.ndarray], np.ndarray],
                        n: int, f_scale: float, iterations: int
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """What :func:`robust_least_squares` returns, by at most ``iterations`` steps of iteratively
    reweighted Gauss-Newton (the soft-L1 loss's weights ``1 / sqrt(1 + (r / f_scale)²)``), stopping
    once a step is under 1e-7 in every unknown: for a start already near the solution, where the
    trust-region solver's own work costs many times the compiled residuals. The first six unknowns
    are a pose increment (m, rad). None when it does not converge within ``iterations``, a step
    turns by more than ``MAX_STEP_RAD`` or moves by more than ``MAX_STEP_M`` (undamped, it can run
    off from a poor start: the caller then uses the trust-region solver)."""
    x = np.zeros(n)
    for _ in range(iterations):
        r, J = residuals(x), jacobian(x)
        w = 1.0 / np.sqrt(1.0 + (r / f_scale) ** 2)
        Jw = J * w[:, None]
        try:
            step = np.linalg.solve(Jw.T @ J, -(Jw.T @ r))
        except np.linalg.LinAlgError:
            return None
        if not (np.all(np.isfinite(step)) and np.linalg.norm(step[3:6]) <= MAX_STEP_RAD
                and np.linalg.norm(step[:3]) <= MAX_STEP_M):
            return None
        x = x + step
        if np.max(np.abs(step)) < 1e-7:
            break
    else:
        return None
    r, J = residuals(x), jacobian(x)
    t = 1.0 + (r / f_scale) ** 2  # the covariance as scipy's: J scaled by the loss, sqrt(rho' + 2 rho'' r²) = t^-3/4
    try:
        covariance = np.linalg.inv((J * t[:, None] ** -1.5).T @ J)
    except np.linalg.LinAlgError:
        return None
    return x, covariance, r


def solve_joint(sets: Sequence[CornerSet], T_init: np.ndarray, t_ref_s: float,
                corner_noise_px: float = 0.5, f_scale_px: float = 1.5,
                velocity_sigma: tuple[float, float] | None = None, iterations: int = 0) -> JointSolution | None:
    """Least-squares cube pose at ``t_ref_s`` over all corner sets (robust soft-L1 loss),
    starting from ``T_init``.

    Without ``velocity_sigma`` the cube is taken as still between the sets' times. With
    ``velocity_sigma = (σ_v m/s, σ_ω rad/s)`` the linear and angular velocities are estimated
    too, under a zero-mean Gaussian prior of those spreads (sets spread over time make them
    observable). ``iterations``: solved by that many steps at most of
    :func:`robust_gauss_newton` (for a ``T_init`` near the solution) instead of the trust-region
    solver, which takes over when it gives up. Returns None if the fit fails or has under four corners.
    """
    n_points = sum(len(s.points_cube_m) for s in sets)
    if n_points < 4:
        return None
    n = 6 if velocity_sigma is None else 12
    packed, zero = packed_sets(sets), np.zeros(3)   # the compiled reprojection's arrays (fuse.filter_kernels)

    def residuals(x: np.ndarray) -> np.ndarray:
        if velocity_sigma is None:  # n == 6
            return reprojection(perturbed(T_init, x[:6]), *packed, 0.0, zero, zero, False, False)[0] / corner_noise_px
        v, w = x[6:9].copy(), x[9:12].copy()
        r = reprojection(perturbed(T_init, x[:6]), *packed, t_ref_s, v, w, True, False)[0] / corner_noise_px
        return np.concatenate([r, v / velocity_sigma[0], w / velocity_sigma[1]])

    def jacobian(x: np.ndarray) -> np.ndarray:
        T = perturbed(T_init, x[:6])
        if n == 6:
            _, J = reprojection(T, *packed, 0.0, zero, zero, False, True)
        else:
            _, J = reprojection(T, *packed, t_ref_s, x[6:9].copy(), x[9:12].copy(), True, True)
        J[:, 3:6] = J[:, 3:6] @ so3_left_jacobian(x[3:6])  # x holds a finite rotation increment
        J /= corner_noise_px
        if n == 12:
            prior = np.zeros((6, 12))
            prior[:, 6:] = np.diag(np.repeat(1.0 / np.asarray(velocity_sigma, dtype=float), 3))
            J = np.vstack([J, prior])
        return J

    f_scale = f_scale_px / corner_noise_px
    solved = robust_gauss_newton(residuals, jacobian, n, f_scale, iterations) if iterations else None
    if solved is None:  # not asked for, or it gave up: the trust-region solver
        solved = robust_least_squares(residuals, jacobian, np.full(n, 0.01), f_scale, 80)
    if solved is None:
        return None
    x, covariance, fun = solved
    r_px = fun[: 2 * n_points] * corner_noise_px
    return JointSolution(
        T_world_cube=perturbed(T_init, x[:6]),
        velocity_m_s=x[6:9].copy() if n == 12 else np.zeros(3),
        angular_velocity_rad_s=x[9:12].copy() if n == 12 else np.zeros(3),
        covariance=covariance,
        rms_px=float(np.sqrt(np.mean(r_px**2))),
        inlier_fraction=float(np.mean(np.abs(r_px) <= 3.0 * f_scale_px)),
        points=n_points,
    )
