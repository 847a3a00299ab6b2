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

import numpy as np

WIDE_MODULE_PX = 2.5  # border modules this wide (across their side) or wider: the nominal corner noise
EXPONENT = 1.7  # the edge fit's corner error against the border module's width: ~ width^-EXPONENT
MAX_SCALE = 8.0  # the largest factor (a module under ~0.9 px: such a marker is barely decoded)


def border_module_px(corners_px: np.ndarray, modules: int) -> np.ndarray:
    """(4,) per corner of a marker's quad (4, 2) px: the narrower width in pixels, across its side,
    of the border modules of the two sides that meet there (the quad's height over each side,
    area / side length, over ``modules``, the cells across the marker with its border)."""
    return np.array(_border_widths(np.asarray(corners_px, dtype=np.float64).reshape(4, 2).tolist(), modules))


def corner_noise_scale(corners_px: np.ndarray, modules: int) -> np.ndarray:
    """(4,) per corner of a marker's quad: its noise over the nominal corner noise, from
    :func:`border_module_px` (1 at :data:`WIDE_MODULE_PX` and wider, at most :data:`MAX_SCALE`)."""
    return np.array(corner_noise_factors(np.asarray(corners_px, dtype=np.float64).reshape(4, 2).tolist(), modules))


def corner_noise_factors(quad: list[list[float]], modules: int) -> list[float]:
    """:func:`corner_noise_scale` of a quad given as four ``[x, y]`` lists (plain arithmetic: this runs
    for every marker of every sighting, where numpy's per-call cost on 4 points would be most of it)."""
    return [min(max((WIDE_MODULE_PX / max(w, 1e-9)) ** EXPONENT, 1.0), MAX_SCALE)
            for w in _border_widths(quad, modules)]


def _border_widths(quad: list[list[float]], modules: int) -> list[float]:
    """:func:`border_module_px` of a quad given as four ``[x, y]`` lists."""
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = quad
    area_px2 = 0.5 * abs((x0 * y1 - x1 * y0) + (x1 * y2 - x2 * y1) + (x2 * y3 - x3 * y2) + (x3 * y0 - x0 * y3))
    sides_px = (math.hypot(x1 - x0, y1 - y0), math.hypot(x2 - x1, y2 - y1), math.hypot(x3 - x2, y3 - y2),
                math.hypot(x0 - x3, y0 - y3))  # side i: corner i -> i + 1
    across = [area_px2 / max(side, 1e-9) / modules for side in sides_px]
    return [min(across[i], across[i - 1]) for i in range(4)]  # corner i: sides i and i - 1
