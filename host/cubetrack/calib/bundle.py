"""Extrinsics refined by a bundle adjustment over world-marker and cube observations.

World-marker calibration (:mod:`cubetrack.calib.extrinsics`) leaves every camera a few millimetres and
a tenth of a degree off: one 25 cm marker seen obliquely from 2+ m is a weak reference, and its
corner bias does not average out. Once the robot drives around, the cube gives many more
corners, seen by several cameras at about the same time. This module refines all camera poses
jointly from

(a) the world marker's four corners in each camera of the calibration recording (the robust
    per-camera average of the edge-refined corners over the frames, as
    :func:`cubetrack.calib.extrinsics.calibrate_robust` averages them). They fix the gauge: the world
    frame stays the world marker's frame;
(b) the cube corners of a tracking recording at *instants* where at least two cameras saw the
    cube within ``max_span_s`` of each other on the host clock (frames stamped by clock sync,
    ``clock.csv``, as the tracker stamps them). Frames of one instant are motion-compensated to
    its mean time with the constant-velocity model of :mod:`cubetrack.estimate.reprojection`; velocities come
    from the instants' own poses (a local linear fit over ``velocity_window_s``), re-estimated
    after each solve; or (``knot_s`` > 0) each robot's pose is a continuous-time trajectory
    (:class:`Trajectory`, the body calibration's) through the instants' frames, each corner at the
    pose interpolated to its row's time, no velocity assumed. The corners are edge-fitted and
    then template-fitted (:func:`cube_frames` with the lenses, as the body calibration measures
    them): the edge fit's outward bias on obliquely seen markers scaled the refined cameras out
    (issue 26).

Unknowns: each camera's 6-dof pose, the cube pose at each instant and (``planar_motion``) one
cube height per robot. Residuals: reprojection errors (pixels, on undistorted points scaled by
the focal length, as in :mod:`cubetrack.estimate.reprojection`) of every corner, with a soft-L1 loss; for ground
robots also the cube's height against its robot's common height and its tilt from its floor's up,
the floor a plane that may tilt from the world marker's by ``floor_tilt_sigma_deg`` (so the world
marker, not the drive's floor, sets the world frame's tilt: the contract's world frame; 0 = the
floor is the marker's plane and holds the tilt). ``scipy.optimize.least_squares`` with an
analytic sparse Jacobian (a corner depends on one camera and one instant), so 5 cameras x
hundreds of instants solve in seconds. Pose increments are world-frame, as in
:mod:`cubetrack.estimate.reprojection`.

Steps (:func:`adjust_extrinsics`, which takes frames and clock samples held anywhere, e.g. in
memory; ``cubetrack.app.calibrate.adjust_recording_extrinsics`` feeds it recording folders):

1. Per camera frame of the tracking recording: cube detections, a single-camera cube estimate
   (:func:`cubetrack.estimate.pose.estimate_cube`) with the prior extrinsics, and the faces matched to
   detections by :func:`cubetrack.estimate.match.match_faces` at that estimate. Frames are grouped into
   instants, each starting from its best-seen camera's estimate; the cube poses are solved with
   the prior cameras held (twice: the second time with velocities from the first).
2. *Relative* solve: cube corners only, the gauge held by a weak prior on every camera.
   The result is aligned to the prior calibration by the rigid transform that most cameras agree
   on; a camera whose aligned pose is more than ``moved_position_m`` / ``moved_rotation_deg``
   from its calibration is reported as *moved* (its world-marker sighting in the calibration
   recording no longer describes it). With two cameras a disagreement cannot be pinned on one of
   them: both are named in a warning and both keep their world-marker terms.
3. Faces are re-matched to detections with the refined poses, velocities re-estimated, and the
   *absolute* solve runs: cube corners of every camera plus the world-marker corners of the
   cameras that did not move.

4. The check (:func:`worse_world_fit`): a camera whose refined pose reprojects its world-marker
   corners more than ``world_corner_noise_px`` worse than its world-marker pose did means the cube
   contradicts the marker; the refinement is then refused (warning; the prior extrinsics returned).

Without a calibration recording the result of step 2 (aligned to the prior extrinsics) is
returned. Several floor markers are not supported: the config names one world marker.
A camera with no multi-camera cube sightings keeps its prior pose (and is named in a warning).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

if TYPE_CHECKING:
    from cubetrack.source.clock import ClockFit

from cubetrack.calib.extrinsics import (
    CalibrationMethod,
    CalibrationParams,
    collect_sightings,
    edge_fitted_corners,
    inlier_frames,
)
from cubetrack.calib.marker_fit import template_fitted_corners
from cubetrack.calib.solver import (
    BodyPrior,
    Freedom,
    IntrinsicsPrior,
    Model,
    Observations,
    PosePrior,
    corner_residuals_px,
    interpolated_poses,
    padded_dist,
    solve,
    world_residuals_px,
)
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample, WorldConfig
from cubetrack.core.errors import CalibrationError, ImageError
from cubetrack.core.geometry import invert_T, make_T, mean_rotation, rotation_angle, shoelace_area
from cubetrack.core.layout import CubeLayout, LayoutMarker, marker_corners_m
from cubetrack.core.params import check, check_non_negative, check_positive, param
from cubetrack.core.progress import Progress
from cubetrack.core.records import Detection, Frame
from cubetrack.detect.detector import Detector, DetectorParams, decode_gray
from cubetrack.detect.template_fit import LensMap
from cubetrack.estimate.match import body_detections, match_faces
from cubetrack.estimate.reprojection import moved_pose

log = logging.getLogger(__name__)

METHOD = "refined"  # CameraExtrinsics.method of a camera after bundle adjustment (the word users see)


@dataclass(frozen=True, slots=True)
class BundleAdjustmentParams:
    """The ``[bundle_adjustment]`` section: how :func:`adjust_extrinsics` selects observations and solves."""

    max_span_s: float = param(0.1, "frames of different cameras whose capture times (host clock) lie within this many "
                                   "seconds form one instant")
    min_cameras: int = param(2, "an instant needs cube corners from at least this many cameras")
    max_instants: int = param(400, "at most this many instants are used (evenly spread over the recording)")
    corner_noise_px: float = param(0.5, "cube corner noise (1 sigma), pixels")
    world_corner_noise_px: float = param(0.5, "noise (1 sigma) of the world marker's averaged corners, pixels")
    f_scale_px: float = param(1.5, "residuals beyond this are down-weighted (soft-L1 loss), pixels")
    association_gate_px: float = param(12.0, "a detection joins a cube face if its corners lie within this many pixels "
                                             "(or half a marker side) of the predicted face")
    velocity_window_s: float = param(0.3, "velocities of an instant are fitted to the instants within "
                                          "this many seconds")
    moved_position_m: float = param(0.02, "a camera whose cube-consensus pose is farther than this from its "
                                          "calibration has moved, metres")
    moved_rotation_deg: float = param(0.5, "... or turned by more than this, degrees")
    gauge_prior_position_m: float = param(0.1, "relative solve: weak prior on each camera's position (holds "
                                               "the gauge), metres")
    gauge_prior_rotation_deg: float = param(3.0, "relative solve: weak prior on each camera's rotation, degrees")
    planar_motion: bool = param(True, "each robot's cube stays at one height above the floor it drives on (ground "
                                      "robots; a plane that may tilt from the world marker's by floor_tilt_sigma_deg); "
                                      "false for robots that climb")
    height_sigma_m: float = param(0.002, "planar motion: spread (1 sigma) of the cube's height along the path, metres")
    upright_sigma_deg: float = param(1.0, "spread (1 sigma) of each cube's tilt from world up (ground robots: the "
                                          "estimator's upright prior); 0 = no such prior, degrees")
    floor_tilt_sigma_deg: float = param(1.0, "ground robots: the floor under the robot's path is a plane that may tilt "
                                             "from the world marker's by this much (1 sigma; the cube's height and "
                                             "upright prior are taken along it), so the world marker sets the world's "
                                             "tilt (contracts: the world frame is the marker's); 0 = that plane is the "
                                             "marker's (a level floor sets the tilt), degrees")
    free_cube_scale: bool = param(False, "absolute solves: estimate each cube's scale too, so the world marker sets "
                                         "the scale (measured worse on simulations: the obliquely seen marker's scale "
                                         "is less sure than the cube's): a corner bias of 0.01 px on a 20 px cube "
                                         "marker changes its apparent size by 0.1 %, which moves every camera "
                                         "radially by 2 mm")
    world_samples: int = param(60, "world-marker sightings averaged per camera of the calibration recording "
                                   "(the first N found)")
    knot_s: float = param(0.05, "the body's pose is a continuous-time trajectory with knots this many seconds apart "
                                "through every instant's frames (each corner at the pose interpolated to its row's "
                                "time, the knots tied by the accel sigmas; as [body_calibration] knot_s); 0 = one pose "
                                "per instant, moved to each frame's time with a fitted velocity")
    accel_sigma_m_s2: float = param(10.0, "trajectory: the body's acceleration between knots (1 sigma), m/s^2")
    angular_accel_sigma_rad_s2: float = param(100.0, "trajectory: the body's angular acceleration between knots "
                                                     "(1 sigma), rad/s^2")
    rounds: int = param(2, "absolute solves, each after re-matching faces and re-estimating velocities")
    max_nfev: int = param(60, "function evaluations per least-squares solve")
    refine_intrinsics: bool = param(False, "absolute solves: refine each camera's focal lengths, principal point, k1 "
                                           "and k2 too, held near its camera_info by the intrinsics_* sigmas")
    intrinsics_focal_sigma: float = param(0.005, "refined intrinsics: the camera_info focal lengths' uncertainty (1 "
                                                 "sigma), relative")
    intrinsics_principal_sigma_px: float = param(4.0, "refined intrinsics: the camera_info principal point's "
                                                      "uncertainty (1 sigma), pixels")
    intrinsics_k1_sigma: float = param(0.01, "refined intrinsics: the camera_info k1's uncertainty (1 sigma)")
    intrinsics_k2_sigma: float = param(0.03, "refined intrinsics: the camera_info k2's uncertainty (1 sigma)")
    def __post_init__(self) -> None:
        check_positive(self, "max_span_s", "corner_noise_px", "world_corner_noise_px", "f_scale_px",
                       "association_gate_px", "velocity_window_s", "moved_position_m", "moved_rotation_deg",
                       "gauge_prior_position_m", "gauge_prior_rotation_deg", "height_sigma_m",
                       "intrinsics_focal_sigma", "intrinsics_principal_sigma_px", "intrinsics_k1_sigma",
                       "intrinsics_k2_sigma", "accel_sigma_m_s2", "angular_accel_sigma_rad_s2")
        check_non_negative(self, "upright_sigma_deg", "floor_tilt_sigma_deg", "knot_s")
        check(self.world_samples >= 1, f"world_samples must be at least 1, got {self.world_samples}")
        check(self.min_cameras >= 2 and self.max_instants >= 1 and self.rounds >= 1 and self.max_nfev >= 1,
              "need min_cameras >= 2, max_instants >= 1, rounds >= 1, max_nfev >= 1")


@dataclass(frozen=True, slots=True)
class BodyCalibrationParams:
    """The ``[body_calibration]`` section: how ``cubetrack calibrate-body``
    (:func:`cubetrack.calib.body.calibrate_body`) models the body, its motion and the cameras on top of
    the ``[bundle_adjustment]`` settings it shares (noise, loss, rounds, intrinsics priors). These were
    ``[bundle_adjustment] body_*`` keys until issue 23 (:data:`MOVED_BODY_KEYS`)."""

    position_sigma_m: float = param(0.003, "how far a marker may be from its nominal place (1 sigma), metres")
    rotation_sigma_deg: float = param(2.0, "how far a marker may be turned from its nominal pose (1 sigma), degrees")
    size_sigma: float = param(0.02, "a marker's printed size against its nominal size (1 sigma), relative")
    camera_sigma_m: float = param(0.01, "cameras are refined too, held near the given extrinsics with this position "
                                        "sigma, metres")
    camera_sigma_deg: float = param(0.3, "... and this rotation sigma, degrees")
    max_span_s: float = param(0.08, "[bundle_adjustment] max_span_s of the body calibration's instants (shorter: the "
                                    "body's motion between the frames of an instant is modelled as constant velocity, "
                                    "which misses sharp turns and vibration; measured in docs/calibration.md)")
    motion_noise_px_per_s: float = param(25.0, "a corner's noise grows by this many pixels per second of its frame's "
                                               "time from its instant (the constant-velocity motion between an "
                                               "instant's frames misses turns and vibration; 0 = not at all)")
    knot_s: float = param(0.05, "the body's pose is a continuous-time trajectory with knots this many seconds apart "
                                "(each corner at the pose interpolated to its row's time, the knots tied by the accel "
                                "sigmas; measured in docs/calibration.md); 0 = one pose per instant moved with a "
                                "fitted velocity (motion_noise_px_per_s applies only then)")
    accel_sigma_m_s2: float = param(10.0, "trajectory: the body's acceleration between knots (1 sigma of the knots' "
                                          "second difference over the squared spacing), m/s^2")
    angular_accel_sigma_rad_s2: float = param(100.0, "trajectory: the body's angular acceleration between knots (1 "
                                                     "sigma), rad/s^2 (the robot's wobble reaches tens)")
    edge_corners: bool = param(True, "re-measure the body's marker corners by the calibration's edge fit (as the world "
                                     "marker's) and then by fitting each marker's whole image "
                                     "(cubetrack.calib.marker_fit, compiled: a few ms per marker seen; "
                                     "docs/calibration.md has the measured errors)")
    heading_from_travel: bool = param(False, "for a robot that only drives forward (not a holonomic or carried "
                                             "body) on the floor the world marker lies on: turn the body frame "
                                             "about its z so that its x is the drive's direction of travel "
                                             "(cubetrack.calib.body.travel_heading) instead of the markers' mean "
                                             "yaw, which carries their build errors (0.5-1 deg; no image shows "
                                             "it); left as it is, with a warning, when the drive moves sideways "
                                             "or heads over 10 deg from the markers' x (docs/tracking.md)")

    def __post_init__(self) -> None:
        check_positive(self, "position_sigma_m", "rotation_sigma_deg", "size_sigma", "camera_sigma_m",
                       "camera_sigma_deg", "max_span_s", "accel_sigma_m_s2", "angular_accel_sigma_rad_s2")
        check_non_negative(self, "knot_s", "motion_noise_px_per_s")


# [bundle_adjustment] key of a config from before issue 23 -> its [body_calibration] key
MOVED_BODY_KEYS = {f"body_{name}": name for name in BodyCalibrationParams.__dataclass_fields__}


# ---------------------------------------------------------------------------------------------
# Observations


@dataclass(frozen=True, slots=True, eq=False)
class WorldMarkerObservation:
    """The world marker in one camera of the calibration recording: the robust average of its
    (edge-refined) corners over ``frames`` inlier frames, (4, 2) px, TL TR BR BL. A world reference
    of more than one marker: ``points_world_m`` (n, 3) its points and ``corners_px`` (n, 2) their
    averaged pixels (:mod:`cubetrack.calib.reference`)."""

    camera: str
    corners_px: np.ndarray
    frames: int
    points_world_m: np.ndarray | None = None


@dataclass(frozen=True, slots=True, eq=False)
class CubeFrame:
    """One camera frame of the tracking recording that saw a robot's cube: its capture time on
    the host clock and its detections of that cube's ids."""

    camera: str
    robot: str
    seq: int
    time_s: float
    detections: tuple[Detection, ...]


