"""Re-calibrating a moved camera from the robots it tracks, while tracking goes on (issue 27).

:class:`cubetrack.fuse.camera_watch.CameraWatch` notices a moved camera, sets it aside and
gathers its sightings against the cube poses the other cameras give. :func:`recalibrate` fits
the camera's new pose to them (the resection of :func:`cubetrack.fuse.camera_watch.refit_camera`
over every corner gathered) and says whether it is good enough to rejoin: known to
``rejoin_sigma_m`` / ``rejoin_sigma_deg`` at the corner noise the fits assume, and to
``rejoin_spread_m`` / ``rejoin_spread_deg`` by the sightings themselves (:func:`block_spread`: the
fits that leave out one block of them in time, each in turn). :class:`WatchedFusion` puts the watcher in front
of any fusion: it keeps a moved camera's sightings out, runs the fit on an executor (a
background thread live, never the tracking thread; inline when none is given, as offline
replay does, so a replay is reproducible), lets the camera back in at its new pose and gives
the fusion that camera's sightings at that pose from then on, and tells its ``state_listeners``
what it says of each camera whenever that changes (:class:`cubetrack.core.records.CameraWatchState`:
settling, watched, suspect, moved, re-calibrating with its progress in tenths, rejoined: the
dashboard's camera tile; a drift's step, ``followed``, is told as watched with the camera's new pose).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future
from dataclasses import dataclass

import numpy as np

from cubetrack.calib.solver import apply_increments, pose_offsets
from cubetrack.core.geometry import invert_T, transform_points
from cubetrack.core.layout import CubeLayout
from cubetrack.core.records import CameraWatchState, CubeSighting, TrackedPose
from cubetrack.estimate.params import EstimatorParams
from cubetrack.estimate.pose import estimate_cube
from cubetrack.estimate.reprojection import moved_pose
from cubetrack.fuse.base import Fusion
from cubetrack.fuse.camera_watch import (
    FIT_ITERATIONS,
    VELOCITY_SIGMA,
    CameraFit,
    CameraState,
    CameraWatch,
    EventKind,
    WatchEvent,
    WatchParams,
    WatchSample,
    refit_camera,
    stacked,
)
from cubetrack.fuse.multi_view_fit import solve_joint

log = logging.getLogger(__name__)

JOINT_STOP_M = 2e-4  # the joint fit stops once a round moves the camera by less than this, metres
JOINT_STOP_DEG = 0.005  # ... and turns it by less than this, degrees
JOINT_MAX_RATIO = 0.8  # the joint fit's extrapolation assumes at most this ratio of one round's step to the last's
JOINT_SAME_DIRECTION = 0.9  # ... and only of steps this aligned (cosine of the angle between them)
RETRY_GROWTH = 1.25  # a refused re-calibration is tried again once the camera has this many times the corners
# a re-calibration's spread (block_spread): its sightings in this many blocks in time, each left out in turn (at the
# first try, ~70 sightings, 8-9 per block: a block spans about a second of driving)
REJOIN_BLOCKS = 8


@dataclass(frozen=True, slots=True, eq=False)
class Recalibration:
    """A moved camera's new pose: ``fit`` over all its ``sightings``; ``spread_m`` / ``spread_deg``
    how well the sightings themselves pin it (:func:`block_spread`); ``consistent``: good enough
    to rejoin (the thresholds of :class:`cubetrack.fuse.camera_watch.WatchParams`)."""

    camera: str
    fit: CameraFit
    sightings: int
    spread_m: float
    spread_deg: float
    consistent: bool


def joint_sample(sample: WatchSample, T_world_cam: np.ndarray, corner_noise_px: float) -> WatchSample:
    """The sample's cube corners placed by a joint fit of the other cameras' corners AND its own,
    its camera taken at ``T_world_cam``; the sample unchanged when it kept no corner sets or the
    fit fails."""
    if not sample.own_sets or sample.T_world_cube is None:
        return sample
    T_cam_world = invert_T(T_world_cam)
    own = [dataclasses.replace(s, T_cam_world=T_cam_world) for s in sample.own_sets]
    solved = solve_joint([*sample.reference_sets, *own], sample.T_world_cube, sample.time_s, corner_noise_px,
                         velocity_sigma=VELOCITY_SIGMA, iterations=FIT_ITERATIONS)
    if solved is None:
        return sample
    points = np.concatenate([transform_points(moved_pose(solved.T_world_cube, solved.velocity_m_s,
                                                         solved.angular_velocity_rad_s, s.time_s - sample.time_s),
                                              s.points_cube_m) for s in sample.own_sets])
    return dataclasses.replace(sample, points_world_m=points, T_world_cube=solved.T_world_cube)


def extrapolation_ratio(step: np.ndarray, last_step: np.ndarray) -> float:
    """How much of the way a round of :func:`joint_fit` takes the camera, from its ``step`` and
    the round's before (pose increments ``[δp (m), δθ (rad)]``): when the cube poses hold the camera
    back, each round goes a steady fraction of what is left, along the same direction, and the
    rest is ``step * ratio / (1 - ratio)`` (Aitken's extrapolation; at most ``JOINT_MAX_RATIO``).
    0 (the step as it is) unless the step is shorter than the last and within
    ``JOINT_SAME_DIRECTION`` of its direction: a step that grows or turns away is no such
    contraction, and extrapolating it ran away (two of five, synthetic: 5x a growing step each
    round, the camera 4.8 m off after 13 rounds)."""
    size, last = float(np.linalg.norm(step)), float(np.linalg.norm(last_step))
    if not 0.0 < size < last or float(step @ last_step) < JOINT_SAME_DIRECTION * size * last:
        return 0.0
    return min(size / last, JOINT_MAX_RATIO)


def joint_fit(samples: Sequence[WatchSample], T_world_cam_init: np.ndarray, params: WatchParams
              ) -> tuple[CameraFit | None, list[WatchSample]]:
    """The camera's pose fitted jointly with the cube's pose at every sample: alternately the
    resection against the cube poses and the cube poses with this camera's corners in them (at
    the resection's pose), until the pose moves by under ``JOINT_STOP_M`` / ``JOINT_STOP_DEG`` or
    after ``params.rejoin_rounds`` rounds. The other cameras' poses stay fixed: they define the
    world. Returns the fit and the samples with their jointly fitted corners."""
    samples = list(samples)
    fit = refit_camera(*stacked(samples), T_world_cam_init, params.corner_noise_px)
    T_next = None if fit is None else fit.T_world_cam
    last_step = np.zeros(6)
    for _ in range(params.rejoin_rounds):
        if fit is None or T_next is None:
            break
        samples = [joint_sample(s, T_next, params.corner_noise_px) for s in samples]
        fit = refit_camera(*stacked(samples), T_next, params.corner_noise_px)
        if fit is None or all(a < b for a, b in zip(fit.offset_from(T_next), (JOINT_STOP_M, JOINT_STOP_DEG),
                                                    strict=True)):
            break
        step = pose_offsets(fit.T_world_cam[None], T_next[None])[0]
        T_next = apply_increments(T_next[None], (step / (1.0 - extrapolation_ratio(step, last_step)))[None])[0]
        last_step = step
    return fit, samples


def block_spread(samples: Sequence[WatchSample], T_world_cam: np.ndarray, corner_noise_px: float,
                 blocks: int = REJOIN_BLOCKS) -> tuple[float, float] | None:
    """How well the samples pin the camera pose fitted to them all (``T_world_cam``): the
    standard error of a block jackknife. The samples, in time order, are cut into ``blocks``
    blocks; the pose is fitted again without each block in turn, and the spread of those fits,
    ``(blocks - 1) / blocks`` times their scatter, is the pose's covariance. Returns the largest
    standard deviation of its position (m) and orientation (deg, about any world axis); None when
    a fit fails or there are fewer samples than blocks.

    Unlike the fit's own covariance, which takes every corner's error as independent noise of
    ``corner_noise_px`` (0.7-1.8 mm / 0.02-0.04 deg at the first try on the realistic scenes),
    this holds what the sightings really leave open: each sighting's corners share its reference's
    error, and where the robot drove decides which cameras gave the reference (2-7 mm / 0.06-0.2
    deg there). Blocks in time also catch a camera still moving. With ``blocks`` 2 it is half the
    distance between the fits of the older and the newer half: one draw, which passed or failed a
    threshold near its own scatter by chance (docs/calibration.md, issue 27, session 26)."""
    samples = list(samples)
    if len(samples) < blocks:
        return None
    edges = np.linspace(0, len(samples), blocks + 1).astype(int)
    left_out = []
    for start, end in zip(edges[:-1], edges[1:], strict=True):
        fit = refit_camera(*stacked(samples[:start] + samples[end:]), T_world_cam, corner_noise_px)
        if fit is None:
            return None
        left_out.append(pose_offsets(fit.T_world_cam[None], T_world_cam[None])[0])
    scatter = np.asarray(left_out) - np.mean(left_out, axis=0)
    covariance = (blocks - 1) / blocks * scatter.T @ scatter
    return (math.sqrt(float(np.linalg.eigvalsh(covariance[:3, :3]).max())),
            math.degrees(math.sqrt(float(np.linalg.eigvalsh(covariance[3:, 3:]).max()))))


def recalibrate(camera: str, samples: Sequence[WatchSample], T_world_cam_init: np.ndarray,
                params: WatchParams) -> Recalibration | None:
    """Fit ``camera``'s pose to its gathered samples (:func:`joint_fit`), started from
    ``T_world_cam_init`` (the pose the watcher's window found when it moved), and how well they pin
    it (:func:`block_spread` of the jointly fitted samples); None when a fit fails."""
    if len(samples) < 4:
        return None
    fit, joint = joint_fit(samples, T_world_cam_init, params)
    if fit is None:
        return None
    spread = block_spread(joint, fit.T_world_cam, params.corner_noise_px)
    if spread is None:
        return None
    spread_m, spread_deg = spread
    consistent = (fit.sigma_m <= params.rejoin_sigma_m and fit.sigma_deg <= params.rejoin_sigma_deg
                  and spread_m <= params.rejoin_spread_m and spread_deg <= params.rejoin_spread_deg)
    return Recalibration(camera, fit, len(samples), spread_m, spread_deg, consistent)


class WatchedFusion:
    """A :class:`cubetrack.fuse.base.Fusion` behind a :class:`CameraWatch` (see the module doc).
    ``events``: the watcher's decisions in order; ``listeners``: called with each event as it
    happens (on the thread that calls :meth:`add`); ``state_listeners``: called, on that thread,
    with a camera's :class:`CameraWatchState` when it changes (see the module doc); ``stats``:
    sightings kept out while their camera was set aside, re-calibrations tried and refused;
    ``executor``: where the re-calibration fits run (None: inline)."""

    def __init__(self, fusion: Fusion, layouts: dict[str, CubeLayout], T_world_cams: dict[str, np.ndarray],
                 params: WatchParams, estimator_params: EstimatorParams | None = None,
                 executor: Executor | None = None):
        self.fusion = fusion
        self.watch = CameraWatch(layouts, T_world_cams, params, estimator_params)
        self.layouts = layouts
        self.estimator_params = estimator_params or EstimatorParams()
        self.executor = executor
        self.stats: Counter[str] = Counter()
        self.listeners: list[Callable[[WatchEvent], None]] = []
        self.state_listeners: list[Callable[[CameraWatchState], None]] = []
        self._announced: dict[str, tuple[str, int]] = {}  # camera -> (state, progress in tenths) last told
        self._running: dict[str, Future[Recalibration | None]] = {}
        self._tried: dict[str, int] = {}  # camera -> corners it had at its last refused re-calibration

    @property
    def events(self) -> list[WatchEvent]:
        return self.watch.events

    def needs_estimate(self, robot: str) -> bool:
        return self.fusion.needs_estimate(robot)

    def predicted_pose(self, robot: str, time_s: float) -> np.ndarray | None:
        return self.fusion.predicted_pose(robot, time_s)

    def flush(self, now_s: float) -> list[TrackedPose]:
        return self.fusion.flush(now_s)

    def release(self, now_s: float) -> list[TrackedPose]:
        self._collect(now_s)
        return self.fusion.release(now_s)

    def add(self, sighting: CubeSighting, now_s: float) -> list[TrackedPose]:
        """Watch the sighting, then fuse it unless its camera is set aside (at its new pose if
        it was re-calibrated)."""
        self._collect(now_s)
        sighting = self._reposed(sighting)
        watched = self._restamped(sighting)
        predicted = self.fusion.predicted_pose(sighting.robot, watched.capture_time_s)
        for event in self.watch.add(watched, predicted):
            self._tell(event)
        self._start(now_s)
        self._announce(sighting.camera, now_s)
        state = self.watch.state.get(sighting.camera)
        if state is CameraState.SUSPECT:
            self.stats["suspect sighting"] += 1
            return []
        if self.watch.excluded(sighting.camera):
            self.stats["set-aside sighting"] += 1
            return []
        if predicted is not None and self.watch.off_prediction(sighting, predicted):
            return []
        return self.fusion.add(sighting, now_s)

    def _restamped(self, sighting: CubeSighting) -> CubeSighting:
        """The sighting as the watcher judges it: taken when the fusion's estimate of its camera's
        time offset says (``[filter] correction_time_sigma_s`` > 0; docs/tracking.md "Per-camera
        corrections"), as the fusion itself takes it. A camera whose stamps are 20 ms off the others'
        misses their cube pose of a moving body by pixels, which the suspect test read as a camera that
        moved (issue 27, the real footage's cam0 and cam1)."""
        state = getattr(self.fusion, "state", {}).get(sighting.robot)
        offset = None if state is None else state.corrections.applied(sighting.camera)
        if offset is None or offset[6] == 0.0:
            return sighting
        return dataclasses.replace(sighting, capture_time_s=sighting.capture_time_s + float(offset[6]))

    def _start(self, now_s: float) -> None:
        """Start the re-calibration of each camera that has gathered enough (again)."""
        for camera in self.watch.ready():
            points = self.watch.points(camera)
            if camera in self._running or points < RETRY_GROWTH * self._tried.get(camera, 0):
                continue
            self._announce(camera, now_s)  # at 100 %: its pose is being fitted
            samples = tuple(self.watch.samples[camera])
            start = next(e.T_world_cam for e in reversed(self.watch.events) if e.camera == camera)
            params = self.watch.params
            if self.executor is None:
                self._finish(camera, recalibrate(camera, samples, start, params), now_s)
            else:
                self._running[camera] = self.executor.submit(recalibrate, camera, samples, start, params)

    def _collect(self, now_s: float) -> None:
        """Apply the background re-calibrations that are done."""
        for camera, future in list(self._running.items()):
            if future.done():
                del self._running[camera]
                self._finish(camera, future.result(), now_s)

    def _finish(self, camera: str, result: Recalibration | None, now_s: float) -> None:
        self.stats["re-calibration tried"] += 1
        if result is None or not result.consistent:
            self.stats["re-calibration refused"] += 1
            self._tried[camera] = self.watch.points(camera)
            return
        self._tried.pop(camera, None)
        self._tell(self.watch.rejoin(camera, result.fit.T_world_cam, now_s, result.sightings))

    def _tell(self, event: WatchEvent) -> None:
        quiet = self.listeners or event.kind is EventKind.FOLLOWED  # a drift's step is no alarm
        log.log(logging.INFO if quiet else logging.WARNING, "%s", event.message)
        for listener in self.listeners:
            listener(event)
        moved = event.kind is EventKind.MOVED
        said = {EventKind.MOVED: "moved", EventKind.REJOINED: "rejoined", EventKind.FOLLOWED: "watched"}[event.kind]
        self._announce(event.camera, event.time_s, (said, 0), event.message.removeprefix(event.camera + " "),
                       None if moved else event.T_world_cam)

    def _announce(self, camera: str, now_s: float, said: tuple[str, int] | None = None, message: str = "",
                  T_world_cam: np.ndarray | None = None) -> None:
        """Tell the state listeners what the watcher says of ``camera`` (``said``: the state and
        progress in tenths; None: from the watcher; ``T_world_cam``: its new pose, on a rejoin or
        a drift's step, always told) when it differs from what they were told last. After a move
        the camera stays ``moved`` until its first corners are gathered; after a rejoin
        ``rejoined`` until it has a settled pose again."""
        if camera not in self.watch.state or not self.state_listeners:
            return
        last, progress = self._announced.get(camera, ("", 0)), 0.0
        state = self.watch.state[camera]
        if said is None and state is CameraState.SUSPECT:
            said, message = ("suspect", 0), "disagrees with the other cameras: out of the fusion"
        elif said is None and state is CameraState.RECALIBRATING:
            points = self.watch.points(camera)
            needed = max(self.watch.params.rejoin_points, math.ceil(RETRY_GROWTH * self._tried.get(camera, 0)))
            progress = min(1.0, points / needed)
            said, message = ("re-calibrating", int(10 * progress)), f"{points} / {needed} corners gathered"
        elif said is None:  # watched, once it has a settled pose
            settling = last if last[0] == "rejoined" else ("settling", 0)
            said = ("watched", 0) if camera in self.watch.settled else settling
        if T_world_cam is None and (said == last or (said[0] == "re-calibrating" and last[0] == "moved"
                                                     and progress == 0.0)):
            return
        self._announced[camera] = said
        state_now = CameraWatchState(camera, now_s, said[0], progress, message, T_world_cam)
        for listener in self.state_listeners:
            listener(state_now)

    def _reposed(self, sighting: CubeSighting) -> CubeSighting:
        """The sighting at its camera's re-calibrated pose (unchanged for a camera that never moved)."""
        T = self.watch.T_world_cam.get(sighting.camera)
        if T is None or np.array_equal(T, sighting.T_world_cam):
            return sighting
        estimate = None
        if sighting.estimate is not None:
            estimate = estimate_cube(sighting.detections, self.layouts[sighting.robot], sighting.intrinsics, T,
                                     camera=sighting.camera, robot=sighting.robot, seq=sighting.seq,
                                     capture_time_s=sighting.capture_time_s, arrival_time_s=sighting.arrival_time_s,
                                     params=self.estimator_params)
        return dataclasses.replace(sighting, T_world_cam=T, estimate=estimate)
