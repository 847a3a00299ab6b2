"""Where each marker really sits on a body, calibrated from a recording of it driving about
(``cubetrack calibrate-body``).

A hand-built cube is not its layout file: each printed marker is shifted by a millimetre or two,
turned by a degree, printed slightly small, and the faces are not quite square. The tracker
takes the layout as exact, so every such error becomes a pose error that changes with the face
in view. :func:`calibrate_body` estimates each marker's pose on the body and its size from the
body's sightings in a tracking recording — a bundle adjustment (:mod:`cubetrack.calib.solver`)
over the frames of multi-camera instants as in the extrinsics refinement
(:mod:`cubetrack.calib.bundle`) but of frames closer in time (``[body_calibration]``,
:class:`~cubetrack.calib.bundle.BodyCalibrationParams`: ``max_span_s``), the corners
measured by the template fit (:mod:`cubetrack.calib.marker_fit`), on a continuous-time trajectory
of the body (``knot_s`` > 0, the default; :class:`Trajectory`: each corner at the pose
interpolated to its row's time, no velocity assumed) or (``knot_s`` = 0) one pose per
instant, moved to each frame's time with a fitted velocity, each corner's noise growing with its
frame's time from its instant (``motion_noise_px_per_s``), with the markers free,
held near the nominal layout by priors (``position_sigma_m``,
``rotation_sigma_deg``, ``size_sigma``), the cameras refined too but held near the given
extrinsics (``camera_sigma_m``, ``camera_sigma_deg``), and (``[bundle_adjustment]
refine_intrinsics``) the
intrinsics near camera_info.

Gauge: the body frame of the result is the nominal layout's best fit — the rigid transform that
brings the calibrated marker corners closest (least squares over all corners) to the nominal
ones is applied to the result, so the body frame moves with no marker in particular and the
tracked pose of a perfectly built body is unchanged. Markers never seen keep their nominal pose
(in that frame) and are named in a warning, as are markers seen in fewer than :data:`FEW_VIEWS` frames.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from cubetrack.calib.bundle import (
    BodyCalibrationParams,
    BundleAdjustmentParams,
    Refinement,
    Trajectory,
    TrajectorySpec,
    layout_with,
    rms_px,
    start_refinement,
)
from cubetrack.calib.solver import Observations, PosePrior, corner_residuals_px
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample
from cubetrack.core.errors import CalibrationError
from cubetrack.core.geometry import invert_T, make_T, rotation_angle
from cubetrack.core.layout import CubeLayout
from cubetrack.core.progress import Progress
from cubetrack.core.records import Frame
from cubetrack.detect.detector import DetectorParams

log = logging.getLogger(__name__)

METHOD = "body-refined"  # CameraExtrinsics.method of the cameras a body calibration refined
# a marker seen in fewer frames (instants) than this is named in a warning: its placement rests on
# those few views (the realistic preset with cameras 0.8 m high: the top marker seen in 3, 4, 8 and
# 19 frames came out 0.21, 0.18, 0.11 and 0.03 deg off; docs/calibration.md)
FEW_VIEWS = 10


@dataclass(frozen=True, slots=True)
class MarkerResult:
    """One calibrated marker: ``corners`` observed (in ``instants`` instants, or frames on a
    continuous-time trajectory), their RMS
    reprojection error (px), and how far the result is from the nominal layout (both in the
    result's body frame): ``shift_m`` (centre), ``turn_deg`` (orientation), ``size_m`` against
    ``nominal_size_m``."""

    face: str
    marker_id: int
    corners: int
    instants: int
    rms_px: float
    shift_m: float
    turn_deg: float
    size_m: float
    nominal_size_m: float


@dataclass(frozen=True, slots=True, eq=False)
class BodyCalibrationReport:
    """What :func:`calibrate_body` found: the calibrated ``layout`` of ``robot`` (body frame = the
    ``nominal`` layout's best fit), per-marker results, the cameras as refined alongside
    (``extrinsics``, ``intrinsics``), the instants used (on a continuous-time trajectory: the
    instants whose frames it follows, and the ``frames`` it explains), the warnings issued, and
    (``[body_calibration] heading_from_travel``) the direction of travel the body frame was turned
    to (``travel.usable``) or not."""

    robot: str
    layout: CubeLayout
    nominal: CubeLayout
    markers: tuple[MarkerResult, ...]
    instants: int
    extrinsics: dict[str, CameraExtrinsics]
    intrinsics: dict[str, CameraIntrinsics]
    warnings: tuple[str, ...] = field(default_factory=tuple)
    frames: int = 0
    travel: TravelHeading | None = None


def best_fit_transform(points_from: np.ndarray, points_to: np.ndarray) -> np.ndarray:
    """The rigid transform T (4x4) minimising sum |T p - q|^2 over (n, 3) point pairs (Kabsch)."""
    a, b = np.asarray(points_from, float), np.asarray(points_to, float)
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _s, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make_T(R, cb - R @ ca)


def moved_layout(layout: CubeLayout, T_new_old: np.ndarray) -> CubeLayout:
    """``layout`` expressed in another body frame: every marker pose becomes ``T_new_old @ T``."""
    return layout_with(layout, np.array([T_new_old @ m.T_cube_marker for m in layout.markers]), layout.sizes_m)


def _check_same_markers(a: CubeLayout, b: CubeLayout, what: str) -> None:
    if [(m.face, m.marker_id) for m in a.markers] != [(m.face, m.marker_id) for m in b.markers]:
        raise CalibrationError(f"{what} has other markers (faces and ids) than the layout: "
                               f"{[(m.face, m.marker_id) for m in b.markers]} vs "
                               f"{[(m.face, m.marker_id) for m in a.markers]}")


def placement_errors(layout: CubeLayout, truth: CubeLayout, aligned: bool = True
                     ) -> dict[str, tuple[float, float, float]]:
    """Per face: (position error m, rotation error deg, size error m) of ``layout``'s markers
    against ``truth``'s (same faces and ids). ``aligned``: first express ``layout`` in the body
    frame that fits ``truth`` best (the body frame is a choice, the markers' placement on the
    body is not); else compare as written."""
    _check_same_markers(layout, truth, "the true layout")
    if aligned:
        layout = moved_layout(layout, best_fit_transform(layout.corners_m.reshape(-1, 3),
                                                         truth.corners_m.reshape(-1, 3)))
    return {m.face: (float(np.linalg.norm(m.T_cube_marker[:3, 3] - t.T_cube_marker[:3, 3])),
                     rotation_angle(m.T_cube_marker[:3, :3], t.T_cube_marker[:3, :3], "deg"), m.size_m - t.size_m)
            for m, t in zip(layout.markers, truth.markers, strict=True)}


# the direction of travel as the body frame's yaw ([body_calibration] heading_from_travel): samples
# of the drive at least this fast (m/s, horizontal, at the body's origin) ...
TRAVEL_MIN_SPEED_M_S = 0.05
# ... velocities by a local cubic over neighbours within this span (s; the body calibration's
# poses are its instants' (7 a second on the renders), each a few tenths of a degree off; over
# 0.5 s the contact point read 1.9 deg off on one scene, over 2 s 1.6 on another) ...
TRAVEL_SPAN_S = 1.0
# ... and the fit kept only when the sideways velocity left over is at most this share of the
# forward speed (RMS: a robot that drives forward, not a holonomic or carried one; from the
# realistic renders' body calibrations 0.02-0.09; a hand-carried body ~1)
TRAVEL_MAX_SIDEWAYS = 0.25
# ... and the heading it gives is within this many degrees of the markers' frame (a cube mounted
# deliberately turned on its robot keeps its own frame)
TRAVEL_MAX_YAW_DEG = 10.0
TRAVEL_MIN_SAMPLES = 20
# ... and the yaw rate is not a multiple of the forward speed (1 - their squared correlation at
# least this): on a circle at one speed a heading off and a body ahead of the turning point move it
# sideways alike, and the drive cannot tell them apart
TRAVEL_MIN_INDEPENDENCE = 0.1


@dataclass(frozen=True, slots=True)
class TravelHeading:
    """Where a forward-driving body travels, seen in its own frame (:func:`travel_heading`):
    ``yaw_deg`` the direction of travel's angle from the body's x axis about its z (positive:
    towards y), ``lever_m`` the body origin's distance ahead of the point that moves straight
    ahead (its turns' sideways velocity over their rate), ``sideways`` the RMS sideways velocity
    the fit leaves over the RMS forward speed, ``independence`` one minus the squared correlation
    of the forward speed and the yaw rate (0: the two cannot be told apart), over ``samples``
    samples; ``usable`` when the fit says the body drives forward and the drive separates the
    two (:data:`TRAVEL_MIN_SAMPLES`, :data:`TRAVEL_MAX_SIDEWAYS`, :data:`TRAVEL_MAX_YAW_DEG`,
    :data:`TRAVEL_MIN_INDEPENDENCE`)."""

    yaw_deg: float
    lever_m: float
    sideways: float
    independence: float
    samples: int

    @property
    def usable(self) -> bool:
        return (self.samples >= TRAVEL_MIN_SAMPLES and self.sideways <= TRAVEL_MAX_SIDEWAYS
                and abs(self.yaw_deg) <= TRAVEL_MAX_YAW_DEG and self.independence >= TRAVEL_MIN_INDEPENDENCE)


def travel_heading(times_s: np.ndarray, T_world_body: np.ndarray, first: np.ndarray | None = None) -> TravelHeading:
    """The direction a body travels against its x axis, from its poses ``T_world_body`` (N, 4, 4)
    at ``times_s`` (N,) in time order, in pieces that each start where ``first`` (N,) is True
    (None: one piece); the world's z = 0 is the floor the robot drives on (the world marker lies
    on it). The point followed is where the body's z axis through its origin meets the floor (the
    wheels' contact: the origin itself sways sideways as the robot tilts). At each pose that
    point's velocity (a local cubic through its neighbours in its piece within
    :data:`TRAVEL_SPAN_S`) is split along and across the body's x axis projected on the floor;
    over the samples faster than :data:`TRAVEL_MIN_SPEED_M_S` the sideways part is fitted (least
    squares) as ``tan(yaw) * forward + lever * yaw rate``: a robot that drives forward moves along
    its heading, except for its turns about a point behind or ahead of that one. Pure: a function
    of the poses."""
    t = np.asarray(times_s, float)
    T = np.asarray(T_world_body, float)
    piece = np.cumsum(np.zeros(len(t), bool) if first is None else np.asarray(first, bool))
    # the point that travels straight is where the wheels touch the floor, not the body's origin
    # (0.3 m up on the renders, it sways sideways as the robot tilts: 0.2-0.4 deg of travel): the
    # body's z axis through its origin meets the floor (z = 0) there
    ground = T[:, :2, 3] - (T[:, 2, 3] / T[:, 2, 2])[:, None] * T[:, :2, 2]
    rows = []
    for i in range(len(t)):
        near = np.flatnonzero((piece == piece[i]) & (np.abs(t - t[i]) <= TRAVEL_SPAN_S / 2))
        a, b = near[0], near[-1]
        if len(near) < 4 or a == i or b == i:
            continue
        # the velocity at the pose: a local cubic in time through the neighbours' positions (a
        # chord over the span turns with the path's curvature: 0.5 deg on a figure eight)
        v = np.polyfit(t[near] - t[i], ground[near], min(3, len(near) - 2))[-2]
        x = T[i, :2, 0] / np.linalg.norm(T[i, :2, 0])
        wz = float(Rotation.from_matrix(T[b, :3, :3] @ T[a, :3, :3].T).as_rotvec()[2]) / (t[b] - t[a])
        rows.append((v @ x, x[0] * v[1] - x[1] * v[0], wz))
    s = np.array(rows, float).reshape(-1, 3)
    s = s[np.hypot(s[:, 0], s[:, 1]) >= TRAVEL_MIN_SPEED_M_S]
    # sideways = tan(yaw) forward + lever * yaw rate: the contact point turns about a point behind or
    # ahead of it (a rate that never moves, e.g. a straight drive, is left out of the fit)
    cols = [0] + ([2] if len(s) and np.sqrt(np.mean(s[:, 2] ** 2)) > 1e-6 else [])
    A = s[:, cols]
    gram = A.T @ A
    if len(s) < 4 or np.linalg.cond(gram) > 1e12:
        return TravelHeading(0.0, 0.0, math.inf, 0.0, len(s))
    independence = float(1.0 / (gram[0, 0] * np.linalg.inv(gram)[0, 0]))  # 1 / the yaw's variance inflation
    coef, *_ = np.linalg.lstsq(A, s[:, 1], rcond=None)
    rest = s[:, 1] - A @ coef
    sideways = float(np.sqrt(np.mean(rest ** 2) / np.mean(s[:, 0] ** 2)))
    lever = float(coef[cols.index(2)]) if 2 in cols else 0.0
    return TravelHeading(math.degrees(math.atan(coef[0])), lever, sideways, independence, len(s))


def calibrate_body(frames: Mapping[str, Iterable[Frame]], extrinsics: Mapping[str, CameraExtrinsics],
                   intrinsics: Mapping[str, CameraIntrinsics], layout: CubeLayout, robot: str = "robot", *,
                   clock_samples: Mapping[str, Sequence[ClockSample]] | None = None,
                   params: BundleAdjustmentParams | None = None, body: BodyCalibrationParams | None = None,
                   detector_params: DetectorParams | None = None, progress: Progress | None = None,
                   frame_count: int = 0, readout_s: Mapping[str, float] | None = None,
                   edge_corners: bool = False) -> BodyCalibrationReport:
    """Calibrate the placement of every marker of ``layout`` (the nominal body of ``robot``) from
    the tracking ``frames`` (camera -> its frames, stamped with ``clock_samples``) of cameras
    with ``extrinsics`` and ``intrinsics``; see the module docstring. ``params``: the
    ``[bundle_adjustment]`` settings (None: the defaults; instants, noise, rounds, the intrinsics
    priors); ``body``: the ``[body_calibration]`` settings (None: the defaults; the instants' span,
    the body's priors and motion, the cameras' priors); ``readout_s``: each
    camera's rolling-shutter readout (seconds; a corner is moved to the time its row was
    exposed; None: the intrinsics' ``readout_s``, from camera_info); ``edge_corners``:
    re-measure the corners by the calibration's edge fit and template fit
    (:mod:`cubetrack.calib.marker_fit`).

    CalibrationError when fewer than two calibrated cameras saw the body at once.
    """
    params = params or BundleAdjustmentParams()
    body = body or BodyCalibrationParams()
    warnings: list[str] = []

    def warn(message: str) -> None:
        warnings.append(message)
        log.warning("%s", message)

    # a trajectory follows every instant's frames (max_instants spreads instants over a recording)
    instants = dataclasses.replace(params, max_span_s=body.max_span_s,
                                   max_instants=sys.maxsize if body.knot_s > 0 else params.max_instants)
    ref, _cameras = start_refinement(frames, extrinsics, intrinsics, {robot: layout}, clock_samples=clock_samples,
                                     params=instants,
                                     detector_params=detector_params, progress=progress,
                                     frame_count=frame_count, warn=warn, readout_s=readout_s,
                                     calibration_corners=edge_corners)
    T_given = ref.model.T_cams.copy()
    camera_prior = PosePrior(T_given, body.camera_sigma_m, np.radians(body.camera_sigma_deg))
    # no ground-robot priors on the body's poses (one height, upright): a robot on a real floor
    # tilts and bounces, and held level the body bent its markers instead (0.1-0.2 deg out of
    # plane; docs/calibration.md); the cameras' prior holds the world frame without them
    free = dataclasses.replace(ref.freedom(camera_prior=camera_prior, intrinsics=params.refine_intrinsics, body=body),
                               height_sigma_m=0.0, upright_sigma_rad=0.0)
    trajectory = Trajectory.start(ref, TrajectorySpec(body.knot_s, body.max_span_s, body.accel_sigma_m_s2,
                                                      body.angular_accel_sigma_rad_s2)) if body.knot_s > 0 else None
    for done in range(params.rounds + 1):
        if progress is not None:
            progress("body calibration: solves", done, params.rounds + 1)
        if trajectory is not None:
            if done:
                trajectory.rematch()
            trajectory.solve(free)
            continue
        if done:
            ref.update_velocities()
            ref.rematch()
        ref.solve(free)
    _fix_gauge(ref, layout)
    travel = _turn_to_travel(ref, trajectory, warn) if body.heading_from_travel else None
    if trajectory is None:
        ref.update_velocities()
        obs, frame_count = ref.observations(), 0
        sample = obs.inst
    else:
        obs, frame_count = trajectory.observations(), len(trajectory.frames)
        sample = trajectory.frame_of_corner()
    return dataclasses.replace(_report(ref, obs, sample, frame_count, robot, layout, extrinsics, intrinsics, warn,
                                       warnings), travel=travel)


def _fix_gauge(ref: Refinement, nominal: CubeLayout) -> None:
    """Move the body frame to the nominal layout's best fit."""
    calibrated = ref.layout(ref.robots[0])
    _move_body_frame(ref, best_fit_transform(calibrated.corners_m.reshape(-1, 3), nominal.corners_m.reshape(-1, 3)))


def _turn_to_travel(ref: Refinement, trajectory: Trajectory | None, warn) -> TravelHeading:
    """Turn the body frame about its z so that its x is the direction of travel over the drive
    (:func:`travel_heading` of the knots, or of the instants' poses), when the fit says the body
    drives forward; else warn and leave it."""
    # one piece: the trajectory's pieces are its instants' frames (a few knots, 0.15 s, each; the
    # velocity within one is the smoothness prior's), the drive between them is continuous
    times = trajectory.times_s if trajectory is not None else np.array([i.time_s for i in ref.instants])
    order = np.argsort(times, kind="stable")
    fit = travel_heading(times[order], ref.model.T_bodies[order])
    if not fit.usable:
        warn(f"heading_from_travel: the drive does not say where the body heads (yaw {fit.yaw_deg:.2f} deg, "
             f"sideways velocity {fit.sideways:.3f} of the forward speed, turns {fit.independence:.2f} independent "
             f"of it, "
             f"{fit.samples} samples; asks at most {TRAVEL_MAX_YAW_DEG:g} deg and {TRAVEL_MAX_SIDEWAYS:g}, at least "
             f"{TRAVEL_MIN_INDEPENDENCE:g} and {TRAVEL_MIN_SAMPLES}): the markers' frame is kept")
        return fit
    log.info("heading_from_travel: body frame turned %.3f deg about its z to the direction of travel "
             "(sideways %.3f, lever %.3f m, %d samples)", fit.yaw_deg, fit.sideways, fit.lever_m, fit.samples)
    _move_body_frame(ref, make_T(Rotation.from_euler("z", -fit.yaw_deg, degrees=True).as_matrix(), np.zeros(3)))
    return fit


def _move_body_frame(ref: Refinement, G: np.ndarray) -> None:
    """Express the body in the frame ``G`` (4x4, new from old) maps to (markers and body poses
    together, so every projection stays as it is)."""
    ref.model = ref.model.replace(T_body_markers=np.einsum("ij,gjk->gik", G, ref.model.T_body_markers),
                                  T_bodies=np.einsum("kij,jl->kil", ref.model.T_bodies, invert_T(G)))


def _report(ref: Refinement, obs: Observations, sample: np.ndarray, frames: int, robot: str, nominal: CubeLayout,
            extrinsics: Mapping[str, CameraExtrinsics], intrinsics: Mapping[str, CameraIntrinsics], warn,
            warnings: list[str]) -> BodyCalibrationReport:
    """The report; ``obs``: the final observations, ``sample`` (N,) each corner's instant (or,
    on a trajectory, frame: ``frames`` of them)."""
    r = corner_residuals_px(obs, ref.model)
    calibrated = ref.layout(robot)
    results = []
    for g, (m, n) in enumerate(zip(calibrated.markers, nominal.markers, strict=True)):
        mine = obs.marker == g
        views = len(np.unique(sample[mine]))
        if not mine.any():
            warn(f"marker {m.face} (id {m.marker_id}) was never seen by two cameras at once: kept as the layout has it")
        elif views < FEW_VIEWS:
            warn(f"marker {m.face} (id {m.marker_id}) was seen in only {views} {'frames' if frames else 'instants'} "
                 f"({int(mine.sum())} corners): its placement rests on those few views; drive where the cameras "
                 "see it more")
        results.append(MarkerResult(
            m.face, m.marker_id, int(mine.sum()), views, rms_px(r[mine]),
            float(np.linalg.norm(m.T_cube_marker[:3, 3] - n.T_cube_marker[:3, 3])),
            rotation_angle(m.T_cube_marker[:3, :3], n.T_cube_marker[:3, :3], "deg"), m.size_m, n.size_m))
    refined = dict(extrinsics)
    for c, T in ref.T_world_cam().items():
        n_inst = len(np.unique(sample[obs.cam == ref.cameras.index(c)]))
        refined[c] = CameraExtrinsics(T, n_inst, 0.0, 0.0, METHOD)
    return BodyCalibrationReport(robot, calibrated, nominal, tuple(results), len(ref.instants), refined,
                                 {**dict(intrinsics), **ref.intrinsics()}, tuple(warnings), frames)
