"""Square-marker detection: a pure function of one grayscale frame (configure once, detect many).

The detector wraps OpenCV 5's ``cv2.aruco.ArucoDetector``. It finds markers of one or more
dictionaries (the world marker and the cubes may use different ones) and returns one
:class:`cubetrack.core.records.Detection` per marker, carrying its dictionary name, id, corners and
pixel area. It does not correct lens distortion and does not estimate pose (see
:mod:`cubetrack.estimate`). Where to look is an input: ``Detector.detect(gray, regions)``
searches the whole image, or only the given boxes (the tracker's regions of interest).

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
import math
import threading
import time
import warnings
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numba
import numpy as np
from numba.core import event as numba_events

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import DetectionError, ImageError, caused_by_interrupt
from cubetrack.core.geometry import shoelace_area
from cubetrack.core.params import check, param
from cubetrack.core.records import Detection
from cubetrack.detect.decode import decode_gray as decode_gray  # also imported from here by other stages
from cubetrack.detect.decode import read_gray as read_gray
from cubetrack.detect.edge_fit import compile_edge_fit, refine_corners_edges
from cubetrack.detect.predicted import compile_cell_reader, marker_box, marker_reads, modules_of, resolvable_markers
from cubetrack.detect.quads import corners_finite
from cubetrack.detect.template_fit import LensMap, compile_template_fit, fast_template_corners

log = logging.getLogger(__name__)
_cold_cache_told = threading.Lock()  # held once a process has warned that numba compiles (it says so once)

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
    fitted with a line, corners are the lines' intersections — unbiased, ~0.6 ms per VGA frame;
    ``template``: the edge fit's corners re-measured by fitting the marker's whole image through
    the camera's lens (:func:`cubetrack.detect.template_fit.fast_template_corners`; 4-7x closer to
    the truth than the edge fit on the realistic simulation, a few ms per marker).
    """

    EDGE = "edge"
    TEMPLATE = "template"
    NONE = "none"
    SUBPIX = "subpix"
    CONTOUR = "contour"
    APRILTAG = "apriltag"


_CV_REFINEMENT = {
    CornerRefinement.EDGE: cv2.aruco.CORNER_REFINE_NONE,  # then refine_corners_edges
    CornerRefinement.TEMPLATE: cv2.aruco.CORNER_REFINE_NONE,  # then refine_corners_edges, then the template fit
    CornerRefinement.NONE: cv2.aruco.CORNER_REFINE_NONE,
    CornerRefinement.SUBPIX: cv2.aruco.CORNER_REFINE_SUBPIX,
    CornerRefinement.CONTOUR: cv2.aruco.CORNER_REFINE_CONTOUR,
    CornerRefinement.APRILTAG: cv2.aruco.CORNER_REFINE_APRILTAG,
}


