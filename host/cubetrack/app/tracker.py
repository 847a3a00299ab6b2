"""The tracking pipeline: frames -> detections -> per-camera cube estimates -> fused poses.

:class:`Tracker` is the one code path for live tracking and offline replay: a source hands it
:class:`~cubetrack.core.records.Frame` objects in arrival order and it returns the fused poses each
frame produced. It is the workflow layer over the stages, and the only place that wires the one
feedback edge of the pipeline: the fusion's predicted poses tell detection where to look
(regions of interest; see :class:`Tracker`).
"""

from __future__ import annotations

import enum
import logging
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from cubetrack.calib.recalibrate import WatchedFusion
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample, WorldConfig
from cubetrack.core.errors import ConfigError, ImageError
from cubetrack.core.geometry import invert_T
from cubetrack.core.layout import CubeLayout
from cubetrack.core.params import check, param
from cubetrack.core.records import CubeSighting, Detection, Frame, FrameJob, FrameOutcome, FrameResult, TrackedPose
from cubetrack.detect.detector import Box, Detector, DetectorParams, DetectResult, decode_gray
from cubetrack.detect.predicted import predicted_view
from cubetrack.estimate.match import body_detections
from cubetrack.estimate.params import EstimatorParams
from cubetrack.estimate.pose import estimate_cube, world_marker_pose
from cubetrack.fuse.base import Fusion
from cubetrack.fuse.camera_watch import EventKind, WatchEvent, WatchParams
from cubetrack.fuse.corner_filter import FilterParams
from cubetrack.fuse.fusion import FilterFusion, FusionMethod, FusionParams, LatestEstimateFusion
from cubetrack.io.config import RobotConfig, TrackerConfig
from cubetrack.io.frame_wire import pack_result, unpack_result
from cubetrack.source.clock import ClockFitMethod, ClockSync

log = logging.getLogger(__name__)

HELD_FRAMES = 32  # per camera, waiting for the first clock round trip (about 4 s at 7.5 fps)


class Forecaster(Protocol):
    """What plans a frame (:meth:`Tracker.plan`): where each robot will be, and which robots' fusion
    asks for per-camera estimates. A :class:`~cubetrack.fuse.base.Fusion` is one; so is the
    :class:`~cubetrack.fuse.forecast.Forecast` a camera worker process is sent."""

    def predicted_pose(self, robot: str, time_s: float) -> np.ndarray | None: ...

    def needs_estimate(self, robot: str) -> bool: ...


@enum.unique
class CameraPoseSource(enum.Enum):
    EXTRINSICS = "extrinsics"
    WORLD_MARKER = "world-marker"


@enum.unique
class Timestamps(enum.Enum):
    CAPTURE = "capture"
    ARRIVAL = "arrival"


@dataclass(frozen=True, slots=True)
class TrackParams:
    """The ``[track]`` section of the tracker config."""

    timestamps: Timestamps = param(
        Timestamps.CAPTURE,
        "capture: stamp each frame with its capture time, the node's X-Timestamp mapped to the host "
        "clock by /time round trips (clock.csv), falling back to arrival times when there are none; "
        "arrival: stamp with the host arrival time (the paper's behaviour, late by the transfer time)",
    )

    roi_detection: bool = param(
        True,
        "while every robot is tracked, detect markers only in the image regions where the filter predicts "
        "the cubes (with calibrated cameras and the filter fusion); the full frame is searched otherwise",
    )
    roi_margin_m: float = param(0.06, "a predicted cube's image region is grown by this much motion, metres")
    full_frame_every: int = param(
        128, "with region detection: search a camera's full frame at least every this many frames (32 before "
        "session 30: a robot found nowhere is searched for in every whole frame once lost, [fusion] lost_after_s, "
        "so this only bounds how long one camera can miss a robot the others track; docs/live.md)")
    camera_poses: CameraPoseSource = param(
        CameraPoseSource.EXTRINSICS,
        "extrinsics: calibrated camera poses (cubetrack calibrate); world-marker: each frame's own "
        "world-marker pose, the paper's uncalibrated mode (frames without it give no estimate)",
    )

    def __post_init__(self) -> None:
        check(self.roi_margin_m >= 0, f"roi_margin_m must not be negative, got {self.roi_margin_m}")
        check(self.full_frame_every >= 1, f"full_frame_every must be at least 1, got {self.full_frame_every}")


