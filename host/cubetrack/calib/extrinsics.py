"""Camera extrinsic calibration against the world marker: ``T_world_cam`` per camera.

Two methods, selected by :class:`CalibrationParams` (``[calibration] method``):

``cma``
    The paper's (section II.C, eq. 1): every frame's world-marker pose gives a camera pose
    sample ``d_t``; position and quaternion components are averaged with the recursive
    cumulative moving average ``CMA_t = CMA_{t-1} + (d_t - CMA_{t-1}) / (t + 1)``, each
    quaternion's sign aligned to the running mean first, the result normalised at the end.

``robust`` (default)
    The camera and the marker do not move during calibration, so the marker's corners are the
    same in every frame; the per-frame pose noise averages out, but a systematic corner bias
    does not (``cv-facts.md`` §5). So: (1) every detection's corners are re-measured from the
    marker's four edges with the camera's lens model (:func:`cubetrack.detect.detector.refine_corners_edges`
    with :data:`EDGE_FIT`: sub-pixel edge points, one straight line per edge in undistorted
    coordinates, corners = line intersections) — free of the inward bias of OpenCV's corners
    (``[calibration] corner_refinement`` may pick another of the detector's methods); (2) frames
    whose corners stray from the per-corner median (a bump, a passer-by, a bad decode) are
    rejected; (3) the inliers' corners are
    averaged and one PnP gives the pose, the planar ambiguity (IPPE's two solutions) being
    settled on the noise-free averaged corners by reprojection error.

Every result carries the number of samples used and their spread: the RMS distance (metres)
and RMS angle (degrees) of the per-frame camera poses from the result.

:func:`calibrate_cameras` takes frames (any iterable of :class:`cubetrack.core.records.Frame`
per camera, e.g. held in memory) and returns a :class:`CalibrationReport`; it reads no file.
``cubetrack.app.calibrate.calibrate_recording`` feeds it a recording folder and a tracker config.

Frames: ``T_cam_marker`` from PnP; the world frame is the world marker's frame (z up), so
``T_world_cam = inv(T_cam_marker)``.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, WorldConfig
from cubetrack.core.errors import CalibrationError, ImageError
from cubetrack.core.geometry import (
    R_from_quat_xyzw,
    invert_T,
    make_T,
    quat_xyzw_from_R,
    rotation_angle,
    shoelace_area,
)
from cubetrack.core.params import check, param
from cubetrack.core.progress import Progress
from cubetrack.core.records import Detection, Frame
from cubetrack.detect.detector import (
    CornerRefinement,
    Detector,
    DetectorParams,
    aruco_dictionary,
    decode_gray,
)
from cubetrack.detect.edge_fit import refine_corners_edges
from cubetrack.estimate.marker import marker_pose
from cubetrack.estimate.match import detections_of

log = logging.getLogger(__name__)


class CalibrationMethod(str, enum.Enum):  # noqa: UP042 (StrEnum would change str() of a member)
    CMA = "cma"
    ROBUST = "robust"


# The edge fit of the robust method (offline, averaged over many frames: bias matters, noise does
# not): denser sampling over more of each side (12-88 %) and iterations than the detector's, and
# edge points from the gradient's peak with a narrow window (focus='peak'), which a narrow white
# margin's outer edge does not pull inward (measured: marker size bias +0.001 px, -0.02 px with
# the detector's tent). Camera positions in `cubetrack simulate` calibrations: docs/calibration.md.
EDGE_FIT: dict[str, Any] = dict(iterations=3, samples_along=64, samples_across=65, span=(0.12, 0.88), focus="peak")


@dataclass(frozen=True, slots=True)
class CalibrationParams:
    """The ``[calibration]`` section of the tracker config."""

    method: CalibrationMethod = param(
        CalibrationMethod.ROBUST,
        "'robust' (edge-refined corners, outlier rejection, one PnP on the averaged corners) or "
        "'cma' (the paper's cumulative moving average of per-frame poses, eq. 1)")
    samples: int = param(200, "world-marker sightings to use per camera (the first N found)")
    min_samples: int = param(5, "fewer sightings than this make the camera fail to calibrate")
    corner_refinement: CornerRefinement = param(
        CornerRefinement.EDGE,
        "robust method only: how the world marker's corners are measured, one of the detector's "
        "methods (edge | none | subpix | contour | apriltag); edge = cubetrack's edge fit with the "
        "camera's lens model, tuned for averaging (frames where it fails are skipped). The values "
        "were 'edges' | 'detector' before; cma always takes the [detector] corners")
    outlier_threshold_px: float = param(
        1.0, "robust method: a frame whose corners lie farther than this (px) from the per-corner "
        "median is an outlier (the threshold grows to 4 robust sigmas when the corners are noisier)")
    edge_min_contrast: float = param(
        20.0, "edge refinement: an edge profile is used when it brightens by more than this from "
        "the marker's black border outwards, grey levels (0-255)")

    def __post_init__(self) -> None:
        check(self.samples >= 1, f"samples must be at least 1, got {self.samples}")
        check(self.min_samples >= 1, f"min_samples must be at least 1, got {self.min_samples}")
        check(self.outlier_threshold_px > 0, f"outlier_threshold_px must be positive, got {self.outlier_threshold_px}")


# ---------------------------------------------------------------------------------------------
# The paper's recursive cumulative moving average (eq. 1)


class CumulativeMovingAverage:
    """Recursive cumulative moving average of vectors (paper eq. 1).

    The first sample initialises the estimate (t = 0); then
    ``CMA_t = CMA_{t-1} + (d_t - CMA_{t-1}) / (t + 1)``.
    """

    def __init__(self) -> None:
        self.count = 0
        self.value: np.ndarray | None = None

    def update(self, d: np.ndarray) -> np.ndarray:
        d = np.asarray(d, dtype=float)
        if self.value is None:
            self.value = d.copy()
        else:
            t = self.count  # index of this sample: 1 for the second one
            self.value = self.value + (d - self.value) / (t + 1)
        self.count += 1
        return self.value


def cma_pose(T_world_cams: Sequence[np.ndarray]) -> np.ndarray:
    """The paper's calibration: CMA over translation and quaternion (x, y, z, w) components.

    Each quaternion's sign is aligned to the running mean before it is averaged (q and -q are
    the same rotation); the mean quaternion is normalised at the end.
    """
    if len(T_world_cams) == 0:
        raise CalibrationError("no camera pose samples to average")
    position = CumulativeMovingAverage()
    quat = CumulativeMovingAverage()
    for T in T_world_cams:
        position.update(T[:3, 3])
        q = quat_xyzw_from_R(T[:3, :3])
        if quat.value is not None and float(np.dot(q, quat.value)) < 0.0:
            q = -q
        quat.update(q)
    mean_q, mean_position = quat.value, position.value
    assert mean_q is not None and mean_position is not None  # at least one sample (checked above)
    return make_T(R_from_quat_xyzw(mean_q / np.linalg.norm(mean_q)), mean_position)


def pose_spread(T_world_cams: Sequence[np.ndarray], T_ref: np.ndarray) -> tuple[float, float]:
    """RMS position distance (m) and RMS rotation angle (deg) of poses from ``T_ref``."""
    if len(T_world_cams) == 0:
        return 0.0, 0.0
    d = np.array([np.linalg.norm(T[:3, 3] - T_ref[:3, 3]) for T in T_world_cams])
    a = np.array([rotation_angle(T[:3, :3], T_ref[:3, :3], "deg") for T in T_world_cams])
    return float(np.sqrt(np.mean(d**2))), float(np.sqrt(np.mean(a**2)))


# ---------------------------------------------------------------------------------------------
# World-marker sightings in a camera's frames


@dataclass(frozen=True, slots=True, eq=False)
class Sighting:
    """The world marker seen in one frame: its detection (refined corners when the robust
    method refines them) and the camera pose it implies (``T_world_cam``, the better IPPE
    solution, and the other one when finite)."""

    seq: int
    detection: Detection
    T_world_cam: np.ndarray
    T_world_cam_alt: np.ndarray | None


@dataclass(frozen=True, slots=True, eq=False)
class CameraCalibration:
    """One camera's calibration and how it went.

    ``frames_read`` = frames decoded; ``skipped`` = frames not used, by reason (corrupt JPEG,
    no world marker, refinement failed); ``inliers`` = sightings kept after outlier rejection.
    """

    camera: str
    extrinsics: CameraExtrinsics
    frames_read: int
    sightings: int
    inliers: int
    skipped: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True, slots=True, eq=False)
class CalibrationReport:
    """The result of :func:`calibrate_cameras`: calibrated cameras, and the cameras that
    never (or too rarely) saw the world marker with the reason."""

    cameras: dict[str, CameraCalibration]
    missing: dict[str, str]

    @property
    def extrinsics(self) -> dict[str, CameraExtrinsics]:
        return {name: c.extrinsics for name, c in self.cameras.items()}


def world_detector(world: WorldConfig, detector_params: DetectorParams | None = None,
                   corner_refinement: CornerRefinement | None = None) -> Detector:
    """A :class:`cubetrack.detect.detector.Detector` for the world reference's dictionaries, with the
    config's ``[detector]`` settings (``detector_params``; None = the defaults) and, when given,
    another ``corner_refinement``."""
    params = dataclasses.replace(detector_params or DetectorParams(), dictionary=world.dictionary)
    if corner_refinement is not None:
        params = dataclasses.replace(params, corner_refinement=corner_refinement)
    return Detector(params, list(world.dictionaries))


def calibration_detector(world: WorldConfig, params: CalibrationParams,
                         detector_params: DetectorParams | None = None) -> tuple[Detector, bool]:
    """The detector calibration measures the world reference with, and whether its corners are
    then re-measured by the edge fit (:data:`EDGE_FIT`): the robust method detects with
    ``[calibration] corner_refinement`` (``edge``: OpenCV's unrefined quad, then the edge fit),
    the paper's CMA with the ``[detector]`` corners."""
    robust = params.method is CalibrationMethod.ROBUST
    refine = robust and params.corner_refinement is CornerRefinement.EDGE
    corner_refinement = (CornerRefinement.NONE if refine else params.corner_refinement) if robust else None
    return world_detector(world, detector_params, corner_refinement), refine


def calibration_images(frames: Iterable[Frame], intrinsics: CameraIntrinsics, skipped: Counter,
                       enough: Callable[[], bool], progress: Progress | None = None, stage: str = "calibrate",
                       total_frames: int = 0) -> Iterator[tuple[Frame, np.ndarray]]:
    """The grey images of a camera's calibration ``frames`` until ``enough()``: corrupt frames and
    frames not of the intrinsics' size are counted in ``skipped`` (never fatal). Progress counts
    frames examined out of ``total_frames`` (0 = unknown)."""
    seen = 0
    for frame in frames:
        if enough():
            break
        seen += 1
        if progress is not None:
            progress(stage, seen, total_frames)
        try:
            gray = decode_gray(frame.jpeg, f"{frame.camera} frame {frame.seq}")
        except ImageError as exc:
            skipped["corrupt JPEG"] += 1
            log.warning("%s; skipped", exc)
            continue
        if intrinsics.width and (gray.shape[1], gray.shape[0]) != (intrinsics.width, intrinsics.height):
            skipped["wrong image size"] += 1
            log.warning("%s frame %d: image is %dx%d, intrinsics are for %dx%d; skipped", frame.camera,
                        frame.seq, gray.shape[1], gray.shape[0], intrinsics.width, intrinsics.height)
            continue
        yield frame, gray
    if progress is not None and total_frames and seen < total_frames:
        progress(stage, total_frames, total_frames)  # enough sightings: done early


def edge_fitted_corners(gray: np.ndarray, corners_px: np.ndarray, dictionary: str, intrinsics: CameraIntrinsics,
                        min_contrast: float) -> np.ndarray:
    """A marker's corners re-measured by the calibration's edge fit (:data:`EDGE_FIT`, the
    camera's lens model); NaN when its edges cannot be fitted."""
    return refine_corners_edges(gray, corners_px, aruco_dictionary(dictionary).markerSize + 2, K=intrinsics.K,
                                dist=intrinsics.dist, min_contrast=min_contrast, **EDGE_FIT)


def _marker_poses(detection: Detection, size_m: float,
                  intrinsics: CameraIntrinsics) -> list[tuple[np.ndarray, float]]:
    """Both planar solutions ``(T_cam_marker, rms reprojection error px)``, best first, from
    :func:`cubetrack.estimate.marker.marker_pose` (each refined by Levenberg-Marquardt on the
    reprojection error: IPPE's closed form is not the least-squares optimum)."""
    mp = marker_pose(detection, size_m, intrinsics)
    if mp is None:
        return []
    out = [(mp.T_cam_marker, mp.reprojection_error_px)]
    if mp.T_cam_marker_alt is not None:
        out.append((mp.T_cam_marker_alt, mp.reprojection_error_alt_px))
    return out


def collect_sightings(
    frames: Iterable[Frame],
    world: WorldConfig,
    intrinsics: CameraIntrinsics,
    params: CalibrationParams,
    progress: Progress | None = None,
    stage: str = "calibrate",
    detector_params: DetectorParams | None = None,
    total_frames: int = 0,
) -> tuple[list[Sighting], int, Counter]:
    """Detect the world marker in ``frames`` until ``params.samples`` sightings are found.

    Progress counts frames examined out of ``total_frames`` (0 = unknown).
    Returns (sightings, frames decoded, skipped frames by reason). Corrupt frames are skipped
    and counted, never fatal. The robust method measures the corners with
    ``params.corner_refinement``; with ``edge`` (the default) the detector's unrefined quad is
    fitted by :func:`cubetrack.detect.detector.refine_corners_edges` with the camera's lens model.
    """
    detector, refine = calibration_detector(world, params, detector_params)
    sightings: list[Sighting] = []
    skipped: Counter = Counter()
    frames_read = 0
    for frame, gray in calibration_images(frames, intrinsics, skipped, lambda: len(sightings) >= params.samples,
                                          progress, stage, total_frames):
        frames_read += 1
        found = detections_of(detector.detect(gray), world.dictionary, (world.marker_id,))
        if not found:
            skipped["no world marker"] += 1
            continue
        if len(found) > 1:
            skipped["world marker id seen twice"] += 1
            continue
        det = found[0]
        if refine:
            corners = edge_fitted_corners(gray, det.corners_px, world.dictionary, intrinsics, params.edge_min_contrast)
            if np.isnan(corners).any():
                skipped["edge refinement failed"] += 1
                continue
            det = Detection(det.marker_id, corners, shoelace_area(corners), det.dictionary)
        poses = _marker_poses(det, world.marker_size_m, intrinsics)
        if not poses:
            skipped["no finite pose"] += 1
            continue
        T_alt = invert_T(poses[1][0]) if len(poses) > 1 else None
        sightings.append(Sighting(frame.seq, det, invert_T(poses[0][0]), T_alt))
    return sightings, frames_read, skipped


# ---------------------------------------------------------------------------------------------
# The two methods over sightings


def calibrate_cma(sightings: Sequence[Sighting]) -> CameraExtrinsics:
    """The paper's calibration (eq. 1) over the sightings' camera poses (better IPPE solution)."""
    Ts = [s.T_world_cam for s in sightings]
    T = cma_pose(Ts)
    spread_m, spread_deg = pose_spread(Ts, T)
    return CameraExtrinsics(T, len(Ts), spread_m, spread_deg, CalibrationMethod.CMA.value)


def inlier_frames(corners: np.ndarray, threshold_px: float) -> np.ndarray:
    """The robust rule for a static marker's corners over frames: of (N, 4, 2) corners, the
    frames whose four corners all lie within ``threshold_px`` of the per-corner median, or
    within 4 robust sigmas (1.4826 x the median deviation) when the corners are noisier.
    Returns an (N,) boolean mask."""
    median = np.median(corners, axis=0)
    dev = np.max(np.linalg.norm(corners - median, axis=2), axis=1)  # worst corner per frame
    sigma = 1.4826 * float(np.median(dev))
    return dev <= max(threshold_px, 4.0 * sigma)


def calibrate_robust(
    sightings: Sequence[Sighting], world: WorldConfig, intrinsics: CameraIntrinsics,
    params: CalibrationParams
) -> tuple[CameraExtrinsics, int]:
    """Robust calibration over sightings of a static camera; returns (extrinsics, inliers).

    Corners of the inlier frames are averaged, one PnP over the averaged corners gives the pose
    (the better of IPPE's two solutions on noise-free corners). Spread is measured over the
    inliers' own poses, each taking the IPPE solution nearer the result (flips do not inflate it).
    """
    corners = np.array([s.detection.corners_px for s in sightings])
    keep = inlier_frames(corners, params.outlier_threshold_px)
    mean = corners[keep].mean(axis=0)
    avg = Detection(world.marker_id, mean, shoelace_area(mean), world.dictionary)
    poses = _marker_poses(avg, world.marker_size_m, intrinsics)
    if not poses:
        raise CalibrationError("the averaged world-marker corners give no finite pose")
    T = invert_T(poses[0][0])
    if len(poses) > 1 and poses[1][1] < 1.5 * poses[0][1] + 0.05:
        log.warning("world marker pose is ambiguous (reprojection %.3f vs %.3f px): the marker is "
                    "small or seen nearly head-on in this camera", poses[0][1], poses[1][1])
    per_frame = []
    for s, k in zip(sightings, keep, strict=True):
        if not k:
            continue
        candidates = [s.T_world_cam] + ([s.T_world_cam_alt] if s.T_world_cam_alt is not None else [])
        per_frame.append(min(candidates, key=lambda c: rotation_angle(c[:3, :3], T[:3, :3])))
    spread_m, spread_deg = pose_spread(per_frame, T)
    n = int(keep.sum())
    return CameraExtrinsics(T, n, spread_m, spread_deg, CalibrationMethod.ROBUST.value), n


def calibrate_camera(
    frames: Iterable[Frame],
    camera: str,
    world: WorldConfig,
    intrinsics: CameraIntrinsics,
    params: CalibrationParams,
    progress: Progress | None = None,
    detector_params: DetectorParams | None = None,
    total_frames: int = 0,
) -> CameraCalibration:
    """Calibrate one camera from its frames; CalibrationError when it saw the world marker in
    fewer than ``params.min_samples`` frames. ``detector_params``: the ``[detector]`` settings
    (:class:`cubetrack.detect.detector.DetectorParams`, its dictionary replaced by the world's). A world
    reference of more than the one marker (more markers, a board) is measured and solved by
    :mod:`cubetrack.calib.reference`."""
    if not world.single_marker:
        return _calibrate_camera_reference(frames, camera, world, intrinsics, params, progress, detector_params,
                                           total_frames)
    sightings, frames_read, skipped = collect_sightings(
        frames, world, intrinsics, params, progress, stage=f"calibrate {camera}",
        detector_params=detector_params, total_frames=total_frames)
    if len(sightings) < params.min_samples:
        why = ", ".join(f"{n} {reason}" for reason, n in skipped.most_common()) or "no frames"
        raise CalibrationError(
            f"camera {camera!r}: world marker {world.dictionary} id {world.marker_id} found in "
            f"{len(sightings)} of {frames_read} frames, need at least {params.min_samples} ({why}); "
            "make sure the camera sees the whole marker")
    if params.method is CalibrationMethod.CMA:
        extrinsics, inliers = calibrate_cma(sightings), len(sightings)
    else:
        extrinsics, inliers = calibrate_robust(sightings, world, intrinsics, params)
    return CameraCalibration(camera, extrinsics, frames_read, len(sightings), inliers, dict(skipped))


def _calibrate_camera_reference(frames: Iterable[Frame], camera: str, world: WorldConfig,
                                intrinsics: CameraIntrinsics, params: CalibrationParams, progress: Progress | None,
                                detector_params: DetectorParams | None, total_frames: int) -> CameraCalibration:
    from cubetrack.calib.reference import calibrate_reference, collect_reference

    sightings, frames_read, skipped = collect_reference(frames, world, intrinsics, params, progress,
                                                        f"calibrate {camera}", detector_params, total_frames)
    if len(sightings) < params.min_samples:
        why = ", ".join(f"{n} {reason}" for reason, n in skipped.most_common()) or "no frames"
        raise CalibrationError(
            f"camera {camera!r}: the world reference found in {len(sightings)} of {frames_read} frames, need at "
            f"least {params.min_samples} ({why}); make sure the camera sees its markers or board")
    try:
        extrinsics, inliers = calibrate_reference(sightings, intrinsics, params)
    except CalibrationError as exc:
        raise CalibrationError(f"camera {camera!r}: {exc}") from None
    return CameraCalibration(camera, extrinsics, frames_read, len(sightings), inliers, dict(skipped))


def calibrate_cameras(
    frames: Mapping[str, Iterable[Frame]],
    intrinsics: Mapping[str, CameraIntrinsics],
    world: WorldConfig,
    params: CalibrationParams = CalibrationParams(),
    detector_params: DetectorParams | None = None,
    progress: Progress | None = None,
    allow_missing: bool = False,
    frame_counts: Mapping[str, int] | None = None,
) -> CalibrationReport:
    """Calibrate every camera of ``frames`` (camera name -> its frames, read lazily: a camera's
    frames are read only until ``params.samples`` sightings are found) with its ``intrinsics``.

    A camera that cannot be calibrated raises CalibrationError naming it — unless
    ``allow_missing``, when it is left out and listed in ``report.missing`` (at least one
    camera must still succeed). ``frame_counts`` (camera -> number of frames) only sizes the
    progress; ``detector_params`` are the ``[detector]`` settings (None: the defaults).
    """
    cameras: dict[str, CameraCalibration] = {}
    missing: dict[str, str] = {}
    for name, camera_frames in frames.items():
        if name not in intrinsics:
            raise CalibrationError(f"camera {name!r}: no intrinsics")
        try:
            cameras[name] = calibrate_camera(camera_frames, name, world, intrinsics[name], params, progress,
                                             detector_params, total_frames=(frame_counts or {}).get(name, 0))
        except CalibrationError as exc:
            missing[name] = str(exc)
            if allow_missing:
                log.warning("%s", exc)
    if missing and (not allow_missing or not cameras):
        first = next(iter(missing.values()))
        more = f" (and {len(missing) - 1} more camera(s): {', '.join(list(missing)[1:])})" if len(missing) > 1 else ""
        hint = "" if allow_missing else "; --allow-missing calibrates the others"
        raise CalibrationError(f"{first}{more}{hint}")
    return CalibrationReport(cameras, missing)


def extrinsics_errors(
    estimated: dict[str, CameraExtrinsics], truth: dict[str, CameraExtrinsics]
) -> dict[str, tuple[float, float]]:
    """Per camera present in both: (position error m, rotation error deg) of the estimate."""
    out = {}
    for name, e in estimated.items():
        if name in truth:
            t = truth[name].T_world_cam
            out[name] = (float(np.linalg.norm(e.T_world_cam[:3, 3] - t[:3, 3])),
                         rotation_angle(e.T_world_cam[:3, :3], t[:3, :3], "deg"))
    return out
