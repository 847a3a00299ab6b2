"""A marker's corners measured by fitting its whole image: the calibration's template fit.

Edge-fitted corners of markers seen more than 45° off their normal are turned by up to 0.4° and
scaled by up to 1 % on average (measured against the truth on the realistic simulation,
``benchmarks/body_calibration.py``); a calibration sees the top marker of a cube only that way.
:func:`template_fitted_corners` re-measures them by the template fit of
:mod:`cubetrack.detect.template_fit` (the model, its template image, homography, lens mapping
and compared pixels are that module's): the compiled Gauss-Newton fit tracking uses
(:func:`cubetrack.detect.template_fit.fast_template_corners`), here with 4 x 4 samples per pixel
and iterated until no corner moves more than 0.001 px. Until session 19 this fit was
``scipy.optimize.least_squares`` on finite differences of the same model (30-120 ms per marker,
nearly all of a refinement's time); the compiled one is 20-30x cheaper and at least as close to
the truth (docs/calibration.md, "The calibration's template fit, compiled").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cubetrack.core.params import check, check_positive
from cubetrack.detect.template_fit import LensMap, TemplateFitSettings, fast_template_corners


@dataclass(frozen=True, slots=True)
class TemplateFitParams(TemplateFitSettings):
    """How :func:`template_fitted_corners` fits a marker: :class:`TemplateFitSettings` (4 x 4
    samples per pixel here) and ``iterations``, the most Gauss-Newton steps (the fit stops
    earlier once no corner moves more than 0.001 px in a step)."""

    supersample: int = 4
    iterations: int = 10

    def __post_init__(self) -> None:
        check_positive(self, "supersample", "white_modules", "margin_modules", "start_blur_px", "max_move_px",
                       "iterations")
        check(self.margin_modules <= self.white_modules,
              f"margin_modules ({self.margin_modules}) must not exceed white_modules ({self.white_modules})")


def template_fitted_corners(gray: np.ndarray, corners_px: np.ndarray, dictionary: str, marker_id: int,
                            lens: LensMap, params: TemplateFitParams = TemplateFitParams()) -> np.ndarray:
    """The (4, 2) corners (TL TR BR BL, px in ``gray``) of marker ``marker_id`` of ``dictionary``
    near ``corners_px`` (e.g. the edge fit's), re-measured by fitting the marker's whole image
    (see the module docstring) through the camera's lens (``lens``: one per camera, built once).
    NaN corners when the fit fails: the marker with its margin is not wholly inside the image, the
    fit diverges, or a corner would move more than ``params.max_move_px``."""
    fitted = fast_template_corners(gray, corners_px, dictionary, marker_id, lens, params.iterations, params)
    return np.full((4, 2), np.nan) if fitted is None else fitted
