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
    after each solve.

Unknowns: each camera's 6-dof pose, the cube pose at each instant and (``planar_motion``) one
cube height per robot. Residuals: reprojection errors (pixels, on undistorted points scaled by
the focal length, as in :mod:`cubetrack.estimate.reprojection`) of every corner, with a soft-L1 loss; for ground
robots also the cube's height against its robot's common height and its tilt from world up (the
floor the world marker lies on is the plane the robot drives on: this fixes the world frame's
tilt, the weak direction of one obliquely seen marker). ``scipy.optimize.least_squares`` with an
analytic sparse Jacobian (a corner depends on one camera and one instant), so 5 cameras x
hundreds of instants solve in seconds. Pose increments are world-frame, as in
:mod:`cubetrack.estimate.reprojection`.

Steps (:func:`adjust_extrinsics`, which takes frames and clock samples held anywhere, e.g. in
memory; ``cubetrack.app.calibrate.adjust_recording_extrinsics`` feeds it recording folders):

1. Per camera frame of the tracking recording: cube detections, a single-camera cube estimate
   (:func:`cubetrack.estimate.estimate_cube`) with the prior extrinsics, and the faces matched to
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

Without a calibration recording the result of step 2 (aligned to the prior extrinsics) is
returned. Several floor markers are not supported: the config names one world marker.
A camera with no multi-camera cube sightings keeps its prior pose (and is named in a warning).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Iterable, Mapping, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

from cubetrack.calib.extrinsics import CalibrationMethod, CalibrationParams, collect_sightings, inlier_frames
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample, WorldConfig
from cubetrack.core.errors import CalibrationError, ImageError
from cubetrack.core.geometry import invert_T, make_T, mean_rotation, rotation_angle
from cubetrack.core.layout import CubeLayout, marker_corners_m
from cubetrack.core.params import check, check_positive, param
from cubetrack.core.progress import Progress
from cubetrack.core.records import Detection, Frame
from cubetrack.detect.detector import Detector, DetectorParams
from cubetrack.estimate.match import body_detections, match_faces
from cubetrack.estimate.reprojection import CornerSet, corner_set, moved_pose, normalize_px, pinhole_normalized

log = logging.getLogger(__name__)

METHOD = "refined"  # CameraExtrinsics.method of a camera after bundle adjustment (the word users see)


@dataclass(frozen=True, slots=True)
class BundleAdjustmentParams:
    """The ``[bundle_adjustment]`` section: how :func:`adjust_extrinsics` selects observations and solves."""

    max_span_s: float = param(0.1, "frames of different cameras whose capture times (host clock) lie within this many seconds form one instant")
    min_cameras: int = param(2, "an instant needs cube corners from at least this many cameras")
    max_instants: int = param(400, "at most this many instants are used (evenly spread over the recording)")
    corner_noise_px: float = param(0.5, "cube corner noise (1 sigma), pixels")
    world_corner_noise_px: float = param(0.5, "noise (1 sigma) of the world marker's averaged corners, pixels")
    f_scale_px: float = param(1.5, "residuals beyond this are down-weighted (soft-L1 loss), pixels")
    association_gate_px: float = param(12.0, "a detection joins a cube face if its corners lie within this many pixels (or half a marker side) of the predicted face")
    velocity_window_s: float = param(0.3, "velocities of an instant are fitted to the instants within this many seconds")
    moved_position_m: float = param(0.02, "a camera whose cube-consensus pose is farther than this from its calibration has moved, metres")
    moved_rotation_deg: float = param(0.5, "... or turned by more than this, degrees")
    gauge_prior_position_m: float = param(0.1, "relative solve: weak prior on each camera's position (holds the gauge), metres")
    gauge_prior_rotation_deg: float = param(3.0, "relative solve: weak prior on each camera's rotation, degrees")
    planar_motion: bool = param(True, "each robot's cube stays at one height above the floor the world marker lies on (ground robots, level floor): fixes the world frame's tilt far better than one marker; false for robots that climb")
    height_sigma_m: float = param(0.002, "planar motion: spread (1 sigma) of the cube's height along the path, metres")
    upright_sigma_deg: float = param(1.0, "spread (1 sigma) of each cube's tilt from world up (ground robots: the estimator's upright prior); 0 = no such prior, degrees")
    free_cube_scale: bool = param(False, "absolute solves: estimate each cube's scale too, so the world marker sets the scale (measured worse on simulations: the obliquely seen marker's scale is less sure than the cube's): a corner bias of 0.01 px on a 20 px cube marker changes its apparent size by 0.1 %, which moves every camera radially by 2 mm")
    world_samples: int = param(60, "world-marker sightings averaged per camera of the calibration recording (the first N found)")
    rounds: int = param(2, "absolute solves, each after re-matching faces and re-estimating velocities")
    max_nfev: int = param(60, "function evaluations per least-squares solve")

    def __post_init__(self) -> None:
        check_positive(self, "max_span_s", "corner_noise_px", "world_corner_noise_px", "f_scale_px",
                       "association_gate_px", "velocity_window_s", "moved_position_m", "moved_rotation_deg",
                       "gauge_prior_position_m", "gauge_prior_rotation_deg", "height_sigma_m")
        check(self.upright_sigma_deg >= 0, f"upright_sigma_deg must not be negative, got {self.upright_sigma_deg}")
        check(self.world_samples >= 1, f"world_samples must be at least 1, got {self.world_samples}")
        check(self.min_cameras >= 2 and self.max_instants >= 1 and self.rounds >= 1 and self.max_nfev >= 1,
              "need min_cameras >= 2, max_instants >= 1, rounds >= 1, max_nfev >= 1")