def opencv_corner_refinement(method: CornerRefinement) -> int:
    """OpenCV's ``cornerRefinementMethod`` for ``method`` (``edge`` is cubetrack's own: it starts
    from OpenCV's unrefined corners, ``CORNER_REFINE_NONE``)."""
    return _CV_REFINEMENT[method]


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
        "corner refinement: edge | template | none | subpix | contour | apriltag. edge (cubetrack's line fit "
        "to each side's sub-pixel edge points) is unbiased, ~0.6 ms per VGA frame more than none; template "
        "re-measures the edge fit's corners by fitting each marker's whole image through the camera's lens "
        "(4-7x closer to the truth, a few ms per marker; pays off with a calibrated body and a [filter] that "
        "trusts the corners, docs/tracking.md); apriltag is 10-30x slower than edge; none/contour are ~0.5 px "
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
        False, "also detect white-on-black (inverted) markers: the image and its negative are searched (twice the "
        "detection's CPU), so every corner refinement works on both (docs/detection.md)",
    )
    detect_normal_marker: bool = param(
        True, "detect ordinary dark-on-white markers; false with detect_inverted_marker = true: white-on-black ones "
        "only, the negative searched alone (half the CPU of both; docs/detection.md)",
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
    edge_iterations: int = param(
        2, "edge only: line fits per side, each sampling along the previous fit's sides. 1 saves "
        "~0.25 ms per VGA frame but is less accurate (simulated frames: mean corner error 0.134 "
        "against 0.125 px, cube position p95 27 against 22 mm; docs/detection.md)",
    )
    predicted_edge_iterations: int = param(
        4, "edge and template: line fits per side of a marker fitted from the corners the tracker predicts "
        "(Detector.find with predicted markers) instead of OpenCV's: a prediction is pixels off at a turn where "
        "OpenCV's contour corners are tenths off, and a fit that has not forgotten where it started hands the "
        "filter its own prediction back (from 3 px off: 0.94 px p95 left after 2 fits, 0.09 after 4; "
        "docs/detection.md \"Predicted markers\")",
    )
    predicted_edge_settled_px: float = param(
        0.05, "edge and template: a marker fitted from its prediction gets no more fits after one that moved none "
        "of its corners by this much along either axis, pixels (0: always predicted_edge_iterations fits). A fit "
        "leaves about 0.4x its move still to go, so a marker stops ~0.02 px from where more fits take it, under a "
        "head-on edge-fit corner's own error (~0.06 px); on the 16 x 30 recording 2.7 fits a marker instead of 4 "
        "(0.01: 3.3), corners within 0.016 px of 4 fits' (p95) and as far from 8 fits' as 4 fits' are (p95 "
        "0.154 px, the markers whose fits do not settle; docs/detection.md \"Predicted markers\")",
    )
    template_iterations: int = param(
        2, "template only: Gauss-Newton iterations of each marker's fit, from the edge fit's corners",
    )

    def __post_init__(self) -> None:
        aruco_dictionary(self.dictionary)  # DetectionError with the valid names
        check(0.0 < self.relative_corner_refinement_win_size <= 4.0,
              f"relative_corner_refinement_win_size must be in (0, 4], got {self.relative_corner_refinement_win_size}")
        check(self.corner_refinement_win_size_px >= 1 and self.corner_refinement_max_iterations >= 1,
              "corner_refinement_win_size_px and corner_refinement_max_iterations must be >= 1")
        check(self.corner_refinement_min_accuracy_px > 0.0, "corner_refinement_min_accuracy_px must be positive")
        lo, hi, step = (self.adaptive_thresh_win_size_min_px, self.adaptive_thresh_win_size_max_px,
                        self.adaptive_thresh_win_size_step_px)
        check(lo >= 3 and hi >= lo and step >= 1,
              f"adaptive threshold windows need 3 <= min <= max and step >= 1, got min {lo}, max {hi}, step {step}")
        check(0.0 < self.min_marker_perimeter_rate < self.max_marker_perimeter_rate,
              "need 0 < min_marker_perimeter_rate < max_marker_perimeter_rate")
        check(0.0 <= self.error_correction_rate <= 1.0,
              f"error_correction_rate must be in [0, 1], got {self.error_correction_rate}")
        check(self.min_area_px2 >= 0.0 and self.min_distance_to_border_px >= 0,
              "min_area_px2 and min_distance_to_border_px must not be negative")
        check(self.detect_normal_marker or self.detect_inverted_marker,
              "detect_normal_marker = false needs detect_inverted_marker = true (no marker would be searched for)")
        check(self.predicted_edge_settled_px >= 0.0,
              f"predicted_edge_settled_px must not be negative, got {self.predicted_edge_settled_px}")
        check(min(self.edge_iterations, self.predicted_edge_iterations, self.template_iterations) >= 1,
              f"edge_iterations, predicted_edge_iterations and template_iterations must be at least 1, got "
              f"{self.edge_iterations}, {self.predicted_edge_iterations} and {self.template_iterations}")


def _cv_parameters(p: DetectorParams) -> cv2.aruco.DetectorParameters:
    cv = cv2.aruco.DetectorParameters()
    cv.cornerRefinementMethod = opencv_corner_refinement(p.corner_refinement)
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
    cv.detectInvertedMarker = False  # Detector.find searches the negated image for inverted markers
    cv.aprilTagQuadDecimate = p.april_tag_quad_decimate
    cv.aprilTagQuadSigma = p.april_tag_quad_sigma
    return cv


@numba.njit(cache=True, nogil=True)
def _quad_kernel(quads: np.ndarray, min_area_px2: float, ok: np.ndarray, area: np.ndarray) -> None:
    """:func:`_quad_checks` into ``ok`` and ``area`` (one compiled pass: as numpy, a dozen calls
    over a handful of quads, and the calls were the cost)."""
    for q in range(quads.shape[0]):
        if not corners_finite(quads, q):
            ok[q], area[q] = False, 0.0
            continue
        twice_area, min_turn = 0.0, math.inf
        for c in range(4):   # edge c: corner c -> c + 1; a right turn (> 0) at its end when clockwise (y down)
            x, y = quads[q, c, 0], quads[q, c, 1]
            x1, y1 = quads[q, (c + 1) % 4, 0], quads[q, (c + 1) % 4, 1]
            x2, y2 = quads[q, (c + 2) % 4, 0], quads[q, (c + 2) % 4, 1]
            ex, ey, fx, fy = x1 - x, y1 - y, x2 - x1, y2 - y1
            min_turn = min(min_turn, ex * fy - ey * fx)
            twice_area += x * y1 - y * x1
        area[q] = 0.5 * abs(twice_area)
        ok[q] = min_turn > 0.0 and area[q] > max(min_area_px2, 0.0)


def _quad_checks(quads: np.ndarray, min_area_px2: float) -> tuple[np.ndarray, np.ndarray]:
    """For (N, 4, 2) quads (float64, writable: the kernel's one signature): which are finite,
    strictly convex, clockwise in the image (y down) and larger than ``min_area_px2``, and their
    shoelace areas (px^2; 0 for a non-finite quad)."""
    ok, area = np.empty(len(quads), dtype=bool), np.empty(len(quads))
    _quad_kernel(np.ascontiguousarray(quads), float(min_area_px2), ok, area)
    return ok, area


def compile_quad_checks() -> None:
    """Compile :func:`_quad_checks`' kernel (or load it from numba's cache) before the first frame."""
    _quad_checks(np.array([[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]]), 0.0)


def is_valid_quad(corners_px: np.ndarray, min_area_px2: float = 0.0) -> bool:
    """True for finite (4, 2) corners forming a strictly convex quad, clockwise in the image
    (y down), whose area exceeds ``min_area_px2``."""
    c = np.array(corners_px, dtype=np.float64)   # a writable copy
    return c.shape == (4, 2) and bool(_quad_checks(c[None], min_area_px2)[0][0])


@dataclass(frozen=True, slots=True)
class DetectResult:
    """One frame's detections, and how many markers OpenCV found that were then dropped, per
    reason (``DROP_EDGE_FIT``, ``DROP_QUAD``): a run that finds markers and keeps none can say so.
    ``predicted``: the detections are the predicted markers, verified; no candidate search ran."""

    detections: tuple[Detection, ...]
    dropped: Mapping[str, int] = field(default_factory=dict)
    predicted: bool = False


DROP_EDGE_FIT = "edge fit failed"
DROP_QUAD = "not a convex quad above min_area_px2"


def _lens_key(lens: CameraIntrinsics) -> tuple:
    """What a lens map depends on, as a value (two equal intrinsics share a map)."""
    return lens.width, lens.height, np.asarray(lens.K).tobytes(), np.asarray(lens.dist).tobytes()


def compile_kernels(what: str, *compile_functions: Callable[[], None]) -> None:
    """Run ``compile_functions`` (each compiles numba kernels or loads them from numba's on-disk
    cache) before the first frame. When numba starts compiling a kernel rather than loading it (a
    cold cache: the first run after an install or upgrade without ``cubetrack compile``), this is
    said at WARNING, naming ``what``, once per process, as the compile starts: the user waiting on a
    silent start for a minute or two knows why; when it is done, its time is logged at INFO."""
    started_s = time.perf_counter()
    notice = _ColdCacheNotice(what)
    try:
        with numba_events.install_listener("numba:compile", notice):
            for compile_function in compile_functions:
                compile_function()
    except SystemError as exc:
        # Ctrl-C (or SIGTERM/SIGHUP, which the CLI turns into it) while numba loads a kernel from its
        # cache comes out of numba's C dispatcher as a SystemError caused by the KeyboardInterrupt:
        # give the command its interrupt back here, before any `except Exception` on the way up takes
        # it for a failure (the CLI's boundary checks the same for other callers)
        if caused_by_interrupt(exc):
            raise KeyboardInterrupt from None
        raise
    if notice.compiled:
        log.info("compiled the %s in %.0f s (numba; once after an install or upgrade: later runs load them from its "
                 "cache)", what, time.perf_counter() - started_s)


def no_cold_cache_warning() -> None:
    """From now on this process gives no cold-cache warning (:func:`compile_kernels`): for
    ``cubetrack compile``, whose compiling is the point."""
    _cold_cache_told.acquire(blocking=False)


class _ColdCacheNotice(numba_events.Listener):
    """Listens to numba's compile events: ``compiled`` once one has started; the first in the
    process warns that the ``what`` are being compiled."""

    def __init__(self, what: str):
        self.what = what
        self.compiled = False

    def on_start(self, event: numba_events.Event) -> None:
        self.compiled = True
        if _cold_cache_told.acquire(blocking=False):
            log.warning("compiling the %s (numba; once after an install or upgrade, a minute or two): run "
                        "`cubetrack compile` after installing to do this ahead ...", self.what)

    def on_end(self, event: numba_events.Event) -> None:
        pass


class Detector:
    """A configured marker detector; ``detect`` / ``find`` / ``detect_jpeg`` may be called per frame.

    ``dictionaries`` lists the dictionary names to search (e.g. the world marker's and the
    cubes'); None means ``params.dictionary``. Each Detection names its dictionary, so equal ids
    from different dictionaries stay apart. Not thread-safe: use one Detector per thread.

    With ``detect_inverted_marker`` every search runs twice: on the image, for dark-on-white
    markers, and on its negative, where white-on-black markers are dark-on-white — so every corner
    refinement (OpenCV's, the edge fit, the template fit) sees the polarity it is made for. Twice
    the detection's CPU; with ``detect_normal_marker`` false too, the negative alone is searched.

    The ``template`` refinement's lens maps (one per camera, :class:`LensMap`) belong to the
    detector: built on a camera's first frame, kept while the detector lives.
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
        self._region_detector = cv2.aruco.ArucoDetector(dicts, _cv_parameters(self.params))
        self._region_params = _cv_parameters(self.params)   # perimeter rates set per region size
        self._region_scale = 1.0                            # the scale _region_detector has now
        self._offset_px = (APRILTAG_PIXEL_OFFSET_PX
                           if self.params.corner_refinement is CornerRefinement.APRILTAG else 0.0)
        self._modules = tuple(d.markerSize + 2 for d in dicts)  # cells across, with a 1-bit border
        self._lens_maps: dict[tuple, LensMap] = {}
        kernels = [compile_quad_checks]   # the compiled kernels, before the first frame
        if self.params.corner_refinement in (CornerRefinement.EDGE, CornerRefinement.TEMPLATE):
            kernels += [compile_edge_fit, compile_cell_reader]
        if self.params.corner_refinement is CornerRefinement.TEMPLATE:
            kernels.append(compile_template_fit)
        compile_kernels("corner fits", *kernels)

    def detect(self, gray: np.ndarray, regions: Sequence[Box] | None = None,
               lens: CameraIntrinsics | None = None) -> tuple[Detection, ...]:
        """The detections of :meth:`find` (without its drop counts)."""
        return self.find(gray, regions, lens).detections

    def find(self, gray: np.ndarray, regions: Sequence[Box] | None = None,
             lens: CameraIntrinsics | None = None, predicted: Sequence[Detection] = ()) -> DetectResult:
        """Detect markers in an 8-bit single-channel image (H, W); sorted by dictionary, id, x.

        ``regions``: None searches the whole image. Otherwise only these boxes ``(x0, y0, x1,
        y1)`` (pixels, end exclusive) are searched, overlapping ones merged first, each as a
        whole-image search would see it: the perimeter limits stay relative to the whole image
        (a small region would otherwise admit every speck of noise as a candidate), and corners
        are in whole-image pixels. Much cheaper than the whole image when the boxes are small; an
        empty sequence searches nothing. ImageError for a box not inside the image.

        ``lens``: the camera's intrinsics, for the ``template`` refinement's lens model (None:
        the image is taken as undistorted); the other refinements ignore it.

        ``predicted``: with ``regions``, the markers where the tracker predicts them (corners
        projected, :func:`cubetrack.detect.predicted.predicted_markers`). With the ``edge`` or
        ``template`` refinement and no inverted markers, their edges are fitted from the predicted
        corners and their bit cells read (:mod:`cubetrack.detect.predicted`); one that does not
        read as its id is searched for by OpenCV in a small box around it (unless its cells are
        predicted narrower than a pixel: unreadable). When at least one reads
        at its prediction, the markers found so are the detections and OpenCV's search of the
        regions is skipped (``DetectResult.predicted``).

        Also counts, per reason, the markers OpenCV found that were dropped (:class:`DetectResult`)."""
        gray = _checked_gray(gray)
        if predicted and regions is not None and self._fits_predictions:
            dropped_near: Counter[str] = Counter()
            kept = self._predicted(gray, tuple(predicted), dropped_near)
            if kept is not None:
                if self.params.corner_refinement is CornerRefinement.TEMPLATE:
                    kept = self._template_refined(gray, kept, lens)
                return DetectResult(kept, dict(dropped_near), predicted=True)
        if regions is not None:
            height, width = gray.shape
            for box in regions:
                x0, y0, x1, y1 = box
                if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
                    raise ImageError(f"region {tuple(box)} is not inside the {width}x{height} image")
            regions = merged_boxes(regions)
        images = ((gray,) if self.params.detect_normal_marker else ()) + (
            (255 - gray,) if self.params.detect_inverted_marker else ())
        found: list[Detection] = []
        dropped: Counter[str] = Counter()
        for image in images:
            if regions is None:
                kept = self._detect(image, self._detector, np.zeros(2), dropped)
            else:
                kept = tuple(d for box in regions for d in self._detect_box(image, box, dropped))
            if self.params.corner_refinement is CornerRefinement.TEMPLATE:
                kept = self._template_refined(image, kept, lens)
            found.extend(kept)
        if len(images) > 1 or regions is not None and len(regions) > 1:
            found.sort(key=_detection_order)
        return DetectResult(tuple(found), dict(dropped))

    @property
    def _fits_predictions(self) -> bool:
        """Whether :meth:`find` may take verified predictions for a search (see there)."""
        return (self.params.corner_refinement in (CornerRefinement.EDGE, CornerRefinement.TEMPLATE)
                and not self.params.detect_inverted_marker)

    def _predicted(self, gray: np.ndarray, predicted: tuple[Detection, ...],
                   dropped: Counter[str]) -> tuple[Detection, ...] | None:
        """The ``predicted`` markers edge-fitted from their predicted corners where they are a valid
        quad that reads as their id there (:func:`cubetrack.detect.predicted.marker_reads`), and
        the others as OpenCV finds them in a box around their prediction
        (:func:`cubetrack.detect.predicted.marker_box`; its drops counted into ``dropped``) — one
        not found there either is not seen, as OpenCV's search would not see it. No box for one
        predicted with cells narrower than a pixel (nothing can read it:
        :func:`cubetrack.detect.predicted.resolvable_markers`), nor for one whose edge fit gave a valid
        quad without a dark border (:func:`cubetrack.detect.predicted.marker_reads`: no marker OpenCV could
        identify lies there, oblique or small past reading); None when none reads at its prediction
        (nothing confirms it: the regions are searched)."""
        quads = np.array([d.corners_px for d in predicted], dtype=np.float64)
        modules = np.array([modules_of(d.dictionary) for d in predicted])
        fitted = refine_corners_edges(gray, quads, modules, self.params.predicted_edge_iterations,  # NaN: failed
                                      settled_px=self.params.predicted_edge_settled_px)
        valid, areas = _quad_checks(fitted, self.params.min_area_px2)
        reads, bordered = marker_reads(gray, np.where(valid[:, None, None], fitted, np.nan), predicted,
                                       self.params.error_correction_rate)
        read = (valid & reads).tolist()
        if not any(read):
            return None
        fitted.setflags(write=False)
        # plain Python from here: a handful of markers
        found = {i: Detection(d.marker_id, fitted[i], area, d.dictionary)
                 for i, (d, area) in enumerate(zip(predicted, areas.tolist(), strict=True)) if read[i]}
        # searched for: the markers whose fit failed (off their prediction, past the fit's reach) and those with
        # a dark border but other cells (turned, another id, a misread bit, OpenCV's border limit), as OpenCV may
        # read them
        unread = [i for i, (is_read, fit, black) in enumerate(zip(read, valid.tolist(), bordered.tolist(), strict=True))
                  if not is_read and (black or not fit)]
        if unread:
            centres = None
            for i in np.array(unread)[resolvable_markers(quads[unread], modules[unread])].tolist():
                # a marker of its id whose centre is nearer its prediction than any other's (a cube may
                # carry one id on every face: the box can show a neighbouring face, found already)
                key = predicted[i].dictionary, predicted[i].marker_id
                for d in self._detect_box(gray, marker_box(quads[i], gray.shape), dropped):
                    if (d.dictionary, d.marker_id) == key:
                        centres = quads.mean(axis=1) if centres is None else centres
                        if int(np.abs(centres - d.corners_px.mean(axis=0)).sum(axis=1).argmin()) == i:
                            found[i] = d
        return tuple(found.values()) if len(found) == 1 else tuple(sorted(found.values(), key=_detection_order))

    def _lens_map(self, lens: CameraIntrinsics | None) -> LensMap:
        """This camera's :class:`LensMap`, built on first use."""
        if lens is None:
            return _NO_LENS
        key = _lens_key(lens)
        mapping = self._lens_maps.get(key)
        if mapping is None:
            mapping = self._lens_maps[key] = LensMap(lens)
        return mapping

    def _template_refined(self, gray: np.ndarray, found: tuple[Detection, ...],
                          lens: CameraIntrinsics | None) -> tuple[Detection, ...]:
        """``found`` (edge-fitted) with each marker's corners re-measured by the template fit; a
        marker whose fit fails (too close to the image border, diverged) keeps its edge fit's."""
        mapping = self._lens_map(lens)
        out = []
        for d in found:
            corners = fast_template_corners(gray, d.corners_px, d.dictionary, d.marker_id, mapping,
                                            self.params.template_iterations)
            if corners is None or not is_valid_quad(corners, self.params.min_area_px2):
                log.debug("template fit of %s id %d failed: kept the edge fit's corners", d.dictionary, d.marker_id)
                out.append(d)
                continue
            corners.setflags(write=False)
            out.append(Detection(d.marker_id, corners, shoelace_area(corners), d.dictionary))
        return tuple(out)

    def detect_gray(self, gray: np.ndarray) -> tuple[Detection, ...]:
        """Deprecated: ``detect(gray)``."""
        warnings.warn("Detector.detect_gray is deprecated; use Detector.detect(gray)", DeprecationWarning, stacklevel=2)
        return self.detect(gray)

    def _detect_box(self, gray: np.ndarray, box: Box, dropped: Counter[str]) -> tuple[Detection, ...]:
        """Detections inside one box of ``gray`` (checked), as :meth:`find` describes."""
        x0, y0, x1, y1 = box
        crop = np.ascontiguousarray(gray[y0:y1, x0:x1])
        scale = max(gray.shape) / max(crop.shape)
        if scale != self._region_scale:
            cv_params = self._region_params
            cv_params.minMarkerPerimeterRate = self.params.min_marker_perimeter_rate * scale
            cv_params.maxMarkerPerimeterRate = self.params.max_marker_perimeter_rate * scale
            self._region_detector.setDetectorParameters(cv_params)
            self._region_scale = scale
        return self._detect(crop, self._region_detector, np.array([x0, y0], dtype=float), dropped)

    def _detect(self, gray: np.ndarray, detector: cv2.aruco.ArucoDetector, offset_px: np.ndarray,
                dropped: Counter[str]) -> tuple[Detection, ...]:
        """Run ``detector`` on ``gray``; refine, check and shift the corners by ``offset_px``;
        count what is dropped into ``dropped``.

        A marker whose edge refinement fails is dropped: OpenCV's unrefined corners can be pixels
        off on small, oblique markers, and downstream stages take corners as precise."""
        corners, ids, _rejected, dict_indices = detector.detectMarkersMultiDict(gray)
        if ids is None or len(ids) == 0:
            return ()
        ids = np.asarray(ids).reshape(-1)
        dict_indices = (np.zeros_like(ids) if dict_indices is None
                        else np.asarray(dict_indices).reshape(-1))
        quads = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2) + self._offset_px
        fit_failed = np.zeros(len(ids), dtype=bool)
        if self.params.corner_refinement in (CornerRefinement.EDGE, CornerRefinement.TEMPLATE):
            modules: int | np.ndarray = (self._modules[0] if len(self._modules) == 1
                                         else np.asarray(self._modules)[dict_indices])
            quads = refine_corners_edges(gray, quads, modules, self.params.edge_iterations)  # NaN: failed
            fit_failed = np.asarray(~np.isfinite(quads).all(axis=(1, 2)))
        valid, areas = _quad_checks(quads, self.params.min_area_px2)
        if not valid.all():
            for reason, n in ((DROP_EDGE_FIT, int(fit_failed.sum())),
                              (DROP_QUAD, int((~valid & ~fit_failed).sum()))):
                if n:
                    dropped[reason] += n
            log.debug("dropped detections of ids %s (edge refinement failed, or not a convex quad)",
                      ids[~valid].tolist())
        quads += offset_px
        quads.setflags(write=False)
        # plain Python from here: a handful of markers
        x_sums, areas, ids, dict_indices = (quads[..., 0].sum(axis=1).tolist(), areas.tolist(), ids.tolist(),
                                            dict_indices.tolist())
        names = [self.dictionaries[k] for k in dict_indices]
        order = sorted(np.flatnonzero(valid).tolist(), key=lambda i: (names[i], ids[i], x_sums[i]))  # _detection_order
        return tuple(Detection(marker_id=ids[i], corners_px=quads[i], area_px2=areas[i], dictionary=names[i])
                     for i in order)

    def detect_jpeg(self, jpeg: bytes, source: str = "JPEG") -> tuple[Detection, ...]:
        """Decode a JPEG to grayscale and detect; ImageError (naming ``source``) when it is empty,
        truncated or corrupt."""
        return self.detect(decode_gray(jpeg, source))