@dataclass(frozen=True, slots=True)
class StageParams:
    """Every stage's parameters, as resolved from a config (recorded next to the outputs)."""

    detector: DetectorParams = field(default_factory=DetectorParams)
    estimator: EstimatorParams = field(default_factory=EstimatorParams)
    fusion: FusionParams = field(default_factory=FusionParams)
    filter: FilterParams = field(default_factory=FilterParams)
    track: TrackParams = field(default_factory=TrackParams)
    camera_watch: WatchParams = field(default_factory=WatchParams)

    @classmethod
    def from_config(cls, config: TrackerConfig) -> StageParams:
        """The tracker's sections of ``config`` (read by :func:`cubetrack.app.config.config_params`)."""
        from cubetrack.app.config import config_params

        return config_params(config).stages


class FrameProcessor:
    """The per-frame work: decode, detect (in the job's regions, else the whole frame), the
    camera's pose, each robot's own detections and, where asked, its per-camera estimate. Holds
    no fusion state, so any number of workers run in threads or processes (one per thread: a
    detector is not shared)."""

    def __init__(self, intrinsics: dict[str, CameraIntrinsics], world: WorldConfig,
                 robots: tuple[RobotConfig, ...], T_world_cam: dict[str, np.ndarray], params: StageParams):
        self.intrinsics = intrinsics
        self.world = world
        self.robots = robots
        self.layouts = {r.name: r.layout for r in robots}
        self.T_world_cam = T_world_cam
        self.params = params
        self.detector = Detector(params.detector,
                                 [world.dictionary, *(d for r in robots for d in r.layout.dictionaries)])

    def camera_pose(self, frame: Frame, detections) -> np.ndarray | None:
        """T_world_cam for this frame: calibrated, or from the frame's own world marker."""
        if self.params.track.camera_poses is CameraPoseSource.EXTRINSICS:
            return self.T_world_cam[frame.camera]
        w = self.world
        pose = world_marker_pose(detections, dictionary=w.dictionary, marker_id=w.marker_id, size_m=w.marker_size_m,
                                 intrinsics=self.intrinsics[frame.camera], params=self.params.estimator)
        return None if pose is None else invert_T(pose.T_cam_marker)

    def work(self, job: FrameJob) -> FrameResult:
        frame = job.frame
        try:
            found, outcome = self._detect(frame.jpeg, f"{frame.camera} frame {frame.seq}", job,
                                          self.intrinsics[frame.camera])
        except ImageError as exc:
            return FrameResult(job, FrameOutcome.CORRUPT, error=str(exc))
        detections = found.detections
        if not detections:
            return FrameResult(job, outcome, dropped=found.dropped)
        T_world_cam = self.camera_pose(frame, detections)
        if T_world_cam is None:
            return FrameResult(job, FrameOutcome.NO_CAMERA_POSE, dropped=found.dropped)
        return FrameResult(job, outcome, self.sightings(job, detections, T_world_cam), dropped=found.dropped)

    def pack(self, result: FrameResult) -> tuple:
        """``result`` as the message of a frame worker process (:func:`cubetrack.io.frame_wire.pack_result`)."""
        return pack_result(result, self.T_world_cam)

    def unpack(self, job: FrameJob, message: tuple) -> FrameResult:
        """The result of ``job`` that :meth:`pack` packed, with this end's intrinsics and camera poses."""
        return unpack_result(job, message, self.intrinsics, self.T_world_cam)

    def sightings(self, job: FrameJob, detections: tuple[Detection, ...], T_world_cam: np.ndarray,
                  robots: tuple[RobotConfig, ...] | None = None) -> tuple[CubeSighting, ...]:
        """The sightings of a frame's detections, seen from ``T_world_cam``: each robot's own
        detections and, for the robots in ``job.estimate_robots``, its per-camera estimate. The
        rest of :meth:`work`, and all of it for detections made elsewhere (a ``cubetrack worker``'s
        message, :func:`cubetrack.app.fusion_service.frame_result`); ``robots``: only these."""
        frame = job.frame
        intrinsics = self.intrinsics[frame.camera]
        sightings = []
        for robot in self.robots if robots is None else robots:
            mine = body_detections(detections, robot.layout)
            if not mine:
                continue
            estimate = None
            if robot.name in job.estimate_robots:
                estimate = estimate_cube(
                    mine, robot.layout, intrinsics, T_world_cam,
                    camera=frame.camera, robot=robot.name, seq=frame.seq,
                    capture_time_s=job.capture_time_s, arrival_time_s=frame.host_time_s,
                    params=self.params.estimator,
                )
            sightings.append(CubeSighting(frame.camera, robot.name, frame.seq, job.capture_time_s, frame.host_time_s,
                                          mine, estimate, T_world_cam, intrinsics))
        return tuple(sightings)

    def _detect(self, jpeg: bytes, source: str, job: FrameJob,
                lens: CameraIntrinsics) -> tuple[DetectResult, FrameOutcome]:
        """Detections in the job's regions (cut to the image; the frame decoded only down to their
        lowest edge, ``decode_gray(rows=...)``; its predicted markers first), or in the whole frame
        (also when the regions find nothing). No regions at all (every robot predicted out of this
        camera's view): nothing to search, so the frame is not decoded (a corrupt one then goes
        unnoticed). ImageError: the frame does not decode."""
        regions, predicted = (job.regions, job.predicted) if job.views is None else projected_views(
            job.views, self.layouts, lens, self.params.track.roi_margin_m, self.params.detector)
        if regions == ():
            return DetectResult(()), FrameOutcome.REGIONS
        if regions is not None:
            gray = decode_gray(jpeg, source, rows=max((box[3] for box in regions), default=None))
            height, width = gray.shape
            regions = tuple(box for box in ((x0, y0, min(x1, width), min(y1, height)) for x0, y0, x1, y1 in regions)
                            if box[2] - box[0] >= 16 and box[3] - box[1] >= 16)
            found = self.detector.find(gray, regions, lens, predicted)
            if found.detections or not regions:
                return found, FrameOutcome.REGIONS
        return self.detector.find(decode_gray(jpeg, source), lens=lens), FrameOutcome.FULL_FRAME