@dataclass(frozen=True, slots=True, eq=False)
class FrameCorners:
    """One camera frame's detections matched to a body's markers: ``markers`` (F,) indices into
    the layout's markers, ``corners_px`` (F, 4, 2) their detected corners (TL TR BR BL)."""

    camera: str
    time_s: float
    markers: np.ndarray
    corners_px: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class Instant:
    """Cube corners of several cameras at about one time: ``sets`` (one per camera), their
    capture times differing by at most ``BundleAdjustmentParams.max_span_s``; ``time_s`` their mean."""

    robot: str
    time_s: float
    frames: tuple[CubeFrame, ...]
    sets: tuple[FrameCorners, ...]
    T_world_cube: np.ndarray


@dataclass(frozen=True, slots=True)
class CameraResidual:
    """One camera after refinement: RMS reprojection error (px) of its ``corners`` cube corners
    in ``instants`` instants and of its world-marker corners (NaN when not used); how far the
    refined pose is from the prior (``shift_m``, ``shift_deg``); ``moved`` when the cube
    consensus says the camera moved after calibration."""

    camera: str
    rms_px: float
    corners: int
    instants: int
    world_rms_px: float
    shift_m: float
    shift_deg: float
    moved: bool


@dataclass(frozen=True, slots=True, eq=False)
class BundleAdjustmentReport:
    """What :func:`adjust_extrinsics` found: the refined ``extrinsics`` (all prior cameras; those
    without multi-camera sightings unchanged), the ``prior`` ones, per-camera residuals, the
    cameras that moved after calibration, the instants used and the warnings issued; ``refused``
    when the refinement was refused (its residuals reported, the prior extrinsics kept)."""

    extrinsics: dict[str, CameraExtrinsics]
    prior: dict[str, CameraExtrinsics]
    cameras: dict[str, CameraResidual]
    moved: tuple[str, ...]
    instants: int
    warnings: tuple[str, ...] = field(default_factory=tuple)
    intrinsics: dict[str, CameraIntrinsics] = field(default_factory=dict)  # refined (refine_intrinsics) or as given
    refused: bool = False  # the refinement was refused (worse_world_fit): extrinsics are the prior ones