# ---------------------------------------------------------------------------------------------
# Observations


@dataclass(frozen=True, slots=True, eq=False)
class WorldMarkerObservation:
    """The world marker in one camera of the calibration recording: the robust average of its
    (edge-refined) corners over ``frames`` inlier frames, (4, 2) px, TL TR BR BL."""

    camera: str
    corners_px: np.ndarray
    frames: int


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
class Instant:
    """Cube corners of several cameras at about one time: ``sets`` (one per camera), their
    capture times differing by at most ``BundleAdjustmentParams.max_span_s``; ``time_s`` their mean."""

    robot: str
    time_s: float
    frames: tuple[CubeFrame, ...]
    sets: tuple[CornerSet, ...]
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
    cameras that moved after calibration, the instants used and the warnings issued."""

    extrinsics: dict[str, CameraExtrinsics]
    prior: dict[str, CameraExtrinsics]
    cameras: dict[str, CameraResidual]
    moved: tuple[str, ...]
    instants: int
    warnings: tuple[str, ...] = field(default_factory=tuple)


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


def _clock_fit(camera: str, samples: Sequence[ClockSample], device_s: Sequence[float], host_s: Sequence[float]):
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
                frame_count: int = 0) -> list[CubeFrame]:
    """Every frame of ``frames`` (camera -> its frames) that shows a robot's cube ids (``layouts``:
    robot -> cube layout), stamped with its capture time on the host clock from the camera's
    ``clock_samples`` (round trips; without them, its frames' arrival times); in time order.
    ``frame_count`` (all cameras' frames) only sizes the progress."""
    detector = Detector(detector_params or DetectorParams(), [lay.dictionary for lay in layouts.values()])
    out, done = [], 0
    for camera, camera_frames in frames.items():
        seen: list[tuple[int, float, tuple[tuple[str, tuple[Detection, ...]], ...]]] = []
        device_s, host_s = [], []
        for frame in camera_frames:
            done += 1
            if progress is not None:
                progress("bundle adjustment: cube detections", done, frame_count)
            device_s.append(frame.device_time_s)
            host_s.append(frame.host_time_s)
            try:
                detections = detector.detect_jpeg(frame.jpeg, f"{camera} frame {frame.seq}")
            except ImageError as exc:
                log.warning("%s; skipped", exc)
                continue
            robots = []
            for robot, lay in layouts.items():
                mine = body_detections(detections, lay)
                if mine:
                    robots.append((robot, mine))
            if robots:
                seen.append((frame.seq, frame.device_time_s, tuple(robots)))
        if not device_s:
            continue
        fit = _clock_fit(camera, (clock_samples or {}).get(camera, ()), device_s, host_s)
        for seq, device_time_s, robots in seen:
            t = fit.to_host(device_time_s)
            out.extend(CubeFrame(camera, robot, seq, t, mine) for robot, mine in robots)
    out.sort(key=lambda f: (f.time_s, f.camera))
    return out


def _frame_corners(frame: CubeFrame, layout: CubeLayout, intrinsics: CameraIntrinsics, T_world_cam: np.ndarray,
                   params: BundleAdjustmentParams) -> CornerSet | None:
    """The frame's corners matched to cube faces at its own single-camera estimate."""
    from cubetrack.estimate.pose import estimate_cube

    est = estimate_cube(frame.detections, layout, intrinsics, T_world_cam, camera=frame.camera, robot=frame.robot,
                        seq=frame.seq, capture_time_s=frame.time_s, arrival_time_s=frame.time_s)
    if est is None:
        return None
    matches = match_faces(frame.detections, layout, intrinsics, T_world_cam, est.T_world_cube,
                          gate_px=params.association_gate_px)
    return corner_set(matches, intrinsics, T_world_cam, frame.camera, frame.time_s)


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
# The bundle adjustment


@dataclass(frozen=True, slots=True, eq=False)
class _Problem:
    """Corner observations as flat arrays (one row per corner)."""

    cam: np.ndarray  # (N,) camera index
    inst: np.ndarray  # (N,) instant index
    points_cube: np.ndarray  # (N, 3)
    observed: np.ndarray  # (N, 2) normalised
    focal: np.ndarray  # (N,)
    motion_R: np.ndarray  # (N, 3, 3) exp(ω dt)
    motion_t: np.ndarray  # (N, 3) v dt
    world_cam: np.ndarray  # (M,) camera index of each world-marker corner
    world_points: np.ndarray  # (M, 3)
    world_observed: np.ndarray  # (M, 2)
    world_focal: np.ndarray  # (M,)
    robot: np.ndarray  # (K,) robot index of each instant
    robots: int


def _build_problem(instants: Sequence[Instant], cam_index: dict[str, int], vel: np.ndarray, angvel: np.ndarray,
                   world: dict[str, tuple[np.ndarray, float]], world_points: np.ndarray) -> _Problem:
    cam, inst, pts, obs, foc, dts = [], [], [], [], [], []
    for k, instant in enumerate(instants):
        for s in instant.sets:
            n = len(s.points_cube_m)
            cam.append(np.full(n, cam_index[s.camera]))
            inst.append(np.full(n, k))
            pts.append(s.points_cube_m)
            obs.append(s.normalized)
            foc.append(np.full(n, s.focal_px))
            dts.append(np.full(n, s.time_s - instant.time_s))
    inst_a = np.concatenate(inst)
    dt = np.concatenate(dts)
    motion_R = Rotation.from_rotvec(angvel[inst_a] * dt[:, None]).as_matrix()
    motion_t = vel[inst_a] * dt[:, None]
    names = list(dict.fromkeys(i.robot for i in instants))
    robot = np.array([names.index(i.robot) for i in instants], dtype=int)
    wc, wp, wo, wf = [], [], [], []
    for name, (normalized, focal) in world.items():
        wc.append(np.full(4, cam_index[name]))
        wp.append(world_points)
        wo.append(normalized)
        wf.append(np.full(4, focal))
    return _Problem(np.concatenate(cam), inst_a, np.vstack(pts), np.vstack(obs), np.concatenate(foc), motion_R,
                    motion_t, np.concatenate(wc) if wc else np.zeros(0, int), np.vstack(wp) if wp else np.zeros((0, 3)),
                    np.vstack(wo) if wo else np.zeros((0, 2)), np.concatenate(wf) if wf else np.zeros(0),
                    robot, len(names))


def _apply(T0: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(K, 4, 4) poses moved by (K, 6) world-frame increments [δp, δθ]."""
    out = T0.copy()
    out[:, :3, :3] = Rotation.from_rotvec(x[:, 3:6]).as_matrix() @ T0[:, :3, :3]
    out[:, :3, 3] = T0[:, :3, 3] + x[:, :3]
    return out


def _project(T_world_cam: np.ndarray, cam: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """Normalised projections of (N, 3) world points in cameras ``cam``; NaN behind a camera."""
    R = T_world_cam[cam, :3, :3]
    return pinhole_normalized(np.einsum("nji,nj->ni", R, points_world - T_world_cam[cam, :3, 3]))


def _corner_residuals_px(prob: _Problem, T_cams: np.ndarray, T_cubes: np.ndarray) -> np.ndarray:
    """(N, 2) cube-corner reprojection residuals in pixels."""
    # the cube moved from the instant's time to the frame's: R' = exp(ω dt) R, p' = p + v dt
    rotated = np.einsum("nij,nj->ni", T_cubes[prob.inst, :3, :3], prob.points_cube)
    pw = np.einsum("nij,nj->ni", prob.motion_R, rotated) + T_cubes[prob.inst, :3, 3] + prob.motion_t
    return (_project(T_cams, prob.cam, pw) - prob.observed) * prob.focal[:, None]


def _world_residuals_px(prob: _Problem, T_cams: np.ndarray) -> np.ndarray:
    """(M, 2) world-marker corner reprojection residuals in pixels."""
    if not len(prob.world_cam):
        return np.zeros((0, 2))
    return (_project(T_cams, prob.world_cam, prob.world_points) - prob.world_observed) * prob.world_focal[:, None]


def _skew(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) cross-product matrices of (N, 3) vectors."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def _camera_part(T_cams: np.ndarray, cam: np.ndarray, points_world: np.ndarray, observed: np.ndarray,
                 focal: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Residuals (N, 2) in units of ``sigma`` of world points seen by cameras ``cam``, their
    derivative by the world point (N, 2, 3) and by the camera's [δp, δθ] (N, 2, 6)."""
    Rc = T_cams[cam, :3, :3]
    y = points_world - T_cams[cam, :3, 3]
    pc = np.einsum("nji,nj->ni", Rc, y)
    z = pc[:, 2]
    ok = z > 1e-6
    zs = np.where(ok, z, 1.0)
    scale = (focal / sigma)[:, None]
    r = np.where(ok[:, None], (pc[:, :2] / zs[:, None] - observed) * scale, 1e3)
    dpi = np.zeros((len(z), 2, 3))
    dpi[:, 0, 0] = dpi[:, 1, 1] = 1.0 / zs
    dpi[:, 0, 2] = -pc[:, 0] / zs**2
    dpi[:, 1, 2] = -pc[:, 1] / zs**2
    dpi *= (scale * ok[:, None])[:, :, None]
    A = dpi @ np.transpose(Rc, (0, 2, 1))  # d r / d X_world
    J_cam = np.concatenate([-A, A @ _skew(y)], axis=2)
    return r, A, J_cam, ok


def _solve(prob: _Problem, T0_cams: np.ndarray, T0_cubes: np.ndarray, params: BundleAdjustmentParams,
           gauge_prior: bool = False, solve_cameras: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares camera and cube poses (cameras held when not ``solve_cameras``); returns
    (T_cams (C,4,4), T_cubes (K,4,4)). Analytic sparse Jacobian, soft-L1 loss."""
    C, K = len(T0_cams), len(T0_cubes)
    nc = 6 * C if solve_cameras else 0
    nh = prob.robots if params.planar_motion else 0  # one cube height per robot
    h0 = np.array([np.median(T0_cubes[prob.robot == j, 2, 3]) for j in range(nh)])
    use_world = solve_cameras and len(prob.world_cam) > 0
    gauge = solve_cameras and gauge_prior
    ns = prob.robots if (use_world and params.free_cube_scale) else 0  # cube scale - 1 per robot
    sigma, sigma_w = params.corner_noise_px, params.world_corner_noise_px
    sigma_u = np.radians(params.upright_sigma_deg) if params.upright_sigma_deg > 0 else 0.0
    prior_scale = np.r_[np.full(3, params.gauge_prior_position_m), np.full(3, np.radians(params.gauge_prior_rotation_deg))]
    N, M = len(prob.cam), len(prob.world_cam) if use_world else 0
    n = nc + 6 * K + nh + ns
    scale_col = nc + 6 * K + nh  # first scale column

    # the Jacobian's pattern, in the order jac() fills in its values
    rows, cols = [], []
    m = 0
    corner_rows = np.repeat(2 * np.arange(N)[:, None] + np.arange(2)[None, :], 1, axis=1)  # (N, 2)
    cube_cols = nc + 6 * prob.inst[:, None] + np.arange(6)[None, :]  # (N, 6)
    if solve_cameras:
        cam_cols = 6 * prob.cam[:, None] + np.arange(6)[None, :]
        block = np.concatenate([cam_cols, cube_cols], axis=1)  # (N, 12)
    else:
        block = cube_cols
    if ns:
        block = np.concatenate([block, scale_col + prob.robot[prob.inst][:, None]], axis=1)
    rows.append(np.broadcast_to(corner_rows[:, :, None], (N, 2, block.shape[1])).ravel())
    cols.append(np.broadcast_to(block[:, None, :], (N, 2, block.shape[1])).ravel())
    m += 2 * N
    if use_world:
        wr = m + 2 * np.arange(M)[:, None] + np.arange(2)[None, :]
        wc = 6 * prob.world_cam[:, None] + np.arange(6)[None, :]
        rows.append(np.broadcast_to(wr[:, :, None], (M, 2, 6)).ravel())
        cols.append(np.broadcast_to(wc[:, None, :], (M, 2, 6)).ravel())
        m += 2 * M
    if nh:
        rows += [m + np.arange(K), m + np.arange(K)]
        cols += [nc + 6 * np.arange(K) + 2, nc + 6 * K + prob.robot]
        m += K
    if sigma_u:
        ur = m + 2 * np.arange(K)[:, None] + np.arange(2)[None, :]
        uc = nc + 6 * np.arange(K)[:, None] + 3 + np.arange(3)[None, :]
        rows.append(np.broadcast_to(ur[:, :, None], (K, 2, 3)).ravel())
        cols.append(np.broadcast_to(uc[:, None, :], (K, 2, 3)).ravel())
        m += 2 * K
    if gauge:
        rows.append(m + np.arange(nc))
        cols.append(np.arange(nc))
        m += nc
    rows_a, cols_a = np.concatenate(rows), np.concatenate(cols)

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T_cams = _apply(T0_cams, x[:nc].reshape(C, 6)) if solve_cameras else T0_cams
        return T_cams, _apply(T0_cubes, x[nc:nc + 6 * K].reshape(K, 6))

    def evaluate(x: np.ndarray, with_jac: bool):
        T_cams, T_cubes = unpack(x)
        points = prob.points_cube
        if ns:
            points = points * (1.0 + x[scale_col + prob.robot[prob.inst]])[:, None]
        a = np.einsum("nij,nj->ni", T_cubes[prob.inst, :3, :3], points)  # R_k s P
        pw = np.einsum("nij,nj->ni", prob.motion_R, a) + T_cubes[prob.inst, :3, 3] + prob.motion_t
        r, A, J_cam, _ok = _camera_part(T_cams, prob.cam, pw, prob.observed, prob.focal, sigma)
        res, vals = [r.ravel()], []
        if with_jac:
            J_cube = np.concatenate([A, -(A @ prob.motion_R) @ _skew(a)], axis=2)
            parts = [J_cam, J_cube] if solve_cameras else [J_cube]
            if ns:
                unscaled = a / (1.0 + x[scale_col + prob.robot[prob.inst]])[:, None]
                parts.append(A @ np.einsum("nij,nj->ni", prob.motion_R, unscaled)[:, :, None])
            vals.append(np.concatenate(parts, axis=2).ravel())
        if use_world:
            rw, _A, Jw, _ = _camera_part(T_cams, prob.world_cam, prob.world_points, prob.world_observed,
                                         prob.world_focal, sigma_w)
            res.append(rw.ravel())
            if with_jac:
                vals.append(Jw.ravel())
        if nh:
            h = h0 + x[nc + 6 * K:nc + 6 * K + nh]
            res.append((T_cubes[:, 2, 3] - h[prob.robot]) / params.height_sigma_m)
            if with_jac:
                vals += [np.full(K, 1.0 / params.height_sigma_m), np.full(K, -1.0 / params.height_sigma_m)]
        if sigma_u:  # the cube's z axis (third column) near world up
            up = T_cubes[:, :3, 2]
            res.append(up[:, :2].ravel() / sigma_u)
            if with_jac:
                vals.append((-_skew(up)[:, :2, :] / sigma_u).ravel())
        if gauge:
            res.append(x[:nc] / np.tile(prior_scale, C))
            if with_jac:
                vals.append(1.0 / np.tile(prior_scale, C))
        return np.concatenate(res), (np.concatenate(vals) if with_jac else None)

    def fun(x: np.ndarray) -> np.ndarray:
        return evaluate(x, False)[0]

    def jac(x: np.ndarray):
        vals = evaluate(x, True)[1]
        return coo_matrix((vals, (rows_a, cols_a)), shape=(m, n)).tocsr()

    result = least_squares(fun, np.zeros(n), jac=jac, method="trf", loss="soft_l1",
                           f_scale=params.f_scale_px / sigma, x_scale=np.full(n, 1e-3),
                           max_nfev=params.max_nfev, tr_solver="lsmr")
    return unpack(result.x)


# ---------------------------------------------------------------------------------------------
# Instants, alignment, the whole refinement


def _pose_distance(Ta: np.ndarray, Tb: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3])), rotation_angle(Ta[:3, :3], Tb[:3, :3], "deg")


def _make_instants(frames: Sequence[CubeFrame], layouts: dict[str, CubeLayout],
                   intrinsics: dict[str, CameraIntrinsics], T_world_cam: dict[str, np.ndarray],
                   params: BundleAdjustmentParams, progress: Progress | None) -> list[Instant]:
    """Instants with at least ``min_cameras`` cameras' corners and a joint initial cube pose."""
    by_robot: dict[str, list[CubeFrame]] = {}
    for f in frames:
        by_robot.setdefault(f.robot, []).append(f)
    groups = [g for robot_frames in by_robot.values()
              for g in group_instants(robot_frames, params.max_span_s, params.min_cameras)]
    groups.sort(key=lambda g: g[0].time_s)
    if len(groups) > params.max_instants:
        keep = np.unique(np.linspace(0, len(groups) - 1, params.max_instants).round().astype(int))
        groups = [groups[i] for i in keep]
    instants = []
    for done, group in enumerate(groups, start=1):
        if progress is not None:
            progress("bundle adjustment: instants", done, len(groups))
        layout = layouts[group[0].robot]
        pairs = [(f, _frame_corners(f, layout, intrinsics[f.camera], T_world_cam[f.camera], params)) for f in group]
        pairs = [(f, s) for f, s in pairs if s is not None]
        if len({f.camera for f, _ in pairs}) < params.min_cameras:
            continue
        t_ref = float(np.mean([f.time_s for f, _ in pairs]))
        # start from the single-camera estimate of the camera seeing the most corners
        start = max(pairs, key=lambda p: len(p[1].points_cube_m))
        est_T = _estimate_T(start[0], layout, intrinsics, T_world_cam)
        if est_T is None:
            continue
        instants.append(Instant(group[0].robot, t_ref, tuple(f for f, _ in pairs), tuple(s for _, s in pairs), est_T))
    return instants


def _estimate_T(frame: CubeFrame, layout: CubeLayout, intrinsics: dict[str, CameraIntrinsics],
                T_world_cam: dict[str, np.ndarray]) -> np.ndarray | None:
    from cubetrack.estimate.pose import estimate_cube

    est = estimate_cube(frame.detections, layout, intrinsics[frame.camera], T_world_cam[frame.camera],
                        camera=frame.camera, robot=frame.robot, seq=frame.seq, capture_time_s=frame.time_s,
                        arrival_time_s=frame.time_s)
    return None if est is None else est.T_world_cube


def _rematch(instants: Sequence[Instant], T_cubes: np.ndarray, vel: np.ndarray, angvel: np.ndarray,
             layouts: dict[str, CubeLayout], intrinsics: dict[str, CameraIntrinsics],
             T_world_cam: dict[str, np.ndarray], params: BundleAdjustmentParams) -> tuple[list[Instant], list[int]]:
    """Faces matched again to the detections where the solved poses project them; returns the
    instants still seen by ``min_cameras`` cameras and their indices."""
    out, keep = [], []
    for k, instant in enumerate(instants):
        sets = []
        for f in instant.frames:
            T = moved_pose(T_cubes[k], vel[k], angvel[k], f.time_s - instant.time_s)
            matches = match_faces(f.detections, layouts[instant.robot], intrinsics[f.camera], T_world_cam[f.camera], T,
                                  gate_px=params.association_gate_px)
            s = corner_set(matches, intrinsics[f.camera], T_world_cam[f.camera], f.camera, f.time_s)
            if s is not None:
                sets.append((f, s))
        if len({f.camera for f, _ in sets}) >= params.min_cameras:
            keep.append(k)
            out.append(Instant(instant.robot, instant.time_s, tuple(f for f, _ in sets), tuple(s for _, s in sets),
                               T_cubes[k]))
    return out, keep


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


def adjust_extrinsics(frames: Mapping[str, Iterable[Frame]], extrinsics: Mapping[str, CameraExtrinsics],
                     intrinsics: Mapping[str, CameraIntrinsics], layouts: Mapping[str, CubeLayout],
                     world: WorldConfig, *, clock_samples: Mapping[str, Sequence[ClockSample]] | None = None,
                     world_frames: Mapping[str, Iterable[Frame]] | None = None,
                     params: BundleAdjustmentParams = BundleAdjustmentParams(),
                     calibration_params: CalibrationParams | None = None,
                     detector_params: DetectorParams | None = None, progress: Progress | None = None,
                     frame_count: int = 0, world_frame_counts: Mapping[str, int] | None = None,
                     ) -> BundleAdjustmentReport:
    """Refine ``extrinsics`` (the world-marker calibration) by bundle adjustment over the cube
    sightings in the tracking ``frames`` (camera -> its frames, stamped with the camera's
    ``clock_samples``) and the world marker in the calibration ``world_frames`` (camera -> its
    frames; None: cube sightings only), see the module docstring. ``layouts``: robot -> cube
    layout; ``intrinsics`` of every camera of ``frames`` that has extrinsics; ``calibration_params``
    and ``detector_params`` are the ``[calibration]`` and ``[detector]`` settings (None: defaults).

    Returns the refined extrinsics of every prior camera, per-camera residuals and moved
    cameras; warnings are also logged. CalibrationError when the frames share fewer than two
    cameras with the extrinsics or no instant has two cameras seeing the cube.
    """
    warnings: list[str] = []

    def warn(message: str) -> None:
        warnings.append(message)
        log.warning("%s", message)

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
                           frame_count)
    instants = _make_instants(observed, layouts, intrinsics, T_prior, params, progress)
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
    cam_index = {c: i for i, c in enumerate(used)}
    T0_cams = np.array([T_prior[c] for c in used])
    world_points = marker_corners_m(world.marker_size_m)

    def vel_of(inst: Sequence[Instant], T_cubes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v, w = np.zeros((len(inst), 3)), np.zeros((len(inst), 3))
        for robot in {i.robot for i in inst}:
            idx = np.array([k for k, i in enumerate(inst) if i.robot == robot])
            v[idx], w[idx] = velocities(np.array([inst[k].time_s for k in idx]), T_cubes[idx], params.velocity_window_s)
        return v, w

    # 1. cube poses with the prior cameras (twice: the second with velocities from the first);
    #    then the relative solve: cube corners only, the gauge held by weak priors
    T_cubes = np.array([i.T_world_cube for i in instants])
    vel, angvel = np.zeros((len(instants), 3)), np.zeros((len(instants), 3))
    for _ in range(2):
        prob = _build_problem(instants, cam_index, vel, angvel, {}, world_points)
        _, T_cubes = _solve(prob, T0_cams, T_cubes, params, solve_cameras=False)
        vel, angvel = vel_of(instants, T_cubes)
    prob = _build_problem(instants, cam_index, vel, angvel, {}, world_points)
    T_cams, T_cubes = _solve(prob, T0_cams, T_cubes, params, gauge_prior=True)
    G, consistent, moved = _align({c: T_cams[i] for c, i in cam_index.items()}, T_prior, params)
    if moved and len(consistent) < 2:
        # two cameras disagree (or none agree): the data cannot say which one moved
        names = ", ".join(used)
        d = max(_pose_distance(G @ T_cams[cam_index[c]], T_prior[c])[0] for c in used)
        warn(f"cameras {names} disagree with their calibration by up to {100 * d:.1f} cm: one of them moved "
             "after calibration, but it takes three cameras to tell which; recalibrate")
        moved = []
    T_cams = np.einsum("ij,cjk->cik", G, T_cams)
    T_cubes = np.einsum("ij,kjl->kil", G, T_cubes)

    # 2. absolute solves: re-matched faces, re-estimated velocities, world-marker corners
    world_terms: dict[str, tuple[np.ndarray, float]] = {}
    observations = {}
    if world_frames is not None:
        observations = world_marker_observations(world_frames, world, intrinsics, calibration_params, detector_params,
                                                 progress, params.world_samples, world_frame_counts)
        for c, obs in observations.items():
            if c in cam_index and c not in moved:
                K = intrinsics[c].K
                world_terms[c] = (normalize_px(obs.corners_px, K, intrinsics[c].dist), float((K[0, 0] + K[1, 1]) / 2.0))
    if not world_terms and world_frames is not None:
        warn("no usable world-marker sightings in the calibration recording; the refined poses keep the prior "
             "calibration's frame (aligned to the cameras that agree)")
    # without world-marker corners the gauge stays held by weak priors at the aligned poses
    for _round in range(params.rounds):
        vel, angvel = vel_of(instants, T_cubes)
        current = {c: T_cams[i] for c, i in cam_index.items()}
        rematched, keep = _rematch(instants, T_cubes, vel, angvel, layouts, intrinsics, current, params)
        instants, T_cubes, vel, angvel = rematched, T_cubes[keep], vel[keep], angvel[keep]
        if not instants:
            raise CalibrationError("no multi-camera cube sightings fit the refined poses")
        prob = _build_problem(instants, cam_index, vel, angvel, world_terms, world_points)
        T_cams, T_cubes = _solve(prob, T_cams, T_cubes, params, gauge_prior=not world_terms)

    # report
    prob = _build_problem(instants, cam_index, *vel_of(instants, T_cubes), world_terms, world_points)
    r = _corner_residuals_px(prob, T_cams, T_cubes)
    rw = _world_residuals_px(prob, T_cams)
    refined = dict(extrinsics)
    report_cams = {}
    for c, i in cam_index.items():
        mine = prob.cam == i
        rms = float(np.sqrt(np.nanmean(np.sum(r[mine] ** 2, axis=1)))) if mine.any() else float("nan")
        wm = prob.world_cam == i
        wrms = float(np.sqrt(np.nanmean(np.sum(rw[wm] ** 2, axis=1)))) if wm.any() else float("nan")
        shift_m, shift_deg = _pose_distance(T_cams[i], T_prior[c])
        n_inst = int(len(np.unique(prob.inst[mine])))
        report_cams[c] = CameraResidual(c, rms, int(mine.sum()), n_inst, wrms, shift_m, shift_deg, c in moved)
        refined[c] = CameraExtrinsics(T_cams[i], n_inst, 0.0, 0.0, METHOD)
        if c in moved:
            warn(f"camera {c} has moved after calibration: the other cameras' cube sightings put it "
                 f"{100 * shift_m:.1f} cm and {shift_deg:.2f} deg from its calibrated pose; its world-marker "
                 "calibration was ignored and its pose re-estimated from the cube")
    for c in cameras:
        if c not in report_cams:
            report_cams[c] = CameraResidual(c, float("nan"), 0, 0, float("nan"), 0.0, 0.0, False)
    return BundleAdjustmentReport(refined, dict(extrinsics), report_cams, tuple(moved), len(instants),
                                  tuple(warnings))
