"""Compiled checks on (N, 4, 2) pixel quads that several detector stages share."""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def corners_finite(quads: np.ndarray, q: int) -> bool:
    """Whether all four corners of quad ``q`` of ``quads`` (N, 4, 2) are finite (a fit marks a
    corner it could not place with NaN)."""
    for c in range(4):
        if not (math.isfinite(quads[q, c, 0]) and math.isfinite(quads[q, c, 1])):
            return False
    return True
