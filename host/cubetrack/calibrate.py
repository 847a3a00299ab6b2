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
    marker's four edges (sub-pixel edge profiles at their 50 % crossing, in undistorted
    coordinates, one straight line per edge, corners = line intersections) — free of the
    inward bias of the detector's corners; (2) frames whose corners stray from the per-corner
    median (a bump, a passer-by, a bad decode) are rejected; (3) the inliers' corners are
    averaged and one PnP gives the pose, the planar ambiguity (IPPE's two solutions) being
    settled on the noise-free averaged corners by reprojection error.

Every result carries the number of samples used and their spread: the RMS distance (metres)
and RMS angle (degrees) of the per-frame camera poses from the result.

Frames: ``T_cam_marker`` from PnP; the world frame is the world marker's frame (z up), so
``T_world_cam = inv(T_cam_marker)``.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Iterable, Sequence

import numpy as np

from cubetrack.errors import CalibrationError, ImageError
from cubetrack.geometry import (
    invert_T,
    make_T,
    quat_xyzw_from_R,
    R_from_quat_xyzw,
    rotation_angle,
    shoelace_area,
)
from cubetrack.io.camera_info import CameraIntrinsics
from cubetrack.io.config import CameraExtrinsics, TrackerConfig, WorldConfig
from cubetrack.params import param, params_from_table
from cubetrack.progress import Progress
from cubetrack.records import Detection, Frame

if TYPE_CHECKING:
    from cubetrack.detect import Detector, DetectorParams
    from cubetrack.io.recording import Recording

log = logging.getLogger(__name__)


class CalibrationMethod(str, enum.Enum):
    CMA = "cma"
    ROBUST = "robust"


class CornerRefinement(str, enum.Enum):
    EDGES = "edges"  # re-measure corners from the marker's edges (offline, bias-free)
    DETECTOR = "detector"  # keep the detector's corners as they are


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
        CornerRefinement.EDGES, "robust method only: 'edges' or 'detector' (corners as detected)")
    outlier_threshold_px: float = param(
        1.0, "robust method: a frame whose corners lie farther than this (px) from the per-corner "
        "median is an outlier (the threshold grows to 4 robust sigmas when the corners are noisier)")
    edge_min_contrast: float = param(
        20.0, "edge refinement: minimum grey-level step across a marker edge to trust it (0-255)")

    def __post_init__(self) -> None:
        if self.samples < 1:
            raise ValueError(f"samples must be at least 1, got {self.samples}")
        if self.min_samples < 1:
            raise ValueError(f"min_samples must be at least 1, got {self.min_samples}")
        if not self.outlier_threshold_px > 0:
            raise ValueError(f"outlier_threshold_px must be positive, got {self.outlier_threshold_px}")


def calibration_params(config: TrackerConfig) -> CalibrationParams:
    """The ``[calibration]`` section of a tracker config as :class:`CalibrationParams`."""
    return params_from_table(CalibrationParams, config.section("calibration"), f"{config.path}: [calibration]")


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
    q = quat.value / np.linalg.norm(quat.value)
    return make_T(R_from_quat_xyzw(q), position.value)


def pose_spread(T_world_cams: Sequence[np.ndarray], T_ref: np.ndarray) -> tuple[float, float]:
    """RMS position distance (m) and RMS rotation angle (deg) of poses from ``T_ref``."""
    if len(T_world_cams) == 0:
        return 0.0, 0.0
    d = np.array([np.linalg.norm(T[:3, 3] - T_ref[:3, 3]) for T in T_world_cams])
    a = np.array([rotation_angle(T[:3, :3], T_ref[:3, :3], "deg") for T in T_world_cams])
    return float(np.sqrt(np.mean(d**2))), float(np.sqrt(np.mean(a**2)))


# ---------------------------------------------------------------------------------------------
# Edge-based corner refinement (offline: accuracy over speed)


