"""A marker's corners measured by fitting its whole image: the template fit's shared core.

Edge fits (:func:`cubetrack.detect.edge_fit.refine_corners_edges`) locate each side of the
black border from the brightness profile across it. A profile also holds the cells next to the
border and, on an obliquely seen marker, they are within a pixel or two of the edge: under the
lens's blur a white cell beside the one-module border pulls the edge, by an amount that depends
on the marker's pattern and on how foreshortened it is (4-7x the template fit's corner error on
the realistic simulation, docs/history/accuracy.md "What better corners would buy").

A template fit instead predicts the whole marker image — its cells (from the dictionary), its
black border and a white margin, through the homography its corners give and the camera's lens
model, averaged over each pixel's area, blurred by a Gaussian of fitted width, times a
brightness that may vary linearly across the marker plus an offset — and moves the four corners
(in the undistorted image) until the prediction matches the pixels in least squares. Every
cell's edge then helps, none biases.

This module holds what every template fit shares — the marker's template image
(:func:`marker_template`), the square's homography (:func:`square_homography`), the lens
mapping (:func:`distort_px`, :class:`LensMap`) and the pixels a fit compares
(:func:`_region_start`, :func:`_region_arrays`: compiled, as the whole fit is but for a lens
model OpenCV alone knows and the cached templates) — and the tracking-time fit,
:func:`fast_template_corners`: Gauss-Newton
on the 8 corner coordinates and the blur with the brightness model solved jointly, the Jacobian
at pixel level (the predicted image's gradient, its blur's kernel differentiated, times the
homography mapping's analytic derivative at the pixel centre), the lens undistortion read from
a per-camera map. The calibration's fit (:func:`cubetrack.calib.marker_fit.template_fitted_corners`)
is :func:`fast_template_corners` with more samples per pixel and more iterations.
"""

from __future__ import annotations

import functools
import math
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
_BEYOND_MIN = 0.05  # the fast fit measures the brightness beyond the margin where a pixel sees this much of it
# LLVM's fast-math flags for the fit's four arithmetic loops (areas, blurs, both normal equations): fused
# multiply-adds, sums reordered (vectorised), reciprocals; not "no NaN / no inf", which would drop the
# fit's finiteness checks. Corners within 1e-8 px of the strict arithmetic's (docs/live.md, session 28).
_FAST_MATH = {"contract", "reassoc", "arcp", "nsz"}
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


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _homography_system(corners: np.ndarray, side: float) -> np.ndarray:
    """The 8x8 matrix of the homography from the square of ``side`` to ``corners`` (4, 2) (h22 = 1)."""
    A = np.zeros((8, 8))
    for i in range(4):
        x, y = _SQUARE[i, 0] * side, _SQUARE[i, 1] * side
        u, v = corners[i, 0], corners[i, 1]
        A[2 * i, 0], A[2 * i, 1], A[2 * i, 2], A[2 * i, 6], A[2 * i, 7] = x, y, 1.0, -u * x, -u * y
        A[2 * i + 1, 3], A[2 * i + 1, 4], A[2 * i + 1, 5], A[2 * i + 1, 6], A[2 * i + 1, 7] = x, y, 1.0, -v * x, -v * y
    return A


def _corner_array(corners: np.ndarray) -> np.ndarray:
    """A writable float64 (4, 2) copy of ``corners``: the compiled kernels' one argument type (numba
    types a read-only array apart, and a detection's corners are read-only)."""
    return np.array(corners, dtype=np.float64).reshape(4, 2)


def square_homography(corners: np.ndarray, side: float) -> np.ndarray:
    """The 3x3 homography taking the square (0, 0), (side, 0), (side, side), (0, side) to the
    (4, 2) ``corners`` (float64 throughout, unlike cv2.getPerspectiveTransform)."""
    c = _corner_array(corners)
    return np.append(np.linalg.solve(_homography_system(c, float(side)), c.ravel()), 1.0).reshape(3, 3)


