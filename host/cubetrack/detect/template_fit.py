"""A marker's corners measured by fitting its whole image: the template fit's shared core.

Edge fits (:func:`cubetrack.detect.edge_fit.refine_corners_edges`) locate each side of the
black border from the brightness profile across it. A profile also holds the cells next to the
border and, on an obliquely seen marker, they are within a pixel or two of the edge: under the
lens's blur a white cell beside the one-module border pulls the edge, by an amount that depends
on the marker's pattern and on how foreshortened it is (4-7x the template fit's corner error on
the realistic simulation, docs/tracking.md "What better corners would buy").

A template fit instead predicts the whole marker image — its cells (from the dictionary), its
black border and a white margin, through the homography its corners give and the camera's lens
model, averaged over each pixel's area, blurred by a Gaussian of fitted width, times a
brightness that may vary linearly across the marker plus an offset — and moves the four corners
(in the undistorted image) until the prediction matches the pixels in least squares. Every
cell's edge then helps, none biases.

This module holds what every template fit shares — the marker's template image
(:func:`marker_template`), the square's homography (:func:`square_homography`), the lens
mapping (:func:`distort_px`, :class:`LensMap`) and the pixels a fit compares
(:func:`marker_region`) — and the tracking-time fit, :func:`fast_template_corners`: Gauss-Newton
on the 8 corner coordinates and the blur with the brightness model solved jointly, the Jacobian
at pixel level (the template's gradient images resampled like the prediction, times the
homography mapping's analytic derivative at the pixel centre), the lens undistortion read from
a per-camera map. The body calibration's fit (:func:`cubetrack.calib.marker_fit.template_fitted_corners`,
finite differences through ``scipy.optimize.least_squares``, 5-6x the CPU) uses the same core.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import undistort_points

TEMPLATE_RES = 16  # template samples per module
TEMPLATE_PAD = 2   # modules of white around the marker in the template image
REGION_PAD_PX = 3  # pixels beyond the fitted region that the blur reads
_TEMPLATE_SHIFT = TEMPLATE_PAD * TEMPLATE_RES - 0.5  # module coordinate 0 in template samples
_BLUR_STEP_PX = 0.05  # the blur's derivative: a forward difference of this much sigma
_BLUR_RANGE_PX = (0.3, 3.0)  # the fast fit keeps its blur sigma within this range
_CONVERGED_PX = 1e-3  # the fast fit stops once no corner moves more than this in an iteration
_REMAP_ROW = 4096  # LensMap.undistort reads the map for this many points per cv2.remap row
_BEYOND_MIN = 0.05  # the fast fit measures the brightness beyond the margin where a pixel sees this much of it
_AREA_STEP = 0.25  # template samples: the fast fit's pre-blurred templates are cached at multiples of this


def distort_px(points_px: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Where ideal pinhole image points (..., 2) of ``K`` lie in the distorted image."""
    Kinv = np.linalg.inv(K)
    xy = points_px.reshape(-1, 2) @ Kinv[:2, :2].T + Kinv[:2, 2]
    rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1).reshape(-1, 1, 3)
    out, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, dist)
    return out.reshape(points_px.shape)


@functools.lru_cache(maxsize=64)
def marker_template(dictionary: str, marker_id: int, white_modules: float) -> tuple[np.ndarray, int]:
    """The marker ``marker_id`` of the OpenCV dictionary named ``dictionary`` in module units
    (``TEMPLATE_RES`` samples per module, ``TEMPLATE_PAD`` modules around it), two images (2, n,
    n): its reflectance (cells, border and ``white_modules`` of white margin; 0 beyond) and the
    indicator of what lies beyond the margin; slightly smoothed so that a fit's objective is
    smooth. Also the modules across (border included)."""
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    modules = d.markerSize + 2
    cells = cv2.aruco.generateImageMarker(d, marker_id, modules, borderBits=1).astype(np.float32) / 255.0
    side = (modules + 2 * TEMPLATE_PAD) * TEMPLATE_RES
    at = (np.arange(side) + 0.5) / TEMPLATE_RES - TEMPLATE_PAD  # module coordinate of each sample
    near = (at > -white_modules) & (at < modules + white_modules)
    image = np.zeros((side, side, 2), np.float32)
    image[..., 0] = near[:, None] & near[None, :]
    image[..., 1] = 1.0 - image[..., 0]
    inner = slice(TEMPLATE_PAD * TEMPLATE_RES, (TEMPLATE_PAD + modules) * TEMPLATE_RES)
    image[inner, inner, 0] = np.kron(cells, np.ones((TEMPLATE_RES, TEMPLATE_RES), np.float32))
    image = np.ascontiguousarray(cv2.GaussianBlur(image, (0, 0), 0.7).transpose(2, 0, 1))
    image.setflags(write=False)
    return image, modules


_SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def _homography_system(corners: np.ndarray, side: float) -> np.ndarray:
    """The 8x8 matrix of the homography from the square of ``side`` to ``corners`` (h22 = 1)."""
    A = np.zeros((8, 8))
    for i, ((x, y), (u, v)) in enumerate(zip(_SQUARE * side, np.asarray(corners, float), strict=True)):
        A[2 * i] = [x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y]
        A[2 * i + 1] = [0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y]
    return A


def square_homography(corners: np.ndarray, side: float) -> np.ndarray:
    """The 3x3 homography taking the square (0, 0), (side, 0), (side, side), (0, side) to the
    (4, 2) ``corners`` (float64 throughout, unlike cv2.getPerspectiveTransform)."""
    return np.append(np.linalg.solve(_homography_system(corners, side), np.asarray(corners, float).ravel()),
                     1.0).reshape(3, 3)


def square_homography_derivatives(corners: np.ndarray, side: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`square_homography` and its derivatives (8, 3, 3) by the corners' 8 coordinates
    (x0, y0, x1, ...): differentiating ``A h = c`` by a corner coordinate leaves
    ``A dh = e_k w_i``, ``w_i`` the homogeneous scale at that corner."""
    A_inv = np.linalg.inv(_homography_system(corners, side))
    h = np.append(A_inv @ np.asarray(corners, float).ravel(), 1.0)
    w = np.repeat(_SQUARE * side @ h[6:8] + 1.0, 2)
    dH = np.zeros((8, 9))
    dH[:, :8] = (A_inv * w).T
    return h.reshape(3, 3), dH.reshape(8, 3, 3)


class LensMap:
    """A camera's lens undistortion as a per-pixel map: the ideal pinhole pixel (of the same
    ``K``) of every pixel centre of its image (``intrinsics.width`` x ``height``) and a one-pixel
    border, float32, read bilinearly (``cv2.remap``) at any point; a
    :class:`~cubetrack.detect.detector.Detector` keeps one per camera. Without intrinsics, the
    identity (the image taken as undistorted)."""

    def __init__(self, intrinsics: CameraIntrinsics | None):
        self.intrinsics = intrinsics
        if intrinsics is None:
            self.K, self.dist, self.map = np.eye(3), np.zeros(5), None
            return
        self.K, self.dist = np.asarray(intrinsics.K, float), np.asarray(intrinsics.dist, float).ravel()
        xs, ys = np.meshgrid(np.arange(-1.0, intrinsics.width + 1.0), np.arange(-1.0, intrinsics.height + 1.0))
        self.map = undistort_points(np.stack([xs, ys], axis=-1), self.K, self.dist, self.K).astype(np.float32)

    def undistort(self, points_px: np.ndarray) -> np.ndarray:
        """Ideal pinhole pixels (..., 2) of distorted ones (within the image and its border),
        float64."""
        if self.map is None:
            return np.asarray(points_px, np.float64)
        flat = np.asarray(points_px, np.float32).reshape(-1, 2) + 1.0
        n = len(flat)  # remap takes at most 32767 rows and columns: rows of _REMAP_ROW points
        pts = np.zeros((-(-n // _REMAP_ROW) * _REMAP_ROW, 2), np.float32)
        pts[:n] = flat
        rows = pts.reshape(-1, _REMAP_ROW, 2)
        out = cv2.remap(self.map, rows[..., 0], rows[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(-1, 2)[:n].astype(np.float64).reshape(np.shape(points_px))


@dataclass(frozen=True, slots=True, eq=False)
class MarkerRegion:
    """The pixels a template fit of one marker compares, with everything the fit needs of them.

    ``start_px`` (4, 2): the starting corners, undistorted; ``modules``: modules across the
    marker; ``origin``: the region's top-left pixel (x, y) and ``shape`` (ny, nx) its size;
    ``samples_px`` (ny s, nx s, 2): undistorted positions of the ``s`` x ``s`` samples of each
    pixel's area; ``centres_px`` (n, 2): undistorted centres of the n compared pixels (those
    whose centre lies on the marker or within ``margin`` modules of it), ``fitted`` (ny nx,)
    marks them, ``pixels`` (n,) are their values and ``gradient`` (n, 2) their position across
    the region (for the brightness's linear variation)."""

    start_px: np.ndarray
    modules: int
    origin: tuple[int, int]
    shape: tuple[int, int]
    samples_px: np.ndarray
    centres_px: np.ndarray
    fitted: np.ndarray
    pixels: np.ndarray
    gradient: np.ndarray


def marker_region(gray: np.ndarray, corners_px: np.ndarray, modules: int, K: np.ndarray, dist: np.ndarray,
                  undistort: Callable[[np.ndarray], np.ndarray], supersample: int,
                  margin_modules: float) -> MarkerRegion | None:
    """The region a template fit of the marker near ``corners_px`` (distorted, TL TR BR BL)
    compares (see :class:`MarkerRegion`), with lens ``K``, ``dist`` and ``undistort`` (distorted
    -> ideal pinhole pixels of ``K``, e.g. :func:`cubetrack.core.geometry.undistort_points` or
    :meth:`LensMap.undistort`); None when the corners do not undistort or the marker with its
    margin and the blur's reach is not wholly inside the image."""
    start = undistort(np.asarray(corners_px, float).reshape(4, 2))
    if not np.isfinite(start).all():
        return None
    m = margin_modules
    ring = np.array([[-m, -m], [modules + m, -m], [modules + m, modules + m], [-m, modules + m]])
    H0 = square_homography(start, modules)
    ring_px = distort_px(cv2.perspectiveTransform(ring.reshape(-1, 1, 2), H0).reshape(-1, 2), K, dist)
    if not np.isfinite(ring_px).all():
        return None
    x0, y0 = np.floor(ring_px.min(axis=0)).astype(int) - REGION_PAD_PX
    x1, y1 = np.ceil(ring_px.max(axis=0)).astype(int) + REGION_PAD_PX + 1
    if x0 < 0 or y0 < 0 or x1 > gray.shape[1] or y1 > gray.shape[0]:
        return None
    ny, nx = y1 - y0, x1 - x0
    s = supersample
    sub = (np.arange(s) + 0.5) / s - 0.5
    xs, ys = np.meshgrid((x0 + np.arange(nx)[:, None] + sub).ravel(), (y0 + np.arange(ny)[:, None] + sub).ravel())
    samples = undistort(np.stack([xs, ys], axis=-1))
    cx, cy = np.meshgrid(x0 + np.arange(nx, dtype=float), y0 + np.arange(ny, dtype=float))
    centres = undistort(np.stack([cx.ravel(), cy.ravel()], axis=1))
    inside = np.column_stack([centres, np.ones(len(centres))]) @ np.linalg.inv(H0).T
    inside = inside[:, :2] / inside[:, 2:3]
    fitted = ((inside > -m) & (inside < modules + m)).all(axis=1)
    gradient = np.column_stack([(cx.ravel()[fitted] - cx.mean()) / nx, (cy.ravel()[fitted] - cy.mean()) / ny])
    return MarkerRegion(start, modules, (int(x0), int(y0)), (int(ny), int(nx)), samples, centres[fitted], fitted,
                        gray[y0:y1, x0:x1].astype(np.float64).ravel()[fitted], gradient)


def _least_squares(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """argmin |A x - b| for a tall A (n, <= 14) by the normal equations (several times cheaper than
    ``np.linalg.lstsq``'s SVD at this size): :func:`_normal_solution`."""
    return _normal_solution(A.T @ A, A.T @ b)


def _normal_solution(N: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The least-squares solution from its normal equations ``N x = rhs`` (``N = A^T A``,
    ``rhs = A^T b``); a column of ``A`` that vanishes (no pixel of the region lies beyond the
    marker's margin) gets 0, as the least-norm solution gives it. LinAlgError when the rest is
    rank-deficient."""
    norms = np.sqrt(np.diag(N))
    kept = norms > 1e-9 * norms.max()
    x = np.zeros(N.shape[1])
    x[kept] = np.linalg.solve(N[np.ix_(kept, kept)], rhs[kept])
    return x


def photometric_columns(predicted: np.ndarray, gradient: np.ndarray) -> np.ndarray:
    """The brightness model's design matrix (n, 5) from the predicted reflectance and beyond-margin
    images (n, 2) of the compared pixels: offset, the marker's brightness and its gradient across
    the region, the brightness beyond the margin."""
    P = predicted[:, 0]
    return np.column_stack([np.ones_like(P), P, P * gradient[:, 0], P * gradient[:, 1], predicted[:, 1]])


@dataclass(frozen=True, slots=True)
class TemplateFitSettings:
    """What every template fit of a marker is told.

    ``supersample``: samples per pixel along each axis (pixel area); ``white_modules``: the
    white margin every marker has around its black border at least (modules; beyond it the fit
    assumes some uniform brightness of its own); ``margin_modules``: how much of that margin is
    fitted (modules); ``start_blur_px``: the blur (Gaussian sigma, px) the fit starts from;
    ``max_move_px``: a corner moving farther than this from its start is a failed fit."""

    supersample: int = 3
    white_modules: float = 1.0
    margin_modules: float = 0.5
    start_blur_px: float = 0.8
    max_move_px: float = 1.5


FAST_SETTINGS = TemplateFitSettings(supersample=2)  # tracking's fit (fast_template_corners)


def _lens_jacobian(lens: LensMap, corners_px: np.ndarray) -> np.ndarray:
    """(2, 2): distorted pixels per undistorted pixel at the marker's centre (the lens's local
    linear map, from ``lens``'s undistortion one pixel either way)."""
    mid = np.asarray(corners_px, float).reshape(4, 2).mean(axis=0)
    probe = lens.undistort(np.array([mid, mid + [1.0, 0.0], mid + [0.0, 1.0]]))
    return np.linalg.inv(np.column_stack([probe[1] - probe[0], probe[2] - probe[0]]))


@functools.lru_cache(maxsize=256)
def _area_template(dictionary: str, marker_id: int, white_modules: float, steps: tuple[int, int]) -> np.ndarray:
    """(2, n, n) float32: :func:`marker_template`'s two images blurred by a Gaussian of
    ``steps`` x ``_AREA_STEP`` template samples along x and y (a sample's area, see
    :func:`_area_steps`), so that reading them at a few points per pixel keeps the sub-pixel place
    of every cell edge; cached per marker and blur: per marker size."""
    template, _ = marker_template(dictionary, marker_id, white_modules)
    sx, sy = (max(k * _AREA_STEP, 0.01) for k in steps)
    out = np.stack([cv2.GaussianBlur(t, (0, 0), sigmaX=sx, sigmaY=sy, borderType=cv2.BORDER_REPLICATE)
                    for t in template])
    out.setflags(write=False)
    return out


def _area_steps(H: np.ndarray, modules: int, lens_jacobian: np.ndarray, supersample: int) -> tuple[int, int]:
    """The area of one of ``supersample`` x ``supersample`` samples of a pixel (a variance of
    1 / (12 s^2) px^2 along each axis) pulled back into the template through the homography ``H``
    and the lens at the marker's centre: its standard deviations along x and y in units of
    ``_AREA_STEP`` template samples."""
    c = np.array([modules / 2.0, modules / 2.0, 1.0])
    h = H @ c
    J = lens_jacobian @ (H[:2, :2] - np.outer(h[:2] / h[2], H[2, :2])) / h[2]  # distorted px per module
    cov = np.linalg.inv(J.T @ J) * (TEMPLATE_RES ** 2 / (12.0 * supersample ** 2))
    sx, sy = np.sqrt(np.diag(cov)) / _AREA_STEP
    return int(round(sx)), int(round(sy))


@dataclass(frozen=True, slots=True, eq=False)
class _FastRegion:
    """What :func:`fast_template_corners` compares: the region's ``shape`` (ny, nx); ``samples``
    (ny s nx s, 3) its pixels' samples and ``centres`` (n, 3) the compared pixels' centres,
    undistorted, homogeneous; ``lens`` (2, 2) the lens's local map (:func:`_lens_jacobian`) and the
    rest as :class:`MarkerRegion`'s."""

    region: MarkerRegion
    samples: np.ndarray
    centres: np.ndarray
    lens: np.ndarray
    index: np.ndarray  # (n,) the compared pixels' flat indices in the region


def _fast_region(gray: np.ndarray, corners_px: np.ndarray, modules: int, lens: LensMap,
                 settings: TemplateFitSettings) -> _FastRegion | None:
    region = marker_region(gray, corners_px, modules, lens.K, lens.dist, lens.undistort, settings.supersample,
                           settings.margin_modules)
    if region is None:
        return None
    samples = region.samples_px.reshape(-1, 2)
    return _FastRegion(region, np.column_stack([samples, np.ones(len(samples))]),
                       np.column_stack([region.centres_px, np.ones(len(region.centres_px))]),
                       _lens_jacobian(lens, corners_px), np.flatnonzero(region.fitted))


@numba.njit(cache=True, nogil=True)
def _template_maps(samples: np.ndarray, H_inv: np.ndarray, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Where each sample (rows x cols of them, homogeneous undistorted px) reads the template:
    ``cv2.remap``'s x and y maps (float32), through the inverse homography ``H_inv``."""
    mx, my = np.empty((rows, cols), np.float32), np.empty((rows, cols), np.float32)
    for i in range(rows):
        for j in range(cols):
            x, y, w = samples[i * cols + j]
            u = H_inv[0, 0] * x + H_inv[0, 1] * y + H_inv[0, 2] * w
            v = H_inv[1, 0] * x + H_inv[1, 1] * y + H_inv[1, 2] * w
            z = H_inv[2, 0] * x + H_inv[2, 1] * y + H_inv[2, 2] * w
            mx[i, j] = TEMPLATE_RES * u / z + _TEMPLATE_SHIFT
            my[i, j] = TEMPLATE_RES * v / z + _TEMPLATE_SHIFT
    return mx, my


@numba.njit(cache=True, nogil=True)
def _pixel_areas(reflectance: np.ndarray, beyond: np.ndarray, s: int) -> np.ndarray:
    """(ny, nx, 2) float32: the mean of each pixel's ``s`` x ``s`` template reads of both images."""
    ny, nx = reflectance.shape[0] // s, reflectance.shape[1] // s
    out = np.empty((ny, nx, 2), np.float32)
    scale = 1.0 / (s * s)
    for i in range(ny):
        for j in range(nx):
            a = b = 0.0
            for di in range(s):
                for dj in range(s):
                    a += reflectance[i * s + di, j * s + dj]
                    b += beyond[i * s + di, j * s + dj]
            out[i, j, 0], out[i, j, 1] = a * scale, b * scale
    return out


@numba.njit(cache=True, nogil=True)
def _brightness_system(image: np.ndarray, index: np.ndarray, gradient: np.ndarray,
                       pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """The brightness model's normal equations (:func:`photometric_columns` against the compared
    pixels' values) at the predicted ``image`` (ny, nx, 2), and whether any compared pixel sees
    the beyond-margin image (``_BEYOND_MIN``; if none, that column is left out: zero)."""
    flat = image.reshape(-1, 2)
    seen = 0.0
    for i in range(index.shape[0]):
        seen = max(seen, np.float64(flat[index[i], 1]))
    beyond = seen >= _BEYOND_MIN
    N, rhs, row = np.zeros((5, 5)), np.zeros(5), np.empty(5)
    for i in range(index.shape[0]):
        P = np.float64(flat[index[i], 0])
        row[0], row[1], row[2], row[3] = 1.0, P, P * gradient[i, 0], P * gradient[i, 1]
        row[4] = np.float64(flat[index[i], 1]) if beyond else 0.0
        for a in range(5):
            rhs[a] += row[a] * pixels[i]
            for b in range(5):
                N[a, b] += row[a] * row[b]
    return N, rhs, beyond


@numba.njit(cache=True, nogil=True)
def _step_system(image: np.ndarray, wider: np.ndarray, gx: np.ndarray, gy: np.ndarray, index: np.ndarray,
                 gradient: np.ndarray, pixels: np.ndarray, centres: np.ndarray, lens: np.ndarray,
                 H_inv: np.ndarray, dH: np.ndarray, coef: np.ndarray, beyond: bool) -> tuple[np.ndarray, np.ndarray]:
    """The normal equations of one Gauss-Newton step (:func:`_gauss_newton_step`), summed pixel by
    pixel: per compared pixel, the 8 corners' columns (the predicted image's gradient ``gx``,
    ``gy`` times the brightness ``coef``, through the lens's local map, times the motion of the
    pixel's template point, ``dH`` at its centre), the blur's (from ``wider``) and the 5
    brightness columns, against the residual at ``coef``."""
    img, wide = image.reshape(-1, 2), wider.reshape(-1, 2)
    dx, dy = gx.reshape(-1, 2), gy.reshape(-1, 2)
    N, rhs, row, d = np.zeros((14, 14)), np.zeros(14), np.empty(14), np.empty(3)
    for i in range(index.shape[0]):
        f = index[i]
        g0, g1 = gradient[i, 0], gradient[i, 1]
        P, Pw = np.float64(img[f, 0]), np.float64(wide[f, 0])
        B = np.float64(img[f, 1]) if beyond else 0.0
        Bw = np.float64(wide[f, 1]) if beyond else 0.0
        gain = coef[1] + coef[2] * g0 + coef[3] * g1
        sx = np.float64(dx[f, 0]) * gain + np.float64(dx[f, 1]) * coef[4]
        sy = np.float64(dy[f, 0]) * gain + np.float64(dy[f, 1]) * coef[4]
        s0, s1 = sx * lens[0, 0] + sy * lens[1, 0], sx * lens[0, 1] + sy * lens[1, 1]
        cx, cy = centres[i, 0], centres[i, 1]
        u0 = H_inv[0, 0] * cx + H_inv[0, 1] * cy + H_inv[0, 2]
        u1 = H_inv[1, 0] * cx + H_inv[1, 1] * cy + H_inv[1, 2]
        u2 = H_inv[2, 0] * cx + H_inv[2, 1] * cy + H_inv[2, 2]
        for k in range(8):
            for a in range(3):
                d[a] = (dH[k, a, 0] * u0 + dH[k, a, 1] * u1 + dH[k, a, 2] * u2) / u2
            row[k] = -(s0 * (d[0] - cx * d[2]) + s1 * (d[1] - cy * d[2]))
        row[8] = (coef[1] * (Pw - P) + coef[2] * (Pw - P) * g0 + coef[3] * (Pw - P) * g1
                  + coef[4] * (Bw - B)) / _BLUR_STEP_PX
        row[9], row[10], row[11], row[12], row[13] = 1.0, P, P * g0, P * g1, B
        r = pixels[i] - (coef[0] + coef[1] * P + coef[2] * P * g0 + coef[3] * P * g1 + coef[4] * B)
        for a in range(14):
            rhs[a] += row[a] * r
            for b in range(a, 14):
                N[a, b] += row[a] * row[b]
    for a in range(14):
        for b in range(a):
            N[a, b] = N[b, a]
    return N, rhs


def _gauss_newton_step(f: _FastRegion, template: np.ndarray, H: np.ndarray, dH: np.ndarray, blur: float,
                       s: int) -> np.ndarray:
    """One Gauss-Newton step of the fast fit at homography ``H`` (derivatives ``dH``) and blur:
    the update of the 8 corner coordinates, the blur and the 5 brightness terms (their values, not
    an update). The Jacobian by the corners is the predicted image's own gradient (in the
    distorted image, through the lens's local map) times the motion of each compared pixel's
    template point when a corner moves. The per-pixel work is compiled (numba): as numpy it was
    ~40 calls per iteration on arrays of a few thousand samples."""
    r = f.region
    ny, nx = r.shape
    H_inv = np.linalg.inv(H)
    mx, my = _template_maps(f.samples, H_inv, ny * s, nx * s)
    read = [cv2.remap(template[k], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=float(k))
            for k in (0, 1)]
    area = _pixel_areas(read[0], read[1], s)
    image = cv2.GaussianBlur(area, (0, 0), blur, borderType=cv2.BORDER_REPLICATE)
    wider = cv2.GaussianBlur(area, (0, 0), blur + _BLUR_STEP_PX, borderType=cv2.BORDER_REPLICATE)
    N, rhs, beyond = _brightness_system(image, f.index, r.gradient, r.pixels)
    coef = _normal_solution(N, rhs)
    gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
    N, rhs = _step_system(image, wider, gx, gy, f.index, r.gradient, r.pixels, f.centres, f.lens, H_inv, dH,
                          coef, beyond)
    return _normal_solution(N, rhs)


def fast_template_corners(gray: np.ndarray, corners_px: np.ndarray, dictionary: str, marker_id: int,
                          lens: LensMap, iterations: int = 3,
                          settings: TemplateFitSettings = FAST_SETTINGS) -> np.ndarray | None:
    """The (4, 2) corners (TL TR BR BL, px in ``gray``) of marker ``marker_id`` of ``dictionary``
    near ``corners_px`` (the edge fit's), re-measured by the template fit (module docstring):
    ``iterations`` Gauss-Newton steps through ``lens``. None when the marker with its
    margin is not wholly inside the image, the fit diverges or a corner would move more than
    ``settings.max_move_px``.

    Tracking's fit reads the template pre-blurred by a sample's area (cached per marker size,
    :func:`_area_template`) at ``settings.supersample`` x ``supersample`` points per pixel (2 x 2:
    a quarter of the body calibration's fit's reads) and takes the corners' Jacobian from the
    predicted image's own gradient (:func:`_gauss_newton_step`)."""
    _, modules = marker_template(dictionary, marker_id, settings.white_modules)
    f = _fast_region(gray, corners_px, modules, lens, settings)
    if f is None:
        return None
    start = f.region.start_px
    s = settings.supersample
    template = _area_template(dictionary, marker_id, settings.white_modules,
                              _area_steps(square_homography(start, modules), modules, f.lens, s))
    p = np.zeros(8)
    blur = settings.start_blur_px
    try:
        for _ in range(iterations):
            H, dH = square_homography_derivatives(start + p.reshape(4, 2), modules)
            delta = _gauss_newton_step(f, template, H, dH, blur, s)
            p = p + delta[:8]
            blur = float(np.clip(blur + delta[8], *_BLUR_RANGE_PX))
            if not np.isfinite(p).all() or np.abs(delta[:8]).max() < _CONVERGED_PX:
                break
    except (np.linalg.LinAlgError, cv2.error):  # a degenerate homography; a region OpenCV refuses
        return None
    if not np.isfinite(p).all() or np.abs(p).max() > settings.max_move_px:
        return None
    return distort_px(start + p.reshape(4, 2), lens.K, lens.dist)


def compile_template_fit() -> None:
    """Compile the template fit's kernels (or load them from numba's on-disk cache) for the
    argument types :func:`fast_template_corners` passes, by fitting one synthetic marker, so that
    no frame pays it: called at start-up, before the first frame (a
    :class:`cubetrack.detect.detector.Detector` with ``template`` corners does)."""
    image = np.full((72, 72), 220, np.uint8)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    image[18:54, 18:54] = np.where(cv2.aruco.generateImageMarker(dictionary, 0, 36, borderBits=1) == 0, 20, 220)
    corners = np.array([[17.5, 17.5], [53.5, 17.5], [53.5, 53.5], [17.5, 53.5]])
    fast_template_corners(image, corners, "DICT_4X4_50", 0, LensMap(None))
