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
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from cubetrack.calib.bundle import (
    BodyCalibrationParams,
    BundleAdjustmentParams,
    CubeFrame,
    FrameCorners,
    Refinement,
    _frame_corners,
    layout_with,
    rms_px,
    start_refinement,
)
from cubetrack.calib.solver import Freedom, Observations, PosePrior, corner_residuals_px, interpolated_poses, solve
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample
from cubetrack.core.errors import CalibrationError
from cubetrack.core.geometry import invert_T, make_T, rotation_angle
from cubetrack.core.layout import CubeLayout
from cubetrack.core.progress import Progress
from cubetrack.core.records import Frame
from cubetrack.detect.detector import DetectorParams
from cubetrack.estimate.reprojection import moved_pose

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
    instants whose frames it follows, and the ``frames`` it explains), the warnings issued."""

    robot: str
    layout: CubeLayout
    nominal: CubeLayout
    markers: tuple[MarkerResult, ...]
    instants: int
    extrinsics: dict[str, CameraExtrinsics]
    intrinsics: dict[str, CameraIntrinsics]
    warnings: tuple[str, ...] = field(default_factory=tuple)
    frames: int = 0


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
    trajectory = Trajectory.start(ref, body) if body.knot_s > 0 else None
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
    if trajectory is None:
        ref.update_velocities()
        obs, frame_count = ref.observations(), 0
        sample = obs.inst
    else:
        obs, frame_count = trajectory.observations(), len(trajectory.frames)
        sample = np.repeat(np.arange(frame_count), [4 * len(s.markers) for s in trajectory.sets])
    return _report(ref, obs, sample, frame_count, robot, layout, extrinsics, intrinsics, warn, warnings)


@dataclass(eq=False)
class Trajectory:
    """The body's continuous-time trajectory through a refinement's frames (``body.knot_s`` > 0):
    body poses at knots ``times_s`` (K,) spaced ``body.knot_s`` apart within pieces of the
    recording where the frames follow each other within ``body.max_span_s`` (``first`` (K,):
    whether a knot starts a piece), each corner seen at the pose interpolated to the time its
    row was exposed, the knots tied by the solver's smoothness prior (``body.accel_sigma_m_s2``,
    ``body.angular_accel_sigma_rad_s2``). The frames are every frame of the refinement's
    instants, each with its corners matched (``sets``) at the trajectory's pose. From
    :meth:`start` on, ``ref.model``'s body poses are the knots' (its instants no longer apply)."""

    ref: Refinement
    body: BodyCalibrationParams
    times_s: np.ndarray
    first: np.ndarray
    frames: list[CubeFrame]
    sets: list[FrameCorners]

    @classmethod
    def start(cls, ref: Refinement, body: BodyCalibrationParams) -> Trajectory:
        """Knots over the instants' frames, started from the instants' poses moved with their
        velocities, and the frames matched at them."""
        if len(ref.robots) != 1:
            raise CalibrationError(f"a body trajectory follows one robot, not {len(ref.robots)}")
        frames = sorted({id(f): f for i in ref.instants for f in i.frames}.values(), key=lambda f: (f.time_s, f.camera))
        t = np.array([f.time_s for f in frames])
        margin = max(ref.readout_s.values(), default=0.0) / 2 + body.knot_s
        breaks = np.flatnonzero(np.diff(t) > body.max_span_s) + 1
        times, first = [], []
        for piece in np.split(t, breaks):
            n = int(np.ceil((piece[-1] - piece[0] + 2 * margin) / body.knot_s)) + 1
            times.append(piece[0] - margin + body.knot_s * np.arange(n))
            first.append(np.arange(n) == 0)
        times_s = np.concatenate(times)
        inst_t = np.array([i.time_s for i in ref.instants])
        after = np.searchsorted(inst_t, times_s).clip(0, len(inst_t) - 1)  # the instants are in time order
        before = (after - 1).clip(0)
        near = np.where(np.abs(times_s - inst_t[before]) < np.abs(times_s - inst_t[after]), before, after)
        knots = np.array([moved_pose(ref.model.T_bodies[k], ref.vel[k], ref.angvel[k], tk - inst_t[k])
                          for k, tk in zip(near, times_s, strict=True)])
        ref.model = ref.model.replace(T_bodies=knots)
        trajectory = cls(ref, body, times_s, np.concatenate(first), frames, [])
        trajectory.rematch()
        return trajectory

    def _knot(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The knot before each time (its piece's last-but-one at most) and the fraction to the next."""
        k = np.clip(np.searchsorted(self.times_s, t, side="right") - 1, 0, len(self.times_s) - 2)
        last = np.r_[self.first[1:], True]  # a piece's last knot: the next knot starts a piece
        k = np.where(last[k], k - 1, k)
        return k, (t - self.times_s[k]) / (self.times_s[k + 1] - self.times_s[k])

    def pose_at(self, time_s: float) -> np.ndarray:
        """The body's pose (4, 4) at ``time_s`` on the trajectory."""
        k, alpha = self._knot(np.array([time_s]))
        R, p = interpolated_poses(self.ref.model.T_bodies[k], self.ref.model.T_bodies[k + 1], alpha)
        return make_T(R[0], p[0])

    def rematch(self) -> None:
        """Every frame's detections matched to the body's markers at the trajectory's pose (frames
        where nothing matches are left out)."""
        ref = self.ref
        intrinsics, T_world_cam, layout = ref.intrinsics(), ref.T_world_cam(), ref.layout(ref.robots[0])
        found = [(f, _frame_corners(f, layout, intrinsics[f.camera], T_world_cam[f.camera], ref.params,
                                    self.pose_at(f.time_s))) for f in self.frames]
        pairs = [(f, s) for f, s in found if s is not None]
        if not pairs:
            raise CalibrationError("no cube sightings fit the body's trajectory")
        self.frames, self.sets = [f for f, _ in pairs], [s for _, s in pairs]

    def observations(self) -> Observations:
        """The solver's observations: every matched corner at the time its row was exposed (as
        :meth:`Refinement.observations` times them) on the trajectory."""
        ref = self.ref
        cam_index = {c: i for i, c in enumerate(ref.cameras)}
        cam = np.concatenate([np.full(4 * len(s.markers), cam_index[s.camera]) for s in self.sets])
        marker = np.concatenate([np.repeat(s.markers, 4) for s in self.sets])
        pixels = np.vstack([s.corners_px.reshape(-1, 2) for s in self.sets])
        height = np.array([ref.given[s.camera].height for s in self.sets for _ in range(4 * len(s.markers))], float)
        row_s = np.array([ref.readout_s.get(s.camera, 0.0)
                          for s in self.sets for _ in range(4 * len(s.markers))]) / height
        times = np.concatenate([np.full(4 * len(s.markers), s.time_s) for s in self.sets])
        k, alpha = self._knot(times + (pixels[:, 1] - (height - 1) / 2.0) * row_s)
        n, K = len(cam), len(self.times_s)
        inner = np.flatnonzero(~self.first[1:-1] & ~self.first[2:]) + 1  # knots with both neighbours in their piece
        return Observations(cam, k, marker, np.tile(np.arange(4), n // 4), pixels, np.tile(np.eye(3), (n, 1, 1)),
                            np.zeros((n, 3)), np.zeros(K, int), 1, np.zeros(0, int), np.zeros((0, 3)),
                            np.zeros((0, 2)), knot_alpha=alpha,
                            knot_triples=np.column_stack([inner - 1, inner, inner + 1]),
                            knot_spacing_s=self.body.knot_s)

    def solve(self, free: Freedom) -> None:
        """Solve the knots, markers and cameras (``free``; no motion noise: nothing is extrapolated)."""
        free = dataclasses.replace(free, motion_noise_px_per_s=0.0, accel_sigma_m_s2=self.body.accel_sigma_m_s2,
                                   angular_accel_sigma_rad_s2=self.body.angular_accel_sigma_rad_s2)
        self.ref.model = solve(self.observations(), self.ref.model, free)


def _fix_gauge(ref: Refinement, nominal: CubeLayout) -> None:
    """Move the body frame to the nominal layout's best fit (markers and body poses together, so
    every projection stays as it is)."""
    calibrated = ref.layout(ref.robots[0])
    G = best_fit_transform(calibrated.corners_m.reshape(-1, 3), nominal.corners_m.reshape(-1, 3))
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
