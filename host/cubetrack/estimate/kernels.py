"""The reprojection model's compiled pieces (numba), shared by :mod:`cubetrack.estimate.reprojection`
and the filter's kernels (:mod:`cubetrack.fuse.filter_kernels`), so that one formula serves both.
Compiled lazily on first call or loaded from numba's on-disk cache (``cache=True``); the filter
compiles them before its first sighting."""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def exp_and_left_jacobian(x: float, y: float, z: float, dt: float, out: np.ndarray) -> None:  # pragma: no cover
    """``out`` (3, 6) = ``[Exp(v dt) | J_l(v dt) dt]`` for an angular velocity ``v = (x, y, z)``
    (rad/s): the rotation of a body turning at ``v`` for ``dt`` seconds and its left Jacobian times
    ``dt`` (the chain rule to ``δω``). Rodrigues ``I + a K + b K²`` and the left Jacobian
    ``I + b K + c K²`` with ``K = [v dt]×``, ``K² = (v dt)(v dt)ᵀ - θ² I``; below 0.01 rad the
    coefficients' Taylor series, where the closed forms lose digits to cancellation."""
    x, y, z = x * dt, y * dt, z * dt
    t2 = x * x + y * y + z * z
    if t2 < 1e-4:
        a = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0)
        b = 0.5 - t2 / 24.0 * (1.0 - t2 / 30.0)
        c = 1.0 / 6.0 - t2 / 120.0 * (1.0 - t2 / 42.0)
    else:
        theta = math.sqrt(t2)
        sin, cos = math.sin(theta), math.cos(theta)
        a, b, c = sin / theta, (1.0 - cos) / t2, (theta - sin) / (t2 * theta)
    xx, yy, zz, xy, xz, yz = x * x - t2, y * y - t2, z * z - t2, x * y, x * z, y * z
    bd, cd = b * dt, c * dt
    out[0, 0], out[0, 1], out[0, 2] = 1.0 + b * xx, -a * z + b * xy, a * y + b * xz
    out[1, 0], out[1, 1], out[1, 2] = a * z + b * xy, 1.0 + b * yy, -a * x + b * yz
    out[2, 0], out[2, 1], out[2, 2] = -a * y + b * xz, a * x + b * yz, 1.0 + b * zz
    out[0, 3], out[0, 4], out[0, 5] = dt + cd * xx, -bd * z + cd * xy, bd * y + cd * xz
    out[1, 3], out[1, 4], out[1, 5] = bd * z + cd * xy, dt + cd * yy, -bd * x + cd * yz
    out[2, 3], out[2, 4], out[2, 5] = -bd * y + cd * xz, bd * x + cd * yz, dt + cd * zz
