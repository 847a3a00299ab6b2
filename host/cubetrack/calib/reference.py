"""The world reference beyond one marker: several markers at known world poses and a ChArUco
board, measured in a static camera's frames.

One 25 cm marker seen obliquely from 2+ m is a weak reference: four corners, 25-50 px apart. More
markers spread over the floor (each with its measured pose in the world) and the markers of a
ChArUco board (at the places OpenCV's board geometry gives them) give many more points, far
apart. Per frame of a calibration recording every marker of the reference is detected and the
robust method re-measures its corners from its edges, as for the single world marker. (The
board's chessboard corners, from ``cv2.aruco.CharucoDetector``, were measured worse on rendered
boards seen obliquely from 2 m: only corners next to detected markers are interpolated, and
single corners were biased by up to 0.9 px, 14-17 mm of camera position against 0.3-0.8 mm from
the markers' edges.) As the camera and the reference do not move, each point is the same in
every frame: per marker (its four corners together), frames that stray from the median are
dropped (:func:`cubetrack.calib.extrinsics.inlier_frames`) and the rest averaged. The
camera pose is one PnP over all averaged points (``cv2.solvePnPGeneric``: IPPE's two solutions
when the points are coplanar, as on a floor, else SQPnP; each polished by Levenberg-Marquardt, the
better kept). The paper's CMA method averages the poses of the single frames instead.

The same averaged points are the world terms of the bundle adjustment (:mod:`cubetrack.calib.bundle`).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from cubetrack.calib.extrinsics import (
    CalibrationMethod,
    CalibrationParams,
    calibration_detector,
    calibration_images,
    cma_pose,
    edge_fitted_corners,
    inlier_frames,
    pose_spread,
)
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, WorldBoard, WorldConfig, WorldMarker
from cubetrack.core.errors import CalibrationError
from cubetrack.core.geometry import T_from_rvec_tvec, invert_T, make_T, transform_points
from cubetrack.core.progress import Progress
from cubetrack.core.records import Frame
from cubetrack.detect.detector import (
    DetectorParams,
    aruco_dictionary,
)
from cubetrack.estimate.match import detections_of

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True, eq=False)
class ReferenceSighting:
    """The reference in one frame: per marker seen (``"marker <k>"``, k its index in the
    reference: the world marker, ``markers``, then the board's) its corners in the world (4, 3)
    and their pixels (4, 2), TL TR BR BL."""

    seq: int
    targets: dict[str, tuple[np.ndarray, np.ndarray]]

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """All (world points (n, 3), pixels (n, 2)) of the frame."""
        return (np.vstack([t[0] for t in self.targets.values()]), np.vstack([t[1] for t in self.targets.values()]))


@dataclass(frozen=True, slots=True, eq=False)
class ReferencePoints:
    """The reference in one camera after averaging: world points (n, 3) and their averaged
    pixels (n, 2); per marker the frames it was averaged over."""

    points_world_m: np.ndarray
    pixels: np.ndarray
    frames: dict[str, int]


def board_markers(board: WorldBoard) -> tuple[WorldMarker, ...]:
    """The board's markers at their poses in the world, where OpenCV's ``CharucoBoard`` puts them
    (``getObjPoints``, legacy pattern included)."""
    cv_board = cv2.aruco.CharucoBoard((board.squares_x, board.squares_y), board.square_size_m, board.marker_size_m,
                                      aruco_dictionary(board.dictionary), np.array(list(board.marker_ids)))
    cv_board.setLegacyPattern(board.legacy_pattern)
    T = board.T_world_board @ board.T_board_opencv
    out = []
    for marker_id, corners in zip(np.asarray(cv_board.getIds()).ravel(), cv_board.getObjPoints(), strict=True):
        c = transform_points(T, np.asarray(corners, float).reshape(4, 3))  # TL TR BR BL
        x = (c[1] - c[0]) / np.linalg.norm(c[1] - c[0])
        y = (c[0] - c[3]) / np.linalg.norm(c[0] - c[3])
        out.append(WorldMarker(int(marker_id), board.marker_size_m, make_T(np.column_stack([x, y, np.cross(x, y)]),
                                                                            c.mean(axis=0)), board.dictionary))
    return tuple(out)


def collect_reference(frames: Iterable[Frame], world: WorldConfig, intrinsics: CameraIntrinsics,
                      params: CalibrationParams,
                      progress: Progress | None = None, stage: str = "calibrate",
                      detector_params: DetectorParams | None = None,
                      total_frames: int = 0) -> tuple[list[ReferenceSighting], int, Counter]:
    """Detect the reference in ``frames`` until ``params.samples`` frames showed any of it
    (``params``: :class:`cubetrack.calib.extrinsics.CalibrationParams`). Returns (sightings,
    frames decoded, skipped frames by reason); corrupt frames are skipped and counted."""
    detector, refine = calibration_detector(world, params, detector_params)
    markers = world.reference_markers() + (board_markers(world.board) if world.board is not None else ())
    sightings: list[ReferenceSighting] = []
    skipped: Counter = Counter()
    frames_read = 0
    for frame, gray in calibration_images(frames, intrinsics, skipped, lambda: len(sightings) >= params.samples,
                                          progress, stage, total_frames):
        frames_read += 1
        targets = {}
        found = detector.detect(gray)
        for k, m in enumerate(markers):
            mine = detections_of(found, m.dictionary, (m.marker_id,))
            if len(mine) != 1:
                continue
            corners = mine[0].corners_px
            if refine:
                corners = edge_fitted_corners(gray, corners, m.dictionary, intrinsics, params.edge_min_contrast)
                if np.isnan(corners).any():
                    continue
            targets[f"marker {k}"] = (m.corners_world_m(), np.asarray(corners, float))
        if not targets:
            skipped["no world reference"] += 1
            continue
        sightings.append(ReferenceSighting(frame.seq, targets))
    return sightings, frames_read, skipped


def average_reference(sightings: Sequence[ReferenceSighting], threshold_px: float, min_frames: int) -> ReferencePoints:
    """Each marker's four corners averaged over the frames that saw it, frames straying from the
    median dropped (:func:`cubetrack.calib.extrinsics.inlier_frames`); markers seen in fewer than
    ``min_frames`` frames are left out. CalibrationError when none is left."""
    seen: dict[str, tuple[np.ndarray, list[np.ndarray]]] = {}
    for s in sightings:
        for name, (target_points, target_pixels) in s.targets.items():
            seen.setdefault(name, (target_points, []))[1].append(target_pixels)
    points, pixels, frames = [], [], {}
    for name, (world_points, corners) in sorted(seen.items()):
        if len(corners) < min_frames:
            continue
        stack = np.array(corners)
        keep = inlier_frames(stack, threshold_px)
        points.append(world_points)
        pixels.append(stack[keep].mean(axis=0))
        frames[name] = int(keep.sum())
    if not points:
        raise CalibrationError(f"no marker of the world reference was seen in {min_frames} or more frames")
    return ReferencePoints(np.vstack(points), np.vstack(pixels), frames)


def pnp_pose(points_world_m: np.ndarray, pixels: np.ndarray, intrinsics: CameraIntrinsics) -> tuple[np.ndarray, float]:
    """``T_world_cam`` from world points and their pixels, and its RMS reprojection error (px):
    IPPE's two solutions for coplanar points, else SQPnP; each polished by Levenberg-Marquardt,
    the better kept. CalibrationError for fewer than four points or no solution."""
    obj = np.asarray(points_world_m, np.float64).reshape(-1, 3)
    img = np.asarray(pixels, np.float64).reshape(-1, 2)
    if len(obj) < 4:
        raise CalibrationError(f"{len(obj)} reference points: a camera pose needs at least four")
    K, dist = np.asarray(intrinsics.K, np.float64), np.asarray(intrinsics.dist, np.float64)
    spread = np.linalg.svd(obj - obj.mean(axis=0), compute_uv=False)
    planar = spread[2] < 1e-6 * max(spread[0], 1e-12)
    flag = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_SQPNP
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, dist, flags=flag)
    except cv2.error as exc:
        raise CalibrationError(f"no camera pose from {len(obj)} reference points: {str(exc).strip()[-80:]}") from None
    best = None
    for rvec, tvec in zip(rvecs[:n], tvecs[:n], strict=True):
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec.copy(), tvec.copy())
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
        if best is None or rms < best[1]:
            best = (T_from_rvec_tvec(rvec.ravel(), tvec.ravel()), rms)
    if best is None or not np.all(np.isfinite(best[0])):
        raise CalibrationError(f"no camera pose from {len(obj)} reference points")
    return invert_T(best[0]), best[1]


def calibrate_reference(sightings: Sequence[ReferenceSighting], intrinsics: CameraIntrinsics,
                        params: CalibrationParams) -> tuple[CameraExtrinsics, int]:
    """A camera's pose from its reference sightings: ``robust`` (one PnP on the averaged points)
    or ``cma`` (the paper's average of per-frame poses). Returns (extrinsics, frames used)."""
    per_frame = []
    for s in sightings:
        try:
            per_frame.append(pnp_pose(*s.points(), intrinsics)[0])
        except CalibrationError:
            continue
    if params.method is CalibrationMethod.CMA:
        if not per_frame:
            raise CalibrationError("no frame shows four or more reference points")
        T, used = cma_pose(per_frame), len(per_frame)
    else:
        averaged = average_reference(sightings, params.outlier_threshold_px, params.min_samples)
        T, _rms = pnp_pose(averaged.points_world_m, averaged.pixels, intrinsics)
        used = max(averaged.frames.values())
    spread_m, spread_deg = pose_spread(per_frame, T)
    return CameraExtrinsics(T, used, spread_m, spread_deg, params.method.value), used
