"""Each detected corner's measurement noise from what its marker's image shows (issue 26).

The edge fit (:mod:`cubetrack.detect.edge_fit`) locates a side from the dark-to-bright step of
the marker's one-module black border; where that border is narrow in the image its step runs into
the next cell's and the fitted lines, extended to meet at the corners, wander. Against the
simulator's exact corners (``benchmarks/corner_ceiling.py``, clean and realistic development
scenes, docs/detection.md "Each corner's noise") the error of a corner follows the width in pixels
of the border modules of the two sides that meet there, measured across each side (the quad's
height over that side, over the modules across the marker): RMS per coordinate ~0.27 px /
width^1.7 (0.18 px at 1.2 px, 0.05 px at 2.8 px). That width falls with the marker's distance and
with how obliquely it is seen, so it carries both the size and the view angle, and it is read off
the detected quad alone.

:func:`corner_noise_scale` turns it into a factor on the filter's ``corner_noise_px`` (which
stands for every error of a corner the filter does not model, not only the edge fit's): 1 for
corners whose border modules are at least :data:`WIDE_MODULE_PX` wide, growing as the modules
narrow, so the filter leans on the corners the frame measures well.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np

WIDE_MODULE_PX = 2.5  # border modules this wide (across their side) or wider: the nominal corner noise
EXPONENT = 1.7  # the edge fit's corner error against the border module's width: ~ width^-EXPONENT
MAX_SCALE = 8.0  # the largest factor (a module under ~0.9 px: such a marker is barely decoded)


@numba.njit(cache=True, nogil=True)
def _border_widths(quads_px: np.ndarray, modules: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """``out`` (4M,): :func:`border_module_px` of each of the M quads stacked in ``quads_px`` (4M, 2) px,
    marker ``k`` having ``modules[k]`` cells across."""
    for k in range(len(modules)):
        q = quads_px[4 * k: 4 * k + 4]
        area_px2 = 0.0
        across = np.empty(4)
        for i in range(4):  # side i: corner i -> i + 1
            j = (i + 1) % 4
            area_px2 += q[i, 0] * q[j, 1] - q[j, 0] * q[i, 1]
            across[i] = math.hypot(q[j, 0] - q[i, 0], q[j, 1] - q[i, 1])
        area_px2 = 0.5 * abs(area_px2)
        for i in range(4):
            across[i] = area_px2 / max(across[i], 1e-9) / modules[k]
        for i in range(4):  # corner i: sides i and i - 1
            out[4 * k + i] = min(across[i], across[i - 1])


@numba.njit(cache=True, nogil=True)
def _noise_factors(quads_px: np.ndarray, modules: np.ndarray) -> np.ndarray:  # pragma: no cover
    """(4M,) :func:`corner_noise_scale` of each of the M quads stacked in ``quads_px`` (4M, 2) px."""
    out = np.empty(len(quads_px))
    _border_widths(quads_px, modules, out)
    for i in range(len(out)):
        out[i] = min(max((WIDE_MODULE_PX / max(out[i], 1e-9)) ** EXPONENT, 1.0), MAX_SCALE)
    return out


def border_module_px(corners_px: np.ndarray, modules: int) -> np.ndarray:
    """(4,) per corner of a marker's quad (4, 2) px: the narrower width in pixels, across its side,
    of the border modules of the two sides that meet there (the quad's height over each side,
    area / side length, over ``modules``, the cells across the marker with its border)."""
    out = np.empty(4)
    _border_widths(np.array(corners_px, dtype=np.float64).reshape(4, 2), np.array([modules], dtype=np.int64), out)
    return out


def corner_noise_scale(corners_px: np.ndarray, modules: int) -> np.ndarray:
    """(4,) per corner of a marker's quad: its noise over the nominal corner noise, from
    :func:`border_module_px` (1 at :data:`WIDE_MODULE_PX` and wider, at most :data:`MAX_SCALE`)."""
    return corner_noise_factors(np.array(corners_px, dtype=np.float64).reshape(4, 2), np.array([modules]))


def corner_noise_factors(quads_px: np.ndarray, modules: Sequence[int] | np.ndarray) -> np.ndarray:
    """(4M,) :func:`corner_noise_scale` of each of the M quads stacked in ``quads_px`` (4M, 2) px (a writable
    float64 array), marker ``k`` with ``modules[k]`` cells across: one compiled call for a sighting's markers
    (this runs for every sighting; numpy's per-call cost on 4 points would be most of it)."""
    return _noise_factors(quads_px, np.asarray(modules, dtype=np.int64))