def _sample_bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of a float image at (..., 2) pixel positions (pixel-centre convention)."""
    h, w = img.shape
    x = np.clip(xy[..., 0], 0.0, w - 1.001)
    y = np.clip(xy[..., 1], 0.0, h - 1.001)
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    fx = x - x0
    fy = y - y0
    return ((img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx) * (1 - fy)
            + (img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx) * fy)


def _fit_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Total-least-squares line (point, unit normal) through (N, 2) points, trimming outliers."""
    keep = np.ones(len(points), dtype=bool)
    for _ in range(3):
        if keep.sum() < 4:
            return None
        p = points[keep]
        centre = p.mean(axis=0)
        _, _, vt = np.linalg.svd(p - centre)
        normal = vt[1]
        r = (points - centre) @ normal
        mad = np.median(np.abs(r[keep])) * 1.4826
        new_keep = np.abs(r) <= max(3.0 * mad, 0.05)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    if keep.sum() < 4:
        return None
    p = points[keep]
    centre = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - centre)
    return centre, vt[1]


def refine_corners_by_edges(
    gray: np.ndarray,
    corners_px: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
    border_bits: float,
    min_contrast: float = 20.0,
) -> np.ndarray | None:
    """Re-measure a square marker's corners from its four edges; None when an edge is unusable.

    ``gray``: the image (uint8 or float); ``corners_px``: (4, 2) initial corners TL, TR, BR, BL
    (OpenCV pixel-centre convention, distorted image); ``border_bits``: cells across the marker
    including its black border (marker bits + 2), which bounds how far inside an edge profile may
    reach. Each edge is sampled across at many points; the sub-pixel 50 % crossing between the
    black border and the white surround is found on each profile; the crossings are undistorted
    (``K``, ``dist``), a straight line is fitted per edge, and adjacent lines are intersected.
    Returns the (4, 2) corners in the distorted image, like the input.
    """
    import cv2

    img = np.asarray(gray, dtype=np.float32)
    c = np.asarray(corners_px, dtype=float).reshape(4, 2)
    centre = c.mean(axis=0)
    lines = []
    for i in range(4):
        a, b = c[i], c[(i + 1) % 4]
        length = float(np.linalg.norm(b - a))
        if length < 8.0:
            return None
        u = (b - a) / length
        n = np.array([u[1], -u[0]])
        if np.dot(n, (a + b) / 2 - centre) < 0:
            n = -n  # outward
        # how wide the black border is across this edge: the marker's extent across / cells
        across = abs(float(np.dot((c[(i + 2) % 4] + c[(i + 3) % 4]) / 2 - (a + b) / 2, n)))
        reach = float(np.clip(0.8 * across / border_bits, 1.5, 6.0))
        ts = np.linspace(0.12, 0.88, max(8, int(0.76 * length / 0.5)))
        offsets = np.arange(-reach, reach + 1e-9, 0.125)
        base = a + ts[:, None] * (b - a)  # (M, 2)
        pts = base[:, None, :] + offsets[None, :, None] * n  # (M, S, 2)
        prof = _sample_bilinear(img, pts)  # (M, S)
        grad = np.gradient(prof, axis=1)
        step = offsets[1] - offsets[0]
        hw = int(round(float(np.clip(0.8 * across / border_bits, 1.0, 2.5)) / step))
        crossings = []
        for m in range(len(ts)):
            j = int(np.argmax(grad[m]))  # the dark-to-light step outward: the marker's edge
            lo, hi = max(0, j - hw), min(len(offsets), j + hw + 1)
            inner, outer = np.sort(prof[m, lo:j + 1]), np.sort(prof[m, j:hi])
            dark, light = inner[:3].mean(), outer[-3:].mean()  # local plateaus either side
            if light - dark < min_contrast:
                continue
            # the edge = centroid of the rising gradient within +-1.25 px, re-centred twice;
            # unlike a 50 % level between plateaus it does not look as far as a nearby second
            # edge (the paper margin's outer edge is often only 2-4 px away)
            g = np.clip(grad[m], 0.0, None)
            s = offsets[j]
            for _ in range(3):
                w = g * (np.abs(offsets - s) <= min(1.25, hw * step))
                if w.sum() <= 0:
                    break
                s = float(np.dot(offsets, w) / w.sum())
            crossings.append(base[m] + s * n)
        if len(crossings) < 6:
            return None
        pts_u = cv2.undistortPoints(np.array(crossings, dtype=np.float64).reshape(-1, 1, 2), K, dist, P=K)
        line = _fit_line(pts_u.reshape(-1, 2))
        if line is None:
            return None
        lines.append(line)
    out = []
    for i in range(4):  # corner i lies on edges i-1 (previous) and i
        (p1, n1), (p2, n2) = lines[(i - 1) % 4], lines[i]
        A = np.array([n1, n2])
        if abs(np.linalg.det(A)) < 1e-6:
            return None
        out.append(np.linalg.solve(A, np.array([n1 @ p1, n2 @ p2])))
    und = np.array(out)
    # back to the distorted image: normalise with K, project with dist
    Kinv = np.linalg.inv(K)
    norm = (np.c_[und, np.ones(4)] @ Kinv.T)
    projected, _ = cv2.projectPoints(norm.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    result = projected.reshape(4, 2)
    if not np.all(np.isfinite(result)) or np.max(np.abs(result - c)) > 3.0:
        return None  # refinement wandered off: keep nothing rather than something wrong
    return result


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
    """The result of :func:`calibrate_recording`: calibrated cameras, and the cameras that
    never (or too rarely) saw the world marker with the reason."""

    cameras: dict[str, CameraCalibration]
    missing: dict[str, str]

    @property
    def extrinsics(self) -> dict[str, CameraExtrinsics]:
        return {name: c.extrinsics for name, c in self.cameras.items()}


def world_detector(world: WorldConfig, detector_params: DetectorParams | None = None) -> Detector:
    """A :class:`cubetrack.detect.Detector` for the world marker's dictionary, with the config's
    ``[detector]`` settings (``detector_params``; None = the defaults)."""
    from cubetrack.detect import Detector, DetectorParams

    params = dataclasses.replace(detector_params or DetectorParams(), dictionary=world.dictionary)
    return Detector(params)


def _marker_poses(detection: Detection, size_m: float, intrinsics: CameraIntrinsics,
                  polish: bool = False) -> list[tuple[np.ndarray, float]]:
    """Both planar solutions ``(T_cam_marker, rms reprojection error px)``, best first, from
    :func:`cubetrack.estimate.marker_pose`; with ``polish`` each is refined by Levenberg-Marquardt
    on the reprojection error (IPPE's closed form is not the least-squares optimum)."""
    from cubetrack.estimate import marker_pose

    mp = marker_pose(detection, size_m, intrinsics)
    if mp is None:
        return []
    out = [(mp.T_cam_marker, mp.reprojection_error_px)]
    if mp.T_cam_marker_alt is not None:
        out.append((mp.T_cam_marker_alt, mp.reprojection_error_alt_px))
    if polish:
        out = [_refine_lm(T, err, detection, size_m, intrinsics) for T, err in out]
        out.sort(key=lambda p: p[1])
    return out


def _refine_lm(T: np.ndarray, err: float, detection: Detection, size_m: float,
               intrinsics: CameraIntrinsics) -> tuple[np.ndarray, float]:
    import cv2

    from cubetrack.geometry import T_from_rvec_tvec, is_finite_pose, rvec_tvec_from_T
    from cubetrack.layout import marker_corners_m

    obj = marker_corners_m(size_m)
    img = np.asarray(detection.corners_px, dtype=np.float64).reshape(4, 1, 2)
    rvec, tvec = rvec_tvec_from_T(T)
    try:
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, intrinsics.K, intrinsics.dist,
                                          rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy())
    except cv2.error:
        return T, err
    T2 = T_from_rvec_tvec(rvec, tvec)
    if not is_finite_pose(T2):
        return T, err
    proj, _ = cv2.projectPoints(obj, rvec, tvec, intrinsics.K, intrinsics.dist)
    err2 = float(np.sqrt(np.mean(np.sum((proj.reshape(4, 2) - img.reshape(4, 2)) ** 2, axis=1))))
    return (T2, err2) if err2 <= err else (T, err)


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
    and counted, never fatal. With the robust method and ``corner_refinement = edges`` the
    corners are re-measured from the marker's edges (:func:`refine_corners_by_edges`).
    """
    from cubetrack.detect import aruco_dictionary, decode_gray

    detector = world_detector(world, detector_params)
    border_bits = aruco_dictionary(world.dictionary).markerSize + 2
    refine = (params.method is CalibrationMethod.ROBUST
              and params.corner_refinement is CornerRefinement.EDGES)
    sightings: list[Sighting] = []
    skipped: Counter = Counter()
    frames_read = 0
    seen = 0
    for frame in frames:
        if len(sightings) >= params.samples:
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
        frames_read += 1
        found = [d for d in detector.detect_gray(gray) if d.marker_id == world.marker_id]
        if not found:
            skipped["no world marker"] += 1
            continue
        if len(found) > 1:
            skipped["world marker id seen twice"] += 1
            continue
        det = found[0]
        if refine:
            corners = refine_corners_by_edges(gray, det.corners_px, intrinsics.K, intrinsics.dist,
                                              border_bits, params.edge_min_contrast)
            if corners is None:
                skipped["edge refinement failed"] += 1
                continue
            det = Detection(det.marker_id, corners, shoelace_area(corners), det.dictionary)
        poses = _marker_poses(det, world.marker_size_m, intrinsics)
        if not poses:
            skipped["no finite pose"] += 1
            continue
        T_alt = invert_T(poses[1][0]) if len(poses) > 1 else None
        sightings.append(Sighting(frame.seq, det, invert_T(poses[0][0]), T_alt))
    if progress is not None and total_frames and seen < total_frames:
        progress(stage, total_frames, total_frames)  # enough sightings: done early
    return sightings, frames_read, skipped


# ---------------------------------------------------------------------------------------------
# The two methods over sightings


def calibrate_cma(sightings: Sequence[Sighting]) -> CameraExtrinsics:
    """The paper's calibration (eq. 1) over the sightings' camera poses (better IPPE solution)."""
    Ts = [s.T_world_cam for s in sightings]
    T = cma_pose(Ts)
    spread_m, spread_deg = pose_spread(Ts, T)
    return CameraExtrinsics(T, len(Ts), spread_m, spread_deg, CalibrationMethod.CMA.value)


def _inlier_mask(corners: np.ndarray, threshold_px: float) -> np.ndarray:
    """Frames whose (4, 2) corners all lie near the per-corner median."""
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
    keep = _inlier_mask(corners, params.outlier_threshold_px)
    mean = corners[keep].mean(axis=0)
    avg = Detection(world.marker_id, mean, shoelace_area(mean), world.dictionary)
    poses = _marker_poses(avg, world.marker_size_m, intrinsics, polish=True)
    if not poses:
        raise CalibrationError("the averaged world-marker corners give no finite pose")
    T = invert_T(poses[0][0])
    if len(poses) > 1 and poses[1][1] < 1.5 * poses[0][1] + 0.05:
        log.warning("world marker pose is ambiguous (reprojection %.3f vs %.3f px): the marker is "
                    "small or seen nearly head-on in this camera", poses[0][1], poses[1][1])
    per_frame = []
    for s, k in zip(sightings, keep):
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
    (:class:`cubetrack.detect.DetectorParams`, its dictionary replaced by the world's)."""
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


