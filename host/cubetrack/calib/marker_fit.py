"""A marker's corners measured by fitting its whole image: the body calibration's template fit.

Edge fits (the detector's, :func:`cubetrack.detect.refine_corners_edges`) locate each side of
the black border from the brightness profile across it. A profile also holds the cells next to
the border and, on an obliquely seen marker, they are within a pixel or two of the edge: under
the lens's blur a white cell beside the one-module border pulls the edge, by an amount that
depends on the marker's pattern and on how foreshortened the marker is. Measured against the
truth on the realistic simulation (``benchmarks/body_calibration.py``), the edge-fitted
corners of markers seen more than 45° off their normal are turned by up to 0.4° and scaled by up
to 1 % on average; a calibration sees the top marker of a cube only that way.

:func:`template_fitted_corners` instead predicts the whole marker image — its cells (from the
dictionary), its black border and a white margin, through the homography its corners give and
the camera's lens model, averaged over each pixel's area, blurred by a Gaussian of fitted width,
times a brightness that may vary linearly across the marker plus an offset — and moves the four
corners (in the undistorted image) until the prediction matches the pixels in least squares.
Every cell's edge then helps, none biases. Cost: about 50-80 ms per marker (against a few ms for
the edge fit), spent once per sighting offline.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from cubetrack.calib.solver import project
from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import undistort_points
from cubetrack.core.params import check, check_positive
from cubetrack.detect.detector import aruco_dictionary

_TEMPLATE_RES = 16  # template samples per module
_TEMPLATE_PAD = 2   # modules of white around the marker in the template image
_REGION_PAD_PX = 3  # pixels beyond the fitted region that the blur reads


@dataclass(frozen=True, slots=True)
class TemplateFitParams:
    """How :func:`template_fitted_corners` fits a marker.

    ``supersample``: samples per pixel along each axis (pixel area); ``white_modules``: the
    white margin every marker of the body has around its black border at least (modules;
    beyond it the fit assumes some uniform brightness of its own); ``margin_modules``: how much
    of that margin is fitted (modules); ``start_blur_px``: the blur (Gaussian sigma, px) the
    fit starts from; ``max_move_px``: a corner moving farther than this from its start is a
    failed fit; ``max_nfev``: function evaluations of the least-squares fit."""

    supersample: int = 4
    white_modules: float = 1.0
    margin_modules: float = 0.5
    start_blur_px: float = 0.8
    max_move_px: float = 1.5
    max_nfev: int = 40

    def __post_init__(self) -> None:
        check_positive(self, "supersample", "white_modules", "margin_modules", "start_blur_px", "max_move_px",
                       "max_nfev")
        check(self.margin_modules <= self.white_modules,
              f"margin_modules ({self.margin_modules}) must not exceed white_modules ({self.white_modules})")


@functools.lru_cache(maxsize=64)
def _template(dictionary: str, marker_id: int, white_modules: float) -> tuple[np.ndarray, int]:
    """The marker in module units (``_TEMPLATE_RES`` samples per module, ``_TEMPLATE_PAD``
    modules around it), two images: its reflectance (cells, border and ``white_modules`` of
    white margin; 0 beyond) and the indicator of what lies beyond the margin; slightly smoothed
    so that the fit's objective is smooth. Also the modules across (border included)."""
    d = aruco_dictionary(dictionary)
    modules = d.markerSize + 2
    cells = cv2.aruco.generateImageMarker(d, marker_id, modules, borderBits=1).astype(np.float32) / 255.0
    side = (modules + 2 * _TEMPLATE_PAD) * _TEMPLATE_RES
    at = (np.arange(side) + 0.5) / _TEMPLATE_RES - _TEMPLATE_PAD  # module coordinate of each sample
    near = (at > -white_modules) & (at < modules + white_modules)
    image = np.zeros((side, side, 2), np.float32)
    image[..., 0] = near[:, None] & near[None, :]
    image[..., 1] = 1.0 - image[..., 0]
    inner = slice(_TEMPLATE_PAD * _TEMPLATE_RES, (_TEMPLATE_PAD + modules) * _TEMPLATE_RES)
    image[inner, inner, 0] = np.kron(cells, np.ones((_TEMPLATE_RES, _TEMPLATE_RES), np.float32))
    image = np.ascontiguousarray(cv2.GaussianBlur(image, (0, 0), 0.7).transpose(2, 0, 1))
    image.setflags(write=False)
    return image, modules


def square_homography(corners: np.ndarray, side: float) -> np.ndarray:
    """The 3x3 homography taking the square (0, 0), (side, 0), (side, side), (0, side) to the
    (4, 2) ``corners`` (float64 throughout, unlike cv2.getPerspectiveTransform)."""
    src = np.array([[0.0, 0.0], [side, 0.0], [side, side], [0.0, side]])
    A, b = np.zeros((8, 8)), np.zeros(8)
    for i, ((x, y), (u, v)) in enumerate(zip(src, np.asarray(corners, float))):
        A[2 * i] = [x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y]
        A[2 * i + 1] = [0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y]
        b[2 * i], b[2 * i + 1] = u, v
    return np.append(np.linalg.solve(A, b), 1.0).reshape(3, 3)


