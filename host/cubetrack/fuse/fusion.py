"""Fusion: per-camera cube sightings, which arrive unsynchronised and late, -> poses per robot.

Two families, chosen by ``[fusion] method``:

- ``filter`` (the default, the best): a constant-velocity SE(3) filter (:mod:`cubetrack.fuse.corner_filter`)
  updated with the matched cube corners of each camera frame at its capture time, as soon as
  the frame has been processed (no waiting for other cameras). A sighting older than the
  filter's newest state (another camera's later frame arrived first) is folded in exactly: each
  robot keeps its last ``history_s`` of sightings with the state before each, goes back to the
  state before the late one and re-applies the newer ones after it, so the state always equals
  processing everything received in capture order. A track starts from a joint multi-camera fit
  (:mod:`cubetrack.fuse.multi_view_fit`); faces are matched to detections by where the predicted
  pose projects them, which resolves IPPE flips and same-id faces; a robot unseen for
  ``lost_after_s`` is reported as not seen, never extrapolated further.
- ``mean`` / ``weighted`` / ``gaussian``, the paper's, for comparison.

The paper's three methods (§II.D) combine the cube poses implied by every face that each camera
saw in its latest frame, over the cameras whose latest estimate is at most ``window_s`` older
than the newest one:

- ``mean``      eq. 2:  p = (1/n) Σ p_i
- ``weighted``  eqs. 3–4: p = Σ a_i p_i / Σ a_i, with a_i the marker's pixel area (shoelace)
- ``gaussian``  eqs. 5–6: σ_i² = 1/a_i², p = σ² Σ p_i/σ_i², σ² = (Σ 1/σ_i²)⁻¹ (i.e. weights a_i²)

Orientation uses the same weights in a chordal L2 rotation mean (sign-safe), not a
component-wise quaternion average. A fused pose is stamped with the newest contributing
capture time (what a live node publishing on every new estimate would do).
"""

from __future__ import annotations

import bisect
import enum
import logging
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import ParamsError
from cubetrack.core.geometry import invert_T, is_finite_pose, mean_rotation, quat_xyzw_from_R
from cubetrack.core.layout import CubeLayout
from cubetrack.core.params import check, check_at_least, check_non_negative, check_positive, param
from cubetrack.core.records import CameraEstimate, CubeSighting, TrackedPose
from cubetrack.estimate.match import FaceMatch, match_faces
from cubetrack.estimate.params import EstimatorParams
from cubetrack.estimate.pose import estimate_cube
from cubetrack.estimate.reprojection import CornerSet, corner_set, noise_scales, normalize_px
from cubetrack.fuse.camera_corrections import (
    TERM_SPAN_S,
    CameraCorrection,
    CameraCorrections,
    CorrectionPriors,
    combined,
    corrected_T_world_cam,
    observed,
    term_due,
    term_observed,
)
from cubetrack.fuse.corner_filter import FilterParams, PoseFilter
from cubetrack.fuse.filter_kernels import compile_filter_kernels, projected_spread_px
from cubetrack.fuse.multi_view_fit import JointSolution, solve_joint
from cubetrack.fuse.smoother import Gains, TrailStep, smoothed_poses

log = logging.getLogger(__name__)


@enum.unique
class FusionMethod(enum.Enum):
    MEAN = "mean"
    WEIGHTED = "weighted"
    GAUSSIAN = "gaussian"
    FILTER = "filter"


@dataclass(frozen=True, slots=True)
class FusionParams:
    """The ``[fusion]`` section of the tracker config."""

    method: FusionMethod = param(
        FusionMethod.FILTER, "filter (default: corner-level constant-velocity filter) | mean | weighted | gaussian "
        "(the paper's eqs. 2, 4, 6)")
    window_s: float = param(0.2, "paper methods: a camera's latest estimate joins the fusion only if it is at most "
                                 "this many seconds older than the newest")
    history_s: float = param(0.5, "filter: a sighting up to this many seconds older than the newest one is folded in "
                                  "exactly (the newer ones are re-applied after it); older ones are dropped, counted")
    lost_after_s: float = param(0.5, "filter: a robot with no accepted sighting for this many seconds is reported as "
                                     "not seen and its track restarts")
    output_rate_hz: float = param(0.0, "filter, live tracking: also emit each tracked robot's pose predicted to the "
                                       "current host time at this rate, for control loops (0: only at each sighting)")
    association_gate_px: float = param(12.0, "filter: a detection joins a face only if its corners lie within this "
                                             "many pixels (or half a marker side) of the predicted face")
    max_view_angle_deg: float = param(70.0, "filter: a face seen more obliquely than this (the angle "
                                      "between its normal and the camera's ray to it at the predicted pose) is left "
                                      "out: its corners are 2-3 times noisier than a face's seen head-on")
    init_window_s: float = param(0.3, "filter: a track starts from a joint fit of pose and velocity over the sightings "
                                      "of the last this many seconds (at least three, from two cameras)")
    max_rejections: int = param(3, "filter: this many rejected sightings in a row restart the track")
    reacquire_m: float = param(0.1, "filter: a sighting the tracked pose does not explain is re-examined "
                               "against its own camera's cube pose (other faces, a flip); if that pose is within this "
                               "many metres of the prediction and explains the corners, the track goes "
                               "on from it at once")

    def __post_init__(self) -> None:
        check_positive(self, "window_s", "lost_after_s", "association_gate_px", "init_window_s", "reacquire_m")
        check(0 < self.max_view_angle_deg <= 90,
              f"max_view_angle_deg must be in (0, 90], got {self.max_view_angle_deg}")
        check_non_negative(self, "history_s", unit="seconds")
        check_non_negative(self, "output_rate_hz", unit="hertz")
        check_at_least(self, 1, "max_rejections")


