"""Fusion: per-camera cube sightings, which arrive unsynchronised and late, -> poses per robot.

Two families, chosen by ``[fusion] method``:

- ``filter`` (the default, the best): a constant-velocity SE(3) filter (:mod:`cubetrack.fuse.corner_filter`)
  updated with the matched cube corners of each camera frame at its capture time. Sightings
  are put back into capture-time order after ``reorder_delay_s``; a track starts from a joint
  multi-camera fit (:mod:`cubetrack.estimate.reprojection`); faces are matched to detections by where the
  predicted pose projects them, which resolves IPPE flips and same-id faces; a robot unseen for
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

import enum
import heapq
import itertools
import logging
from collections import Counter, deque
from dataclasses import dataclass

import numpy as np

from cubetrack.core.errors import ParamsError
from cubetrack.core.geometry import mean_rotation, quat_xyzw_from_R
from cubetrack.core.layout import CubeLayout
from cubetrack.core.params import param
from cubetrack.core.records import CameraEstimate, CubeSighting, TrackedPose
from cubetrack.estimate.match import match_faces
from cubetrack.estimate.reprojection import CornerSet, corner_set
from cubetrack.fuse.corner_filter import FilterParams, PoseFilter
from cubetrack.fuse.multi_view_fit import solve_joint

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
    window_s: float = param(0.2, "paper methods: a camera's latest estimate joins the fusion only if it is at most this many seconds older than the newest")
    reorder_delay_s: float = param(0.3, "filter: sightings are processed in capture-time order this many seconds after they arrive; later ones are dropped")
    lost_after_s: float = param(0.5, "filter: a robot with no accepted sighting for this many seconds is reported as not seen and its track restarts")
    output_rate_hz: float = param(0.0, "filter: also emit poses on a fixed clock at this rate between accepted sightings (0: only at each sighting)")
    association_gate_px: float = param(12.0, "filter: a detection joins a face only if its corners lie within this many pixels (or half a marker side) of the predicted face")
    init_window_s: float = param(0.3, "filter: a track starts from a joint fit of pose and velocity over the sightings of the last this many seconds (at least three, from two cameras)")
    max_rejections: int = param(3, "filter: this many rejected sightings in a row restart the track")

    def __post_init__(self) -> None:
        for name in ("window_s", "lost_after_s", "association_gate_px", "init_window_s"):
            if not getattr(self, name) > 0:
                raise ParamsError(f"{name} must be positive, got {getattr(self, name)}")
        if self.reorder_delay_s < 0 or self.output_rate_hz < 0 or self.max_rejections < 1:
            raise ParamsError("reorder_delay_s and output_rate_hz must not be negative, max_rejections >= 1")


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
    """A :class:`~cubetrack.fuse.base.Fusion`. Keeps each camera's latest estimate per robot and fuses them on every new estimate.

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
        )


def pose_record(robot: str, T_world_cube: np.ndarray, time_s: float, now_s: float, cameras: tuple[str, ...],
                markers: tuple[str, ...]) -> TrackedPose:
    return TrackedPose(robot=robot, time_s=time_s, position_m=T_world_cube[:3, 3].copy(),
                       quaternion_xyzw=quat_xyzw_from_R(T_world_cube[:3, :3]), cameras=cameras,
                       markers=markers, latency_s=max(0.0, now_s - time_s))