def robust_average_corners(corners_px: np.ndarray, threshold_px: float) -> tuple[np.ndarray, int]:
    """Mean of (N, 4, 2) corner sets over the frames the robust rule keeps
    (:func:`cubetrack.calib.extrinsics.inlier_frames`, as the robust calibration applies it to its
    sightings): (4, 2) mean, inliers."""
    corners = np.asarray(corners_px, dtype=float).reshape(-1, 4, 2)
    keep = inlier_frames(corners, threshold_px)
    return corners[keep].mean(axis=0), int(keep.sum())


def world_marker_observations(frames: Mapping[str, Iterable[Frame]], world: WorldConfig,
                              intrinsics: Mapping[str, CameraIntrinsics], params: CalibrationParams | None = None,
                              detector_params: DetectorParams | None = None, progress: Progress | None = None,
                              samples: int | None = None,
                              frame_counts: Mapping[str, int] | None = None) -> dict[str, WorldMarkerObservation]:
    """The world marker's averaged corners per camera of the calibration ``frames`` (camera ->
    frames; cameras without ``intrinsics`` are left out).

    Sightings are collected by :func:`cubetrack.calib.extrinsics.collect_sightings` with the
    ``[calibration]`` settings ``params`` (always with the robust method's edge-refined corners;
    ``samples`` overrides its number of sightings); a camera with fewer than ``min_samples``
    sightings is left out with a warning.
    """
    params = dataclasses.replace(params or CalibrationParams(), method=CalibrationMethod.ROBUST)
    if samples is not None:
        params = dataclasses.replace(params, samples=samples, min_samples=min(params.min_samples, samples))
    out = {}
    for camera, camera_frames in frames.items():
        if camera not in intrinsics:
            continue
        if not world.single_marker:
            reference = _reference_observation(camera, camera_frames, world, intrinsics[camera], params,
                                               detector_params, progress, (frame_counts or {}).get(camera, 0))
            if reference is not None:
                out[camera] = reference
            continue
        sightings, _read, _skipped = collect_sightings(
            camera_frames, world, intrinsics[camera], params, progress,
            stage=f"bundle adjustment: world marker {camera}", detector_params=detector_params,
            total_frames=(frame_counts or {}).get(camera, 0))
        if len(sightings) < params.min_samples:
            log.warning("%s: world marker seen in %d calibration frames (need %d): no world-marker term for it",
                        camera, len(sightings), params.min_samples)
            continue
        mean, n = robust_average_corners(np.array([s.detection.corners_px for s in sightings]),
                                         params.outlier_threshold_px)
        out[camera] = WorldMarkerObservation(camera, mean, n)
    return out


def _reference_observation(camera: str, frames: Iterable[Frame], world: WorldConfig, intrinsics: CameraIntrinsics,
                           params: CalibrationParams, detector_params: DetectorParams | None,
                           progress: Progress | None, total_frames: int) -> WorldMarkerObservation | None:
    """The averaged points of a world reference of several markers or a board in one camera."""
    from cubetrack.calib.reference import average_reference, collect_reference

    sightings, _read, _skipped = collect_reference(frames, world, intrinsics, params, progress,
                                                   f"bundle adjustment: world reference {camera}", detector_params,
                                                   total_frames)
    try:
        averaged = average_reference(sightings, params.outlier_threshold_px, params.min_samples)
    except CalibrationError:
        log.warning("%s: world reference seen in %d calibration frames: no world term for it", camera, len(sightings))
        return None
    return WorldMarkerObservation(camera, averaged.pixels, max(averaged.frames.values()), averaged.points_world_m)


def _clock_fit(camera: str, samples: Sequence[ClockSample], device_s: Sequence[float],
               host_s: Sequence[float]) -> ClockFit:
    """Device -> host clock of one camera over the whole recording (offline: not causal): the
    usable ``/time`` round trips, else the frames' arrival times (``device_s``, ``host_s``)."""
    from cubetrack.source.clock import ClockSyncParams, fit_arrivals, fit_round_trips

    limit = ClockSyncParams().max_round_trip_s
    trips = [s for s in samples if 0.0 <= s.host_recv_s - s.host_send_s <= limit]
    if trips:
        return fit_round_trips(np.array([s.host_send_s for s in trips]),
                               np.array([s.device_time_s for s in trips]),
                               np.array([s.host_recv_s for s in trips]))
    log.warning("%s: no usable clock.csv round trips; frames are stamped from arrival times "
                "(late by the transfer time), which blurs the instants", camera)
    return fit_arrivals(np.array(device_s), np.array(host_s))


def cube_frames(frames: Mapping[str, Iterable[Frame]], layouts: Mapping[str, CubeLayout],
                clock_samples: Mapping[str, Sequence[ClockSample]] | None = None,
                detector_params: DetectorParams | None = None, progress: Progress | None = None,
                frame_count: int = 0, lenses: Mapping[str, CameraIntrinsics] | None = None,
                edge_min_contrast: float = 20.0) -> list[CubeFrame]:
    """Every frame of ``frames`` (camera -> its frames) that shows a robot's cube ids (``layouts``:
    robot -> cube layout), stamped with its capture time on the host clock from the camera's
    ``clock_samples`` (round trips; without them, its frames' arrival times); in time order.
    ``frame_count`` (all cameras' frames) only sizes the progress.

    ``lenses`` (camera -> intrinsics): the cube corners are measured for the refinement and the
    body calibration:
    as the world marker's are for calibration (:func:`cubetrack.detect.detector.refine_corners_edges` with
    :data:`cubetrack.calib.extrinsics.EDGE_FIT` and the camera's lens model: sides straight in
    the undistorted image, edge points from the gradient's peak), then by fitting the whole marker
    image (:func:`cubetrack.calib.marker_fit.template_fitted_corners`: no bias on obliquely seen
    markers); detections whose edges cannot be fitted (``edge_min_contrast``) or whose template
    fit fails are dropped."""
    detector = Detector(detector_params or DetectorParams(),
                        [name for lay in layouts.values() for name in lay.dictionaries])
    out: list[CubeFrame] = []
    done = 0
    for camera, camera_frames in frames.items():
        lens_map: LensMap | None = None  # the template fit's, built at the camera's first cube sighting
        seen: list[tuple[int, float, tuple[tuple[str, tuple[Detection, ...]], ...]]] = []
        device_s, host_s = [], []
        for frame in camera_frames:
            done += 1
            if progress is not None:
                progress("bundle adjustment: cube detections", done, frame_count)
            device_s.append(frame.device_time_s)
            host_s.append(frame.host_time_s)
            try:
                gray = decode_gray(frame.jpeg, f"{camera} frame {frame.seq}")
            except ImageError as exc:
                log.warning("%s; skipped", exc)
                continue
            detections = detector.detect(gray)
            robots: list[tuple[str, tuple[Detection, ...]]] = []
            for robot, lay in layouts.items():
                mine = body_detections(detections, lay)
                if mine and lenses is not None and camera in lenses:
                    lens_map = lens_map or LensMap(lenses[camera])
                    mine = _edge_fitted(gray, mine, lenses[camera], lens_map, edge_min_contrast)
                if mine:
                    robots.append((robot, mine))
            if robots:
                seen.append((frame.seq, frame.device_time_s, tuple(robots)))
        if not device_s:
            continue
        fit = _clock_fit(camera, (clock_samples or {}).get(camera, ()), device_s, host_s)
        for seq, device_time_s, seen_robots in seen:
            t = fit.to_host(device_time_s)
            out.extend(CubeFrame(camera, robot, seq, t, mine) for robot, mine in seen_robots)
    out.sort(key=lambda f: (f.time_s, f.camera))
    return out