def _distort(points_px: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Where ideal pinhole pixels (n, 2) of ``K`` lie in the distorted image."""
    rays = np.column_stack([points_px, np.ones(len(points_px))]) @ np.linalg.inv(K).T
    return project(rays, K, dist)[0]


def _to_marker(H: np.ndarray, points_h: np.ndarray) -> np.ndarray:
    """Marker-plane coordinates (n, 2) (modules) of homogeneous undistorted pixels (n, 3)."""
    m = points_h @ np.linalg.inv(H).T
    return m[:, :2] / m[:, 2:3]


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
    template, modules = _template(dictionary, marker_id, params.white_modules)
    start = undistort_points(np.asarray(corners_px, float).reshape(4, 2), K, dist, K)
    if not np.isfinite(start).all():
        return failed
    margin = params.margin_modules
    ring = np.array([[-margin, -margin], [modules + margin, -margin], [modules + margin, modules + margin],
                     [-margin, modules + margin]])
    H0 = square_homography(start, modules)
    ring_px = _distort(cv2.perspectiveTransform(ring.reshape(-1, 1, 2), H0).reshape(-1, 2), K, dist)
    x0, y0 = np.floor(ring_px.min(axis=0)).astype(int) - _REGION_PAD_PX
    x1, y1 = np.ceil(ring_px.max(axis=0)).astype(int) + _REGION_PAD_PX + 1
    if x0 < 0 or y0 < 0 or x1 > gray.shape[1] or y1 > gray.shape[0]:
        return failed
    image = gray[y0:y1, x0:x1].astype(np.float64)
    ny, nx = image.shape
    s = params.supersample
    sub = (np.arange(s) + 0.5) / s - 0.5
    xs, ys = np.meshgrid((x0 + np.arange(nx)[:, None] + sub).ravel(), (y0 + np.arange(ny)[:, None] + sub).ravel())
    sx, sy = undistort_points(np.stack([xs, ys], axis=-1), K, dist, K).transpose(2, 0, 1)  # (ny s, nx s) each
    cx, cy = np.meshgrid(x0 + np.arange(nx, dtype=float), y0 + np.arange(ny, dtype=float))
    centres = undistort_points(np.stack([cx.ravel(), cy.ravel()], axis=1), K, dist, K)
    inside = _to_marker(H0, np.column_stack([centres, np.ones(len(centres))]))
    fitted = ((inside > -margin) & (inside < modules + margin)).all(axis=1)  # the pixels compared
    pixels = image.ravel()[fitted]
    gx = (cx.ravel()[fitted] - cx.mean()) / nx  # brightness may vary linearly across the marker
    gy = (cy.ravel()[fitted] - cy.mean()) / ny

    def residuals(p: np.ndarray) -> np.ndarray:
        h = np.linalg.inv(square_homography(start + p[:8].reshape(4, 2), modules))
        h = h * (_TEMPLATE_RES / h[2, 2])
        w = h[2, 0] / _TEMPLATE_RES * sx + h[2, 1] / _TEMPLATE_RES * sy + 1.0
        shift = _TEMPLATE_PAD * _TEMPLATE_RES - 0.5
        mx = ((h[0, 0] * sx + h[0, 1] * sy + h[0, 2]) / w + shift).astype(np.float32)
        my = ((h[1, 0] * sx + h[1, 1] * sy + h[1, 2]) / w + shift).astype(np.float32)
        # one image at a time (cv2.remap interpolates several channels at 1/32 sample steps
        # only); the pixel's area: an exact box average
        predicted = np.stack([cv2.resize(cv2.remap(template[k], mx, my, cv2.INTER_LINEAR,
                                                   borderMode=cv2.BORDER_CONSTANT, borderValue=float(k)),
                                         (nx, ny), interpolation=cv2.INTER_AREA) for k in (0, 1)], axis=-1)
        blur = abs(p[8])
        if blur > 0.05:
            predicted = cv2.GaussianBlur(predicted, (0, 0), blur, borderType=cv2.BORDER_REPLICATE)
        P, out = predicted[..., 0].ravel()[fitted], predicted[..., 1].ravel()[fitted]
        # offset, the marker's brightness and its gradient, the brightness beyond the margin
        A = np.column_stack([np.ones_like(P), P, P * gx, P * gy, out])
        coef, *_ = np.linalg.lstsq(A, pixels, rcond=None)
        return pixels - A @ coef

    try:
        result = least_squares(residuals, np.r_[np.zeros(8), params.start_blur_px], method="trf", diff_step=1e-3,
                               x_scale=np.full(9, 0.1), xtol=1e-3, max_nfev=params.max_nfev)
    except (np.linalg.LinAlgError, ValueError):
        return failed
    moves = result.x[:8].reshape(4, 2)
    if not np.isfinite(result.x).all() or np.abs(moves).max() > params.max_move_px:
        return failed
    return _distort(start + moves, K, dist)
