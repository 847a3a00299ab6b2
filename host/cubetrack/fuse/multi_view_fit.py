"""A multi-camera fit of one body pose (and optionally its velocities) over every matched corner.

The paper fuses per-marker poses; each of those is a monocular estimate of a small marker, weak
in depth and prone to planar flips. Here the unknown is the body pose itself and the residual is
the reprojection error of every matched corner in every camera (see
:mod:`cubetrack.estimate.reprojection`), with a robust (soft-L1) loss; the fit is compiled
(:func:`cubetrack.fuse.filter_kernels.joint_fit`: the minimum scipy's ``least_squares`` finds).
Used to start a track from sightings of several cameras.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from cubetrack.estimate.reprojection import CornerSet, perturbed
from cubetrack.fuse.filter_kernels import joint_fit, packed_sets

JOINT_FIT_STEPS = 100  # Gauss-Newton steps at most (a fit converges in 5-15)


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


def robust_gauss_newton(residuals: Callable[[np.ndarray], np.ndarray], jacobian: Callable[[np.ndarray], np.ndarray],
                        n: int, f_scale: float, iterations: int
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A soft-L1 fit of increments started at zero (``residuals`` in units of their noise): the
    solution, its covariance and the residuals there (None when a matrix is singular or the fit is not
    finite), by at most ``iterations`` steps of iteratively
    reweighted Gauss-Newton (the soft-L1 loss's weights ``1 / sqrt(1 + (r / f_scale)²)``), stopping
    once a step is under 1e-7 in every unknown: for a start already near the solution, where the
    trust-region solver's own work costs many times the compiled residuals."""
    x = np.zeros(n)
    for _ in range(iterations):
        r, J = residuals(x), jacobian(x)
        w = 1.0 / np.sqrt(1.0 + (r / f_scale) ** 2)
        Jw = J * w[:, None]
        try:
            step = np.linalg.solve(Jw.T @ J, -(Jw.T @ r))
        except np.linalg.LinAlgError:
            return None
        x = x + step
        if not np.all(np.isfinite(x)):
            return None
        if np.max(np.abs(step)) < 1e-7:
            break
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
    observable). ``iterations``: Gauss-Newton steps at most (0: ``JOINT_FIT_STEPS``; the camera
    watcher's fits start near the solution and stop sooner). Returns None if the fit fails or has under
    four corners.
    """
    n_points = sum(len(s.points_cube_m) for s in sets)
    if n_points < 4:
        return None
    n = 6 if velocity_sigma is None else 12
    sigma_v, sigma_w = (1.0, 1.0) if velocity_sigma is None else velocity_sigma
    ok, x, covariance, fun = joint_fit(np.array(T_init, dtype=np.float64), n, *packed_sets(sets), t_ref_s,
                                       corner_noise_px, f_scale_px / corner_noise_px, float(sigma_v), float(sigma_w),
                                       iterations or JOINT_FIT_STEPS)
    if not ok:
        return None
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
