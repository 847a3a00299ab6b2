"""Square-marker detection: a pure function of one grayscale frame (configure once, detect many).

The detector wraps OpenCV 5's ``cv2.aruco.ArucoDetector``. It finds markers of one or more
dictionaries (the world marker and the cubes may use different ones) and returns one
:class:`cubetrack.records.Detection` per marker, carrying its dictionary name, id, corners and
pixel area. It does not correct lens distortion and does not estimate pose (see
:mod:`cubetrack.estimate`).

Conventions (docs/detection.md has the details and the measurements behind the defaults):

- Corners are float64 (4, 2), clockwise in the image from the marker's top-left corner
  (TL, TR, BR, BL), in OpenCV's pixel-centre convention: (0, 0) is the centre of the top-left
  pixel. OpenCV's APRILTAG refinement returns corners in AprilTag's convention (origin at the
  top-left pixel's corner, i.e. +0.5 px); they are shifted by -0.5 px here so every refinement
  method reports the same convention.
- A detection whose corners are not finite, not a strictly convex clockwise quad, or whose area
  is below ``DetectorParams.min_area_px2`` is dropped (logged at debug level), never passed on.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from cubetrack.errors import DetectionError, ImageError
from cubetrack.geometry import shoelace_area
from cubetrack.params import param
from cubetrack.records import Detection

log = logging.getLogger(__name__)

# OpenCV's APRILTAG refinement reports corners with AprilTag's pixel convention (the top-left
# pixel's centre at (0.5, 0.5)); this brings them to OpenCV's (centre at (0, 0)).
APRILTAG_PIXEL_OFFSET_PX = -0.5


class CornerRefinement(enum.Enum):
    """How marker corners are refined after the quad is found (values are the TOML strings).

    ``none``: corners at the centres of the outermost black pixels (biased ~0.5 px inward);
    ``subpix``: ``cv2.cornerSubPix`` in a window of ``relative_corner_refinement_win_size``
    modules; ``contour``: line fit to the contour; ``apriltag``: AprilTag-2 quad fitting
    (accurate, 10-50x slower); ``edge`` (cubetrack's own, :func:`refine_corners_edges`): each
    side's sub-pixel edge points (gradient centroids across the black border's outer edge) are
    fitted with a line, corners are the lines' intersections — unbiased, ~1 ms per frame.
    """

    EDGE = "edge"
    NONE = "none"
    SUBPIX = "subpix"
    CONTOUR = "contour"
    APRILTAG = "apriltag"


_CV_REFINEMENT = {
    CornerRefinement.EDGE: cv2.aruco.CORNER_REFINE_NONE,  # then refine_corners_edges
    CornerRefinement.NONE: cv2.aruco.CORNER_REFINE_NONE,
    CornerRefinement.SUBPIX: cv2.aruco.CORNER_REFINE_SUBPIX,
    CornerRefinement.CONTOUR: cv2.aruco.CORNER_REFINE_CONTOUR,
    CornerRefinement.APRILTAG: cv2.aruco.CORNER_REFINE_APRILTAG,
}


def dictionary_names() -> tuple[str, ...]:
    """Names of every predefined OpenCV marker dictionary (``DICT_4X4_50``, ...)."""
    return tuple(sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_")))


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """The predefined OpenCV dictionary called ``name``; DetectionError naming the valid ones."""
    value = getattr(cv2.aruco, name, None) if isinstance(name, str) and name.startswith("DICT_") else None
    if not isinstance(value, int):
        raise DetectionError(
            f"unknown marker dictionary {name!r}; valid names: {', '.join(dictionary_names())}"
        )
    return cv2.aruco.getPredefinedDictionary(value)


@dataclass(frozen=True, slots=True)
class DetectorParams:
    """Detector settings; the ``[detector]`` TOML table maps 1:1 onto these fields."""

    dictionary: str = param(
        "DICT_4X4_50",
        "OpenCV predefined dictionary name, used when the Detector is built without an explicit "
        "list of dictionaries (the tracker passes the world's and the cubes' dictionaries)",
    )
    corner_refinement: CornerRefinement = param(
        CornerRefinement.EDGE,
        "corner refinement: edge | none | subpix | contour | apriltag. edge (cubetrack's line fit "
        "to each side's sub-pixel edge points) is the most accurate and unbiased, ~1 ms per VGA "
        "frame more than none; apriltag is the next most accurate but 10-30x slower; none/contour are ~0.5 px "
        "biased inward (docs/detection.md)",
    )
    relative_corner_refinement_win_size: float = param(
        0.3,
        "subpix only: half-window as a fraction of the marker's module (bit cell) size; the window is "
        "min(corner_refinement_win_size_px, this x module size). 0.8 halves the error on isolated "
        "markers but reaches the cube's edge on the paper's cube (docs/detection.md)",
    )
    corner_refinement_win_size_px: int = param(
        5, "subpix only: upper bound of the half-window, pixels",
    )
    corner_refinement_max_iterations: int = param(
        30, "subpix/contour iteration limit",
    )
    corner_refinement_min_accuracy_px: float = param(
        0.1, "subpix/contour stop when a corner moves less than this, pixels",
    )
    adaptive_thresh_win_size_min_px: int = param(
        3, "smallest adaptive-threshold window, pixels (odd)",
    )
    adaptive_thresh_win_size_max_px: int = param(
        23, "largest adaptive-threshold window, pixels; 13 is ~30 % faster at VGA when markers are small",
    )
    adaptive_thresh_win_size_step_px: int = param(
        10, "step between adaptive-threshold windows, pixels (one thresholding pass per window)",
    )
    adaptive_thresh_constant: float = param(
        7.0, "constant subtracted from the local mean in adaptive thresholding, grey levels",
    )
    min_marker_perimeter_rate: float = param(
        0.03, "smallest marker perimeter as a fraction of the larger image side (0.03 x 640 = 19 px)",
    )
    max_marker_perimeter_rate: float = param(
        4.0, "largest marker perimeter as a fraction of the larger image side",
    )
    polygonal_approx_accuracy_rate: float = param(
        0.05, "polygon approximation tolerance as a fraction of the candidate's perimeter",
    )
    min_corner_distance_rate: float = param(
        0.05, "smallest distance between corners of one marker as a fraction of its perimeter",
    )
    min_marker_distance_rate: float = param(
        0.125, "candidates closer than this fraction of the marker's perimeter are merged",
    )
    min_distance_to_border_px: int = param(
        3, "markers with a corner closer than this to the image border are dropped, pixels",
    )
    error_correction_rate: float = param(
        0.6, "fraction of the dictionary's maximum correctable bits that may be corrected (0..1)",
    )
    detect_inverted_marker: bool = param(
        False, "also detect white-on-black (inverted) markers",
    )
    april_tag_quad_decimate: float = param(
        0.0, "apriltag refinement only: image decimation for quad search (0 = off; 2 halves its cost)",
    )
    april_tag_quad_sigma: float = param(
        0.0, "apriltag refinement only: Gaussian blur sigma before quad search, pixels (0 = off)",
    )
    min_area_px2: float = param(
        4.0, "detections whose shoelace area is below this are dropped as degenerate, square pixels",
    )

    def __post_init__(self) -> None:
        aruco_dictionary(self.dictionary)  # DetectionError with the valid names
        if not 0.0 < self.relative_corner_refinement_win_size <= 4.0:
            raise ValueError(f"relative_corner_refinement_win_size must be in (0, 4], got "
                             f"{self.relative_corner_refinement_win_size}")
        if self.corner_refinement_win_size_px < 1 or self.corner_refinement_max_iterations < 1:
            raise ValueError("corner_refinement_win_size_px and corner_refinement_max_iterations must be >= 1")
        if not self.corner_refinement_min_accuracy_px > 0.0:
            raise ValueError("corner_refinement_min_accuracy_px must be positive")
        lo, hi, step = (self.adaptive_thresh_win_size_min_px, self.adaptive_thresh_win_size_max_px,
                        self.adaptive_thresh_win_size_step_px)
        if lo < 3 or hi < lo or step < 1:
            raise ValueError(f"adaptive threshold windows need 3 <= min <= max and step >= 1, got "
                             f"min {lo}, max {hi}, step {step}")
        if not 0.0 < self.min_marker_perimeter_rate < self.max_marker_perimeter_rate:
            raise ValueError("need 0 < min_marker_perimeter_rate < max_marker_perimeter_rate")
        if not 0.0 <= self.error_correction_rate <= 1.0:
            raise ValueError(f"error_correction_rate must be in [0, 1], got {self.error_correction_rate}")
        if self.min_area_px2 < 0.0 or self.min_distance_to_border_px < 0:
            raise ValueError("min_area_px2 and min_distance_to_border_px must not be negative")


def _cv_parameters(p: DetectorParams) -> cv2.aruco.DetectorParameters:
    cv = cv2.aruco.DetectorParameters()
    cv.cornerRefinementMethod = _CV_REFINEMENT[p.corner_refinement]
    cv.relativeCornerRefinmentWinSize = p.relative_corner_refinement_win_size  # (sic) OpenCV's spelling
    cv.cornerRefinementWinSize = p.corner_refinement_win_size_px
    cv.cornerRefinementMaxIterations = p.corner_refinement_max_iterations
    cv.cornerRefinementMinAccuracy = p.corner_refinement_min_accuracy_px
    cv.adaptiveThreshWinSizeMin = p.adaptive_thresh_win_size_min_px
    cv.adaptiveThreshWinSizeMax = p.adaptive_thresh_win_size_max_px
    cv.adaptiveThreshWinSizeStep = p.adaptive_thresh_win_size_step_px
    cv.adaptiveThreshConstant = p.adaptive_thresh_constant
    cv.minMarkerPerimeterRate = p.min_marker_perimeter_rate
    cv.maxMarkerPerimeterRate = p.max_marker_perimeter_rate
    cv.polygonalApproxAccuracyRate = p.polygonal_approx_accuracy_rate
    cv.minCornerDistanceRate = p.min_corner_distance_rate
    cv.minMarkerDistanceRate = p.min_marker_distance_rate
    cv.minDistanceToBorder = p.min_distance_to_border_px
    cv.errorCorrectionRate = p.error_correction_rate
    cv.detectInvertedMarker = p.detect_inverted_marker
    cv.aprilTagQuadDecimate = p.april_tag_quad_decimate
    cv.aprilTagQuadSigma = p.april_tag_quad_sigma
    return cv


def is_valid_quad(corners_px: np.ndarray, min_area_px2: float = 0.0) -> bool:
    """True for finite (4, 2) corners forming a strictly convex quad, clockwise in the image
    (y down), whose area exceeds ``min_area_px2``."""
    c = np.asarray(corners_px, dtype=float)
    if c.shape != (4, 2) or not np.all(np.isfinite(c)):
        return False
    edges = np.roll(c, -1, axis=0) - c
    turns = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    return bool(np.all(turns > 0.0) and shoelace_area(c) > max(min_area_px2, 0.0))


_EDGE_SAMPLES_ALONG = 12   # edge samples per side, spread over its middle 60 %
_EDGE_SAMPLES_ACROSS = 17  # profile samples across the edge


def _fit_lines(q: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted total-least-squares lines through points q (..., k, 2) with weights w (..., k).

    Returns unit normals (..., 2) and offsets (...,) with normal . x = offset on the line."""
    wsum = np.maximum(w.sum(axis=-1), 1e-12)
    mu = (q * w[..., None]).sum(axis=-2) / wsum[..., None]
    d = q - mu[..., None, :]
    a = (w * d[..., 0] ** 2).sum(axis=-1)
    b = (w * d[..., 0] * d[..., 1]).sum(axis=-1)
    c = (w * d[..., 1] ** 2).sum(axis=-1)
    theta = 0.5 * np.arctan2(2.0 * b, a - c)  # direction of the line
    normal = np.stack([-np.sin(theta), np.cos(theta)], axis=-1)
    return normal, (normal * mu).sum(axis=-1)


