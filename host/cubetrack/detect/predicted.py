"""Markers where the tracker predicts them: found without OpenCV's candidate search.

When the fusion predicts a cube well, its markers' corners in the next frame are known to a pixel
or two. :func:`predicted_view` projects them (the tracker calls it per camera and robot while
planning a frame); the detector (:meth:`Detector.find <cubetrack.detect.detector.Detector.find>`
with ``predicted``) fits each predicted quad's edges with the compiled edge fit
(:func:`cubetrack.detect.edge_fit.refine_corners_edges`, from the predicted corners instead of
OpenCV's), then :func:`marker_reads` reads the marker's bit cells at the fitted corners, as
OpenCV's dictionary identification does: the border cells must be black (at most
``int(0.35 x markerSize^2)`` white, OpenCV's ``maxErroneousBitsInBorderRate``) and the inner cells
the predicted id's bits in the predicted rotation, with at most ``int(maxCorrectionBits x
errorCorrectionRate)`` wrong. A marker that fails (small and oblique, moved off its prediction,
another id, occluded) is searched for by OpenCV in a small box around its prediction
(:func:`marker_box`); one not found there either is not seen, as a search of the regions would not
see it. One predicted with cells narrower than a pixel (:func:`resolvable_markers`) is not searched
for: its bits cannot be told apart in the image, by this reader or by OpenCV's. When no marker at
all reads at its prediction, nothing confirms it and the detector searches the regions as before.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numba
import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import transform_points
from cubetrack.core.layout import CubeLayout
from cubetrack.core.records import Detection
from cubetrack.detect.quads import corners_finite

if TYPE_CHECKING:
    from cubetrack.detect.detector import DetectorParams

BORDER_ERROR_RATE = 0.35   # OpenCV's DetectorParameters.maxErroneousBitsInBorderRate default
MIN_CELL_CONTRAST = 30.0   # grey levels between the darkest and brightest cell of a readable marker
_CELL_SAMPLES = (-0.25, 0.0, 0.25)   # 3 x 3 samples per cell, module units from its centre (the middle half)
_NO_ROTATION = np.zeros(3)  # (and no translation) for cv2.projectPoints of camera-frame points (a tilted sensor)
NEAREST_M = 0.05   # a cube predicted closer to the camera than this is not projected (the whole frame is searched)
MIN_BOX_PX = 16    # a predicted box narrower or lower than this (cut to the image) is out of view
MIN_PX_PER_MODULE = 1.0   # a marker's shortest side over its cells across, below which its bits are not resolved
COMPILED_DISTORTION = 12  # projected_px takes up to this many coefficients (OpenCV's tilted sensor, 14: cv2's own)


@dataclass(frozen=True, slots=True)
class PredictedView:
    """Where one predicted cube lies in one camera's image: the box to search (x0, y0, x1, y1,
    pixels, end exclusive; None when it is out of view) and its markers' projected corners."""

    box: tuple[int, int, int, int] | None
    markers: tuple[Detection, ...]


def predicted_view(T_cam_cube: np.ndarray, layout: CubeLayout, intrinsics: CameraIntrinsics, margin_m: float,
                   detector: DetectorParams) -> PredictedView | None:
    """The cube of ``layout`` at ``T_cam_cube`` projected into the camera: the box around its corners,
    grown by ``margin_m`` of motion at its nearest corner (+ 8 px) and cut to the image, and the
    markers a search would find there (:func:`predicted_markers`, with ``detector``'s perimeter and
    border limits). None when a corner is within ``NEAREST_M`` of the camera's plane."""
    pc = transform_points(T_cam_cube, layout.corners_m.reshape(-1, 3))
    nearest_m = float(pc[:, 2].min())
    if nearest_m <= NEAREST_M:
        return None
    dist = intrinsics.dist.ravel()
    if len(dist) <= COMPILED_DISTORTION:   # (cv2.projectPoints' pixels to the bit; it also makes a Jacobian)
        px = projected_px(pc, intrinsics.K, dist)
    else:
        px = cv2.projectPoints(pc, _NO_ROTATION, _NO_ROTATION, intrinsics.K, dist)[0].reshape(-1, 2)
    grow = float(intrinsics.K[0, 0]) * margin_m / nearest_m + 8.0
    width, height = intrinsics.width, intrinsics.height
    x0, y0, x1, y1 = _grown_box(px, grow, width, height)
    if x1 - x0 < MIN_BOX_PX or y1 - y0 < MIN_BOX_PX:
        return PredictedView(None, ())
    markers = predicted_markers(px, layout, width, height, detector.min_marker_perimeter_rate * max(width, height),
                                detector.min_distance_to_border_px)
    return PredictedView((x0, y0, x1, y1), markers)