def projected_views(views: tuple[tuple[str, np.ndarray], ...], layouts: Mapping[str, CubeLayout],
                    intrinsics: CameraIntrinsics, margin_m: float,
                    detector: DetectorParams) -> tuple[tuple[Box, ...] | None, tuple[Detection, ...]]:
    """Image boxes (x0, y0, x1, y1) around every robot's predicted cube (``views``: robot, T_cam_cube)
    and its markers' predicted corners (:func:`cubetrack.detect.predicted.predicted_view`), or None
    (and no markers) when the full frame must be searched (a cube too near the camera's plane)."""
    boxes: list[Box] = []
    markers: list[Detection] = []
    for robot, T_cam_cube in views:
        view = predicted_view(T_cam_cube, layouts[robot], intrinsics, margin_m, detector)
        if view is None:
            return None, ()
        if view.box is not None:  # else: predicted out of this camera's view
            boxes.append(view.box)
            markers.extend(view.markers)
    return tuple(boxes), tuple(markers)


@dataclass(slots=True)
class TrackStats:
    """Counters of one tracking run (visible state, updated as frames pass)."""

    frames: int = 0
    corrupt_frames: int = 0
    frames_without_camera_pose: int = 0
    frames_before_clock_sync: int = 0
    region_detections: int = 0  # frames searched only around the predicted cubes
    dropped_detections: Counter = field(default_factory=Counter)  # markers found, then dropped: reason -> count
    estimates: Counter = field(default_factory=Counter)  # (robot, camera) -> count
    poses: Counter = field(default_factory=Counter)  # robot -> count