def calibrate_recording(
    config: TrackerConfig,
    recording: Recording,
    params: CalibrationParams | None = None,
    progress: Progress | None = None,
    allow_missing: bool = False,
) -> CalibrationReport:
    """Calibrate every camera of ``recording`` (a :class:`cubetrack.io.recording.Recording`).

    Intrinsics come from the config's ``camera_info`` or the recording's ``camera_info/``.
    A camera that cannot be calibrated raises CalibrationError naming it — unless
    ``allow_missing``, when it is left out and listed in ``report.missing`` (at least one
    camera must still succeed).
    """
    from cubetrack.detect import DetectorParams
    from cubetrack.io.camera_info import read_camera_info
    from cubetrack.io.config import camera_intrinsics_path

    params = params or calibration_params(config)
    detector_params = params_from_table(DetectorParams, config.section("detector"),
                                        f"{config.path}: [detector]")
    cameras: dict[str, CameraCalibration] = {}
    missing: dict[str, str] = {}
    for name in recording.camera_names:
        intrinsics = read_camera_info(camera_intrinsics_path(config, name, recording.path))
        try:
            cameras[name] = calibrate_camera(recording.frames(name), name, config.world, intrinsics,
                                             params, progress, detector_params,
                                             total_frames=len(recording.index(name)))
        except CalibrationError as exc:
            missing[name] = str(exc)
            if allow_missing:
                log.warning("%s", exc)
    if missing and (not allow_missing or not cameras):
        first = next(iter(missing.values()))
        more = f" (and {len(missing) - 1} more camera(s): {', '.join(list(missing)[1:])})" if len(missing) > 1 else ""
        hint = "" if allow_missing else "; --allow-missing calibrates the others"
        raise CalibrationError(f"{recording.path}: {first}{more}{hint}")
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
