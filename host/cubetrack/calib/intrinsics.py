"""Intrinsic camera calibration from photos of a ChArUco board (OpenCV 5).

Per image: ``CharucoDetector.detectBoard`` finds the board's markers and interpolates and
refines its chessboard corners; ``board.matchImagePoints`` pairs them with the board's 3D
points. ``cv2.calibrateCameraExtended`` then fits ``K`` and plumb_bob distortion
(k1, k2, p1, p2, k3) over all usable views. The result is written as ROS camera_info YAML by
:func:`cubetrack.io.camera_info.write_camera_info`.

A view is usable when it shows at least ``min_corners`` ChArUco corners that are not all on one
line; fewer than ``min_views`` usable views is an error (the fit would be underdetermined).
Pixel convention: OpenCV's, (0, 0) = centre of the top-left pixel.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import CalibrationError, ImageError
from cubetrack.core.params import check, param
from cubetrack.core.progress import Progress
from cubetrack.detect.detector import CornerRefinement, aruco_dictionary, opencv_corner_refinement, read_gray

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class IntrinsicsParams:
    """The ChArUco board and what makes a view usable."""

    squares_x: int = param(5, "board squares along x (columns), e.g. 5 for a '5x7' board")
    squares_y: int = param(7, "board squares along y (rows), e.g. 7 for a '5x7' board")
    square_m: float = param(0.04, "chessboard square side, metres")
    marker_m: float = param(0.02, "ArUco marker side inside a white square, metres")
    dictionary: str = param("DICT_6X6_250", "OpenCV dictionary of the board's markers")
    legacy_pattern: bool = param(
        False, "boards made with OpenCV < 4.6 that have an even number of rows need this")
    marker_refinement: CornerRefinement = param(
        CornerRefinement.APRILTAG,
        "corner refinement of the board's markers, which seed the chessboard corners: apriltag "
        "(offline: the most accurate) | subpix | contour | none (edge is the tracker's own, not "
        "available inside OpenCV's ChArUco detector)")
    min_corners: int = param(6, "ChArUco corners a view needs to be used")
    min_views: int = param(3, "usable views needed to calibrate")

    def __post_init__(self) -> None:
        check(self.squares_x >= 2 and self.squares_y >= 2,
              f"a ChArUco board needs at least 2x2 squares, got {self.squares_x}x{self.squares_y}")
        check(0 < self.marker_m < self.square_m,
              f"marker side ({self.marker_m} m) must be positive and smaller than the square side ({self.square_m} m)")
        check(self.min_corners >= 4 and self.min_views >= 1, "min_corners must be at least 4 and min_views at least 1")
        aruco_dictionary(self.dictionary)
        check(self.marker_refinement is not CornerRefinement.EDGE,
              "marker_refinement 'edge' is not available for ChArUco boards (OpenCV's CharucoDetector refines the "
              "markers itself); use apriltag, subpix, contour or none")


@dataclass(frozen=True, slots=True)
class ViewResult:
    """One image: how many ChArUco corners were found, whether it was used (else why not) and,
    when used, its RMS reprojection error (px)."""

    name: str
    corners: int
    used: bool
    reason: str = ""
    rms_px: float = float("nan")


@dataclass(frozen=True, slots=True, eq=False)
class IntrinsicsResult:
    """The calibration: intrinsics, overall RMS reprojection error (px), per-view results and
    the standard deviations of fx and fy (px) estimated by OpenCV."""

    intrinsics: CameraIntrinsics
    rms_px: float
    views: tuple[ViewResult, ...]
    std_fx_px: float
    std_fy_px: float


def make_board(params: IntrinsicsParams):
    """The ``cv2.aruco.CharucoBoard`` described by ``params``."""
    import cv2

    board = cv2.aruco.CharucoBoard((params.squares_x, params.squares_y), params.square_m,
                                   params.marker_m, aruco_dictionary(params.dictionary))
    board.setLegacyPattern(params.legacy_pattern)
    return board


def _charuco_detector(board, params: IntrinsicsParams):
    import cv2

    dp = cv2.aruco.DetectorParameters()
    dp.cornerRefinementMethod = opencv_corner_refinement(params.marker_refinement)
    return cv2.aruco.CharucoDetector(board, cv2.aruco.CharucoParameters(), dp)


def calibrate_intrinsics(
    images: Sequence[tuple[str, np.ndarray]],
    params: IntrinsicsParams | None = None,
    camera_name: str = "camera",
    progress: Progress | None = None,
) -> IntrinsicsResult:
    """Calibrate ``K`` and distortion from ``(name, grayscale image)`` views of the board.

    All images must have the same size. CalibrationError when fewer than ``min_views`` views
    are usable, naming how many corners each image showed.
    """
    import cv2

    params = params or IntrinsicsParams()
    if not images:
        raise CalibrationError("no images given: pass photos of the ChArUco board")
    board = make_board(params)
    detector = _charuco_detector(board, params)
    size = None
    objs, imgs, used = [], [], []
    views: list[ViewResult] = []
    for i, (name, gray) in enumerate(images):
        h, w = gray.shape[:2]
        if size is None:
            size = (w, h)
        elif (w, h) != size:
            raise ImageError(f"{name}: image is {w}x{h}, the first one is {size[0]}x{size[1]}; "
                             "all views must come from the same camera mode")
        charuco_corners, charuco_ids, _, _ = detector.detectBoard(gray)
        n = 0 if charuco_ids is None else len(charuco_ids)
        if progress is not None:
            progress("detect board", i + 1, len(images))
        if n < params.min_corners:
            views.append(ViewResult(name, n, False, f"{n} corners (< {params.min_corners})"))
            continue
        if board.checkCharucoCornersCollinear(charuco_ids):
            views.append(ViewResult(name, n, False, "corners on one line"))
            continue
        obj, img = board.matchImagePoints(charuco_corners, charuco_ids)
        objs.append(np.asarray(obj, dtype=np.float32).reshape(-1, 1, 3))
        imgs.append(np.asarray(img, dtype=np.float32).reshape(-1, 1, 2))
        used.append(len(views))
        views.append(ViewResult(name, n, True))
    if len(objs) < params.min_views:
        found = ", ".join(f"{v.name}: {v.corners}" for v in views)
        raise CalibrationError(
            f"only {len(objs)} of {len(images)} images show the {params.squares_x}x{params.squares_y} "
            f"{params.dictionary} ChArUco board with at least {params.min_corners} corners; need "
            f"{params.min_views} (corners found: {found}). Check --board, --dictionary and --legacy")
    assert size is not None  # set by every used view, and there are min_views of them
    try:
        # OpenCV's stubs do not allow None for the cameraMatrix and distCoeffs outputs; OpenCV does
        rms, K, dist, rvecs, tvecs, std_intr, _, _ = cv2.calibrateCameraExtended(  # type: ignore[call-overload]
            objs, imgs, size, None, None)
    except cv2.error as exc:
        raise CalibrationError(f"calibration failed: {str(exc).strip().splitlines()[-1]}") from None
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise CalibrationError("calibration diverged (non-finite or negative focal length); add views "
                               "that show the board at different angles and positions")
    for k, obj, img, rvec, tvec in zip(used, objs, imgs, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        err = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img.reshape(-1, 2)) ** 2, axis=1))))
        views[k] = ViewResult(views[k].name, views[k].corners, True, "", err)
    std = np.asarray(std_intr, dtype=float).reshape(-1)
    intr = CameraIntrinsics(size[0], size[1], np.asarray(K, dtype=float),
                            np.asarray(dist, dtype=float).reshape(-1), camera_name)
    log.info("calibrated %s from %d views: rms %.3f px, fx %.2f fy %.2f", camera_name, len(objs), rms,
             K[0, 0], K[1, 1])
    return IntrinsicsResult(intr, float(rms), tuple(views),
                            float(std[0]), float(std[1]))


def calibrate_intrinsics_files(
    paths: Sequence[str | Path],
    params: IntrinsicsParams | None = None,
    camera_name: str = "camera",
    progress: Progress | None = None,
) -> IntrinsicsResult:
    """:func:`calibrate_intrinsics` over image files; a missing or corrupt file is an ImageError
    naming it."""
    images = []
    for i, p in enumerate(paths):
        images.append((str(p), read_gray(p)))
        if progress is not None:
            progress("read images", i + 1, len(paths))
    return calibrate_intrinsics(images, params, camera_name, progress)