class Tracker:
    """Frames in, fused robot poses out. Cameras need intrinsics; camera poses come from
    ``extrinsics`` (calibrated) or, with ``CameraPoseSource.WORLD_MARKER``, from each frame.

    Per frame: its capture time (held back until a polled camera's clock is known), detection
    (:meth:`cubetrack.detect.detector.Detector.detect`), each robot's own detections
    (:func:`cubetrack.estimate.match.body_detections`), a per-camera estimate when the fusion
    asks for one, and the fusion (any :class:`cubetrack.fuse.base.Fusion`).

    The feedback edge, wired here and nowhere else: before detecting in a frame of a calibrated
    camera, the tracker asks the fusion where every robot will be at the frame's capture time
    (``Fusion.predicted_pose``). When every robot has a prediction (the filter tracks them all),
    detection searches only the image boxes around the predicted cubes (grown by
    ``[track] roi_margin_m`` of motion), ``detect(gray, regions)``; otherwise, when region
    detection is off, with the paper's fusions (which never predict), or with
    ``CameraPoseSource.WORLD_MARKER`` (the camera pose is not known before detection), the
    whole frame. A camera's whole frame is also searched at least every ``[track]
    full_frame_every`` frames (a robot that was never tracked can appear anywhere) and whenever
    its boxes find nothing. Stages never call back into the fusion themselves.
    """

    def __init__(self, intrinsics: dict[str, CameraIntrinsics], world: WorldConfig,
                 robots: tuple[RobotConfig, ...], extrinsics: dict[str, CameraExtrinsics] | None,
                 params: StageParams = StageParams(), synced_cameras: frozenset[str] = frozenset(),
                 defer_views: bool = False):
        """``synced_cameras``: cameras whose clock is polled by /time round trips; their frames wait
        for the first usable round trip instead of being stamped by their late arrival.
        ``defer_views``: :meth:`plan` leaves the regions' projection to the per-frame work (a
        replay's workers do it, off the planning thread)."""
        self.intrinsics = intrinsics
        self.world = world
        self.robots = robots
        self.params = params
        if params.track.camera_poses is CameraPoseSource.EXTRINSICS:
            missing = sorted(set(intrinsics) - set(extrinsics or {}))
            if missing:
                raise ConfigError(f"no extrinsics for camera(s) {', '.join(missing)}: run cubetrack calibrate")
            self.T_world_cam = {name: e.T_world_cam for name, e in (extrinsics or {}).items()}
        else:
            self.T_world_cam = {}
        self.T_cam_world = {name: invert_T(T) for name, T in self.T_world_cam.items()}  # what regions are planned by
        self.recalibrated: dict[str, np.ndarray] = {}  # camera -> its pose re-calibrated while tracking (issue 27)
        self.processor = FrameProcessor(intrinsics, world, robots, self.T_world_cam, params)
        self.fusion: Fusion
        if params.fusion.method is FusionMethod.FILTER:
            self.fusion = FilterFusion({r.name: r.layout for r in robots}, params.fusion, params.filter,
                                       params.estimator)
        else:
            self.fusion = LatestEstimateFusion(params.fusion)
        if params.camera_watch.enabled and self.T_world_cam:  # docs/calibration.md, "Watching the cameras"
            self.fusion = WatchedFusion(self.fusion, {r.name: r.layout for r in robots}, self.T_world_cam,
                                        params.camera_watch, params.estimator)
            self.fusion.listeners.append(self._rejoined)
        self.clocks = {name: ClockSync() for name in intrinsics}
        self.synced_cameras = synced_cameras
        self.held: dict[str, deque[Frame]] = {}  # frames waiting for their camera's first round trip
        self.frames_since_full: Counter[str] = Counter()  # per camera, for region detection
        self.stats = TrackStats()
        self.last_now_s = 0.0  # the host time the last frame became available
        self.defer_views = defer_views

    def _rejoined(self, event: WatchEvent) -> None:
        if event.kind is not EventKind.MOVED:  # rejoined, or a drift's step followed
            self.plan_cameras_at({event.camera: event.T_world_cam})

    def plan_cameras_at(self, poses: Mapping[str, np.ndarray]) -> None:
        """Plan the frames of each camera of ``poses`` (camera -> ``T_world_cam``, re-calibrated
        while tracking) through that pose: their regions are where the robots are predicted in the
        camera as it now stands. Sightings keep the calibrated pose (a frame worker process made
        them with it); the watched fusion moves them to the new one."""
        for camera, T_world_cam in poses.items():
            before = self.recalibrated.get(camera)
            if camera in self.T_cam_world and (before is None or not np.array_equal(before, T_world_cam)):
                self.recalibrated[camera] = T_world_cam
                self.T_cam_world[camera] = invert_T(T_world_cam)

    def add_clock_sample(self, camera: str, sample: ClockSample) -> list[TrackedPose]:
        """Take one /time round trip of ``camera`` (feed them as they complete). Frames held back
        for want of a clock are processed once it is known; their poses are returned."""
        return [pose for frame, capture_time_s in self.released_frames(camera, sample)
                for pose in self._track(frame, capture_time_s, sample.host_recv_s)]

    def released_frames(self, camera: str, sample: ClockSample) -> list[tuple[Frame, float]]:
        """Take one /time round trip of ``camera``; the frames held back for want of a clock
        that it releases, with their capture times, for the caller to plan (:meth:`plan`) and
        process in this order (:meth:`add_clock_sample` does all that)."""
        if camera not in self.clocks:
            return []
        clock = self.clocks[camera]
        clock.add_round_trip(sample.host_send_s, sample.device_time_s, sample.host_recv_s)
        if clock.method is not ClockFitMethod.ROUND_TRIP or camera not in self.held:
            return []
        return [(frame, clock.to_host(frame.device_time_s)) for frame in self.held.pop(camera)]

    def capture_time(self, frame: Frame) -> float | None:
        """The frame's capture time on the host clock (Unix seconds), per ``[track] timestamps``;
        None while a camera that answers /time has not yet given a usable round trip."""
        if self.params.track.timestamps is Timestamps.ARRIVAL:
            return frame.host_time_s
        clock = self.clocks[frame.camera]
        clock.add_arrival(frame.device_time_s, frame.host_time_s)
        if frame.camera in self.synced_cameras and clock.method is not ClockFitMethod.ROUND_TRIP:
            return None
        return clock.to_host(frame.device_time_s)

    def process(self, frame: Frame, now_s: float | None = None) -> list[TrackedPose]:
        """Run one frame through detection, estimation and fusion; returns the poses it produced.

        ``now_s`` is the host time the frame became available (default: its arrival time).
        A frame whose camera's clock is not known yet is held (see ``add_clock_sample``).
        """
        job = self.admit(frame)
        if job is None:
            return []
        return self.fuse(self.processor.work(job), frame.host_time_s if now_s is None else now_s)

    def admit(self, frame: Frame, hold: bool = True, forecast: Forecaster | None = None) -> FrameJob | None:
        """Count a frame and plan its per-frame work (:meth:`plan`, with ``forecast``); None when
        there is nothing to do now: a camera without intrinsics, or a polled camera whose clock is
        not known yet (the frame is held for :meth:`add_clock_sample`, or with ``hold=False`` given
        up and counted, as live tracking does: a frame that waited for the clock is stale)."""
        self.stats.frames += 1
        if frame.camera not in self.intrinsics:
            return None
        capture_time_s = self.capture_time(frame)
        if capture_time_s is None:
            if not hold:
                self.stats.frames_before_clock_sync += 1
                return None
            held = self.held.setdefault(frame.camera, deque(maxlen=HELD_FRAMES))
            if len(held) == held.maxlen:
                self.stats.frames_before_clock_sync += 1  # the oldest is given up
            held.append(frame)
            return None
        return self.plan(frame, capture_time_s, forecast)

    def _track(self, frame: Frame, capture_time_s: float, now_s: float) -> list[TrackedPose]:
        """Detection, estimation and fusion of a frame whose capture time is known, in turn."""
        return self.fuse(self.processor.work(self.plan(frame, capture_time_s)), now_s)

    def plan(self, frame: Frame, capture_time_s: float, forecast: Forecaster | None = None) -> FrameJob:
        """The per-frame work order of a frame whose capture time is known: the regions where
        ``forecast`` predicts the robots, and the robots whose fusion wants an estimate.
        ``forecast`` None: this tracker's own fusion; a camera worker process, which has no
        fusion, gives the fusion's latest :class:`cubetrack.fuse.forecast.Forecast`. With
        :attr:`defer_views` the job carries the robots' predicted poses in the camera and the
        per-frame work projects them into regions (the same regions, made on a replay's worker)."""
        forecast = self.fusion if forecast is None else forecast
        estimate_robots = frozenset(r.name for r in self.robots if forecast.needs_estimate(r.name))
        views = self._views(frame.camera, capture_time_s, forecast)
        if views is None:
            return FrameJob(frame, capture_time_s, None, estimate_robots)
        if self.defer_views:
            return FrameJob(frame, capture_time_s, None, estimate_robots, views=views)
        regions, predicted = projected_views(views, self.processor.layouts, self.intrinsics[frame.camera],
                                             self.params.track.roi_margin_m, self.params.detector)
        return FrameJob(frame, capture_time_s, regions, estimate_robots, predicted)

    def fuse(self, result: FrameResult, now_s: float) -> list[TrackedPose]:
        """Count what the per-frame work found and fuse its sightings (``now_s``: the host time
        they became available). Results of several workers may come in any order; a corrupt
        JPEG is counted and skipped."""
        self.last_now_s = now_s
        if not self.count(result):
            return []
        poses = []
        for sighting in result.sightings:
            if sighting.estimate is not None:
                self.stats.estimates[(sighting.robot, sighting.camera)] += 1
            poses.extend(self.fusion.add(sighting, now_s))
        for pose in poses:
            self.stats.poses[pose.robot] += 1
        return poses

    def release(self, now_s: float) -> list[TrackedPose]:
        """Poses the fusion held back whose time is up at host time ``now_s`` though what they
        wait for has not come (a fixed lag's poses of a robot no camera sees any more). Call it
        once every frame that had arrived by ``now_s`` has been fused: live after each batch of
        results and while none comes, in a replay with the arrival time of the first frame not
        yet fused."""
        poses = self.fusion.release(now_s)
        for pose in poses:
            self.stats.poses[pose.robot] += 1
        return poses

    def count(self, result: FrameResult) -> bool:
        """Count what the per-frame work found (and when the camera's whole frame was last
        searched); False for a corrupt JPEG (logged)."""
        frame = result.job.frame
        self.stats.dropped_detections.update(result.dropped)
        if result.outcome is FrameOutcome.CORRUPT:
            self.stats.corrupt_frames += 1
            log.warning("skipping corrupt frame: %s", result.error)
            return False
        if result.outcome is FrameOutcome.REGIONS:
            self.frames_since_full[frame.camera] += 1
            self.stats.region_detections += 1
        elif result.outcome is FrameOutcome.FULL_FRAME:
            self.frames_since_full[frame.camera] = 0
        else:
            self.stats.frames_without_camera_pose += 1
        return True

    def _views(self, camera: str, time_s: float, forecast: Forecaster) -> tuple[tuple[str, np.ndarray], ...] | None:
        """Every robot's predicted cube pose in the camera (robot, T_cam_cube), for the regions
        (:func:`projected_views`), or None when the full frame must be searched (a robot not
        predicted, a full search due, region search off)."""
        track = self.params.track
        if (not track.roi_detection or track.camera_poses is not CameraPoseSource.EXTRINSICS
                or self.frames_since_full[camera] + 1 >= track.full_frame_every):
            return None
        views = []
        for robot in self.robots:
            T_world_cube = forecast.predicted_pose(robot.name, time_s)
            if T_world_cube is None:
                return None
            views.append((robot.name, self.T_cam_world[camera] @ T_world_cube))
        return tuple(views)

    def finish(self, now_s: float | None = None) -> list[TrackedPose]:
        """Poses still held back by the fusion (call at the end of a session); ``now_s``: the host
        time now (default: when the last frame became available)."""
        poses = self.fusion.flush(self.last_now_s if now_s is None else now_s)
        for pose in poses:
            self.stats.poses[pose.robot] += 1
        return poses
