"""A marker's corners measured by fitting its whole image: the body calibration's template fit.

Edge-fitted corners of markers seen more than 45° off their normal are turned by up to 0.4° and
scaled by up to 1 % on average (measured against the truth on the realistic simulation,
``benchmarks/body_calibration.py``); a calibration sees the top marker of a cube only that way.
:func:`template_fitted_corners` re-measures them by the template fit
(:mod:`cubetrack.detect.template_fit`: the model, its template image, homography, lens mapping
and compared pixels are that module's, shared with tracking's fast fit) with
``scipy.optimize.least_squares`` on finite differences. Cost: about 30-80 ms per marker (5-6x
tracking's Gauss-Newton fit, which gives the same corners up to 70° off the normal), spent once
per sighting offline.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import undistort_points
from cubetrack.core.params import check, check_positive
from cubetrack.detect.template_fit import (
    TEMPLATE_PAD,
    TEMPLATE_RES,
    TemplateFitSettings,
    distort_px,
    marker_region,
    marker_template,
    photometric_columns,
    square_homography,
)

_TEMPLATE_SHIFT = TEMPLATE_PAD * TEMPLATE_RES - 0.5  # module coordinate 0 in template samples


@dataclass(frozen=True, slots=True)
class TemplateFitParams(TemplateFitSettings):
    """How :func:`template_fitted_corners` fits a marker: :class:`TemplateFitSettings` (4 x 4
    samples per pixel here) and ``max_nfev``, the function evaluations of the least-squares fit."""

    supersample: int = 4
    max_nfev: int = 40

    def __post_init__(self) -> None:
        check_positive(self, "supersample", "white_modules", "margin_modules", "start_blur_px", "max_move_px",
                       "max_nfev")
        check(self.margin_modules <= self.white_modules,
              f"margin_modules ({self.margin_modules}) must not exceed white_modules ({self.white_modules})")


def template_fitted_corners(gray: np.ndarray, corners_px: np.ndarray, dictionary: str, marker_id: int,
                            intrinsics: CameraIntrinsics, params: TemplateFitParams = TemplateFitParams()
                            ) -> np.ndarray:
    """The (4, 2) corners (TL TR BR BL, px in ``gray``) of marker ``marker_id`` of ``dictionary``
    near ``corners_px`` (e.g. the edge fit's), re-measured by fitting the marker's whole image
    (see the module docstring) through the camera's lens model (``intrinsics``). NaN corners when
    the fit fails: the marker with its margin is not wholly inside the image, the fit does not
    converge, or a corner would move more than ``params.max_move_px``."""
    failed = np.full((4, 2), np.nan)
    K, dist = np.asarray(intrinsics.K, float), np.asarray(intrinsics.dist, float).ravel()
    template, modules = marker_template(dictionary, marker_id, params.white_modules)
    region = marker_region(gray, corners_px, modules, K, dist, lambda pts: undistort_points(pts, K, dist, K),
                           params.supersample, params.margin_modules)
    if region is None:
        return failed
    ny, nx = region.shape
    sx, sy = region.samples_px.transpose(2, 0, 1)  # (ny s, nx s) each
    start = region.start_px

    def residuals(p: np.ndarray) -> np.ndarray:
        h = np.linalg.inv(square_homography(start + p[:8].reshape(4, 2), modules))
        h = h * (TEMPLATE_RES / h[2, 2])
        w = h[2, 0] / TEMPLATE_RES * sx + h[2, 1] / TEMPLATE_RES * sy + 1.0
        mx = ((h[0, 0] * sx + h[0, 1] * sy + h[0, 2]) / w + _TEMPLATE_SHIFT).astype(np.float32)
        my = ((h[1, 0] * sx + h[1, 1] * sy + h[1, 2]) / w + _TEMPLATE_SHIFT).astype(np.float32)
        # one image at a time (cv2.remap interpolates several channels at 1/32 sample steps
        # only); the pixel's area: an exact box average
        predicted = np.stack([cv2.resize(cv2.remap(template[k], mx, my, cv2.INTER_LINEAR,
                                                   borderMode=cv2.BORDER_CONSTANT, borderValue=float(k)),
                                         (nx, ny), interpolation=cv2.INTER_AREA) for k in (0, 1)], axis=-1)
        blur = abs(p[8])
        if blur > 0.05:
            predicted = cv2.GaussianBlur(predicted, (0, 0), blur, borderType=cv2.BORDER_REPLICATE)
        A = photometric_columns(predicted.reshape(ny * nx, 2)[region.fitted], region.gradient)
        coef, *_ = np.linalg.lstsq(A, region.pixels, rcond=None)
        return region.pixels - A @ coef

    try:
        # scipy-stubs types diff_step as an array; scipy takes a scalar too (its docs: array_like)
        result = least_squares(residuals, np.r_[np.zeros(8), params.start_blur_px], method="trf",
                               diff_step=1e-3,  # type: ignore[arg-type]
                               x_scale=np.full(9, 0.1), xtol=1e-3, max_nfev=params.max_nfev)
    except (np.linalg.LinAlgError, ValueError):
        return failed
    moves = result.x[:8].reshape(4, 2)
    if not np.isfinite(result.x).all() or np.abs(moves).max() > params.max_move_px:
        return failed
    return distort_px(start + moves, K, dist)