def _edge_fitted(gray: np.ndarray, detections: Sequence[Detection], lens: CameraIntrinsics, lens_map: LensMap,
                 min_contrast: float) -> tuple[Detection, ...]:
    """Detections with their corners re-measured by the calibration's edge fit (the camera's
    ``lens``) and then the template fit (through ``lens_map``, the same lens as a map); those
    either cannot fit are left out."""
    corners = [edge_fitted_corners(gray, d.corners_px, d.dictionary, lens, min_contrast) for d in detections]
    corners = [c if np.isnan(c).any() else template_fitted_corners(gray, c, d.dictionary, d.marker_id, lens_map)
               for d, c in zip(detections, corners, strict=True)]
    return tuple(Detection(d.marker_id, c, shoelace_area(c), d.dictionary)
                 for d, c in zip(detections, corners, strict=True) if not np.isnan(c).any())


def _frame_corners(frame: CubeFrame, layout: CubeLayout, intrinsics: CameraIntrinsics, T_world_cam: np.ndarray,
                   params: BundleAdjustmentParams, T_world_cube: np.ndarray | None = None) -> FrameCorners | None:
    """The frame's detections matched to the layout's markers at ``T_world_cube``, or (None) at
    the frame's own single-camera estimate; None when nothing matched."""
    if T_world_cube is None:
        from cubetrack.estimate.pose import estimate_cube

        est = estimate_cube(frame.detections, layout, intrinsics, T_world_cam, camera=frame.camera,
                            robot=frame.robot, seq=frame.seq, capture_time_s=frame.time_s,
                            arrival_time_s=frame.time_s)
        if est is None:
            return None
        T_world_cube = est.T_world_cube
    matches = match_faces(frame.detections, layout, intrinsics, T_world_cam, T_world_cube,
                          gate_px=params.association_gate_px)
    if not matches:
        return None
    return FrameCorners(frame.camera, frame.time_s, np.array([m.marker for m in matches]),
                        np.array([m.detection.corners_px for m in matches], dtype=float))


def group_instants(frames: Sequence[CubeFrame], max_span_s: float, min_cameras: int) -> list[list[CubeFrame]]:
    """Greedy grouping of time-ordered frames (one robot) into instants: a group starts at the
    earliest frame not yet grouped and takes the following frames of other cameras within
    ``max_span_s`` of it; groups with fewer than ``min_cameras`` cameras are dropped."""
    frames = sorted(frames, key=lambda f: (f.time_s, f.camera))
    groups, i = [], 0
    while i < len(frames):
        group = [frames[i]]
        j = i + 1
        while j < len(frames) and frames[j].time_s - frames[i].time_s <= max_span_s:
            if all(f.camera != frames[j].camera for f in group):
                group.append(frames[j])
            j += 1
        if len(group) >= min_cameras:
            groups.append(group)
        # the next group starts after this one's last member (a frame is used once)
        last = max(frames.index(f) for f in group)
        i = last + 1 if len(group) >= min_cameras else i + 1
    return groups