@numba.njit(cache=True, nogil=True)
def projected_px(points: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:  # pragma: no cover
    """(N, 2) pixels of camera-frame points (N, 3) through camera matrix ``K`` and up to
    ``COMPILED_DISTORTION`` coefficients ``dist`` (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]]): the
    arithmetic of ``cv2.projectPoints`` (its ``cvProjectPoints2Internal``) with no rotation nor
    translation, in its order (``r6 = r4 r2``, the rational term as a reciprocal), so the same
    pixels to the bit (a test holds them so for each coefficient count), without its Jacobian."""
    k = np.zeros(12)
    k[:dist.shape[0]] = dist
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    out = np.empty((points.shape[0], 2))
    for i in range(points.shape[0]):
        z = points[i, 2]
        iz = 1.0 / z if z != 0.0 else 1.0
        x, y = points[i, 0] * iz, points[i, 1] * iz
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        a1, a2, a3 = 2.0 * x * y, r2 + 2.0 * x * x, r2 + 2.0 * y * y
        cdist = 1.0 + k[0] * r2 + k[1] * r4 + k[4] * r6
        icdist2 = 1.0 / (1.0 + k[5] * r2 + k[6] * r4 + k[7] * r6)
        out[i, 0] = (x * cdist * icdist2 + k[2] * a1 + k[3] * a2 + k[8] * r2 + k[9] * r4) * fx + cx
        out[i, 1] = (y * cdist * icdist2 + k[2] * a3 + k[3] * a1 + k[10] * r2 + k[11] * r4) * fy + cy
    return out


@numba.njit(cache=True, nogil=True)
def _grown_box(px: np.ndarray, grow: float, width: int, height: int) -> tuple[int, int, int, int]:
    """The box (x0, y0, x1, y1; pixels, end exclusive) around the points ``px`` (N, 2), grown by
    ``grow`` px on every side (out to whole pixels) and cut to a ``width`` x ``height`` image."""
    lo_x, lo_y, hi_x, hi_y = px[0, 0], px[0, 1], px[0, 0], px[0, 1]
    for i in range(1, px.shape[0]):
        lo_x, hi_x = min(lo_x, px[i, 0]), max(hi_x, px[i, 0])
        lo_y, hi_y = min(lo_y, px[i, 1]), max(hi_y, px[i, 1])
    return (max(int(math.floor(lo_x - grow)), 0), max(int(math.floor(lo_y - grow)), 0),
            min(int(math.ceil(hi_x + grow)), width), min(int(math.ceil(hi_y + grow)), height))


@numba.njit(cache=True, nogil=True)
def _facing_quads(quads: np.ndarray, min_perimeter_px: float, border_px: float, width: int, height: int,
                  area: np.ndarray) -> np.ndarray:
    """(M,) bool for the quads (M, 4, 2) that are clockwise and convex in the image, at least
    ``min_perimeter_px`` around and ``border_px`` inside the image; ``area`` (M,): their areas."""
    keep = np.zeros(quads.shape[0], dtype=np.bool_)
    for q in range(quads.shape[0]):
        perimeter, twice_area, convex, inside = 0.0, 0.0, True, True
        for c in range(4):
            x, y = quads[q, c, 0], quads[q, c, 1]
            x1, y1 = quads[q, (c + 1) % 4, 0], quads[q, (c + 1) % 4, 1]
            ex, ey, fx, fy = x1 - x, y1 - y, quads[q, (c + 2) % 4, 0] - x1, quads[q, (c + 2) % 4, 1] - y1
            convex &= ex * fy - ey * fx > 0.0      # a right turn at every corner: clockwise (y down)
            inside &= border_px <= x <= width - 1 - border_px and border_px <= y <= height - 1 - border_px
            perimeter += math.hypot(ex, ey)
            twice_area += x * y1 - y * x1
        area[q] = 0.5 * twice_area
        keep[q] = convex and inside and perimeter >= min_perimeter_px
    return keep


def predicted_markers(quads_px: np.ndarray, layout: CubeLayout, width: int, height: int,
                      min_perimeter_px: float, border_px: float) -> tuple[Detection, ...]:
    """The markers of ``layout`` whose projected corners ``quads_px`` ((M x 4, 2) or (M, 4, 2), the
    layout's order) face the camera (a clockwise convex quad in the image), are at least
    ``min_perimeter_px`` around and lie ``border_px`` inside the ``width`` x ``height`` image, as
    Detections (the area is the projected quad's)."""
    quads = np.array(quads_px, dtype=np.float64).reshape(-1, 4, 2)   # a copy: the Detections' corners
    area = np.empty(len(quads))
    keep = _facing_quads(quads, float(min_perimeter_px), float(border_px), int(width), int(height), area)
    quads.setflags(write=False)   # after the call: a read-only array is another type to numba (another compile)
    ids, names, areas = layout.marker_ids.tolist(), layout.marker_dictionaries, area.tolist()
    return tuple(Detection(ids[i], quads[i], areas[i], names[i]) for i, facing in enumerate(keep.tolist()) if facing)


@functools.lru_cache(maxsize=256)
def marker_cells(dictionary_name: str, marker_id: int) -> np.ndarray:
    """(modules, modules) bool, True for a white cell: ``marker_id``'s bits in the OpenCV dictionary
    ``dictionary_name`` with its one-cell black border, in the detector's rotation (top-left corner
    first), read-only."""
    dictionary = _dictionary(dictionary_name)
    modules = dictionary.markerSize + 2
    cells = cv2.aruco.generateImageMarker(dictionary, marker_id, modules, borderBits=1) > 127
    cells.setflags(write=False)
    return cells


@functools.lru_cache(maxsize=16)
def _dictionary(name: str) -> cv2.aruco.Dictionary:
    """OpenCV's predefined dictionary ``name`` (checked by the detector's params)."""
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def modules_of(dictionary_name: str) -> int:
    """Cells across a marker of OpenCV's dictionary ``dictionary_name``, its border included."""
    return int(_dictionary(dictionary_name).markerSize) + 2


@numba.njit(cache=True, nogil=True)
def _sample(gray: np.ndarray, x: float, y: float) -> float:
    """``gray`` at (x, y), bilinear, the border replicated (OpenCV's pixel-centre convention)."""
    h, w = gray.shape   # at least 2 x 2
    x, y = min(max(x, 0.0), w - 1.0), min(max(y, 0.0), h - 1.0)
    x0, y0 = min(int(x), w - 2), min(int(y), h - 2)
    fx, fy = x - x0, y - y0
    top = gray[y0, x0] * (1.0 - fx) + gray[y0, x0 + 1] * fx
    bottom = gray[y0 + 1, x0] * (1.0 - fx) + gray[y0 + 1, x0 + 1] * fx
    return top * (1.0 - fy) + bottom * fy


@numba.njit(cache=True, nogil=True)
def _cell_means(gray: np.ndarray, quad: np.ndarray, modules: int, out: np.ndarray) -> None:
    """``out[:modules, :modules]``: each cell's mean grey level, 3 x 3 bilinear samples around its
    centre, for the marker with corners ``quad`` (4, 2; TL, TR, BR, BL): the unit square mapped
    onto the quad by the homography in closed form (Heckbert, "Fundamentals of texture mapping")."""
    x0, y0, x1, y1 = quad[0, 0], quad[0, 1], quad[1, 0], quad[1, 1]
    x2, y2, x3, y3 = quad[2, 0], quad[2, 1], quad[3, 0], quad[3, 1]
    dx1, dx2, dx3 = x1 - x2, x3 - x2, x0 - x1 + x2 - x3
    dy1, dy2, dy3 = y1 - y2, y3 - y2, y0 - y1 + y2 - y3
    den = dx1 * dy2 - dx2 * dy1
    g = (dx3 * dy2 - dx2 * dy3) / den
    h = (dx1 * dy3 - dx3 * dy1) / den
    a, b, d, e = x1 - x0 + g * x1, x3 - x0 + h * x3, y1 - y0 + g * y1, y3 - y0 + h * y3
    for r in range(modules):
        for c in range(modules):
            total = 0.0
            for dv in _CELL_SAMPLES:
                v = (r + 0.5 + dv) / modules
                for du in _CELL_SAMPLES:
                    u = (c + 0.5 + du) / modules
                    z = g * u + h * v + 1.0
                    total += _sample(gray, (a * u + b * v + x0) / z, (d * u + e * v + y0) / z)
            out[r, c] = total / 9.0


@numba.njit(cache=True, nogil=True)
def _cell_errors(gray: np.ndarray, quads: np.ndarray, modules: np.ndarray, expected: np.ndarray,
                 min_contrast: float, out: np.ndarray) -> None:
    """For each marker ``q`` of ``quads`` (N, 4, 2): ``out[q]`` = (white border cells, inner cells
    unlike ``expected[q]`` (N, M, M bool, True = white)), each cell white above the midpoint of the
    darkest and brightest; (-1, -1) when they differ by less than ``min_contrast``, or for a quad
    with a corner not finite (not read)."""
    means = np.empty((expected.shape[1], expected.shape[2]))
    for q in range(quads.shape[0]):
        m = modules[q]
        if not corners_finite(quads, q):
            out[q, 0], out[q, 1] = -1, -1
            continue
        _cell_means(gray, quads[q], m, means)
        lo, hi = means[0, 0], means[0, 0]
        for r in range(m):
            for c in range(m):
                lo, hi = min(lo, means[r, c]), max(hi, means[r, c])
        if hi - lo < min_contrast:
            out[q, 0], out[q, 1] = -1, -1
            continue
        mid = 0.5 * (lo + hi)
        border, inner = 0, 0
        for r in range(m):
            for c in range(m):
                white = means[r, c] > mid
                if r == 0 or c == 0 or r == m - 1 or c == m - 1:
                    border += white
                elif white != expected[q, r, c]:
                    inner += 1
        out[q, 0], out[q, 1] = border, inner


@functools.lru_cache(maxsize=1024)
def _expected_cells(markers: tuple[tuple[str, int], ...]) -> tuple[np.ndarray, np.ndarray]:
    """For markers (dictionary name, id): their cells across (N,) and their cells (N, S, S; True =
    white, S the largest), as :func:`_cell_errors` takes them (shared: not to be written)."""
    modules = np.array([modules_of(name) for name, _ in markers], dtype=np.int64)
    size = int(modules.max()) if len(modules) else 0
    expected = np.zeros((len(markers), size, size), dtype=np.bool_)
    for k, (name, marker_id) in enumerate(markers):
        expected[k, :modules[k], :modules[k]] = marker_cells(name, marker_id)
    return modules, expected


@functools.lru_cache(maxsize=64)
def _error_limits(dictionary_name: str, error_correction_rate: float) -> tuple[int, int, int]:
    """The white border cells and the wrong inner cells a marker of ``dictionary_name`` may have
    and still read (OpenCV's limits, as the module's docstring describes), and the white border
    cells of a dark border (:func:`marker_reads`)."""
    dictionary = _dictionary(dictionary_name)
    border_max = int(dictionary.markerSize ** 2 * BORDER_ERROR_RATE)
    return (border_max, int(dictionary.maxCorrectionBits * error_correction_rate),
            max(border_max, int(4 * (dictionary.markerSize + 1) * BORDER_ERROR_RATE)))


def cell_errors(gray: np.ndarray, quads_px: np.ndarray, predicted: Sequence[Detection]) -> np.ndarray:
    """(N, 2) int: for the markers of ``predicted`` at corners ``quads_px`` (N, 4, 2; TL, TR, BR,
    BL), the white cells in each one's border and its inner cells unlike its id's bits, each
    cell's mean of 3 x 3 bilinear samples taken as white above the midpoint of the marker's darkest
    and brightest cell; (-1, -1) for a marker whose cells differ by less than ``MIN_CELL_CONTRAST``
    grey levels (nothing readable there) or whose corners are not all finite."""
    modules, expected = _expected_cells(tuple((d.dictionary, d.marker_id) for d in predicted))
    out = np.zeros((len(predicted), 2), dtype=np.int64)
    _cell_errors(np.ascontiguousarray(gray), np.ascontiguousarray(quads_px, dtype=np.float64), modules, expected,
                 MIN_CELL_CONTRAST, out)
    return out


def marker_reads(gray: np.ndarray, fitted_px: np.ndarray, predicted: tuple[Detection, ...],
                 error_correction_rate: float) -> tuple[np.ndarray, np.ndarray]:
    """For the markers of ``predicted`` at their fitted corners ``fitted_px`` (N, 4, 2; NaN where the
    edge fit failed): (N,) bool, which read as their ids there (as the module's docstring describes),
    and (N,) bool, which have a dark border there: readable cells and at most ``BORDER_ERROR_RATE`` of
    the border's own cells white (``4 x (markerSize + 1)``, 20 for ``DICT_4X4_50``: 7, where OpenCV
    allows ``int(0.35 x markerSize^2)``, 5, for reading; never fewer than those), a marker lying at
    the corners whether or not its cells read as its id's."""
    errors = cell_errors(gray, fitted_px, predicted).tolist()   # plain ints: a handful of markers
    read, bordered = [], []
    for (border, inner), (border_max, inner_max, dark_max) in zip(
            errors, (_error_limits(d.dictionary, error_correction_rate) for d in predicted), strict=True):
        bordered.append(0 <= border <= dark_max)
        read.append(0 <= border <= border_max and inner <= inner_max)
    return np.array(read, dtype=bool), np.array(bordered, dtype=bool)


def compile_cell_reader() -> None:
    """Compile the bit-cell reader and the projected quads' check (or load them from numba's
    on-disk cache) before the first frame, on one synthetic marker (the detector calls it at
    start-up, as the edge fit's)."""
    gray = np.full((48, 48), 200, dtype=np.uint8)
    gray[12:36, 12:36] = 20
    corners = np.array([[[11.5, 11.5], [35.5, 11.5], [35.5, 35.5], [11.5, 35.5]]])
    cell_errors(gray, corners, [Detection(0, corners[0], 576.0, "DICT_4X4_50")])
    _facing_quads(corners, 19.0, 3.0, 48, 48, np.empty(1))
    _grown_box(corners[0], 8.0, 48, 48)
    projected_px(np.array([[0.0, 0.0, 1.0]]), np.eye(3), np.zeros(5))


def resolvable_markers(quads_px: np.ndarray, modules: np.ndarray) -> np.ndarray:
    """(N,) bool: which quads ``quads_px`` (N, 4, 2) have every side at least ``MIN_PX_PER_MODULE``
    pixels per cell of their marker (``modules`` (N,): cells across, border included). Narrower,
    neighbouring cells share a pixel and the marker's bits are not in the image (below the sampling
    limit of one pixel per cell), so neither :func:`marker_reads` nor OpenCV's identification
    can read it: the detector spends no search on such a marker that did not read at its
    prediction. (On the live benchmark's 16-camera scene, seed 7, 3,000 frames: 1,055 of 3,037
    searches around unread predictions were of such markers, and none found one; issue 31.)"""
    out = np.empty(len(quads_px), dtype=bool)
    # plain floats: a handful of quads, and numpy's per-call cost was most of this
    for q, (quad, cells) in enumerate(zip(np.asarray(quads_px).tolist(), np.asarray(modules).tolist(), strict=True)):
        shortest = min(math.sqrt((x - x0) * (x - x0) + (y - y0) * (y - y0))
                       for (x0, y0), (x, y) in zip(quad[-1:] + quad[:-1], quad, strict=True))
        out[q] = shortest >= MIN_PX_PER_MODULE * cells
    return out


def marker_box(corners_px: np.ndarray, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    """The box (x0, y0, x1, y1) around a predicted marker's corners, grown by half its longest
    side (at least ``MIN_BOX_PX`` / 2) and cut to an image of ``shape`` (H, W): where a search for
    a marker that its prediction did not find looks."""
    xy = corners_px.tolist()   # four corners: plain floats cost less than numpy calls
    grow = max(0.5 * max(math.dist(xy[c - 1], xy[c]) for c in range(4)), 0.5 * MIN_BOX_PX)
    xs, ys = [x for x, _ in xy], [y for _, y in xy]
    return (max(int(min(xs) - grow), 0), max(int(min(ys) - grow), 0),
            min(math.ceil(max(xs) + grow), shape[1]), min(math.ceil(max(ys) + grow), shape[0]))