def square_homography_derivatives(corners: np.ndarray, side: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`square_homography` and its derivatives (8, 3, 3) by the corners' 8 coordinates
    (x0, y0, x1, ...): differentiating ``A h = c`` by a corner coordinate leaves
    ``A dh = e_k w_i``, ``w_i`` the homogeneous scale at that corner."""
    return _homography_with_derivatives(_corner_array(corners), float(side))


class LensMap:
    """A camera's lens undistortion as a per-pixel map: the ideal pinhole pixel (of the same
    ``K``) of every pixel centre of its image (``intrinsics.width`` x ``height``) and a one-pixel
    border, float32, read bilinearly at any point (as ``cv2.remap`` reads it; compiled,
    :func:`_map_read`); a
    :class:`~cubetrack.detect.detector.Detector` keeps one per camera. Without intrinsics, the
    identity (the image taken as undistorted)."""

    def __init__(self, intrinsics: CameraIntrinsics | None):
        self.intrinsics = intrinsics
        self._samples: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}  # :meth:`samples`'
        if intrinsics is None:
            self.K, self.dist, self.map = np.eye(3), np.zeros(5), None
            self.K_inv: np.ndarray = np.eye(3)  # (:meth:`distort`'s)
            return
        self.K, self.dist = np.asarray(intrinsics.K, float), np.asarray(intrinsics.dist, float).ravel()
        self.K_inv = np.linalg.inv(self.K)
        xs, ys = np.meshgrid(np.arange(-1.0, intrinsics.width + 1.0), np.arange(-1.0, intrinsics.height + 1.0))
        self.map = undistort_points(np.stack([xs, ys], axis=-1), self.K, self.dist, self.K).astype(np.float32)

    def samples(self, s: int, shape: tuple[int, int],
                box: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray, int, int]:
        """Where a template fit keeps the undistorted centres of the ``s`` x ``s`` samples of each
        pixel of its region ``box`` (x0, y0, nx, ny) of an image of ``shape`` (height, width)
        (:func:`_filled_samples`): the samples (rows, cols, s s, 2: a pixel's together), which
        pixels have theirs (rows, cols) and the region's first pixel's place (column, row) in them. With a lens, this
        camera's table of the whole image, filled as fits first read a pixel and kept for the next
        fits (float32: :func:`_map_point` reads float32 values; pages untouched stay unallocated);
        without, room for the region alone (float64)."""
        x0, y0, nx, ny = box
        if self.map is None:
            return np.empty((ny, nx, s * s, 2)), np.zeros((ny, nx), np.bool_), 0, 0
        key = (s, *shape)
        table = self._samples.get(key)
        if table is None:
            height, width = shape
            table = self._samples[key] = (np.empty((height, width, s * s, 2), np.float32),
                                          np.zeros((height, width), np.bool_))
        return table[0], table[1], x0, y0

    def undistort(self, points_px: np.ndarray) -> np.ndarray:
        """Ideal pinhole pixels (..., 2) of distorted ones (within the image and its border),
        float64."""
        if self.map is None:
            return np.asarray(points_px, np.float64)
        flat = np.require(points_px, np.float64, ("C", "W")).reshape(-1, 2)  # writable: numba types read-only
        # arrays apart (a copy only when needed)
        return _map_read(self.map, flat).reshape(np.shape(points_px))

    def distort(self, points_px: np.ndarray) -> np.ndarray:
        """:func:`distort_px` through this lens: compiled for the 4 or 5 coefficients of OpenCV's
        model (:func:`_distorted`, the same values as ``cv2.projectPoints``), else OpenCV's."""
        if self.dist.shape[0] not in (4, 5):
            return distort_px(points_px, self.K, self.dist)
        flat = np.require(points_px, np.float64, ("C", "W")).reshape(-1, 2)
        return _distorted(flat, self.K, self.K_inv, self.dist).reshape(np.shape(points_px))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _distorted(points_px: np.ndarray, K: np.ndarray, K_inv: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(n, 2): ``cv2.projectPoints`` of the rays of ideal pinhole pixels ``points_px`` (n, 2) of
    ``K`` (``K_inv`` its inverse) through OpenCV's lens model with 4 or 5 coefficients ``dist``
    (k1 k2 p1 p2 [k3]), its arithmetic in its order (no skew: OpenCV reads fx, fy, cx, cy only)."""
    k1, k2, p1, p2 = dist[0], dist[1], dist[2], dist[3]
    k3 = dist[4] if dist.shape[0] > 4 else 0.0
    out = np.empty_like(points_px)
    for n in range(points_px.shape[0]):
        u, v = points_px[n, 0], points_px[n, 1]
        x = u * K_inv[0, 0] + v * K_inv[0, 1] + K_inv[0, 2]
        y = u * K_inv[1, 0] + v * K_inv[1, 1] + K_inv[1, 2]
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        a1, a2, a3 = 2 * x * y, r2 + 2 * x * x, r2 + 2 * y * y
        cdist = 1 + k1 * r2 + k2 * r4 + k3 * r6
        out[n, 0] = (x * cdist + p1 * a1 + p2 * a2) * K[0, 0] + K[0, 2]
        out[n, 1] = (y * cdist + p1 * a3 + p2 * a1) * K[1, 1] + K[1, 2]
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _map_read(table: np.ndarray, points_px: np.ndarray) -> np.ndarray:
    """(n, 2) float64: ``table`` (a :class:`LensMap`'s map) read at ``points_px`` (n, 2) by
    :func:`_map_point`."""
    out = np.empty((points_px.shape[0], 2))
    for n in range(points_px.shape[0]):
        out[n, 0], out[n, 1] = _map_point(table, points_px[n, 0], points_px[n, 1])
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _map_point(table: np.ndarray, x: float, y: float) -> tuple[float, float]:
    """``table`` (a :class:`LensMap`'s map: pixel (-1, -1) at [0, 0]) read bilinearly at (``x``,
    ``y``), its border replicated, as ``cv2.remap``'s ``INTER_LINEAR`` reads a float32 image at
    float32 points: the point rounded to 1/32 px, the result rounded to float32 (here without
    remap's 32767-column limit and its call overhead)."""
    rows, cols = table.shape[0], table.shape[1]
    qx = int(np.rint((np.float32(x) + np.float32(1.0)) * np.float32(32.0)))
    qy = int(np.rint((np.float32(y) + np.float32(1.0)) * np.float32(32.0)))
    fx, fy = np.float32((qx & 31) / 32.0), np.float32((qy & 31) / 32.0)
    c0, r0 = qx >> 5, qy >> 5
    ca, cb = min(max(c0, 0), cols - 1), min(max(c0 + 1, 0), cols - 1)
    ra, rb = min(max(r0, 0), rows - 1), min(max(r0 + 1, 0), rows - 1)
    top = table[ra, ca, 0] * (np.float32(1.0) - fx) + table[ra, cb, 0] * fx
    bottom = table[rb, ca, 0] * (np.float32(1.0) - fx) + table[rb, cb, 0] * fx
    u = np.float64(np.float32(top * (np.float32(1.0) - fy) + bottom * fy))
    top = table[ra, ca, 1] * (np.float32(1.0) - fx) + table[ra, cb, 1] * fx
    bottom = table[rb, ca, 1] * (np.float32(1.0) - fx) + table[rb, cb, 1] * fx
    return u, np.float64(np.float32(top * (np.float32(1.0) - fy) + bottom * fy))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _region_start(table: np.ndarray, corners_px: np.ndarray, modules: int,
                  margin: float) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray]:
    """A fit's start from the marker's distorted ``corners_px`` (4, 2, TL TR BR BL) through the
    lens map ``table`` (:func:`_map_point`; empty: the identity): whether they undistort, the
    undistorted corners (4, 2), the homography ``H0`` from the square of ``modules`` to them
    (:func:`square_homography`) and the undistorted ring (4, 2) ``margin`` modules around the
    marker (``cv2.perspectiveTransform``'s arithmetic)."""
    start = corners_px.copy() if table.shape[0] == 0 else _map_read(table, corners_px)
    H0, ring = np.eye(3), np.empty((4, 2))
    if not np.isfinite(start).all():
        return False, start, H0, ring
    h = np.linalg.solve(_homography_system(start, float(modules)), start.ravel())
    H0.ravel()[:8] = h
    for i in range(4):
        x = -margin if i in (0, 3) else modules + margin
        y = -margin if i in (0, 1) else modules + margin
        w = x * H0[2, 0] + y * H0[2, 1] + H0[2, 2]
        w = 1.0 / w if abs(w) > np.finfo(np.float32).eps else 0.0
        ring[i, 0] = (x * H0[0, 0] + y * H0[0, 1] + H0[0, 2]) * w
        ring[i, 1] = (x * H0[1, 0] + y * H0[1, 1] + H0[1, 2]) * w
    return True, start, H0, ring


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _region_arrays(table: np.ndarray, corners_px: np.ndarray, H0: np.ndarray, ring_px: np.ndarray, modules: int,
                   margin: float, width: int, height: int) -> tuple[bool, tuple[int, int, int, int], np.ndarray,
                                                                    np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                                    np.ndarray]:
    """The pixels a fit of the marker (distorted ``corners_px``, its homography ``H0`` and its
    ring ``ring_px`` (4, 2) in the distorted image, :func:`_region_start`) compares, through the
    lens map ``table``: whether its region (the ring's bounds and ``REGION_PAD_PX``, what the blur
    reads) lies wholly inside the ``width`` x ``height`` image; the region (x0, y0, nx, ny); the
    compared pixels (those whose centre lies on the marker or within ``margin`` modules of it):
    which (ny, nx), their flat indices (n,) in the region,
    their undistorted centres (n, 2) and their places across the region (n, 2,
    :func:`_compared_pixels`), the lens's local map (2, 2) at the marker's centre
    (:func:`_map_jacobian`; the identity without a lens) and at each compared pixel, the other way (n, 2, 2:
    undistorted px per distorted px, from its neighbours' centres)."""
    empty, no_spans = np.empty((0, 2)), np.empty((0, 2, 2))
    if not np.isfinite(ring_px).all():
        return (False, (0, 0, 0, 0), np.zeros((0, 0), np.bool_), np.empty(0, np.int64), empty, empty, np.eye(2),
                no_spans)
    x0 = int(np.floor(ring_px[:, 0].min())) - REGION_PAD_PX
    y0 = int(np.floor(ring_px[:, 1].min())) - REGION_PAD_PX
    x1 = int(np.ceil(ring_px[:, 0].max())) + REGION_PAD_PX + 1
    y1 = int(np.ceil(ring_px[:, 1].max())) + REGION_PAD_PX + 1
    if x0 < 0 or y0 < 0 or x1 > width or y1 > height:
        return (False, (0, 0, 0, 0), np.zeros((0, 0), np.bool_), np.empty(0, np.int64), empty, empty, np.eye(2),
                no_spans)
    nx, ny = x1 - x0, y1 - y0
    centres = _pixel_centres(table, x0, y0, nx, ny)
    fitted, gradient = _compared_pixels(centres, np.linalg.inv(H0), modules, margin, nx, ny)
    index = np.flatnonzero(fitted)
    lens = np.eye(2) if table.shape[0] == 0 else _map_jacobian(table, corners_px)
    spans = np.empty((len(index), 2, 2))  # undistorted px per pixel at each compared one: its neighbours' centres
    for k in range(len(index)):
        f = index[k]
        for a in range(2):
            spans[k, a, 0] = 0.5 * (centres[f + 1, a] - centres[f - 1, a])
            spans[k, a, 1] = 0.5 * (centres[f + nx, a] - centres[f - nx, a])
    return True, (x0, y0, nx, ny), fitted.reshape(ny, nx), index, centres[index], gradient, lens, spans


_NO_TABLE = np.zeros((0, 0, 2), np.float32)  # :func:`_pixel_centres`'s lens map of the identity (no lens)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _filled_samples(table: np.ndarray, x0: int, y0: int, s: int, samples: np.ndarray, have: np.ndarray, at_x: int,
                    at_y: int, need: np.ndarray) -> None:
    """Fill in ``samples`` (rows, cols, s s, 2) the centres (x, y) of ``s`` x ``s`` equal parts of
    each pixel of the region from (``x0``, ``y0``) that ``need`` (ny, nx) names and ``have``
    (rows, cols) does not (then marked there), undistorted through the lens map ``table``
    (:func:`_map_point`; an empty one: the identity); the region's first pixel is at column
    ``at_x``, row ``at_y`` of ``have`` (:meth:`LensMap.samples`)."""
    identity = table.shape[0] == 0
    ny, nx = need.shape
    for pi in range(ny):
        for pj in range(nx):
            if not need[pi, pj] or have[at_y + pi, at_x + pj]:
                continue
            have[at_y + pi, at_x + pj] = True
            for di in range(s):
                y = y0 + pi + (di + 0.5) / s - 0.5
                for dj in range(s):
                    x = x0 + pj + (dj + 0.5) / s - 0.5
                    k = di * s + dj
                    samples[at_y + pi, at_x + pj, k, 0], samples[at_y + pi, at_x + pj, k, 1] = (
                        (x, y) if identity else _map_point(table, x, y))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _needed(fitted: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """What a blur of ``half`` taps either side reads to give the compared pixels ``fitted`` (ny,
    nx): the pixels its pass along the rows must give (``fitted`` widened by ``half`` rows, within
    the region) and the pixel areas that pass reads (that, widened by ``half`` columns)."""
    ny, nx = fitted.shape
    rows, need = np.zeros((ny, nx), np.bool_), np.zeros((ny, nx), np.bool_)
    for i in range(ny):
        for j in range(nx):
            if fitted[i, j]:
                rows[max(i - half, 0):min(i + half + 1, ny), j] = True
    for i in range(ny):
        for j in range(nx):
            if rows[i, j]:
                need[i, max(j - half, 0):min(j + half + 1, nx)] = True
    return rows, need


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pixel_centres(table: np.ndarray, x0: int, y0: int, nx: int, ny: int) -> np.ndarray:
    """(ny nx, 2) the centres of the ``ny`` x ``nx`` pixels from (``x0``, ``y0``), row by row,
    undistorted through the lens map ``table`` (:func:`_map_point`; an empty one: the identity)."""
    identity = table.shape[0] == 0
    centres = np.empty((ny * nx, 2))
    for i in range(ny):
        for j in range(nx):
            x, y = float(x0 + j), float(y0 + i)
            centres[i * nx + j, 0], centres[i * nx + j, 1] = (x, y) if identity else _map_point(table, x, y)
    return centres


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _compared_pixels(centres_px: np.ndarray, H0_inv: np.ndarray, modules: int, margin: float, nx: int,
                     ny: int) -> tuple[np.ndarray, np.ndarray]:
    """Which of a region's ``ny`` x ``nx`` pixels (undistorted ``centres_px``, row by row) a fit
    compares — those whose centre lies on the marker (through ``H0_inv``, px -> modules) or within
    ``margin`` modules of it — and their places across the region (n, 2), each in [-0.5, 0.5)."""
    fitted = np.zeros(ny * nx, np.bool_)
    for n in range(ny * nx):
        x, y = centres_px[n, 0], centres_px[n, 1]
        w = H0_inv[2, 0] * x + H0_inv[2, 1] * y + H0_inv[2, 2]
        u = (H0_inv[0, 0] * x + H0_inv[0, 1] * y + H0_inv[0, 2]) / w
        v = (H0_inv[1, 0] * x + H0_inv[1, 1] * y + H0_inv[1, 2]) / w
        fitted[n] = -margin < u < modules + margin and -margin < v < modules + margin
    index = np.flatnonzero(fitted)
    gradient = np.empty((len(index), 2))
    for k in range(len(index)):
        gradient[k, 0] = (index[k] % nx - (nx - 1) / 2.0) / nx
        gradient[k, 1] = (index[k] // nx - (ny - 1) / 2.0) / ny
    return fitted, gradient


@dataclass(frozen=True, slots=True)
class TemplateFitSettings:
    """What every template fit of a marker is told.

    ``supersample``: samples per pixel along each axis (pixel area); ``white_modules``: the
    white margin every marker has around its black border at least (modules; beyond it the fit
    assumes some uniform brightness of its own); ``margin_modules``: how much of that margin is
    fitted (modules); ``start_blur_px``: the blur (Gaussian sigma, px) the fit starts from;
    ``max_move_px``: a corner moving farther than this from its start is a failed fit;
    ``blur_in_template``: each step predicts the compared pixels alone in closed form
    (:func:`_read_offsets`; ``supersample`` unused) instead of reading pixel areas and blurring them."""

    supersample: int = 3
    white_modules: float = 1.0
    margin_modules: float = 0.5
    start_blur_px: float = 0.8
    max_move_px: float = 1.5
    blur_in_template: bool = False


FAST_SETTINGS = TemplateFitSettings(supersample=2)  # tracking's fit (fast_template_corners)
# The same with the blur in the template (:func:`_read_offsets`, session 30): 1.5x cheaper per marker, corners
# no worse overall but worse head-on and on the clean scenes (docs/detection.md): not tracking's default.
READ_SETTINGS = TemplateFitSettings(supersample=2, blur_in_template=True)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _map_jacobian(table: np.ndarray, corners_px: np.ndarray) -> np.ndarray:
    """(2, 2): distorted pixels per undistorted pixel at the mean of ``corners_px`` (4, 2) (the
    lens's local linear map, from a :class:`LensMap`'s ``table`` one pixel either way)."""
    mid_x = (corners_px[0, 0] + corners_px[1, 0] + corners_px[2, 0] + corners_px[3, 0]) / 4.0
    mid_y = (corners_px[0, 1] + corners_px[1, 1] + corners_px[2, 1] + corners_px[3, 1]) / 4.0
    probe = _map_read(table, np.array([[mid_x, mid_y], [mid_x + 1.0, mid_y], [mid_x, mid_y + 1.0]]))
    J = np.empty((2, 2))
    J[:, 0], J[:, 1] = probe[1] - probe[0], probe[2] - probe[0]
    return np.ascontiguousarray(np.linalg.inv(J))  # C order, as numpy's: the fit's kernels take one layout


@functools.lru_cache(maxsize=256)
def _area_template(dictionary: str, marker_id: int, white_modules: float, steps: tuple[int, int]) -> np.ndarray:
    """(n, n, 2) float32: :func:`marker_template`'s two images blurred by a Gaussian of
    ``steps`` x ``_AREA_STEP`` template samples along x and y (a sample's area, see
    :func:`_area_steps`), so that reading them at a few points per pixel keeps the sub-pixel place
    of every cell edge; cached per marker and blur: per marker size."""
    template, _ = marker_template(dictionary, marker_id, white_modules)
    sx, sy = (max(k * _AREA_STEP, 0.01) for k in steps)
    out = np.stack([cv2.GaussianBlur(t, (0, 0), sigmaX=sx, sigmaY=sy, borderType=cv2.BORDER_REPLICATE)
                    for t in template], axis=-1)  # (n, n, 2): a bilinear read's four corners hold both images
    out.setflags(write=False)
    return out


def _area_steps(H: np.ndarray, modules: int, lens_jacobian: np.ndarray, supersample: int) -> tuple[int, int]:
    """The area of one of ``supersample`` x ``supersample`` samples of a pixel (a variance of
    1 / (12 s^2) px^2 along each axis) pulled back into the template through the homography ``H``
    and the lens at the marker's centre: its standard deviations along x and y in units of
    ``_AREA_STEP`` template samples."""
    sx, sy = _area_sigmas(H, float(modules), lens_jacobian, float(supersample))
    return int(round(sx)), int(round(sy))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _area_sigmas(H: np.ndarray, modules: float, lens_jacobian: np.ndarray, supersample: float) -> tuple[float, float]:
    """:func:`_area_steps` before rounding, compiled."""
    c = np.array([modules / 2.0, modules / 2.0, 1.0])
    h = H @ c
    J = lens_jacobian @ (H[:2, :2] - np.outer(h[:2] / h[2], H[2, :2])) / h[2]  # distorted px per module
    cov = np.linalg.inv(J.T @ J) * (TEMPLATE_RES ** 2 / (12.0 * supersample ** 2))
    return np.sqrt(cov[0, 0]) / _AREA_STEP, np.sqrt(cov[1, 1]) / _AREA_STEP


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST_MATH)
def _pixel_areas(template: np.ndarray, samples: np.ndarray, at_x: int, at_y: int, H_inv: np.ndarray,
                 need: np.ndarray, s: int) -> np.ndarray:
    """(ny, nx, 2) float32: each pixel's mean of its ``s`` x ``s`` samples' reads of both template
    images, where ``need`` (ny, nx) asks for it (elsewhere unset); a sample (undistorted px,
    ``samples`` (rows, cols, s s, 2), the region's first pixel's at column ``at_x``, row ``at_y``:
    :func:`_filled_samples`) reads them through the inverse homography ``H_inv``
    bilinearly, 0 and 1 beyond them
    (``cv2.remap``'s ``INTER_LINEAR`` and ``BORDER_CONSTANT``, at the exact point where OpenCV
    rounds it to 1/32 of a sample)."""
    rows, cols = template.shape[0], template.shape[1]
    ny, nx = need.shape
    out = np.empty((ny, nx, 2), np.float32)
    scale = 1.0 / (s * s)
    h00, h01, h02, h10, h11, h12 = H_inv[0, 0], H_inv[0, 1], H_inv[0, 2], H_inv[1, 0], H_inv[1, 1], H_inv[1, 2]
    h20, h21, h22 = H_inv[2, 0], H_inv[2, 1], H_inv[2, 2]  # locals: the loop reloads array elements
    for i in range(ny):
        for j in range(nx):
            if not need[i, j]:
                continue
            a = b = 0.0
            for di in range(s):
                for dj in range(s):
                    k = di * s + dj
                    x, y = np.float64(samples[at_y + i, at_x + j, k, 0]), np.float64(samples[at_y + i, at_x + j, k, 1])
                    z = h20 * x + h21 * y + h22
                    u = TEMPLATE_RES * (h00 * x + h01 * y + h02) / z + _TEMPLATE_SHIFT
                    v = TEMPLATE_RES * (h10 * x + h11 * y + h12) / z + _TEMPLATE_SHIFT
                    c0, r0 = int(np.floor(u)), int(np.floor(v))
                    fx, fy = u - c0, v - r0
                    if 0 <= c0 < cols - 1 and 0 <= r0 < rows - 1:
                        w00, w01, w10, w11 = (1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy
                        a += (w00 * template[r0, c0, 0] + w01 * template[r0, c0 + 1, 0]
                              + w10 * template[r0 + 1, c0, 0] + w11 * template[r0 + 1, c0 + 1, 0])
                        b += (w00 * template[r0, c0, 1] + w01 * template[r0, c0 + 1, 1]
                              + w10 * template[r0 + 1, c0, 1] + w11 * template[r0 + 1, c0 + 1, 1])
                    else:  # at or beyond the template's edge: the border values
                        a += _border_read(template, 0, r0, c0, fx, fy, 0.0)
                        b += _border_read(template, 1, r0, c0, fx, fy, 1.0)
            out[i, j, 0], out[i, j, 1] = a * scale, b * scale
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _border_read(image: np.ndarray, k: int, r0: int, c0: int, fx: float, fy: float, border: float) -> float:
    """A bilinear read of the (rows, cols, 2) ``image``'s image ``k`` between rows ``r0``, ``r0 + 1``
    and columns ``c0``, ``c0 + 1`` (weights ``fx``, ``fy``) where some of the four lie beyond it:
    those read ``border``."""
    total = 0.0
    for dr in range(2):
        for dc in range(2):
            r, c = r0 + dr, c0 + dc
            value = image[r, c, k] if 0 <= r < image.shape[0] and 0 <= c < image.shape[1] else border
            total += value * (fx if dc else 1.0 - fx) * (fy if dr else 1.0 - fy)
    return total


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _blurred(image: np.ndarray, sigma: float, rows: np.ndarray, fitted_t: np.ndarray) -> np.ndarray:
    """(ny, nx, 2) ``image`` blurred by a Gaussian of ``sigma`` px, border replicated:
    ``cv2.GaussianBlur(image, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)``'s kernel (4 sigma
    either side for a float image, :func:`_gaussian_kernel`), summed in float64; given where
    ``fitted_t`` (nx, ny) says, from the pass along the rows where ``rows`` (ny, nx) says
    (:func:`_needed`: ``image`` is read where that pass needs it, within the kernel's half)."""
    kernel, _ = _gaussian_kernel(sigma)
    return _filtered_across(_filtered_across(image, kernel, rows), kernel, fitted_t).astype(np.float32)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _gaussian_kernel(sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.GaussianBlur``'s kernel for ``sigma`` px (odd, 4 sigma either side, summing to 1) and,
    on the same taps, the slope of the image it blurs taken as linear between the pixel centres,
    blurred by the Gaussian (the derivative by the place it is centred on of the triangle's
    convolution with it: ``-(Phi(k + 1) - 2 Phi(k) + Phi(k - 1))`` at offset k, Phi the Gaussian's
    integral; half the difference of the two neighbours as sigma goes to 0)."""
    half = _kernel_half(sigma)
    offsets = np.arange(-half, half + 1).astype(np.float64)
    kernel = np.exp(-0.5 * (offsets / sigma) ** 2)
    kernel /= kernel.sum()
    slope = np.empty_like(offsets)
    scale = 1.0 / (sigma * np.sqrt(2.0))
    for k in range(len(offsets)):
        t = offsets[k]
        slope[k] = -0.5 * (math.erf((t + 1.0) * scale) - 2.0 * math.erf(t * scale) + math.erf((t - 1.0) * scale))
    return kernel, slope


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _kernel_half(sigma: float) -> int:
    """The taps either side of ``cv2.GaussianBlur``'s kernel for ``sigma`` px (float images)."""
    return (int(np.rint(sigma * 8.0 + 1.0)) | 1) // 2


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _blurred_with_gradient(image: np.ndarray, sigma: float, rows_mask: np.ndarray,
                           fitted_t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_blurred` of the (ny, nx, 2) ``image`` (float32) and that blurred image's gradient
    along x and y (float64): the blur's kernel differentiated along one axis (the derivative of
    the sampled Gaussian sum at each pixel, where half the difference of the two neighbours
    understates an edge blurred by ~0.8 px by ~20 %: the Gauss-Newton steps overshot, the fit
    was not converged at three; docs/detection.md), where :func:`_blurred` gives them."""
    kernel, slope = _gaussian_kernel(sigma)
    rows = _filtered_across(image, kernel, rows_mask)
    blurred = _filtered_across(rows, kernel, fitted_t).astype(np.float32)
    gy = _filtered_across(rows, slope, fitted_t)
    gx = _filtered_across(_filtered_across(image, slope, rows_mask), kernel, fitted_t)
    return blurred, gx, gy


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST_MATH)
def _filtered_across(image: np.ndarray, kernel: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(nx, ny, 2) float64: the (ny, nx, 2) ``image`` filtered along its rows by the odd-sized
    ``kernel``, border replicated, and transposed (so that a second call filters the columns);
    only where ``mask`` (ny, nx) says (elsewhere unset)."""
    ny, nx, half = image.shape[0], image.shape[1], len(kernel) // 2
    cols = np.minimum(np.maximum(np.arange(-half, nx + half), 0), nx - 1)  # replicated border
    out = np.empty((nx, ny, 2))
    for i in range(ny):
        for j in range(nx):
            if not mask[i, j]:
                continue
            a = b = 0.0
            for k in range(2 * half + 1):
                c = cols[j + k]
                a += kernel[k] * image[i, c, 0]
                b += kernel[k] * image[i, c, 1]
            out[j, i, 0], out[j, i, 1] = a, b
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST_MATH)
def _brightness_system(image: np.ndarray, index: np.ndarray, gradient: np.ndarray,
                       pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """The brightness model's normal equations (its columns per compared pixel: offset, the
    marker's brightness and its gradient across the region, the brightness beyond the margin;
    against the compared pixels' values) at the predicted ``image`` (ny, nx, 2), and whether any
    compared pixel sees the beyond-margin image (``_BEYOND_MIN``; if none, that column is left
    out: zero)."""
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
            ra = row[a]  # a local, as in _step_system
            rhs[a] += ra * pixels[i]
            for b in range(5):
                N[a, b] += ra * row[b]
    return N, rhs, beyond


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST_MATH)
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
    N, rhs, row = np.zeros((14, 14)), np.zeros(14), np.empty(14)
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
        inv = 1.0 / u2
        for k in range(8):
            e0 = dH[k, 0, 0] * u0 + dH[k, 0, 1] * u1 + dH[k, 0, 2] * u2
            e1 = dH[k, 1, 0] * u0 + dH[k, 1, 1] * u1 + dH[k, 1, 2] * u2
            e2 = dH[k, 2, 0] * u0 + dH[k, 2, 1] * u1 + dH[k, 2, 2] * u2
            row[k] = -(s0 * (e0 - cx * e2) + s1 * (e1 - cy * e2)) * inv
        row[8] = (coef[1] * (Pw - P) + coef[2] * (Pw - P) * g0 + coef[3] * (Pw - P) * g1
                  + coef[4] * (Bw - B)) / _BLUR_STEP_PX
        row[9], row[10], row[11], row[12], row[13] = 1.0, P, P * g0, P * g1, B
        r = pixels[i] - (coef[0] + coef[1] * P + coef[2] * P * g0 + coef[3] * P * g1 + coef[4] * B)
        for a in range(14):
            ra = row[a]  # a local: the matrix's stores would reload it
            rhs[a] += ra * r
            for b in range(a, 14):
                N[a, b] += ra * row[b]
    for a in range(14):
        for b in range(a):
            N[a, b] = N[b, a]
    return N, rhs


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _normal_solution(N: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The least-squares solution from its normal equations ``N x = rhs`` (``N = A^T A``,
    ``rhs = A^T b``); a column of ``A`` that vanishes (no pixel of the region lies beyond the
    marker's margin) gets 0, as the least-norm solution gives it. LinAlgError when the rest is
    rank-deficient."""
    norms = np.sqrt(np.diag(N))
    kept = np.flatnonzero(norms > 1e-9 * norms.max())
    sub = np.empty((len(kept), len(kept)))
    for a in range(len(kept)):
        for b in range(len(kept)):
            sub[a, b] = N[kept[a], kept[b]]
    x = np.zeros(N.shape[1])
    x[kept] = np.linalg.solve(sub, rhs[kept])
    return x


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _homography_with_derivatives(corners: np.ndarray, side: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`square_homography_derivatives`, compiled."""
    A = _homography_system(corners, side)
    A_inv = np.linalg.inv(A)
    h = np.ones(9)
    h[:8] = A_inv @ corners.ravel()
    dH = np.zeros((8, 9))
    for k in range(8):
        w = _SQUARE[k // 2, 0] * side * h[6] + _SQUARE[k // 2, 1] * side * h[7] + 1.0
        for r in range(8):
            dH[k, r] = A_inv[r, k] * w
    return h.reshape(3, 3), dH.reshape(8, 3, 3)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _gauss_newton_step(template: np.ndarray,
                       region: tuple[np.ndarray, int, int, int, np.ndarray, np.ndarray, int, int],
                       masks: tuple[np.ndarray, np.ndarray, np.ndarray], index: np.ndarray, gradient: np.ndarray,
                       pixels: np.ndarray, centres: np.ndarray, lens: np.ndarray, H: np.ndarray, dH: np.ndarray,
                       blur: float) -> np.ndarray:
    """One Gauss-Newton step of the fast fit at homography ``H`` (derivatives ``dH``) and blur:
    the update of the 8 corner coordinates, the blur and the 5 brightness terms (their values, not
    an update). The Jacobian by the corners is the predicted image's own gradient (in the
    distorted image, through the lens's local map) times the motion of each compared pixel's
    template point when a corner moves. Compiled whole (numba): as OpenCV calls and numpy it was
    ~0.45 ms per step on 30 px markers, nearly all of it per-call overhead. Only what the blurs
    need for the compared pixels is read and filtered (``masks``: :func:`_needed`'s two for the
    wider blur's reach, the larger, and the compared pixels (nx, ny); the ``region``'s samples,
    :func:`_fitted_offsets`, filled as they are first read)."""
    table, x0, y0, s, samples, have, at_x, at_y = region
    rows, need, fitted_t = masks
    _filled_samples(table, x0, y0, s, samples, have, at_x, at_y, need)
    H_inv = np.linalg.inv(H)
    area = _pixel_areas(template, samples, at_x, at_y, H_inv, need, s)
    image, gx, gy = _blurred_with_gradient(area, blur, rows, fitted_t)
    wider = _blurred(area, blur + _BLUR_STEP_PX, rows, fitted_t)
    N, rhs, beyond = _brightness_system(image, index, gradient, pixels)
    coef = _normal_solution(N, rhs)
    N, rhs = _step_system(image, wider, gx, gy, index, gradient, pixels, centres, lens, H_inv, dH, coef, beyond)
    return _normal_solution(N, rhs)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fitted_offsets(template: np.ndarray, table: np.ndarray, box: tuple[int, int], s: int,
                    store: tuple[np.ndarray, np.ndarray, int, int], fitted: np.ndarray, index: np.ndarray,
                    gradient: np.ndarray, pixels: np.ndarray, centres: np.ndarray, lens: np.ndarray,
                    start: np.ndarray, modules: int, blur: float, iterations: int) -> np.ndarray:
    """The fast fit's Gauss-Newton iterations from the undistorted corners ``start`` (4, 2): the
    corners' offsets (8,) from it (NaN where it diverged); LinAlgError on a degenerate homography.
    ``store``: where the ``s`` x ``s`` samples of the pixels of the region whose corner is ``box``
    (x0, y0) are kept (:meth:`LensMap.samples`), undistorted through the lens map ``table`` as
    the steps first read them."""
    p = np.zeros(8)
    region = (table, box[0], box[1], s, *store)
    fitted_t = np.ascontiguousarray(fitted.T)
    half = -1
    rows = need = fitted
    for _ in range(iterations):
        if _kernel_half(blur + _BLUR_STEP_PX) != half:  # the wider blur's reach: the larger
            half = _kernel_half(blur + _BLUR_STEP_PX)
            rows, need = _needed(fitted, half)
        H, dH = _homography_with_derivatives(start + p.reshape(4, 2), float(modules))
        delta = _gauss_newton_step(template, region, (rows, need, fitted_t), index, gradient, pixels, centres, lens,
                                   H, dH, blur)
        p = p + delta[:8]
        blur = min(max(blur + delta[8], _BLUR_RANGE_PX[0]), _BLUR_RANGE_PX[1])
        if not np.isfinite(p).all() or np.abs(delta[:8]).max() < _CONVERGED_PX:
            break
    return p


# The blur in the template (session 30, issue 31). The fit above predicts the marker image on the region's pixel
# grid (each pixel's area read from a pre-blurred template, then blurred in the image with its gradient and a
# wider blur: ~1,100 pixel areas and three filter passes per step on a ~21 px marker). Its template is piecewise
# constant on the module grid (cells, border, margin, what lies beyond), so the same image blurred by a Gaussian
# is a sum of products of normal integrals along the two template axes. Here each compared pixel reads that sum
# at its undistorted centre directly, with its gradient and its derivative by the blur, in closed form: the blur
# (sigma px), the pixel's area (1/12 px^2, a box taken as a Gaussian of its variance) and the template's own
# smoothing (``_TEMPLATE_SMOOTHING``) pulled back into the template through the homography and the lens at that
# pixel. Only the covariance's diagonal is kept: exact across every cell edge (all along the template's axes),
# approximate where two edges meet.
_TEMPLATE_SMOOTHING = 0.7 / TEMPLATE_RES  # modules: marker_template's Gaussian (0.7 samples)
_READ_REACH = 5.0  # standard deviations: a cell edge farther than this from a read is taken as wholly passed
_NORMAL_STEPS = 256  # the normal integral and density tabulated per standard deviation (linear reads: 5e-7 off)


@functools.lru_cache(maxsize=1)
def _normal_table() -> np.ndarray:
    """(n, 2): the standard normal integral and density at ``1 / _NORMAL_STEPS`` steps over +-``_READ_REACH``
    (and one step beyond), read linearly by :func:`_interval_weights` (math.erf and math.exp per cell edge
    were half of a step's reads)."""
    z = np.arange(-_READ_REACH * _NORMAL_STEPS, _READ_REACH * _NORMAL_STEPS + 2) / _NORMAL_STEPS
    table = np.stack([0.5 * (1.0 + np.vectorize(math.erf)(z / math.sqrt(2.0))),
                      np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)], axis=-1)
    table.setflags(write=False)
    return table


@functools.lru_cache(maxsize=256)
def _module_cells(dictionary: str, marker_id: int, white_modules: float) -> tuple[np.ndarray, np.ndarray]:
    """The marker ``marker_id`` of ``dictionary`` as :func:`_blurred_reads` reads it: its reflectance on the
    module grid extended by the white margin and what lies beyond, ((modules + 4) x (modules + 4): beyond,
    margin, the cells with the border, margin, beyond; 0 beyond, 1 on the margin) and the edges between those
    intervals along either axis (modules + 3, in modules: -white_modules, 0, 1, ..., modules, modules +
    white_modules)."""
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    modules = d.markerSize + 2
    cells = np.zeros((modules + 4, modules + 4))
    cells[1:-1, 1:-1] = 1.0
    cells[2:-2, 2:-2] = cv2.aruco.generateImageMarker(d, marker_id, modules, borderBits=1) / 255.0
    edges = np.concatenate([[-white_modules], np.arange(modules + 1.0), [modules + white_modules]])
    cells.setflags(write=False)
    edges.setflags(write=False)
    return cells, edges


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST_MATH)
def _interval_weights(t: float, spread: float, edges: np.ndarray, normal: np.ndarray, w: np.ndarray,
                      dw: np.ndarray, sw: np.ndarray) -> tuple[int, int]:
    """How much of a Gaussian of standard deviation ``spread`` centred at ``t`` falls in each interval
    between ``edges`` (the first interval before the first edge, the last after the last; the normal
    integral and density read from ``normal``, :func:`_normal_table`): ``w``, its
    derivative by ``t`` (``dw``) and by ``spread`` (``sw``), filled between the first and the last
    interval it reaches (returned; the rest unset)."""
    reach = _READ_REACH * spread
    n = edges.shape[0]
    lo = 0
    while lo < n and edges[lo] <= t - reach:
        lo += 1
    hi = lo
    while hi < n and edges[hi] < t + reach:
        hi += 1
    # edges lo .. hi - 1 lie within reach: intervals lo .. hi
    below, d_below, s_below = 0.0, 0.0, 0.0  # the normal integral up to the last edge, and its derivatives
    inv = 1.0 / spread
    last = normal.shape[0] - 2
    for k in range(lo, hi):
        z = (edges[k] - t) * inv
        at = (z + _READ_REACH) * _NORMAL_STEPS
        j = min(max(int(at), 0), last)
        frac = at - j
        F = normal[j, 0] + frac * (normal[j + 1, 0] - normal[j, 0])
        f = (normal[j, 1] + frac * (normal[j + 1, 1] - normal[j, 1])) * inv
        w[k], dw[k], sw[k] = F - below, -f - d_below, -f * z - s_below
        below, d_below, s_below = F, -f, -f * z
    w[hi], dw[hi], sw[hi] = 1.0 - below, -d_below, -s_below
    return lo, hi


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST_MATH)
def _blurred_reads(cells: np.ndarray, edges: np.ndarray, normal: np.ndarray, centres: np.ndarray,
                   H_inv: np.ndarray, spans: np.ndarray, blur: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The predicted image at the compared pixels (undistorted ``centres`` (n, 2)): the template
    (``cells``, ``edges``: :func:`_module_cells`; the marker's image and the indicator of what lies beyond
    its margin) at each pixel's template point (``H_inv``: undistorted px -> modules), blurred by a
    Gaussian of ``blur`` px in the distorted image, with the pixel's area and the template's smoothing
    through the lens; (n, 2) values, (n, 2, 2) their gradient
    (undistorted px: [pixel, image, x / y]) and (n, 2) their derivative by ``blur``. ``spans`` (n, 2, 2):
    undistorted px per distorted px at each pixel (:func:`_region_arrays`)."""
    n, size = centres.shape[0], cells.shape[0]
    values, gradient, by_blur = np.empty((n, 2)), np.empty((n, 2, 2)), np.empty((n, 2))
    wx, dwx, swx = np.zeros(size), np.zeros(size), np.zeros(size)
    wy, dwy, swy = np.zeros(size), np.zeros(size), np.zeros(size)
    variance = blur * blur + 1.0 / 12.0
    smoothing = _TEMPLATE_SMOOTHING * _TEMPLATE_SMOOTHING
    last = edges.shape[0] - 1
    for i in range(n):
        cx, cy = centres[i, 0], centres[i, 1]
        u0 = H_inv[0, 0] * cx + H_inv[0, 1] * cy + H_inv[0, 2]
        u1 = H_inv[1, 0] * cx + H_inv[1, 1] * cy + H_inv[1, 2]
        inv = 1.0 / (H_inv[2, 0] * cx + H_inv[2, 1] * cy + H_inv[2, 2])
        u, v = u0 * inv, u1 * inv
        # d: modules per undistorted px at the pixel; a = d spans: modules per distorted px
        d00, d01 = (H_inv[0, 0] - u * H_inv[2, 0]) * inv, (H_inv[0, 1] - u * H_inv[2, 1]) * inv
        d10, d11 = (H_inv[1, 0] - v * H_inv[2, 0]) * inv, (H_inv[1, 1] - v * H_inv[2, 1]) * inv
        a00 = d00 * spans[i, 0, 0] + d01 * spans[i, 1, 0]
        a01 = d00 * spans[i, 0, 1] + d01 * spans[i, 1, 1]
        a10 = d10 * spans[i, 0, 0] + d11 * spans[i, 1, 0]
        a11 = d10 * spans[i, 0, 1] + d11 * spans[i, 1, 1]
        ax, ay = a00 * a00 + a01 * a01, a10 * a10 + a11 * a11
        sx, sy = math.sqrt(variance * ax + smoothing), math.sqrt(variance * ay + smoothing)
        ix0, ix1 = _interval_weights(u, sx, edges, normal, wx, dwx, swx)
        iy0, iy1 = _interval_weights(v, sy, edges, normal, wy, dwy, swy)
        P = Pu = Pv = Psx = Psy = Puv = Pusv = Psuv = Pss = 0.0
        for r in range(iy0, iy1 + 1):
            a = b = c = 0.0
            for q in range(ix0, ix1 + 1):
                a += cells[r, q] * wx[q]
                b += cells[r, q] * dwx[q]
                c += cells[r, q] * swx[q]
            P += wy[r] * a
            Pu += wy[r] * b
            Psx += wy[r] * c
            Pv += dwy[r] * a
            Psy += swy[r] * a
            Puv += dwy[r] * b
            Pusv += dwy[r] * c
            Psuv += swy[r] * b
            Pss += swy[r] * c
        # the covariance's off-diagonal, to second order: d/dcov_uv = d2/du dv, and d2/du2 = d/ds / s
        cov = variance * (a00 * a10 + a01 * a11)
        P += cov * Puv + 0.5 * cov * cov * Pss / (sx * sy)
        Pu += cov * Pusv / sx
        Pv += cov * Psuv / sy
        # beyond the margin: 1 - (the share within the margin along x) (along y)
        Nx = Ny = Nxu = Nyv = Nxs = Nys = 0.0
        for q in range(max(ix0, 1), min(ix1, last) + 1):
            Nx, Nxu, Nxs = Nx + wx[q], Nxu + dwx[q], Nxs + swx[q]
        for r in range(max(iy0, 1), min(iy1, last) + 1):
            Ny, Nyv, Nys = Ny + wy[r], Nyv + dwy[r], Nys + swy[r]
        dsx, dsy = blur * ax / sx, blur * ay / sy  # the spreads' derivatives by the blur
        values[i, 0] = P
        values[i, 1] = 1.0 - Nx * Ny - cov * Nxu * Nyv - 0.5 * cov * cov * Nxs * Nys / (sx * sy)
        gradient[i, 0, 0], gradient[i, 0, 1] = Pu * d00 + Pv * d10, Pu * d01 + Pv * d11
        Bu, Bv = -Nxu * Ny, -Nx * Nyv
        gradient[i, 1, 0], gradient[i, 1, 1] = Bu * d00 + Bv * d10, Bu * d01 + Bv * d11
        by_blur[i, 0], by_blur[i, 1] = Psx * dsx + Psy * dsy, -(Nxs * Ny * dsx + Nx * Nys * dsy)
    return values, gradient, by_blur


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath=_FAST_MATH)
def _read_systems(values: np.ndarray, grads: np.ndarray, by_blur: np.ndarray, gradient: np.ndarray,
                  pixels: np.ndarray, centres: np.ndarray, H_inv: np.ndarray,
                  dH: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One Gauss-Newton step's normal equations from :func:`_blurred_reads`' predictions: the brightness
    model's first (as :func:`_brightness_system`, solved here), then the 14 columns' (as
    :func:`_step_system`: the 8 corners' through each pixel's motion when a corner moves, the blur's, the
    5 brightness terms') against the residual at that brightness."""
    n = values.shape[0]
    seen = 0.0
    for i in range(n):
        seen = max(seen, values[i, 1])
    beyond = seen >= _BEYOND_MIN
    N, rhs, row = np.zeros((5, 5)), np.zeros(5), np.empty(5)
    for i in range(n):
        P = values[i, 0]
        row[0], row[1], row[2], row[3] = 1.0, P, P * gradient[i, 0], P * gradient[i, 1]
        row[4] = values[i, 1] if beyond else 0.0
        for a in range(5):
            ra = row[a]
            rhs[a] += ra * pixels[i]
            for b in range(5):
                N[a, b] += ra * row[b]
    coef = _normal_solution(N, rhs)
    N, rhs, row = np.zeros((14, 14)), np.zeros(14), np.empty(14)
    c4 = coef[4] if beyond else 0.0
    for i in range(n):
        g0, g1 = gradient[i, 0], gradient[i, 1]
        P = values[i, 0]
        B = values[i, 1] if beyond else 0.0
        gain = coef[1] + coef[2] * g0 + coef[3] * g1
        s0 = grads[i, 0, 0] * gain + grads[i, 1, 0] * c4
        s1 = grads[i, 0, 1] * gain + grads[i, 1, 1] * c4
        cx, cy = centres[i, 0], centres[i, 1]
        u0 = H_inv[0, 0] * cx + H_inv[0, 1] * cy + H_inv[0, 2]
        u1 = H_inv[1, 0] * cx + H_inv[1, 1] * cy + H_inv[1, 2]
        u2 = H_inv[2, 0] * cx + H_inv[2, 1] * cy + H_inv[2, 2]
        for k in range(8):
            e0 = dH[k, 0, 0] * u0 + dH[k, 0, 1] * u1 + dH[k, 0, 2] * u2
            e1 = dH[k, 1, 0] * u0 + dH[k, 1, 1] * u1 + dH[k, 1, 2] * u2
            e2 = dH[k, 2, 0] * u0 + dH[k, 2, 1] * u1 + dH[k, 2, 2] * u2
            row[k] = -(s0 * (e0 - cx * e2) + s1 * (e1 - cy * e2))
        row[8] = gain * by_blur[i, 0] + c4 * by_blur[i, 1]
        row[9], row[10], row[11], row[12], row[13] = 1.0, P, P * g0, P * g1, B
        r = pixels[i] - (coef[0] + gain * P + c4 * B)
        for a in range(14):
            ra = row[a]
            rhs[a] += ra * r
            for b in range(a, 14):
                N[a, b] += ra * row[b]
    return _symmetric(N), rhs


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _symmetric(N: np.ndarray) -> np.ndarray:
    """``N`` with its lower triangle copied from its upper one (in place)."""
    for a in range(N.shape[0]):
        for b in range(a):
            N[a, b] = N[b, a]
    return N


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _read_offsets(cells: np.ndarray, edges: np.ndarray, normal: np.ndarray, gradient: np.ndarray, pixels: np.ndarray,
                  centres: np.ndarray, spans: np.ndarray, start: np.ndarray, modules: int, blur: float,
                  iterations: int) -> np.ndarray:
    """:func:`_fitted_offsets` with the blur in the template: each step predicts the compared pixels
    alone (:func:`_blurred_reads`); no pixel areas, no filter passes, no sample table."""
    p = np.zeros(8)
    for _ in range(iterations):
        H, dH = _homography_with_derivatives(start + p.reshape(4, 2), float(modules))
        H_inv = np.linalg.inv(H)
        values, grads, by_blur = _blurred_reads(cells, edges, normal, centres, H_inv, spans, blur)
        N, rhs = _read_systems(values, grads, by_blur, gradient, pixels, centres, H_inv, dH)
        delta = _normal_solution(N, rhs)
        p = p + delta[:8]
        blur = min(max(blur + delta[8], _BLUR_RANGE_PX[0]), _BLUR_RANGE_PX[1])
        if not np.isfinite(p).all() or np.abs(delta[:8]).max() < _CONVERGED_PX:
            break
    return p


def fast_template_corners(gray: np.ndarray, corners_px: np.ndarray, dictionary: str, marker_id: int,
                          lens: LensMap, iterations: int = 2,
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
    table = _NO_TABLE if lens.map is None else lens.map
    corners = _corner_array(corners_px)
    s, m = settings.supersample, settings.margin_modules
    try:
        ok, start, H0, ring = _region_start(table, corners, modules, m)
        if not ok:
            return None
        ok, (x0, y0, nx, ny), fitted, index, centres, gradient, local, spans = _region_arrays(
            table, corners, H0, lens.distort(ring), modules, m, gray.shape[1], gray.shape[0])
        if not ok:
            return None
        pixels = np.take(gray[y0:y0 + ny, x0:x0 + nx], index).astype(np.float64)
        if settings.blur_in_template:
            cells, edges = _module_cells(dictionary, marker_id, settings.white_modules)
            p = _read_offsets(cells, edges, _normal_table(), gradient, pixels, centres, spans, start, modules,
                              settings.start_blur_px, iterations)
        else:
            template = _area_template(dictionary, marker_id, settings.white_modules,
                                      _area_steps(H0, modules, local, s))
            store = lens.samples(s, gray.shape[:2], (x0, y0, nx, ny))
            p = _fitted_offsets(template, table, (x0, y0), s, store, fitted, index, gradient, pixels, centres,
                                local, start, modules, settings.start_blur_px, iterations)
    except np.linalg.LinAlgError:  # a degenerate homography
        return None
    if not np.isfinite(p).all() or np.abs(p).max() > settings.max_move_px:
        return None
    return lens.distort(start + p.reshape(4, 2))


def compile_template_fit() -> None:
    """Compile the template fit's kernels (or load them from numba's on-disk cache) for the
    argument types :func:`fast_template_corners` passes, by fitting one synthetic marker, so that
    no frame pays it: called at start-up, before the first frame (a
    :class:`cubetrack.detect.detector.Detector` with ``template`` corners does)."""
    image = np.full((72, 72), 220, np.uint8)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    image[18:54, 18:54] = np.where(cv2.aruco.generateImageMarker(dictionary, 0, 36, borderBits=1) == 0, 20, 220)
    corners = np.array([[17.5, 17.5], [53.5, 17.5], [53.5, 53.5], [17.5, 53.5]])
    pinhole = CameraIntrinsics(72, 72, np.array([[80.0, 0.0, 35.5], [0.0, 80.0, 35.5], [0.0, 0.0, 1.0]]), np.zeros(5))
    for lens in (LensMap(None), LensMap(pinhole)):  # the identity and a lens map's reads
        fast_template_corners(image, corners, "DICT_4X4_50", 0, lens)