def refine_corners_edges(gray: np.ndarray, corners_px: np.ndarray, modules: int | np.ndarray,
                         iterations: int = 3) -> np.ndarray:
    """Refine marker corners by fitting a line to each side's outer edge (the ``edge`` method).

    ``gray``: float32 image; ``corners_px``: (4, 2) or (M, 4, 2) initial corners (TL, TR, BR, BL,
    clockwise in the image); ``modules``: cells across each marker including its black border
    (6 for a 4x4 dictionary). Along the middle 60 % of every side the image is sampled across
    the edge (bilinear; half-width 0.8 module, clipped to [1.5, 4] px); each edge point is the
    centroid of the positive (dark inside -> bright outside) intensity gradient, which is
    unbiased for any symmetric blur. A weighted total-least-squares line per side (one robust
    re-fit without 2.5-sigma outliers) is intersected with its neighbours; this repeats
    ``iterations`` times from the new corners. Returns corners of the input's shape; a marker
    whose fit fails (low contrast, a degenerate quad, a corner moving more than two modules)
    gets NaN corners, so the caller can keep its initial ones. Vectorised over markers.
    """
    c0 = np.asarray(corners_px, dtype=np.float64)
    single = c0.ndim == 2
    c0 = c0.reshape(-1, 4, 2)
    n_markers = c0.shape[0]
    modules = np.broadcast_to(np.asarray(modules, dtype=np.float64), (n_markers,))
    c = c0.copy()
    good = np.ones(n_markers, dtype=bool)
    t = np.linspace(0.2, 0.8, _EDGE_SAMPLES_ALONG)
    unit = np.linspace(-1.0, 1.0, _EDGE_SAMPLES_ACROSS)
    for _ in range(iterations):
        p0, p1 = c, np.roll(c, -1, axis=1)                       # side i runs corner i -> i+1
        vec = p1 - p0
        length = np.linalg.norm(vec, axis=-1)                    # (M, 4)
        good &= np.all(length > 4.0, axis=1)
        u = vec / np.maximum(length, 1e-9)[..., None]
        n = np.stack([u[..., 1], -u[..., 0]], axis=-1)           # outward normal (clockwise, y down)
        across = 0.5 * (np.roll(length, -1, axis=1) + np.roll(length, 1, axis=1)) / modules[:, None]
        w = np.clip(0.8 * across, 1.5, 4.0)                      # (M, 4) half-width, px
        s = unit[None, None, :] * w[..., None]                   # (M, 4, m)
        base = p0[:, :, None, :] + (t[None, None, :, None] * vec[:, :, None, :])    # (M, 4, k, 2)
        pts = base[:, :, :, None, :] + s[:, :, None, :, None] * n[:, :, None, None, :]  # (M,4,k,m,2)
        flat = pts.reshape(1, -1, 2).astype(np.float32)
        prof = cv2.remap(gray, flat[..., 0], flat[..., 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE).astype(np.float64).reshape(pts.shape[:-1])
        g = np.maximum(np.diff(prof, axis=-1), 0.0)              # (M, 4, k, m-1)
        mass = g.sum(axis=-1)
        s_mid = 0.5 * (s[..., 1:] + s[..., :-1])                  # (M, 4, m-1)
        off = (g * s_mid[:, :, None, :]).sum(axis=-1) / np.maximum(mass, 1e-12)
        weight = np.where((mass > 1e-6) & (prof[..., -1] - prof[..., 0] > 8.0), mass, 0.0)
        good &= np.all((weight > 0).sum(axis=-1) >= 3, axis=1)
        q = base + off[..., None] * n[:, :, None, :]              # edge points (M, 4, k, 2)
        normal, offset = _fit_lines(q, weight)
        resid = (q * normal[:, :, None, :]).sum(axis=-1) - offset[..., None]
        rms = np.sqrt((weight * resid ** 2).sum(axis=-1) / np.maximum(weight.sum(axis=-1), 1e-12))
        weight = np.where(np.abs(resid) <= np.maximum(2.5 * rms, 0.1)[..., None], weight, 0.0)
        good &= np.all((weight > 0).sum(axis=-1) >= 3, axis=1)
        normal, offset = _fit_lines(q, weight)
        # corner i = side (i-1) meets side i
        na, da = np.roll(normal, 1, axis=1), np.roll(offset, 1, axis=1)
        det = na[..., 0] * normal[..., 1] - na[..., 1] * normal[..., 0]
        good &= np.all(np.abs(det) > 1e-6, axis=1)
        det = np.where(np.abs(det) > 1e-6, det, 1.0)
        x = (da * normal[..., 1] - na[..., 1] * offset) / det
        y = (na[..., 0] * offset - da * normal[..., 0]) / det
        c = np.where(good[:, None, None], np.stack([x, y], axis=-1), c0)
    module_px = np.linalg.norm(np.roll(c0, -1, axis=1) - c0, axis=-1).mean(axis=1) / modules
    moved = np.linalg.norm(c - c0, axis=-1).max(axis=1)
    good &= np.all(np.isfinite(c), axis=(1, 2)) & (moved <= np.maximum(2.0 * module_px, 3.0))
    c[~good] = np.nan
    return c[0] if single else c


def _refine_edges_in_roi(gray: np.ndarray, quads: np.ndarray, modules: np.ndarray) -> np.ndarray:
    """``refine_corners_edges`` on the float copy of only the region around the quads (a margin
    of 12 px covers the 4 px sampling half-width and the corners' moves)."""
    finite = quads[np.all(np.isfinite(quads), axis=(1, 2))].reshape(-1, 2)
    if len(finite) == 0:
        return np.full_like(quads, np.nan)
    x0, y0 = np.maximum(np.floor(finite.min(axis=0)) - 12, 0).astype(int)
    x1, y1 = (np.ceil(finite.max(axis=0)) + 13).astype(int)
    offset = np.array([x0, y0], dtype=np.float64)
    roi = gray[y0:y1, x0:x1].astype(np.float32)
    return refine_corners_edges(roi, quads - offset, modules) + offset


class Detector:
    """A configured marker detector; ``detect_gray`` / ``detect_jpeg`` may be called per frame.

    ``dictionaries`` lists the dictionary names to search (e.g. the world marker's and the
    cubes'); None means ``params.dictionary``. Each Detection names its dictionary, so equal ids
    from different dictionaries stay apart. Not thread-safe: use one Detector per thread.
    """

    def __init__(self, params: DetectorParams | None = None,
                 dictionaries: Sequence[str] | None = None) -> None:
        self.params = params or DetectorParams()
        if dictionaries is None:
            names = [self.params.dictionary]
        elif isinstance(dictionaries, str):
            names = [dictionaries]
        else:
            names = list(dict.fromkeys(dictionaries))  # drop repeats, keep order
        if not names:
            raise DetectionError("a detector needs at least one marker dictionary")
        self.dictionaries: tuple[str, ...] = tuple(names)
        dicts = [aruco_dictionary(n) for n in names]
        self._detector = cv2.aruco.ArucoDetector(dicts, _cv_parameters(self.params))
        self._offset_px = (APRILTAG_PIXEL_OFFSET_PX
                           if self.params.corner_refinement is CornerRefinement.APRILTAG else 0.0)
        self._modules = tuple(d.markerSize + 2 for d in dicts)  # cells across, with a 1-bit border

    def detect_gray(self, gray: np.ndarray) -> tuple[Detection, ...]:
        """Detect markers in an 8-bit single-channel image (H, W); sorted by dictionary, id, x."""
        gray = np.asarray(gray)
        if gray.ndim != 2 or gray.dtype != np.uint8 or gray.size == 0:
            raise ImageError(
                f"detection needs a non-empty 8-bit grayscale image (H, W), got {gray.dtype} {gray.shape}"
            )
        corners, ids, _rejected, dict_indices = self._detector.detectMarkersMultiDict(gray)
        if ids is None or len(ids) == 0:
            return ()
        ids = np.asarray(ids).reshape(-1)
        dict_indices = (np.zeros_like(ids) if dict_indices is None
                        else np.asarray(dict_indices).reshape(-1))
        quads = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2) + self._offset_px
        if self.params.corner_refinement is CornerRefinement.EDGE:
            modules = np.array([self._modules[int(k)] for k in dict_indices])
            refined = _refine_edges_in_roi(gray, quads, modules)
            ok = np.all(np.isfinite(refined), axis=(1, 2))
            if not ok.all():
                log.debug("edge refinement failed for ids %s; kept OpenCV's corners", ids[~ok].tolist())
            quads = np.where(ok[:, None, None], refined, quads)
        out = []
        for c, marker_id, k in zip(quads, ids, dict_indices):
            c = c.copy()
            if not is_valid_quad(c, self.params.min_area_px2):
                log.debug("dropped degenerate detection of id %d: %s", marker_id, c.tolist())
                continue
            c.setflags(write=False)
            out.append(Detection(marker_id=int(marker_id), corners_px=c, area_px2=shoelace_area(c),
                                 dictionary=self.dictionaries[int(k)]))
        out.sort(key=lambda d: (d.dictionary, d.marker_id, float(d.corners_px[:, 0].mean())))
        return tuple(out)

    def detect_jpeg(self, jpeg: bytes, source: str = "JPEG") -> tuple[Detection, ...]:
        """Decode a JPEG to grayscale and detect; ImageError (naming ``source``) when it is empty,
        truncated or corrupt."""
        gray = decode_gray(jpeg, source)
        return self.detect_gray(gray)


def decode_gray(jpeg: bytes, source: str = "JPEG") -> np.ndarray:
    """Decode JPEG (or any OpenCV-readable image) bytes to an 8-bit grayscale image.

    Raises ImageError naming ``source`` for empty, truncated or undecodable data. A JPEG must end
    with its end-of-image marker: libjpeg would otherwise pad a truncated frame with grey.
    """
    data = bytes(jpeg) if not isinstance(jpeg, bytes) else jpeg
    if len(data) == 0:
        raise ImageError(f"{source}: empty image data")
    if data[:2] == b"\xff\xd8" and b"\xff\xd9" not in data[-64:]:
        raise ImageError(f"{source}: truncated JPEG (no end-of-image marker)")
    try:
        gray = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    except cv2.error as exc:
        raise ImageError(f"{source}: cannot decode image: {str(exc).strip().splitlines()[-1]}") from None
    if gray is None or gray.size == 0:
        raise ImageError(f"{source}: not a decodable JPEG/image ({len(data)} bytes)")
    return gray