class FilterFusion:
    """A :class:`~cubetrack.fuse.base.Fusion`: corner-level filtering of every robot (see the module doc). Visible state: ``filters``
    (robot -> PoseFilter), ``pending`` (the reorder buffer), ``stats`` (counters)."""

    def __init__(self, layouts: dict[str, CubeLayout], params: FusionParams = FusionParams(),
                 filter_params: FilterParams = FilterParams()):
        self.layouts = layouts
        self.params = params
        self.filter_params = filter_params
        self.filters: dict[str, PoseFilter] = {}
        self.pending: list[tuple[float, int, CubeSighting]] = []
        self.recent: dict[str, deque[CubeSighting]] = {r: deque(maxlen=64) for r in layouts}
        self.last_accepted: dict[str, float] = {}
        self.rejections: Counter[str] = Counter()
        self.stats: Counter[str] = Counter()
        self._order = itertools.count()

    def needs_estimate(self, robot: str) -> bool:
        """A per-camera estimate is only needed to start a track: not while one runs."""
        return robot not in self.filters

    def predicted_pose(self, robot: str, time_s: float) -> np.ndarray | None:
        """Where the robot's cube is expected at ``time_s`` (None while it is not tracked)."""
        f = self.filters.get(robot)
        return None if f is None else f.predicted(time_s)

    def add(self, sighting: CubeSighting, now_s: float) -> list[TrackedPose]:
        """Queue a sighting; returns the poses of every sighting whose reorder delay has passed."""
        heapq.heappush(self.pending, (sighting.capture_time_s, next(self._order), sighting))
        return self._drain(now_s, now_s - self.params.reorder_delay_s)

    def flush(self, now_s: float) -> list[TrackedPose]:
        """Process everything still queued (end of a replay)."""
        return self._drain(now_s, float("inf"))

    def _drain(self, now_s: float, until_s: float) -> list[TrackedPose]:
        out = []
        while self.pending and self.pending[0][0] <= until_s:
            _, _, sighting = heapq.heappop(self.pending)
            out.extend(self._process(sighting, now_s))
        return out

    def _corners(self, sighting: CubeSighting, T_world_cube: np.ndarray) -> CornerSet | None:
        matches = match_faces(sighting.detections, self.layouts[sighting.robot], sighting.intrinsics,
                              sighting.T_world_cam, T_world_cube, gate_px=self.params.association_gate_px)
        return corner_set(matches, sighting.intrinsics, sighting.T_world_cam, sighting.camera, sighting.capture_time_s)

    def _process(self, sighting: CubeSighting, now_s: float) -> list[TrackedPose]:
        robot, t = sighting.robot, sighting.capture_time_s
        self.recent[robot].append(sighting)
        f = self.filters.get(robot)
        if f is not None and t < f.time_s:
            self.stats["late sighting"] += 1
            return []
        if f is not None and t - self.last_accepted[robot] > self.params.lost_after_s:
            log.info("%s: not seen for %.2f s; track restarts", robot, t - self.last_accepted[robot])
            del self.filters[robot]
            f = None
        if f is None:
            return self._start(sighting, now_s)
        ticks_from = f.time_s
        f.predict(t)
        corners = self._corners(sighting, f.T_world_cube)
        result = f.update([corners]) if corners is not None else None
        if result is None or not result.accepted:
            self.stats["rejected sighting"] += 1
            self.rejections[robot] += 1
            if self.rejections[robot] >= self.params.max_rejections:
                log.info("%s: %d sightings rejected in a row; track restarts", robot, self.rejections[robot])
                del self.filters[robot]
            return []
        self.rejections[robot] = 0
        self.last_accepted[robot] = t
        self.stats["accepted sighting"] += 1
        markers = tuple(f"{sighting.camera}:{face}" for face in corners.faces)
        return [*self._ticks(robot, f, ticks_from, t, now_s),
                pose_record(robot, f.T_world_cube, t, now_s, (sighting.camera,), markers)]

    def _ticks(self, robot: str, f: PoseFilter, after_s: float, until_s: float, now_s: float) -> list[TrackedPose]:
        """Fixed-rate poses strictly between two accepted sightings (never past them)."""
        rate = self.params.output_rate_hz
        if rate <= 0:
            return []
        first = np.floor(after_s * rate) + 1
        ticks = np.arange(first, np.ceil(until_s * rate)) / rate
        return [pose_record(robot, f.predicted(tick), float(tick), now_s, (), ()) for tick in ticks if tick < until_s]

    def _start(self, sighting: CubeSighting, now_s: float) -> list[TrackedPose]:
        """Start a track from a joint fit of pose and velocity over the recent sightings.

        Every recent single-camera estimate is tried as the starting guess (one may be a flipped
        or misidentified face); the fit that explains the most corners within the gate wins.
        """
        robot, t = sighting.robot, sighting.capture_time_s
        window = [s for s in self.recent[robot] if 0.0 <= t - s.capture_time_s <= self.params.init_window_s]
        if len({s.capture_time_s for s in window}) < 3 or len({s.camera for s in window}) < 2:
            return []  # wait for three sightings from two cameras: pose and velocity both observable
        fp = self.filter_params
        best = None
        for guess in {id(s.estimate): s.estimate for s in window if s.estimate is not None}.values():
            sets = [c for c in (self._corners(s, guess.T_world_cube) for s in window) if c is not None]
            if len({c.camera for c in sets}) < 2:
                continue
            solution = solve_joint(sets, guess.T_world_cube, t, corner_noise_px=fp.corner_noise_px,
                                   velocity_sigma=(fp.init_velocity_sigma, fp.init_angular_velocity_sigma))
            if solution is None or solution.rms_px > fp.gate_rms_px or solution.inlier_fraction < 0.9:
                continue
            if best is None or (solution.points, -solution.rms_px) > (best[0].points, -best[0].rms_px):
                best = (solution, sets)
        if best is None:
            self.stats["failed track start"] += 1
            return []
        solution, sets = best
        self.filters[robot] = PoseFilter(fp, t, solution.T_world_cube, solution.covariance,
                                         solution.velocity_m_s, solution.angular_velocity_rad_s)
        self.last_accepted[robot] = t
        self.rejections[robot] = 0
        self.stats["track start"] += 1
        cameras = tuple(sorted({s.camera for s in sets}))
        markers = tuple(f"{s.camera}:{face}" for s in sets for face in s.faces)
        return [pose_record(robot, solution.T_world_cube, t, now_s, cameras, markers)]