def spread_instants(groups: Sequence[list[CubeFrame]], keep: int, velocity_window_s: float
                    ) -> list[list[CubeFrame]]:
    """``keep`` of one robot's time-ordered ``groups``, evenly spread over them. When so few are kept
    that neighbours would lie more than half ``velocity_window_s`` apart, they are kept in runs of
    three consecutive groups instead: :func:`velocities` needs three poses within its window, and
    an instant without them is motion-compensated with no velocity at all (a robot at 0.4 m/s then
    seems to jump 4 cm between frames 0.1 s apart, and the cameras absorb it: 30 instants of a
    7.5 s lap moved a correct camera 1.4 cm spread singly, 0.2 cm in runs; docs/calibration.md)."""
    n = len(groups)
    if keep >= n:
        return list(groups)
    span_s = groups[-1][0].time_s - groups[0][0].time_s
    run = 1 if span_s / max(keep - 1, 1) <= velocity_window_s / 2 else min(3, keep)
    starts = np.linspace(0, n - run, max(keep // run, 1)).round().astype(int)
    return [groups[i] for i in np.unique(starts[:, None] + np.arange(run)).tolist()]


def velocities(times_s: np.ndarray, Ts: np.ndarray, window_s: float) -> tuple[np.ndarray, np.ndarray]:
    """World-frame linear (m/s) and angular (rad/s) velocity at each of (K,) times of (K, 4, 4)
    poses: slopes of a local linear fit over the poses within ``window_s``; zero when fewer than
    three poses span the window."""
    K = len(times_s)
    v, w = np.zeros((K, 3)), np.zeros((K, 3))
    for k in range(K):
        near = np.flatnonzero(np.abs(times_s - times_s[k]) <= window_s)
        dt = times_s[near] - times_s[k]
        if len(near) < 3 or np.ptp(dt) < 1e-3:
            continue
        x = dt - dt.mean()
        denom = float(x @ x)
        v[k] = x @ (Ts[near, :3, 3] - Ts[near, :3, 3].mean(axis=0)) / denom
        rv = Rotation.from_matrix(Ts[near, :3, :3] @ Ts[k, :3, :3].T).as_rotvec()
        w[k] = x @ (rv - rv.mean(axis=0)) / denom
    return v, w


# ---------------------------------------------------------------------------------------------
# One refinement's state: instants, their matched corners, the model being solved

_OPENCV_DIST_LENGTHS = (5, 8, 12, 14)  # distortion vector lengths cv2.projectPoints takes


def layout_with(layout: CubeLayout, T_body_markers: np.ndarray, sizes_m: np.ndarray) -> CubeLayout:
    """``layout`` with its markers (same faces, ids, dictionary; its motion) at ``T_body_markers``
    (M, 4, 4) and of sides ``sizes_m`` (M,)."""
    markers = zip(layout.markers, T_body_markers, sizes_m, strict=True)
    return CubeLayout(layout.dictionary, tuple(LayoutMarker(m.face, m.marker_id, float(s), np.array(T, float))
                                               for m, T, s in markers), layout.motion)


def _intrinsics_arrays(intrinsics: Sequence[CameraIntrinsics]) -> tuple[np.ndarray, np.ndarray]:
    """(C, 3, 3) camera matrices and (C, D) distortion vectors padded to one length OpenCV takes."""
    dists = [padded_dist(i.dist) for i in intrinsics]
    n = next(k for k in _OPENCV_DIST_LENGTHS if k >= max(len(d) for d in dists))
    return (np.array([i.K for i in intrinsics], float),
            np.array([np.concatenate([d, np.zeros(n - len(d))]) for d in dists]))


@dataclass(eq=False)
class Refinement:
    """One bundle adjustment in progress (:func:`adjust_extrinsics`, and
    :func:`cubetrack.calib.body.calibrate_body`): the ``instants`` and their matched corners, the
    ``cameras`` and ``robots`` in model order, the ``model`` being solved, the velocities of the
    instants and what the priors hold to (the given intrinsics and layouts)."""

    params: BundleAdjustmentParams
    cameras: list[str]
    robots: list[str]
    layouts: dict[str, CubeLayout]  # as given (the body prior)
    given: dict[str, CameraIntrinsics]
    instants: list[Instant]
    model: Model
    vel: np.ndarray
    angvel: np.ndarray
    readout_s: dict[str, float] = field(default_factory=dict)  # rolling-shutter readout per camera (0: global)

    @classmethod
    def start(cls, instants: Sequence[Instant], cameras: Sequence[str], T_world_cam: Mapping[str, np.ndarray],
              intrinsics: Mapping[str, CameraIntrinsics], layouts: Mapping[str, CubeLayout],
              params: BundleAdjustmentParams, readout_s: Mapping[str, float] | None = None) -> Refinement:
        robots = list(dict.fromkeys(i.robot for i in instants))
        K, dist = _intrinsics_arrays([intrinsics[c] for c in cameras])
        markers = [m for r in robots for m in layouts[r].markers]
        model = Model(np.array([T_world_cam[c] for c in cameras], float), K, dist,
                      np.array([i.T_world_cube for i in instants], float),
                      np.array([m.T_cube_marker for m in markers], float), np.array([m.size_m for m in markers], float),
                      np.array([j for j, r in enumerate(robots) for _ in layouts[r].markers]), np.ones(len(robots)))
        zeros = np.zeros((len(instants), 3))
        return cls(params, list(cameras), robots, {r: layouts[r] for r in robots}, {c: intrinsics[c] for c in cameras},
                   list(instants), model, zeros, zeros.copy(), dict(readout_s or {}))

    def first_marker(self, robot: str) -> int:
        """Index in the model's markers of the robot's first layout marker."""
        return sum(len(self.layouts[r].markers) for r in self.robots[:self.robots.index(robot)])

    def layout(self, robot: str) -> CubeLayout:
        """The robot's layout as the model has it now (refined when the body is)."""
        i, n = self.first_marker(robot), len(self.layouts[robot].markers)
        return layout_with(self.layouts[robot], self.model.T_body_markers[i:i + n], self.model.sizes_m[i:i + n])

    def T_world_cam(self) -> dict[str, np.ndarray]:
        return {c: self.model.T_cams[i] for i, c in enumerate(self.cameras)}

    def intrinsics(self) -> dict[str, CameraIntrinsics]:
        """Each camera's intrinsics as the model has them now (the given ones unless refined)."""
        out = {}
        for i, c in enumerate(self.cameras):
            g = self.given[c]
            if np.array_equal(self.model.K[i], g.K) and np.array_equal(self.model.dist[i, :len(g.dist)], g.dist):
                out[c] = g
            else:
                dist = self.model.dist[i, :max(len(g.dist), 5)]
                out[c] = dataclasses.replace(g, K=self.model.K[i].copy(), dist=dist.copy())
        return out

    def update_velocities(self) -> None:
        """Velocities of every instant from the solved body poses (per robot)."""
        T = self.model.T_bodies
        self.vel, self.angvel = np.zeros((len(self.instants), 3)), np.zeros((len(self.instants), 3))
        for robot in self.robots:
            idx = np.array([k for k, i in enumerate(self.instants) if i.robot == robot], dtype=int)
            if len(idx):
                self.vel[idx], self.angvel[idx] = velocities(np.array([self.instants[k].time_s for k in idx]), T[idx],
                                                             self.params.velocity_window_s)

    def observations(self, world: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None) -> Observations:
        """The solver's observations: every instant's corners, motion-compensated with the current
        velocities to the time their row was exposed (a rolling shutter's row ``v`` of ``H``
        rows is exposed ``(v - (H - 1) / 2) readout / H`` after the frame's stamp), and ``world``
        points (camera -> (points (n, 3) m, pixels (n, 2)))."""
        cam_index = {c: i for i, c in enumerate(self.cameras)}
        row_time = {c: self.readout_s.get(c, 0.0) / self.given[c].height for c in self.cameras}
        firsts = {r: self.first_marker(r) for r in self.robots}
        cam, inst, marker, pixels, dts = [], [], [], [], []
        for k, instant in enumerate(self.instants):
            for s in instant.sets:
                n = 4 * len(s.markers)
                cam.append(np.full(n, cam_index[s.camera]))
                inst.append(np.full(n, k))
                marker.append(np.repeat(s.markers + firsts[instant.robot], 4))
                px = s.corners_px.reshape(-1, 2)
                pixels.append(px)
                rows = (px[:, 1] - (self.given[s.camera].height - 1) / 2.0) * row_time[s.camera]
                dts.append(s.time_s - instant.time_s + rows)
        inst_a, dt = np.concatenate(inst), np.concatenate(dts)
        wc, wp, wx = [], [], []
        for name, (points, px) in (world or {}).items():
            wc.append(np.full(len(points), cam_index[name]))
            wp.append(points)
            wx.append(px)
        return Observations(np.concatenate(cam), inst_a, np.concatenate(marker),
                            np.tile(np.arange(4), len(inst_a) // 4),
                            np.vstack(pixels), Rotation.from_rotvec(self.angvel[inst_a] * dt[:, None]).as_matrix(),
                            self.vel[inst_a] * dt[:, None],
                            np.array([self.robots.index(i.robot) for i in self.instants], dtype=int), len(self.robots),
                            np.concatenate(wc) if wc else np.zeros(0, int), np.vstack(wp) if wp else np.zeros((0, 3)),
                            np.vstack(wx) if wx else np.zeros((0, 2)), dt)

    def freedom(self, *, cameras: bool = True, camera_prior: PosePrior | None = None, intrinsics: bool = False,
                body: BodyCalibrationParams | None = None, free_scale: bool = False) -> Freedom:
        """A :class:`~cubetrack.calib.solver.Freedom` with this refinement's noise, loss, ground-robot
        priors and, when asked, intrinsics held near the given ones and (``body``: its priors) markers
        near the given layouts."""
        p = self.params
        intrinsics_prior = body_prior = None
        if intrinsics:
            K, dist = _intrinsics_arrays([self.given[c] for c in self.cameras])
            intrinsics_prior = IntrinsicsPrior(K, dist, p.intrinsics_focal_sigma, p.intrinsics_principal_sigma_px,
                                               p.intrinsics_k1_sigma, p.intrinsics_k2_sigma)
        if body is not None:
            markers = [m for r in self.robots for m in self.layouts[r].markers]
            body_prior = BodyPrior(np.array([m.T_cube_marker for m in markers]), np.array([m.size_m for m in markers]),
                                   body.position_sigma_m, np.radians(body.rotation_sigma_deg), body.size_sigma)
        return Freedom(cameras, camera_prior, intrinsics_prior, body_prior, free_scale, p.corner_noise_px,
                       p.world_corner_noise_px, p.f_scale_px, p.height_sigma_m if p.planar_motion else 0.0,
                       float(np.radians(p.upright_sigma_deg)), float(np.radians(p.floor_tilt_sigma_deg)),
                       p.max_nfev, body.motion_noise_px_per_s if body is not None else 0.0)

    def solve(self, free: Freedom, world: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None) -> None:
        self.model = solve(self.observations(world), self.model, free)

    def rematch(self) -> None:
        """Faces matched again to the detections where the solved poses (and the current layouts
        and intrinsics) project them; instants no longer seen by ``min_cameras`` cameras are
        dropped. CalibrationError when none is left."""
        intrinsics, T_world_cam = self.intrinsics(), self.T_world_cam()
        layouts = {r: self.layout(r) for r in self.robots}
        keep, out = [], []
        for k, instant in enumerate(self.instants):
            sets = []
            for f in instant.frames:
                T = moved_pose(self.model.T_bodies[k], self.vel[k], self.angvel[k], f.time_s - instant.time_s)
                s = _frame_corners(f, layouts[instant.robot], intrinsics[f.camera], T_world_cam[f.camera],
                                   self.params, T)
                if s is not None:
                    sets.append((f, s))
            if len({f.camera for f, _ in sets}) >= self.params.min_cameras:
                keep.append(k)
                out.append(Instant(instant.robot, instant.time_s, tuple(f for f, _ in sets), tuple(s for _, s in sets),
                                   self.model.T_bodies[k]))
        if not out:
            raise CalibrationError("no multi-camera cube sightings fit the refined poses")
        self.instants = out
        self.model = self.model.replace(T_bodies=self.model.T_bodies[keep])
        self.vel, self.angvel = self.vel[keep], self.angvel[keep]


@dataclass(frozen=True, slots=True)
class TrajectorySpec:
    """A continuous-time trajectory's settings (:class:`Trajectory`): knots ``knot_s`` apart, a new
    piece where the frames lie more than ``gap_s`` apart, the smoothness prior's sigmas."""

    knot_s: float
    gap_s: float
    accel_sigma_m_s2: float
    angular_accel_sigma_rad_s2: float


@dataclass(eq=False)
class Trajectory:
    """Each body's continuous-time trajectory through a refinement's frames (the body calibration's
    and, with ``[bundle_adjustment] knot_s`` > 0, the extrinsics refinement's): body poses at knots
    ``times_s`` (K,) ``spec.knot_s`` apart within pieces of the recording where a robot's frames
    follow each other within ``spec.gap_s`` (``first`` (K,): whether a knot starts a piece;
    ``robot`` (K,): whose body, each robot's knots together), each corner seen at the pose
    interpolated to the time its row was exposed, the knots tied by the solver's smoothness prior.
    So frames of different cameras up to ``max_span_s`` apart are compared at their own times, with
    no velocity assumed (a constant velocity across an instant's frames misses turns and the
    robot's wobble). The frames are every frame of the refinement's instants, each with its corners
    matched (``sets``) at the trajectory's pose. From :meth:`start` on, ``ref.model``'s body poses
    are the knots' (its instants no longer apply)."""

    ref: Refinement
    spec: TrajectorySpec
    times_s: np.ndarray
    first: np.ndarray
    robot: np.ndarray
    frames: list[CubeFrame]
    sets: list[FrameCorners]

    @classmethod
    def start(cls, ref: Refinement, spec: TrajectorySpec) -> Trajectory:
        """Knots over the instants' frames, started from the instants' poses moved with their
        velocities, and the frames matched at them."""
        frames = sorted({id(f): f for i in ref.instants for f in i.frames}.values(), key=lambda f: (f.time_s, f.camera))
        margin = max(ref.readout_s.values(), default=0.0) / 2 + spec.knot_s
        times, first, robot, knots = [], [], [], []
        for j, name in enumerate(ref.robots):
            t = np.array([f.time_s for f in frames if f.robot == name])
            mine = [k for k, i in enumerate(ref.instants) if i.robot == name]
            inst_t = np.array([ref.instants[k].time_s for k in mine])  # in time order
            for piece in np.split(t, np.flatnonzero(np.diff(t) > spec.gap_s) + 1):
                n = int(np.ceil((piece[-1] - piece[0] + 2 * margin) / spec.knot_s)) + 1
                piece_s = piece[0] - margin + spec.knot_s * np.arange(n)
                after = np.searchsorted(inst_t, piece_s).clip(0, len(inst_t) - 1)
                before = (after - 1).clip(0)
                near = np.where(np.abs(piece_s - inst_t[before]) < np.abs(piece_s - inst_t[after]), before, after)
                knots += [moved_pose(ref.model.T_bodies[mine[k]], ref.vel[mine[k]], ref.angvel[mine[k]],
                                     tk - inst_t[k]) for k, tk in zip(near, piece_s, strict=True)]
                times.append(piece_s)
                first.append(np.arange(n) == 0)
                robot.append(np.full(n, j))
        ref.model = ref.model.replace(T_bodies=np.array(knots))
        trajectory = cls(ref, spec, np.concatenate(times), np.concatenate(first), np.concatenate(robot), frames, [])
        trajectory.rematch()
        return trajectory

    def _knot(self, t: np.ndarray, robot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The knot of each ``robot`` (index) before each time (its piece's last-but-one at most)
        and the fraction to the next."""
        k = np.empty(len(t), dtype=int)
        for j in np.unique(robot):
            mine = np.flatnonzero(self.robot == j)
            at = robot == j
            k[at] = mine[0] + np.clip(np.searchsorted(self.times_s[mine], t[at], side="right") - 1, 0, len(mine) - 2)
        last = np.r_[self.first[1:], True]  # a piece's last knot: the next knot starts a piece
        k = np.where(last[k], k - 1, k)
        return k, (t - self.times_s[k]) / (self.times_s[k + 1] - self.times_s[k])

    def pose_at(self, robot: str, time_s: float) -> np.ndarray:
        """The ``robot``'s body pose (4, 4) at ``time_s`` on the trajectory."""
        k, alpha = self._knot(np.array([time_s]), np.array([self.ref.robots.index(robot)]))
        R, p = interpolated_poses(self.ref.model.T_bodies[k], self.ref.model.T_bodies[k + 1], alpha)
        return make_T(R[0], p[0])

    def rematch(self) -> None:
        """Every frame's detections matched to its body's markers at the trajectory's pose (frames
        where nothing matches are left out)."""
        ref = self.ref
        intrinsics, T_world_cam = ref.intrinsics(), ref.T_world_cam()
        layouts = {r: ref.layout(r) for r in ref.robots}
        found = [(f, _frame_corners(f, layouts[f.robot], intrinsics[f.camera], T_world_cam[f.camera], ref.params,
                                    self.pose_at(f.robot, f.time_s))) for f in self.frames]
        pairs = [(f, s) for f, s in found if s is not None]
        if not pairs:
            raise CalibrationError("no cube sightings fit the body's trajectory")
        self.frames, self.sets = [f for f, _ in pairs], [s for _, s in pairs]

    def frame_of_corner(self) -> np.ndarray:
        """(N,) each observed corner's frame (index into ``frames``), in :meth:`observations`' order."""
        return np.repeat(np.arange(len(self.sets)), [4 * len(s.markers) for s in self.sets])

    def observations(self, world: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None) -> Observations:
        """The solver's observations: every matched corner at the time its row was exposed (as
        :meth:`Refinement.observations` times them) on the trajectory, and ``world`` points (as
        there)."""
        ref = self.ref
        cam_index = {c: i for i, c in enumerate(ref.cameras)}
        firsts = {r: ref.first_marker(r) for r in ref.robots}
        frame = self.frame_of_corner()
        cam = np.array([cam_index[s.camera] for s in self.sets], dtype=int)[frame]
        robot = np.array([ref.robots.index(f.robot) for f in self.frames], dtype=int)[frame]
        marker = np.concatenate([np.repeat(s.markers + firsts[f.robot], 4) for f, s in zip(self.frames, self.sets,
                                                                                         strict=True)])
        pixels = np.vstack([s.corners_px.reshape(-1, 2) for s in self.sets])
        height = np.array([ref.given[s.camera].height for s in self.sets], float)[frame]
        row_s = np.array([ref.readout_s.get(s.camera, 0.0) for s in self.sets])[frame] / height
        times = np.array([s.time_s for s in self.sets])[frame]
        k, alpha = self._knot(times + (pixels[:, 1] - (height - 1) / 2.0) * row_s, robot)
        n = len(cam)
        inner = np.flatnonzero(~self.first[1:-1] & ~self.first[2:]) + 1  # knots with both neighbours in their piece
        wc, wp, wx = [], [], []
        for name, (points, px) in (world or {}).items():
            wc.append(np.full(len(points), cam_index[name]))
            wp.append(points)
            wx.append(px)
        return Observations(cam, k, marker, np.tile(np.arange(4), n // 4), pixels, np.tile(np.eye(3), (n, 1, 1)),
                            np.zeros((n, 3)), self.robot, len(ref.robots),
                            np.concatenate(wc) if wc else np.zeros(0, int), np.vstack(wp) if wp else np.zeros((0, 3)),
                            np.vstack(wx) if wx else np.zeros((0, 2)), knot_alpha=alpha,
                            knot_triples=np.column_stack([inner - 1, inner, inner + 1]),
                            knot_spacing_s=self.spec.knot_s)

    def solve(self, free: Freedom, world: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None) -> None:
        """Solve the knots and what ``free`` frees (no motion noise: nothing is extrapolated)."""
        free = dataclasses.replace(free, motion_noise_px_per_s=0.0, accel_sigma_m_s2=self.spec.accel_sigma_m_s2,
                                   angular_accel_sigma_rad_s2=self.spec.angular_accel_sigma_rad_s2)
        self.ref.model = solve(self.observations(world), self.ref.model, free)


def rms_px(residuals: np.ndarray) -> float:
    """RMS length of (n, 2) pixel residuals; NaN when there are none."""
    return float(np.sqrt(np.nanmean(np.sum(residuals ** 2, axis=1)))) if len(residuals) else float("nan")


# ---------------------------------------------------------------------------------------------
# Instants, alignment, the whole refinement


def _pose_distance(Ta: np.ndarray, Tb: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3])), rotation_angle(Ta[:3, :3], Tb[:3, :3], "deg")


def make_instants(frames: Sequence[CubeFrame], layouts: Mapping[str, CubeLayout],
                  intrinsics: Mapping[str, CameraIntrinsics], T_world_cam: Mapping[str, np.ndarray],
                  params: BundleAdjustmentParams, progress: Progress | None = None) -> list[Instant]:
    """Instants (:func:`group_instants`) with at least ``min_cameras`` cameras' matched corners,
    each starting from its best-seen camera's single-camera estimate; at most ``max_instants``,
    evenly spread."""
    by_robot: dict[str, list[CubeFrame]] = {}
    for f in frames:
        by_robot.setdefault(f.robot, []).append(f)
    grouped = [group_instants(robot_frames, params.max_span_s, params.min_cameras)
               for robot_frames in by_robot.values()]
    total = sum(len(g) for g in grouped)
    groups = [g for robot_groups in grouped
              for g in spread_instants(robot_groups, round(params.max_instants * len(robot_groups) / total)
                                       if total > params.max_instants else len(robot_groups),
                                       params.velocity_window_s)]
    groups.sort(key=lambda g: g[0].time_s)
    instants = []
    for done, group in enumerate(groups, start=1):
        if progress is not None:
            progress("bundle adjustment: instants", done, len(groups))
        layout = layouts[group[0].robot]
        found = [(f, _frame_corners(f, layout, intrinsics[f.camera], T_world_cam[f.camera], params)) for f in group]
        pairs = [(f, s) for f, s in found if s is not None]
        if len({f.camera for f, _ in pairs}) < params.min_cameras:
            continue
        t_ref = float(np.mean([f.time_s for f, _ in pairs]))
        # start from the single-camera estimate of the camera seeing the most markers
        start = max(pairs, key=lambda p: len(p[1].markers))
        est_T = _estimate_T(start[0], layout, intrinsics, T_world_cam)
        if est_T is None:
            continue
        instants.append(Instant(group[0].robot, t_ref, tuple(f for f, _ in pairs), tuple(s for _, s in pairs), est_T))
    return instants


def _estimate_T(frame: CubeFrame, layout: CubeLayout, intrinsics: Mapping[str, CameraIntrinsics],
                T_world_cam: Mapping[str, np.ndarray]) -> np.ndarray | None:
    from cubetrack.estimate.pose import estimate_cube

    est = estimate_cube(frame.detections, layout, intrinsics[frame.camera], T_world_cam[frame.camera],
                        camera=frame.camera, robot=frame.robot, seq=frame.seq, capture_time_s=frame.time_s,
                        arrival_time_s=frame.time_s)
    return None if est is None else est.T_world_cube


def _align(T_rel: dict[str, np.ndarray], T_prior: dict[str, np.ndarray],
           params: BundleAdjustmentParams) -> tuple[np.ndarray, list[str], list[str]]:
    """The rigid transform G (prior world <- relative frame) most cameras agree on; returns
    (G, consistent cameras, cameras that disagree)."""
    names = list(T_rel)
    cands = {c: T_prior[c] @ invert_T(T_rel[c]) for c in names}

    def agree(G: np.ndarray) -> tuple[list[str], float]:
        ok, cost = [], 0.0
        for c in names:
            d_m, d_deg = _pose_distance(G @ T_rel[c], T_prior[c])
            cost += d_m / params.moved_position_m + d_deg / params.moved_rotation_deg
            if d_m <= params.moved_position_m and d_deg <= params.moved_rotation_deg:
                ok.append(c)
        return ok, cost

    scored = [(agree(G), c) for c, G in cands.items()]
    (inliers, _), _c = max(scored, key=lambda s: (len(s[0][0]), -s[0][1]))
    if not inliers:
        inliers = names
    Gs = np.array([cands[c] for c in inliers])
    G = make_T(mean_rotation(Gs[:, :3, :3]), Gs[:, :3, 3].mean(axis=0))
    inliers, _ = agree(G)
    if not inliers:
        inliers = names
    return G, inliers, [c for c in names if c not in inliers]


def world_marker_terms(observations: Mapping[str, WorldMarkerObservation], world: WorldConfig,
                       cameras: Iterable[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The solver's world points of the ``cameras`` that have a world-marker observation: the
    marker's four corners (world frame), or the reference's points, and their averaged pixels."""
    marker = marker_corners_m(world.marker_size_m)
    terms: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for c in cameras:
        if c in observations:
            points_m = observations[c].points_world_m
            terms[c] = (marker if points_m is None else points_m, observations[c].corners_px)
    return terms


def start_refinement(frames: Mapping[str, Iterable[Frame]], extrinsics: Mapping[str, CameraExtrinsics],
                     intrinsics: Mapping[str, CameraIntrinsics], layouts: Mapping[str, CubeLayout], *,
                     clock_samples: Mapping[str, Sequence[ClockSample]] | None,
                     params: BundleAdjustmentParams, detector_params: DetectorParams | None,
                     progress: Progress | None, frame_count: int, warn: Callable[[str], None],
                     readout_s: Mapping[str, float] | None = None,
                     calibration_corners: bool = False) -> tuple[Refinement, list[str]]:
    """The first steps every refinement shares: the cube frames of the cameras with extrinsics,
    instants, and body poses solved with the cameras held (twice: the second time with
    velocities from the first). ``readout_s``: each camera's rolling-shutter readout (None: the
    intrinsics' ``readout_s``, from camera_info). Returns the refinement and all cameras with
    extrinsics (some may have no multi-camera sightings: warned about). CalibrationError for too
    few cameras or no instant."""
    unknown = [c for c in frames if c not in extrinsics]
    cameras = [c for c in frames if c in extrinsics]
    if len(cameras) < 2:
        raise CalibrationError(
            f"cameras {', '.join(frames)} share "
            f"{len(cameras)} camera(s) with the extrinsics ({', '.join(extrinsics) or 'none'}); refinement needs "
            "a tracking recording of at least two calibrated cameras")
    if unknown:
        warn(f"camera(s) {', '.join(unknown)} have no extrinsics and are left out")
    missing = [c for c in cameras if c not in intrinsics]
    if missing:
        raise CalibrationError(f"camera(s) {', '.join(missing)}: no intrinsics")
    T_prior = {c: extrinsics[c].T_world_cam for c in cameras}
    observed = cube_frames({c: frames[c] for c in cameras}, layouts, clock_samples, detector_params, progress,
                           frame_count, {c: intrinsics[c] for c in cameras} if calibration_corners else None)
    instants = make_instants(observed, layouts, intrinsics, T_prior, params, progress)
    if not instants:
        raise CalibrationError(
            f"no instant where {params.min_cameras}+ cameras saw a robot's cube within "
            f"{1000 * params.max_span_s:.0f} ms ({len(observed)} frames with cube markers); record the robot "
            "driving where several cameras see it")
    used = sorted({s.camera for i in instants for s in i.sets}, key=cameras.index)
    for c in cameras:
        if c not in used:
            warn(f"{c}: no multi-camera cube sightings in the tracking recording; its calibration is kept as it is")
    if len(used) < 2:
        raise CalibrationError(f"only {used[0]} has multi-camera cube sightings; "
                               "refinement needs at least two cameras seeing the cube at once")
    if readout_s is None:
        readout_s = {c: intrinsics[c].readout_s for c in used}
    refinement = Refinement.start(instants, used, T_prior, intrinsics, layouts, params, readout_s)
    for _ in range(2):
        refinement.solve(refinement.freedom(cameras=False))
        refinement.update_velocities()
    return refinement, cameras


def adjust_extrinsics(frames: Mapping[str, Iterable[Frame]], extrinsics: Mapping[str, CameraExtrinsics],
                     intrinsics: Mapping[str, CameraIntrinsics], layouts: Mapping[str, CubeLayout],
                     world: WorldConfig, *, clock_samples: Mapping[str, Sequence[ClockSample]] | None = None,
                     world_frames: Mapping[str, Iterable[Frame]] | None = None,
                     params: BundleAdjustmentParams = BundleAdjustmentParams(),
                     calibration_params: CalibrationParams | None = None,
                     detector_params: DetectorParams | None = None, progress: Progress | None = None,
                     frame_count: int = 0, world_frame_counts: Mapping[str, int] | None = None,
                     readout_s: Mapping[str, float] | None = None) -> BundleAdjustmentReport:
    """Refine ``extrinsics`` (the world-marker calibration) by bundle adjustment over the cube
    sightings in the tracking ``frames`` (camera -> its frames, stamped with the camera's
    ``clock_samples``) and the world marker in the calibration ``world_frames`` (camera -> its
    frames; None: cube sightings only), see the module docstring. ``layouts``: robot -> cube
    layout; ``intrinsics`` of every camera of ``frames`` that has extrinsics; ``calibration_params``
    and ``detector_params`` are the ``[calibration]`` and ``[detector]`` settings (None: defaults).

    Returns the refined extrinsics of every prior camera, per-camera residuals and moved
    cameras (and, with ``refine_intrinsics``, the refined intrinsics); warnings are also logged.
    ``readout_s``: each camera's rolling-shutter readout (s; None: the intrinsics' ``readout_s``).
    CalibrationError when the frames share fewer than two cameras with the extrinsics or no
    instant has two cameras seeing the cube.
    """
    warnings: list[str] = []

    def warn(message: str) -> None:
        warnings.append(message)
        log.warning("%s", message)

    # the cube's corners template-fitted, as the body calibration's: the edge fit's outward bias
    # on obliquely seen markers scaled the refined cameras out (issue 26, docs/calibration.md)
    ref, cameras = start_refinement(frames, extrinsics, intrinsics, layouts, clock_samples=clock_samples,
                                    params=params, detector_params=detector_params, progress=progress,
                                    frame_count=frame_count, warn=warn, readout_s=readout_s,
                                    calibration_corners=True)
    T_prior = {c: extrinsics[c].T_world_cam for c in cameras}
    used = ref.cameras
    trajectory = Trajectory.start(ref, TrajectorySpec(params.knot_s, params.max_span_s, params.accel_sigma_m_s2,
                                                      params.angular_accel_sigma_rad_s2)) if params.knot_s > 0 else None
    poses: Refinement | Trajectory = trajectory or ref  # what the solves move: the instants' poses or the knots

    moved = _relative_solve(ref, poses, T_prior, params, warn)

    # 2. absolute solves: re-matched faces, re-estimated velocities, world-marker corners
    world_terms: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    if world_frames is not None:
        observations = world_marker_observations(world_frames, world, intrinsics, calibration_params, detector_params,
                                                 progress, params.world_samples, world_frame_counts)
        world_terms = world_marker_terms(observations, world, [c for c in used if c not in moved])
        if not world_terms:
            warn("no usable world-marker sightings in the calibration recording; the refined poses keep the prior "
                 "calibration's frame (aligned to the cameras that agree)")
    # without world-marker corners the gauge stays held by weak priors at the aligned poses
    K_prior, dist_prior = ref.model.K.copy(), ref.model.dist.copy()
    for _round in range(params.rounds):
        if trajectory is None:
            ref.update_velocities()
            ref.rematch()
        else:
            trajectory.rematch()
        gauge = None if world_terms else PosePrior(ref.model.T_cams.copy(), params.gauge_prior_position_m,
                                                   np.radians(params.gauge_prior_rotation_deg))
        poses.solve(ref.freedom(camera_prior=gauge, intrinsics=params.refine_intrinsics,
                              free_scale=params.free_cube_scale and bool(world_terms)), world_terms)

    prior = ref.model.replace(T_cams=np.array([T_prior[c] for c in used]), K=K_prior, dist=dist_prior)
    worse = worse_world_fit(poses.observations(world_terms), prior, ref.model, used, params.world_corner_noise_px)
    if worse:
        warn(f"refinement refused: {'; '.join(worse)}: the cube sightings disagree with the world marker beyond its "
             f"corners' noise ({params.world_corner_noise_px:g} px; a wrong marker or cube size in the config, a body "
             "that is not rigid, or the world marker moved); the world-marker calibration is kept")
    return _adjustment_report(ref, trajectory, extrinsics, intrinsics, cameras, T_prior, moved, world_terms, warn,
                              warnings, refused=bool(worse))


def _relative_solve(ref: Refinement, poses: Refinement | Trajectory, T_prior: dict[str, np.ndarray],
                    params: BundleAdjustmentParams, warn: Callable[[str], None]) -> list[str]:
    """Step 1 of :func:`adjust_extrinsics`: the cube corners only, the gauge held by weak priors on
    the cameras; then the whole solution aligned to the cameras that agree with ``T_prior``.
    Returns the cameras that moved (none when fewer than two agree: the data cannot say which)."""
    gauge = PosePrior(ref.model.T_cams.copy(), params.gauge_prior_position_m,
                      np.radians(params.gauge_prior_rotation_deg))
    poses.solve(ref.freedom(camera_prior=gauge))
    G, consistent, moved = _align(ref.T_world_cam(), T_prior, params)
    if moved and len(consistent) < 2:
        # two cameras disagree (or none agree): the data cannot say which one moved
        d = max(_pose_distance(G @ T, T_prior[c])[0] for c, T in ref.T_world_cam().items())
        warn(f"cameras {', '.join(ref.cameras)} disagree with their calibration by up to {100 * d:.1f} cm: one of "
             "them moved after calibration, but it takes three cameras to tell which; recalibrate")
        moved = []
    ref.model = ref.model.replace(T_cams=np.einsum("ij,cjk->cik", G, ref.model.T_cams),
                                  T_bodies=np.einsum("ij,kjl->kil", G, ref.model.T_bodies))
    return list(moved)


def worse_world_fit(obs: Observations, prior: Model, refined: Model, cameras: Sequence[str],
                    noise_px: float) -> list[str]:
    """The refinement's check by the data's own residuals (issue 26): per camera with world-marker
    terms in ``obs``, its world-marker corners' RMS reprojection error with the ``prior`` (the
    world-marker calibration) and the ``refined`` model; one line per camera the refinement fits
    more than ``noise_px`` worse (the refinement must never leave the cameras worse than the world
    marker left them), empty when none."""
    before, after = world_residuals_px(obs, prior), world_residuals_px(obs, refined)
    out = []
    for i, c in enumerate(cameras):
        mine = obs.world_cam == i
        if mine.any() and rms_px(after[mine]) > rms_px(before[mine]) + noise_px:
            out.append(f"{c}'s world marker reprojects {rms_px(after[mine]):.2f} px off after refinement, "
                       f"{rms_px(before[mine]):.2f} px before")
    return out


def _adjustment_report(ref: Refinement, trajectory: Trajectory | None, extrinsics: Mapping[str, CameraExtrinsics],
                       intrinsics: Mapping[str, CameraIntrinsics], cameras: Sequence[str],
                       T_prior: Mapping[str, np.ndarray], moved: Sequence[str],
                       world_terms: dict[str, tuple[np.ndarray, np.ndarray]], warn: Callable[[str], None],
                       warnings: list[str], refused: bool = False) -> BundleAdjustmentReport:
    """The refined extrinsics and each camera's residuals after the last solve (see
    :func:`adjust_extrinsics`; ``trajectory``: the body poses were its knots); a moved camera is
    also warned about. ``refused``: the residuals are reported but the extrinsics (and
    intrinsics) stay the prior ones. A camera's ``instants`` are, on a trajectory, its frames."""
    used = ref.cameras
    if trajectory is None:
        ref.update_velocities()
        obs = ref.observations(world_terms)
        sample = obs.inst
    else:
        obs = trajectory.observations(world_terms)
        sample = trajectory.frame_of_corner()
    r, rw = corner_residuals_px(obs, ref.model), world_residuals_px(obs, ref.model)
    refined = dict(extrinsics)
    report_cams = {}
    for i, c in enumerate(used):
        mine = obs.cam == i
        shift_m, shift_deg = _pose_distance(ref.model.T_cams[i], T_prior[c])
        n_inst = len(np.unique(sample[mine]))
        report_cams[c] = CameraResidual(c, rms_px(r[mine]), int(mine.sum()), n_inst, rms_px(rw[obs.world_cam == i]),
                                        shift_m, shift_deg, c in moved)
        refined[c] = CameraExtrinsics(ref.model.T_cams[i], n_inst, 0.0, 0.0, METHOD)
        if c in moved:
            warn(f"camera {c} has moved after calibration: the other cameras' cube sightings put it "
                 f"{100 * shift_m:.1f} cm and {shift_deg:.2f} deg from its calibrated pose; its world-marker "
                 "calibration was ignored and its pose re-estimated from the cube")
    for c in cameras:
        if c not in report_cams:
            report_cams[c] = CameraResidual(c, float("nan"), 0, 0, float("nan"), 0.0, 0.0, False)
    if refused:
        return BundleAdjustmentReport(dict(extrinsics), dict(extrinsics), report_cams, (), len(ref.instants),
                                      tuple(warnings), dict(intrinsics), refused=True)
    return BundleAdjustmentReport(refined, dict(extrinsics), report_cams, tuple(moved), len(ref.instants),
                                  tuple(warnings), {**dict(intrinsics), **ref.intrinsics()})