_NO_LENS = LensMap(None)


Box = tuple[int, int, int, int]  # x0, y0, x1, y1: pixels, end exclusive


def _detection_order(d: Detection) -> tuple[str, int, float]:
    """Dictionary, id, then x: the corners' summed x (the mean's order, at half its cost)."""
    return d.dictionary, d.marker_id, float(d.corners_px[:, 0].sum())


def merged_boxes(boxes: Iterable[Box]) -> list[Box]:
    """``boxes`` with every group of overlapping boxes replaced by their bounding box (repeated
    until none overlap), so that no part of the image is searched twice."""
    out: list[Box] = []
    for box in boxes:
        x0, y0, x1, y1 = box
        merged = True
        while merged:
            merged = False
            for i, (a0, b0, a1, b1) in enumerate(out):
                if x0 < a1 and a0 < x1 and y0 < b1 and b0 < y1:
                    x0, y0, x1, y1 = min(x0, a0), min(y0, b0), max(x1, a1), max(y1, b1)
                    del out[i]
                    merged = True
                    break
        out.append((x0, y0, x1, y1))
    return out


def _checked_gray(gray: np.ndarray) -> np.ndarray:
    gray = np.asarray(gray)
    if gray.ndim != 2 or gray.dtype != np.uint8 or gray.size == 0:
        raise ImageError(f"detection needs a non-empty 8-bit grayscale image (H, W), got {gray.dtype} {gray.shape}")
    return gray