def paper_weights(method: FusionMethod, areas_px2: np.ndarray) -> np.ndarray:
    """Fusion weights of the paper's methods from marker pixel areas (px²)."""
    areas = np.asarray(areas_px2, dtype=float)
    if method is FusionMethod.MEAN:
        return np.ones_like(areas)
    if method is FusionMethod.WEIGHTED:
        return areas
    return areas**2  # 1 / σ_i² with σ_i² = 1 / a_i²


def fuse_poses(positions_m: np.ndarray, Rs: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean of (N, 3) positions and chordal mean of (N, 3, 3) rotations."""
    w = np.asarray(weights, dtype=float)
    position = (w[:, None] * np.asarray(positions_m)).sum(axis=0) / w.sum()
    return position, mean_rotation(Rs, w / w.sum())


class LatestEstimateFusion:
    """A :class:`~cubetrack.fuse.base.Fusion`. Keeps each camera's latest estimate per robot and fuses
    them on every new estimate.

    State: ``latest[(robot, camera)]`` — visible and small. Feed estimates in arrival order.
    """

    def __init__(self, params: FusionParams = FusionParams()):
        self.params = params
        self.latest: dict[tuple[str, str], CameraEstimate] = {}

    def needs_estimate(self, robot: str) -> bool:
        """The paper's methods fuse per-camera estimates: always make them."""
        return True

    def add(self, sighting: CubeSighting, now_s: float) -> list[TrackedPose]:
        """Take one camera's sighting (``now_s`` = host time it became available) and fuse."""
        if sighting.estimate is None:
            return []
        return [self.fuse(sighting.estimate, now_s)]

    def predicted_pose(self, robot: str, time_s: float) -> None:
        """The paper's methods have no motion model: they never predict."""
        return None

    def flush(self, now_s: float) -> list[TrackedPose]:
        """Nothing is held back: every estimate was fused when it came."""
        return []

    def release(self, now_s: float) -> list[TrackedPose]:
        """None: nothing waits for a later sighting."""
        return []

    def fuse(self, estimate: CameraEstimate, now_s: float) -> TrackedPose:
        """Fuse ``estimate`` with every other camera's latest estimate of the same robot."""
        self.latest[(estimate.robot, estimate.camera)] = estimate
        newest = estimate.capture_time_s
        current = [
            e for (robot, _), e in self.latest.items()
            if robot == estimate.robot and newest - self.params.window_s <= e.capture_time_s <= newest
        ]
        faces = [(e, f) for e in current for f in e.faces]
        positions = np.array([f.T_world_cube[:3, 3] for _, f in faces])
        Rs = np.array([f.T_world_cube[:3, :3] for _, f in faces])
        weights = paper_weights(self.params.method, np.array([f.area_px2 for _, f in faces]))
        position, R = fuse_poses(positions, Rs, weights)
        return TrackedPose(
            robot=estimate.robot,
            time_s=newest,
            position_m=position,
            quaternion_xyzw=quat_xyzw_from_R(R),
            cameras=tuple(sorted({e.camera for e in current})),
            markers=tuple(f"{e.camera}:{f.face}" for e, f in faces),
            latency_s=now_s - newest,
            arrival_latency_s=now_s - estimate.arrival_time_s,
        )


GATE_SIGMAS = 3.0  # the association gate grows by this many standard deviations of the predicted corners


def prediction_gate_px(covariance: np.ndarray, T_world_cube: np.ndarray, T_world_cam: np.ndarray,
                       intrinsics: CameraIntrinsics, reach_m: float) -> float:
    """How far (``GATE_SIGMAS`` standard deviations, pixels) the corners of a body predicted at
    ``T_world_cube`` with ``covariance`` (6x6 or more, ``[δp (m), δθ (rad)]`` first) may be from where they
    project: the largest position spread plus the largest rotation spread times ``reach_m``, the
    body's farthest corner from its origin (:func:`cubetrack.fuse.filter_kernels.spread_m`), over
    the body's depth in the camera, times the focal length (0 for a body not in front of the camera:
    :func:`cubetrack.fuse.filter_kernels.projected_spread_px`)."""
    focal_px = math.sqrt(intrinsics.K[0, 0] * intrinsics.K[1, 1])
    return projected_spread_px(covariance, T_world_cube, T_world_cam, GATE_SIGMAS * focal_px, reach_m)


def pose_record(sighting: CubeSighting, f: PoseFilter, now_s: float, cameras: tuple[str, ...],
                markers: tuple[str, ...]) -> TrackedPose:
    """The filter's state after ``sighting`` as a pose (with its velocities and pose covariance)."""
    return TrackedPose(robot=sighting.robot, time_s=f.time_s, position_m=f.position_m.copy(),
                       quaternion_xyzw=quat_xyzw_from_R(f.R_world_cube), cameras=cameras,
                       markers=markers, latency_s=max(0.0, now_s - f.time_s), velocity_m_s=f.velocity_m_s.copy(),
                       angular_velocity_rad_s=f.angular_velocity_rad_s.copy(), covariance=f.pose_covariance,
                       arrival_latency_s=max(0.0, now_s - sighting.arrival_time_s))


def sighting_corner_sets(matches: Sequence[FaceMatch], intrinsics: CameraIntrinsics, T_world_cam: np.ndarray,
                         camera: str, time_s: float, T_cam_world: np.ndarray | None = None) -> list[CornerSet]:
    """A camera frame's matched faces as corner sets: one, taken at its capture time ``time_s``;
    under a rolling shutter (the camera's ``readout_s``) one per face, taken when the rows of its
    corners were (their mean row's time), each corner at its own row's instant (``row_offsets_s``:
    a moving face is seen sheared, which one instant per face reads as a tilt); none when nothing
    matched. ``T_cam_world``: ``T_world_cam``'s inverse if the caller holds it."""
    if not matches:
        return []
    T_cam_world = invert_T(T_world_cam) if T_cam_world is None else T_cam_world
    if intrinsics.readout_s <= 0:
        sets = [corner_set(matches, intrinsics, T_world_cam, camera, time_s, T_cam_world)]
        return [s for s in sets if s is not None]  # (none is: it has matches)
    # the faces' sets share one undistortion and one camera pose (a set per face of corner_set's making)
    row_s, middle = intrinsics.readout_s / intrinsics.height, (intrinsics.height - 1) / 2.0
    corners_px = np.concatenate([m.detection.corners_px for m in matches])
    normalized = normalize_px(corners_px, intrinsics.K, intrinsics.dist)
    rows = corners_px[:, 1].reshape(-1, 4).astype(np.float64)  # float32 corners would round the offsets
    means = rows.sum(axis=1) / 4.0
    offsets_s = (rows - means[:, None]) * row_s
    focal_px = float((intrinsics.K[0, 0] + intrinsics.K[1, 1]) / 2.0)
    scales = noise_scales(matches, corners_px)
    return [CornerSet(camera, time_s + (float(means[i]) - middle) * row_s, T_cam_world, focal_px, m.points_body_m,
                      normalized[4 * i: 4 * i + 4], (m.face,), scales[4 * i: 4 * i + 4], offsets_s[i])
            for i, m in enumerate(matches)]


@dataclass(frozen=True, slots=True)
class RobotState:
    """What processing one robot's sightings in capture order has built. Never modified: a step
    makes a new one (the filter it holds is a snapshot that nothing updates in place)."""

    filter: PoseFilter | None = None
    last_accepted_s: float = float("-inf")
    rejections: int = 0
    corrections: CameraCorrections = field(default_factory=CameraCorrections)  # the cameras', kept over restarts


@dataclass(slots=True, eq=False)
class HistoryStep:
    """One sighting in a robot's history, the state just before it and what applying it did."""

    key: tuple[float, str, int]  # capture order: (capture time, camera, seq)
    sighting: CubeSighting
    before: RobotState
    outcome: str = ""
    poses: list[TrackedPose] = field(default_factory=list)  # what applying it gave, due
    pose: TrackedPose | None = None  # its pose, due or not, while the fusion keeps a trail
    # the corner sets its update took, kept for the calibration term's samples only (none: not applied, or the
    # term is off: a step holds no corner set it will not read)
    corners: list[CornerSet] = field(default_factory=list)
    # its corner sets by the faces its detections matched (FilterFusion._corners): a re-application that matches
    # them alike takes them from here instead of undistorting the same corners again
    sets: dict[tuple[tuple[int, int], ...], list[CornerSet]] = field(default_factory=dict)


class FilterFusion:
    """A :class:`~cubetrack.fuse.base.Fusion`: corner-level filtering of every robot (see the module
    doc). Visible state: ``state`` (robot -> :class:`RobotState` after its newest sighting),
    ``history`` (robot -> the last ``history_s`` of :class:`HistoryStep` in capture order),
    ``stats`` (counters of the outcomes of capture-order processing, plus ``late sighting``,
    ``replayed sighting`` and ``too late sighting``).

    With :meth:`keep_trail` it also keeps every sighting's final state and pose, for
    :func:`cubetrack.fuse.smoother.smoothed_poses` (offline; off by default). With the filter's
    ``smooth_lag_s`` each pose leaves once a sighting that much newer has been applied, smoothed
    over the sightings up to then (:mod:`cubetrack.fuse.smoother`; 0, the default: at once), or
    at the latest with :meth:`release` once its time is up on the host clock.

    A late sighting is put in its place in the history at once, and the steps from there on are
    re-applied when the robot's state is next needed for a pose (its next newest sighting, or
    :meth:`settled_state`): a burst of late sightings costs one re-application, not one each.
    Predictions for region detection (:meth:`predicted_pose`) do not wait for that."""

    START_WINDOW = 64  # a track start looks at most at this many sightings (the newest)

    def __init__(self, layouts: dict[str, CubeLayout], params: FusionParams = FusionParams(),
                 filter_params: FilterParams = FilterParams(), estimator_params: EstimatorParams | None = None):
        """``estimator_params``: how a camera's own cube pose is found where the filter needs one
        (re-acquiring a track), as the per-camera estimates are. A body whose layout says
        ``motion = "free"`` (hand-held) is tracked with :meth:`FilterParams.for_free_body`, the
        others with ``filter_params``."""
        self.layouts = layouts
        self.params = params
        self.filter_params = filter_params
        self._body_params = {r: filter_params.for_free_body() if layout.motion == "free" else filter_params
                             for r, layout in layouts.items()}
        self.estimator_params = estimator_params or EstimatorParams()
        fp = filter_params
        self._priors = CorrectionPriors(fp.correction_position_sigma_m, math.radians(fp.correction_rotation_sigma_deg),
                                        fp.correction_time_sigma_s, fp.correction_memory_s)
        self.state: dict[str, RobotState] = {r: RobotState() for r in layouts}
        self.history: dict[str, list[HistoryStep]] = {r: [] for r in layouts}
        self._keys: dict[str, list[tuple[float, str, int]]] = {r: [] for r in layouts}
        self._stale: dict[str, int] = {}  # robot -> first history index whose step must be re-applied
        self._sent: dict[str, tuple[float, str, int]] = {}  # robot -> key of the newest step whose poses left
        self._gains = {r: Gains() for r in layouts}  # robot -> the fixed lag's smoother gains, from pass to pass
        self.stats: Counter[str] = Counter()
        self._trails: dict[str, list[TrailStep]] | None = None  # robot -> steps no late sighting can reach
        self._cameras: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]] = {}  # see _camera_pose
        if filter_params.smooth_lag_s > params.history_s:
            raise ParamsError(f"[filter] smooth_lag_s ({filter_params.smooth_lag_s}) must not exceed [fusion] "
                              f"history_s ({params.history_s}): the steps it waits for are kept that long")
        self._reach_m = {r: float(np.sqrt(np.max(np.sum(layout.corners_m.reshape(-1, 3) ** 2, axis=1))))
                         for r, layout in layouts.items()}   # each body's farthest corner from its origin
        compile_filter_kernels()  # before the first sighting

    def keep_trail(self) -> None:
        """From now on keep each sighting's final filter state and pose (about 3 KB a sighting:
        for recordings) for :meth:`trail`."""
        if self._trails is None:
            self._trails = {r: [] for r in self.layouts}

    def trail(self, robot: str, now_s: float) -> list[TrailStep]:
        """The robot's sightings since :meth:`keep_trail`, in capture order, each as processing
        every sighting received in capture order applies it (pending late ones are folded in)."""
        if self._trails is None:
            raise ParamsError("the fusion keeps no trail: call keep_trail() before the sightings")
        self.settled_state(robot, now_s)
        return self._trails[robot] + self._trail_steps(robot, 0, len(self.history[robot]))

    def _trail_steps(self, robot: str, start: int, stop: int) -> list[TrailStep]:
        """The robot's history steps ``start:stop`` as trail steps (each with the filter after it)."""
        history = self.history[robot]
        after = [step.before.filter for step in history[start + 1: stop + 1]]
        if stop >= len(history):
            after.append(self.state[robot].filter)
        return [TrailStep(step.outcome, f, step.pose, step.sighting.arrival_time_s, step.key[0])
                for step, f in zip(history[start:stop], after, strict=True)]

    def camera_corrections(self) -> dict[str, CameraCorrection]:
        """Each camera's correction as the sightings so far estimate it, over every robot's
        (:mod:`cubetrack.fuse.camera_corrections`; late sightings still pending not folded in):
        what a watcher of moved cameras reads."""
        return combined([state.corrections for state in self.state.values()], self._priors)

    def needs_estimate(self, robot: str) -> bool:
        """A per-camera estimate is only needed to start a track: not while one runs."""
        return self.state[robot].filter is None

    def last_state(self, robot: str) -> tuple[str, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """The robot's filter state after its newest sighting (None while not tracked): ``(robot, time_s,
        T_world_cube, velocity_m_s, angular_velocity_rad_s, covariance (12x12 over [δp, δθ, v, ω]))``,
        what :meth:`seed` takes."""
        state = self.state.get(robot)
        f = None if state is None else state.filter
        return None if f is None else (robot, f.time_s, f.T_world_cube, f.velocity_m_s, f.angular_velocity_rad_s, f.P)

    def seed(self, robot: str, time_s: float, T_world_cube: np.ndarray, velocity_m_s: np.ndarray,
             angular_velocity_rad_s: np.ndarray, covariance: np.ndarray) -> bool:
        """Take over a robot's track from another fusion's :meth:`last_state` (a fleet's shard that
        died: docs/scaling.md): its filter goes on from that state as if its sighting had just been
        accepted here (this fusion's camera corrections kept), unless this fusion's own state of the
        robot is as new. Whether it was taken."""
        state = self.state.get(robot)
        if state is None or state.last_accepted_s >= time_s:
            return False
        f = PoseFilter(self._body_params[robot], time_s, T_world_cube, covariance, velocity_m_s, angular_velocity_rad_s)
        self.state[robot] = RobotState(f, time_s, 0, state.corrections)
        self.stats["track taken over"] += 1
        return True

    def predicted_pose(self, robot: str, time_s: float) -> np.ndarray | None:
        """Where the robot's cube is expected at ``time_s`` (None while it is not tracked, or once
        it has not been seen for ``lost_after_s``), from the state after its newest sighting
        (late sightings that came since are not folded in yet)."""
        state = self.state.get(robot)
        if state is None or state.filter is None or time_s - state.last_accepted_s > self.params.lost_after_s:
            return None
        return state.filter.predicted(time_s)

    def add(self, sighting: CubeSighting, now_s: float) -> list[TrackedPose]:
        """Fuse a sighting now. Returns the poses it made due: its own if it was accepted and is
        the robot's newest, after those of earlier sightings that re-applying the late ones made
        newer than the robot's last pose out (a track that starts within the re-applied steps
        gives its poses from its start on). A late sighting (older than the newest) is folded in
        exactly and gives no pose by itself, so each robot's poses leave in capture order."""
        robot = sighting.robot
        history, keys = self.history[robot], self._keys[robot]
        key = (sighting.capture_time_s, sighting.camera, sighting.seq)
        if keys and sighting.capture_time_s < keys[-1][0] - self.params.history_s:
            self.stats["too late sighting"] += 1
            return []
        i = bisect.bisect_right(keys, key)
        if i < len(history):  # late: the state before it is that of the step it goes before
            self.stats["late sighting"] += 1
            history.insert(i, HistoryStep(key, sighting, history[i].before))
            keys.insert(i, key)
            self._stale[robot] = min(self._stale.get(robot, i), i)
            return []
        history.append(HistoryStep(key, sighting, self.state[robot]))
        keys.append(key)
        self._apply_from(robot, self._stale.pop(robot, len(history) - 1), now_s)
        poses = self._due_poses(robot, now_s, keys[-1][0] - self.filter_params.smooth_lag_s)
        self._forget(robot)
        return poses

    def settled_state(self, robot: str, now_s: float) -> RobotState:
        """The robot's state after processing every sighting received, in capture order (poses
        this makes due leave with the next :meth:`add` of the robot, or :meth:`flush`)."""
        if robot in self._stale:
            self._apply_from(robot, self._stale.pop(robot), now_s)
        return self.state[robot]

    def flush(self, now_s: float) -> list[TrackedPose]:
        """Fold in the late sightings still pending and return the poses that makes due (nothing
        else is held back)."""
        poses = []
        for robot in self.history:
            self.settled_state(robot, now_s)
            poses += self._due_poses(robot, now_s, math.inf)
        return poses

    def release(self, now_s: float) -> list[TrackedPose]:
        """With ``smooth_lag_s``: the poses whose time is up at ``now_s`` (host clock) though no
        sighting that much newer came (the robot left every camera's view, a camera stalled):
        every one captured more than ``smooth_lag_s + smooth_margin_s`` before ``now_s``, smoothed
        over the sightings there are (late ones pending folded in first). A sighting that comes
        after its pose left is folded in as a late one and gives no second pose. Without the lag:
        none (each pose left with its sighting)."""
        fp = self.filter_params
        if fp.smooth_lag_s == 0:
            return []
        before_s = now_s - fp.smooth_lag_s - fp.smooth_margin_s
        poses = []
        for robot, keys in self._keys.items():
            sent = self._sent.get(robot)
            start, stop = 0 if sent is None else bisect.bisect_right(keys, sent), bisect.bisect_left(keys, (before_s,))
            if any(step.poses for step in self.history[robot][start:stop]) or (robot in self._stale and stop > start):
                self.settled_state(robot, now_s)
                due = self._due_poses(robot, now_s, before_s)
                self.stats["pose released before its lag"] += len(due)
                poses += due
        return poses

    def _apply_from(self, robot: str, start: int, now_s: float) -> None:
        """Apply the robot's steps from ``start`` on in capture order (each on the state the one
        before left), keeping each step's poses with it."""
        history = self.history[robot]
        sent = self._sent.get(robot)
        state = history[start].before
        for index in range(start, len(history)):
            step = history[index]
            step.before = state
            # a step whose poses already left (re-applied after a late sighting) gives none again
            due = sent is None or step.key > sent
            state, step.pose, outcome = self._apply(state, history, index, now_s, due or self._trails is not None)
            step.poses = [step.pose] if due and step.pose is not None else []
            if step.outcome:
                self.stats[step.outcome] -= 1
                self.stats["replayed sighting"] += 1
            self.stats[outcome] += 1
            step.outcome = outcome
        self.state[robot] = state

    def _due_poses(self, robot: str, now_s: float, before_s: float) -> list[TrackedPose]:
        """The poses of the robot's steps after the last one whose poses left, in capture order;
        with ``smooth_lag_s`` only those of steps captured before ``before_s``, smoothed over the
        steps after them."""
        history, keys = self.history[robot], self._keys[robot]
        sent = self._sent.get(robot)
        start = 0 if sent is None else bisect.bisect_right(keys, sent)
        lag_s = self.filter_params.smooth_lag_s
        stop = len(history) if lag_s == 0 else bisect.bisect_left(keys, (before_s,))
        poses = []
        for step in history[start:stop]:
            if step.poses:
                poses += step.poses
                self._sent[robot] = step.key
        if lag_s == 0 or not poses:
            return poses
        return smoothed_poses(self._trail_steps(robot, start, len(history)), now_s, stop - start, lag_s,
                              self._gains[robot])

    def _forget(self, robot: str) -> None:
        """Drop the steps no late sighting can reach any more (nor a track start's window)."""
        history, keys = self.history[robot], self._keys[robot]
        oldest = keys[-1][0] - self.params.history_s - self.params.init_window_s
        n = bisect.bisect_left(keys, (oldest,))
        if n > 0:
            if self._trails is not None:
                self._trails[robot] += self._trail_steps(robot, 0, n)
            del history[:n], keys[:n]

    def _corners(self, sighting: CubeSighting, T_world_cube: np.ndarray, corrections: CameraCorrections | None = None,
                 covariance: np.ndarray | None = None,
                 made: dict[tuple[tuple[int, int], ...], list[CornerSet]] | None = None) -> list[CornerSet]:
        """The sighting's corners matched to faces where ``T_world_cube`` projects them, seen
        from its camera as ``corrections`` put it (its extrinsics corrected, its stamp moved by its
        time offset: :mod:`cubetrack.fuse.camera_corrections`): one set, taken at the capture time;
        under a rolling shutter (the camera's ``readout_s``) one set
        per face, taken when the rows of its corners were (their mean row's time). ``covariance``
        (6x6 or the filter's 12x12, ``[δp, δθ]`` first): how uncertain that pose is, which widens the association gate
        (:func:`prediction_gate_px`) of a body whose ids are all distinct (where an id repeats, the
        gate is what tells its faces apart: it stays ``association_gate_px``). ``made``: the sighting's
        corner sets made before (:attr:`HistoryStep.sets`), by the faces matched, which a camera without a
        correction applied takes again when its detections match the same faces."""
        intrinsics, t, T_world_cam = sighting.intrinsics, sighting.capture_time_s, sighting.T_world_cam
        offset = None if corrections is None else corrections.applied(sighting.camera)
        if offset is not None:
            t, T_world_cam = t + float(offset[6]), corrected_T_world_cam(T_world_cam, offset)
        layout = self.layouts[sighting.robot]
        T_world_cam, T_cam_world = self._camera_pose(sighting.camera, T_world_cam)
        gate_px = self.params.association_gate_px
        if covariance is not None and not layout.has_repeated_ids:  # a repeated id's face is told by the gate
            gate_px += prediction_gate_px(covariance, T_world_cube, T_world_cam, intrinsics,
                                          self._reach_m[sighting.robot])
        matches = match_faces(sighting.detections, layout, intrinsics, T_world_cam, T_world_cube, gate_px=gate_px,
                              max_view_angle_deg=self.params.max_view_angle_deg,
                              camera_checked=T_cam_world is not None)
        if made is None or offset is not None:   # a correction moves the camera and the stamp: sets of its own
            return sighting_corner_sets(matches, intrinsics, T_world_cam, sighting.camera, t, T_cam_world)
        faces = tuple((m.marker, id(m.detection)) for m in matches)   # the detections are the sighting's own
        sets = made.get(faces)
        if sets is None:
            sets = made[faces] = sighting_corner_sets(matches, intrinsics, T_world_cam, sighting.camera, t,
                                                      T_cam_world)
        return list(sets)

    def _camera_pose(self, camera: str, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """``T_world_cam`` as a float array and its inverse (None unless it is a finite rigid pose:
        :func:`cubetrack.estimate.match.match_faces` then says what is wrong), made once per array: a
        camera's sightings share the tracker's array of its pose (a camera that moves gets a new
        array, a correction a new one per sighting; none is written in place)."""
        held = self._cameras.get(camera)
        if held is None or held[0] is not T_world_cam:
            pose = np.asarray(T_world_cam, dtype=float)
            held = self._cameras[camera] = (T_world_cam, pose, invert_T(pose) if is_finite_pose(pose) else None)
        return held[1], held[2]

    def _apply(self, state: RobotState, history: list[HistoryStep], index: int, now_s: float,
               record: bool) -> tuple[RobotState, TrackedPose | None, str]:
        """One step of capture-order processing: the sighting ``history[index]`` on ``state``.
        Returns the new state, the pose it gives (None unless ``record``) and its outcome (a stats key)."""
        sighting = history[index].sighting
        robot, t = sighting.robot, sighting.capture_time_s
        history[index].corners = []
        if state.filter is not None and t - state.last_accepted_s > self.params.lost_after_s:
            log.info("%s: not seen for %.2f s; track restarts", robot, t - state.last_accepted_s)
            state = replace(state, filter=None)
        if state.filter is None:
            window = history[max(0, index + 1 - self.START_WINDOW): index + 1]
            return self._start(state, sighting, [s.sighting for s in window], now_s, record)
        f = state.filter.copy()
        f.predict(t)
        corners = self._corners(sighting, f.T_world_cube, state.corrections, f.P, history[index].sets)
        prior, outcome = f.copy(), "accepted sighting"
        if not (corners and f.update(corners, state.corrections.term_scale(sighting.camera)).accepted):
            again = self._reacquire(sighting, f, state.corrections)
            if again is not None:
                (f, corners), outcome = again, "re-acquired sighting"
            else:
                outcome = "rejected sighting"
        if outcome == "rejected sighting":
            rejections = state.rejections + 1
            if rejections >= self.params.max_rejections:
                log.info("%s: %d sightings rejected in a row; track restarts", robot, rejections)
                return replace(state, filter=None, rejections=rejections), None, "rejected sighting"
            return replace(state, filter=f, rejections=rejections), None, "rejected sighting"
        fp, corrections = self.filter_params, state.corrections
        if fp.camera_term_samples_per_s > 0:
            history[index].corners = corners
        if outcome == "accepted sighting":  # the camera against the prediction (the others' consensus)
            corrections = observed(corrections, self._priors, corners, prior.T_world_cube, prior.velocity_m_s,
                                   prior.angular_velocity_rad_s, prior.time_s, prior.P,
                                   fp.corner_noise_px, fp.huber_px)
            corrections = self._term_sample(history, index, f, corrections)
        new = RobotState(f, t, 0, corrections)
        if not record:
            return new, None, outcome
        markers = tuple(f"{sighting.camera}:{face}" for c in corners for face in c.faces)
        return new, pose_record(sighting, f, now_s, (sighting.camera,), markers), outcome

    def _reacquire(self, sighting: CubeSighting, f: PoseFilter,
                   corrections: CameraCorrections) -> tuple[PoseFilter, list[CornerSet]] | None:
        """The other hypothesis for a sighting the predicted pose ``f`` does not explain: the
        camera's own cube pose from its detections (another face, a flip, a turn the motion model
        missed). If it lies within ``reacquire_m`` of the prediction and its matched corners pass
        the filter's gate, the track goes on from it (a broad pose prior, the prediction's velocities
        with their covariance: a start's ``init_velocity_sigma`` here would let the next frame of a
        camera that disagrees, a few ms later, become velocity; issue 25): (the new filter, its
        corners); else None."""
        estimate = sighting.estimate or estimate_cube(
            sighting.detections, self.layouts[sighting.robot], sighting.intrinsics, sighting.T_world_cam,
            camera=sighting.camera, robot=sighting.robot, seq=sighting.seq,
            capture_time_s=sighting.capture_time_s, arrival_time_s=sighting.arrival_time_s,
            params=self.estimator_params)
        if estimate is None or np.linalg.norm(estimate.T_world_cube[:3, 3] - f.position_m) > self.params.reacquire_m:
            return None
        corners = self._corners(sighting, estimate.T_world_cube, corrections)
        if not corners:
            return None
        prior = np.zeros((12, 12))
        prior[:6, :6] = np.diag(np.repeat([self.params.reacquire_m**2, np.radians(30.0) ** 2], 3))
        prior[6:, 6:] = f.P[6:, 6:]
        g = PoseFilter(f.params, f.time_s, estimate.T_world_cube, prior, f.velocity_m_s,
                       f.angular_velocity_rad_s)
        return (g, corners) if g.update(corners, corrections.term_scale(sighting.camera)).accepted else None

    def _term_sample(self, history: list[HistoryStep], index: int, f: PoseFilter,
                     corrections: CameraCorrections) -> CameraCorrections:
        """``corrections`` with a sample of the most overdue camera's calibration term
        (:func:`cubetrack.fuse.camera_corrections.term_observed`): its newest accepted sighting up to
        ``history[index]`` against each other camera's accepted sighting nearest to it within
        ``TERM_SPAN_S``, each with the corner sets its own update took (no association again);
        unchanged when no camera is due."""
        fp = self.filter_params
        if fp.camera_term_samples_per_s <= 0:
            return corrections
        t, recent = history[index].key[0], list[HistoryStep]()
        for step in reversed(history[max(0, index + 1 - self.START_WINDOW): index + 1]):
            if t - step.key[0] > 2 * TERM_SPAN_S:
                break
            if step.corners:
                recent.append(step)
        newest = {s.sighting.camera: s for s in reversed(recent) if t - s.key[0] <= TERM_SPAN_S}
        camera = term_due(corrections, sorted(newest), t, 1.0 / fp.camera_term_samples_per_s)
        if camera is None or len(newest) < 3:
            return corrections
        own, nearest = newest[camera], dict[str, HistoryStep]()
        for s in recent:
            gap = abs(s.key[0] - own.key[0])
            if s.sighting.camera != camera and gap <= TERM_SPAN_S and (
                    s.sighting.camera not in nearest or gap < abs(nearest[s.sighting.camera].key[0] - own.key[0])):
                nearest[s.sighting.camera] = s
        others = [c for s in nearest.values() for c in s.corners]
        sigmas = (fp.camera_position_sigma_m, math.radians(fp.camera_rotation_sigma_deg), fp.camera_scale_sigma)
        return term_observed(corrections, own.corners, others, f.predicted(own.key[0]), f.velocity_m_s,
                             f.angular_velocity_rad_s, sigmas, fp.corner_noise_px)

    def _started_filter(self, robot: str, time_s: float, solution: JointSolution,
                        frames: list[tuple[str, list[CornerSet]]], corrections: CameraCorrections) -> PoseFilter | None:
        """The filter a track starts with: at the joint fit's pose and velocities at ``time_s`` (the
        newest sighting's), from a broad prior (``reacquire_m``, 30 deg, the start's velocity spreads),
        updated with each camera frame of the fit in turn as every later frame is (each corner's
        own noise, its camera's calibration term; an older frame informs the velocities too). Its
        covariance is then what the sightings pin: the joint fit's own counts the corners' noise
        alone, and a start from a few markers far away claimed a centimetre's depth too little
        (issue 27). None if no frame passes the filter's gate."""
        fp = self._body_params[robot]
        prior = np.diag(np.repeat([self.params.reacquire_m**2, math.radians(30.0) ** 2,
                                   fp.init_velocity_sigma**2, fp.init_angular_velocity_sigma**2], 3))
        f = PoseFilter(fp, time_s, solution.T_world_cube, prior,
                       solution.velocity_m_s, solution.angular_velocity_rad_s)
        accepted = [f.update(frame, corrections.term_scale(camera)).accepted for camera, frame in frames if frame]
        return f if any(accepted) else None

    def _start(self, state: RobotState, sighting: CubeSighting, recent: list[CubeSighting], now_s: float,
               record: bool) -> tuple[RobotState, TrackedPose | None, str]:
        """Start a track from a joint fit of pose and velocity over the recent sightings.

        Every recent single-camera estimate is tried as the starting guess (one may be a flipped
        or misidentified face); the fit that explains the most corners within the gate wins.
        """
        t = sighting.capture_time_s
        window = [s for s in recent if 0.0 <= t - s.capture_time_s <= self.params.init_window_s]
        if len({s.capture_time_s for s in window}) < 3 or len({s.camera for s in window}) < 2:
            return state, None, "sighting before track start"  # three sightings from two cameras: pose and velocity
        fp = self.filter_params
        best = None
        for guess in {id(s.estimate): s.estimate for s in window if s.estimate is not None}.values():
            frames = [(s.camera, self._corners(s, guess.T_world_cube, state.corrections)) for s in window]
            sets = [c for _, frame in frames for c in frame]
            if len({c.camera for c in sets}) < 2:
                continue
            solution = solve_joint(sets, guess.T_world_cube, t, corner_noise_px=fp.corner_noise_px,
                                   velocity_sigma=(fp.init_velocity_sigma, fp.init_angular_velocity_sigma))
            if solution is None or solution.rms_px > fp.gate_rms_px or solution.inlier_fraction < 0.9:
                continue
            if best is None or (solution.points, -solution.rms_px) > (best[0].points, -best[0].rms_px):
                best = (solution, frames)
        if best is None:
            return state, None, "failed track start"
        solution, frames = best
        f = self._started_filter(sighting.robot, t, solution, frames, state.corrections)
        if f is None:
            return state, None, "failed track start"
        sets = [c for _, frame in frames for c in frame]
        if not record:
            return RobotState(f, t, 0, state.corrections), None, "track start"
        cameras = tuple(sorted({s.camera for s in sets}))
        markers = tuple(f"{s.camera}:{face}" for s in sets for face in s.faces)
        return RobotState(f, t, 0, state.corrections), pose_record(sighting, f, now_s, cameras, markers), "track start"
