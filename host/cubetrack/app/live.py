"""Live tracking and recording from camera nodes over HTTP: :class:`cubetrack.source.streams.LiveCameras`
(or camera worker processes) feeding the same :class:`cubetrack.app.tracker.Tracker` that replays
recordings (:func:`cubetrack.app.track.track_recording`); only the source differs.

- :func:`track_live`: the config's camera URLs -> ``<out>/<robot>.tum`` and ``.jsonl``, written
  and flushed as poses come, optionally recording the session as it goes;
- :func:`record_live`: the config's camera URLs -> a recording folder (contracts §3) that
  ``cubetrack track --recording`` replays.

Both are loops on the session runtime (:mod:`cubetrack.app.session`): they run until
``duration_s`` has passed, ``stop`` is set, or Ctrl-C / SIGTERM, which end the session like the
end of the duration: everything received so far is kept and the result says ``interrupted``. A
status callback gets a :class:`LiveStatus` every ``status_every_s``.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import shutil
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from cubetrack.app.camera_workers import FORECAST_EVERY_S, CameraProcesses
from cubetrack.app.config import config_params, parameter_tables
from cubetrack.app.outputs import open_outputs
from cubetrack.app.session import PoseStream, RunSpec, Session, idle_wait_s
from cubetrack.app.tracker import FrameProcessor, StageParams, Tracker, TrackStats
from cubetrack.app.watch_log import attach_watch_log
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample
from cubetrack.core.errors import ConfigError
from cubetrack.core.frame_pool import FramePool, LiveParams, WorkerKind, by_capture_time
from cubetrack.core.records import CameraView, Frame, FrameResult
from cubetrack.fuse.forecast import forecast_of
from cubetrack.io.camera_info import read_camera_info
from cubetrack.io.config import TrackerConfig
from cubetrack.io.frame_wire import unpack_result
from cubetrack.io.recording import CameraEntry, RecordingWriter
from cubetrack.io.run import RUN_FILE
from cubetrack.sink.base import Outputs, Sink
from cubetrack.source.health import HEALTH_EVERY_S, HealthMeter, LiveStatus, StatusRates
from cubetrack.source.order import CaptureOrder
from cubetrack.source.streams import CameraStats, ClockReading, LiveCameras, SourceParams

log = logging.getLogger(__name__)


def live_camera_urls(config: TrackerConfig) -> dict[str, str]:
    """Camera name -> stream URL; every camera of a live config needs one."""
    if not config.cameras:
        raise ConfigError(f"{config.path}: no [[cameras]]; live use needs each camera's name and url")
    missing = [c.name for c in config.cameras if not c.url]
    if missing:
        raise ConfigError(f"{config.path}: camera(s) {', '.join(missing)} have no url; live use reads each camera's "
                          'stream, e.g. url = "http://192.168.1.21/stream" in its [[cameras]] table')
    return {c.name: c.url for c in config.cameras}


def live_intrinsics(config: TrackerConfig) -> dict[str, CameraIntrinsics]:
    """Every camera's intrinsics from the config's ``camera_info`` (a live run has no recording
    folder to take them from)."""
    missing = [c.name for c in config.cameras if c.camera_info is None]
    if missing:
        raise ConfigError(
            f"{config.path}: camera(s) {', '.join(missing)} have no camera_info; live tracking takes intrinsics "
            'from the config only (there is no recording folder): add camera_info = "calib/<camera>.yaml" '
            "(ROS camera_info YAML, e.g. from cubetrack calibrate-intrinsics) to each [[cameras]] table")
    return {c.name: read_camera_info(c.camera_info) for c in config.cameras if c.camera_info is not None}


class _Recorder:
    """A :class:`RecordingWriter` shared by the reader threads (one lock), with the config's
    intrinsics copied into ``camera_info/``."""

    def __init__(self, out: str | Path, config: TrackerConfig, urls: dict[str, str], overwrite: bool = False):
        self.writer = RecordingWriter(out, [CameraEntry(name, url) for name, url in urls.items()], overwrite)
        self.path = self.writer.path
        self.lock = threading.Lock()
        self.frames = 0
        for c in config.cameras:
            if c.camera_info is not None and c.camera_info.exists():
                shutil.copyfile(c.camera_info, self.writer.camera_info_path(c.name))

    def frame(self, frame: Frame) -> None:
        with self.lock:
            self.writer.add_frame(frame.camera, frame.seq, frame.device_time_s, frame.host_time_s, frame.jpeg)
            self.frames += 1

    def clock(self, camera: str, sample: ClockSample) -> None:
        with self.lock:
            self.writer.add_clock_sample(camera, sample)

    def close(self) -> None:
        with self.lock:
            self.writer.close()


@dataclass(frozen=True, slots=True)
class LiveResult:
    """What a live session produced. ``outputs``: robot -> (TUM, JSONL) (empty for a recording
    session); ``recording``: the recording folder written, if any; ``interrupted``: Ctrl-C ended it;
    latencies are medians over the session's fused poses."""

    stats: TrackStats | None
    cameras: dict[str, CameraStats]
    outputs: dict[str, tuple[Path, Path]]
    recording: Path | None
    duration_s: float
    interrupted: bool
    latency_s: float | None  # capture -> pose output
    arrival_latency_s: float | None = None  # frame arrival -> pose output
    ended_by: str | None = None  # the signal that ended the session (Ctrl-C: SIGINT), if one did


class _FramePoolFeed:
    """Live frames read by :class:`LiveCameras`' threads, their per-frame work done on a
    :class:`FramePool` of ``[live] workers``; this thread plans each frame when a worker is free
    (the fusion's prediction tells detection where to look) and fuses the results in capture order
    (:class:`CaptureOrder`). A frame still waiting when its camera's next one arrives is dropped."""

    def __init__(self, stream: PoseStream, urls: dict[str, str], source: SourceParams, live_params: LiveParams,
                 recorder: _Recorder | None, fused: Callable[[FrameResult], None], clock: Callable[[], float]):
        tracker = stream.tracker
        self.stream, self.tracker, self.fused, self.order, self.clock = stream, tracker, fused, CaptureOrder(), clock
        self.wake = threading.Event()
        make_worker = functools.partial(FrameProcessor, tracker.intrinsics, tracker.world, tracker.robots,
                                        tracker.T_world_cam, tracker.params)
        self.pool = FramePool(make_worker, live_params.worker_count, live_params.worker_kind, self.wake.set)
        self.live = LiveCameras(urls, source, on_frame=recorder.frame if recorder else None,
                                on_clock=recorder.clock if recorder else None, clock=clock, wake=self._source_woke)

    def _source_woke(self) -> None:
        """A frame or clock sample came: worth waking for only when a worker could take a frame
        (otherwise the next result wakes this thread; clock samples can wait that long)."""
        if self.pool.idle() or not self.pool.ready:
            self.wake.set()

    def step(self, timeout_s: float) -> None:
        self.wake.wait(timeout_s)
        self.wake.clear()
        for result in self.order.ready(self.pool.take(), self.clock()):
            self.fused(result)
        self._take_events()

    def _take_events(self) -> None:
        """Clock samples always; frames while a worker is free, in arrival order, the freshest first once
        behind (cubetrack.source.order; the others wait in the source, one per camera). Until the first
        worker has started, this thread does the per-frame work itself."""
        pool = self.pool
        while (event := self.live.get(0, frames=pool.idle() > 0 or not pool.ready, newest_if_behind=True)) is not None:
            if isinstance(event, ClockReading):
                self.stream.clock_sample(event.camera, event.sample)
            elif (job := self.tracker.admit(event, hold=False)) is not None:
                if pool.ready:
                    pool.submit(self.order.started(job))
                else:
                    self.fused(self.tracker.processor.work(job))

    def working(self) -> bool:
        """Work that had arrived when the session ended is still being done."""
        return self.pool.busy() > 0 or self.live.pending() > 0 or self.order.held() > 0

    def stats(self) -> TrackStats:
        return self.tracker.stats

    def close(self) -> None:
        self.live.stop()
        self.pool.close()


class _CameraProcessFeed:
    """Camera worker processes (:mod:`cubetrack.app.camera_workers`) read the cameras and do the
    per-frame work; this thread takes their clock samples and results, oldest capture first, and
    sends back, at most every ``FORECAST_EVERY_S``, the fusion's new
    :class:`~cubetrack.fuse.forecast.Forecast` for them to plan frames with."""

    def __init__(self, stream: PoseStream, make_tracker: Callable[[], Tracker], urls: dict[str, str],
                 source: SourceParams, live_params: LiveParams, views: bool, fused: Callable[[FrameResult], None],
                 clock: Callable[[], float]):
        """``make_tracker``: each process's tracker (picklable: a ``functools.partial`` of the
        arguments ``stream``'s tracker was made with)."""
        tracker = stream.tracker
        self.stream, self.tracker, self.fused, self.clock = stream, tracker, fused, clock
        unpack = functools.partial(unpack_result, intrinsics=tracker.intrinsics, T_world_cam=tracker.T_world_cam)
        self.live = CameraProcesses(urls, source, make_tracker, live_params.worker_count, unpack, views=views,
                                    clock=clock)
        self.next_forecast_s = 0.0

    def step(self, timeout_s: float) -> None:
        results, readings = self.live.take(timeout_s)
        for reading in readings:
            self.stream.clock_sample(reading.camera, reading.sample)
        for result in by_capture_time(results):
            self.fused(result)
        if results:
            now_s = self.clock()
            forecast = None
            if now_s >= self.next_forecast_s:
                self.next_forecast_s = now_s + FORECAST_EVERY_S
                forecast = forecast_of(self.tracker.fusion, self.stream.robots, now_s, self.tracker.recalibrated)
            self.live.forecast(forecast)

    def working(self) -> bool:
        return self.live.running or self.live.pending() > 0

    def stats(self) -> TrackStats:
        """The fusion's counters with the frames the worker processes admitted and gave up."""
        frames, before_clock = self.live.frame_counts()
        return dataclasses.replace(self.tracker.stats, frames=frames, frames_before_clock_sync=before_clock)

    def close(self) -> None:
        self.live.stop()
        self.live.close()


class _Fused:
    """What follows each fused frame live: its poses out (:class:`PoseStream`), its transfer time
    for the camera's health and, for outputs that show images, the frame with what detection
    found in it."""

    def __init__(self, stream: PoseStream, health: HealthMeter, outputs: Outputs):
        self.stream, self.health, self.outputs = stream, health, outputs

    def __call__(self, result: FrameResult) -> None:
        self.stream.fuse(result)
        frame = result.job.frame
        self.health.frame(frame, result.job.capture_time_s)
        if self.outputs.wants_views:
            found = tuple(d for sighting in result.sightings for d in sighting.detections)
            self.outputs.camera_view(CameraView(frame.camera, frame.seq, result.job.capture_time_s, frame.jpeg, found))


def track_live(config: TrackerConfig, extrinsics: dict[str, CameraExtrinsics] | None, out_dir: str | Path,
               params: StageParams | None = None, source: SourceParams | None = None, *,
               duration_s: float | None = None, record_to: str | Path | None = None,
               stop: threading.Event | None = None, status: Callable[[LiveStatus], None] | None = None,
               status_every_s: float = 2.0, clock: Callable[[], float] = time.time,
               sinks: Sequence[Sink] = (), live_params: LiveParams | None = None,
               extrinsics_path: str | Path | None = None, command: str = "track",
               update_extrinsics: bool = False) -> LiveResult:
    """Track every robot of ``config`` live from its cameras' URLs, writing ``<out_dir>/<robot>.tum``
    and ``.jsonl`` (flushed per pose) and ``<out_dir>/run.json`` (the session runtime's record,
    :mod:`cubetrack.app.session`, of ``command``). ``record_to``: also record the session there
    (everything that arrived, including frames the tracker had to drop). Frames are stamped with
    their capture time through each camera's ``/time`` round trips, exactly as in a replay.

    Per-frame work runs on ``[live] workers`` (:mod:`cubetrack.core.frame_pool`) or camera worker
    processes (:mod:`cubetrack.app.camera_workers`); this thread is the one ordered consumer that
    fuses. Frames of a camera whose clock is not known yet are given up (counted). The runtime
    releases the poses a fixed lag held once their time is up and, with ``[fusion]
    output_rate_hz``, outputs each tracked robot's predicted pose at that rate. Runs until
    ``duration_s``, ``stop``, Ctrl-C or SIGTERM; ``sinks``: other outputs, fed the same poses.
    With ``[camera_watch] enabled`` the watcher's events go to ``<out_dir>/camera_watch.jsonl``, the
    log and run.json, a re-calibrated camera's new pose to a versioned extrinsics file beside them
    (and over ``extrinsics_path`` with ``update_extrinsics``): :mod:`cubetrack.app.watch_log`."""
    if params is None or source is None or live_params is None:
        settings = config_params(config)
        params, source, live_params = params or settings.stages, source or settings.source, live_params or settings.live
    urls = live_camera_urls(config)
    intrinsics = live_intrinsics(config)
    make_tracker = functools.partial(Tracker, intrinsics, config.world, config.robots, extrinsics, params,
                                     synced_cameras=frozenset(urls))
    tracker = make_tracker()
    out_dir = Path(out_dir)
    recorder = _Recorder(record_to, config, urls) if record_to is not None else None
    outputs, files = open_outputs(config, intrinsics, extrinsics, out_dir, sinks)
    feed: _FramePoolFeed | _CameraProcessFeed | None = None
    watch_log = attach_watch_log(tracker, outputs, out_dir, extrinsics, extrinsics_path if update_extrinsics else None)
    try:
        session = Session(duration_s=duration_s, stop=stop, status_every_s=status_every_s, record=RunSpec(
            out_dir / RUN_FILE, command, {**parameter_tables(params), "source": source},
            {"config": config.path, "extrinsics": extrinsics_path, "recorded_to": record_to}, {"cameras": urls}))
        rates = StatusRates(list(urls), [r.name for r in config.robots])
        stream = PoseStream(tracker, outputs, clock, on_poses=rates.add_poses)
        fused = _Fused(stream, HealthMeter(list(urls), tracker.clocks, clock), outputs)
        kind = live_params.kind_for(len(urls), recorder is not None)
        if live_params.worker_kind is WorkerKind.CAMERA_PROCESS and recorder is not None:
            log.warning("recording: frames are recorded by this process, so they are read here and processed by "
                        "worker threads instead of camera worker processes")
        live_params = dataclasses.replace(live_params, worker_kind=kind)
        feed = (_CameraProcessFeed(stream, make_tracker, urls, source, live_params, outputs.wants_views, fused, clock)
                if kind is WorkerKind.CAMERA_PROCESS
                else _FramePoolFeed(stream, urls, source, live_params, recorder, fused, clock))
        _attach_live_ticks(session, stream, feed.live, fused.health, rates, status)
        feed.live.start()
        log.info("live tracking %d camera(s) with %d %s worker(s): %s", len(urls), live_params.worker_count,
                 kind.value, ", ".join(f"{n} {u}" for n, u in urls.items()))
        session.run(feed.step, idle_wait_s(params), draining=feed.working, drained=feed.live.stop)
        feed.live.stop()
        stream.finish()
        _log_late_sightings(tracker)
        stats = feed.stats()
    finally:
        if feed is not None:
            feed.close()
        if watch_log is not None:
            watch_log.close()
        outputs.close()
        if recorder is not None:
            recorder.close()
    session.finish({**stream.summary(stats), **(watch_log.summary() if watch_log is not None else {})})
    return LiveResult(stats, feed.live.stats(), files.outputs, recorder.path if recorder else None,
                      session.elapsed_s, session.interrupted, stream.latencies.median(),
                      stream.arrival_latencies.median(), session.ended_by)


def _attach_live_ticks(session: Session, stream: PoseStream, live: LiveCameras | CameraProcesses, health: HealthMeter,
                       rates: StatusRates, status: Callable[[LiveStatus], None] | None) -> None:
    """A live session's periodic duties: the tracker's (:meth:`PoseStream.attach`), each camera's
    health for the outputs every ``HEALTH_EVERY_S`` and the status every ``status_every_s``."""
    stream.attach(session)

    def send_health() -> None:
        for snapshot in health.snapshots(live.stats()):
            stream.outputs.camera_health(snapshot)

    session.every(HEALTH_EVERY_S, send_health)
    if status is not None:
        session.every(session.status_every_s, lambda: status(rates.snapshot(
            live.stats(), live.pending(), dict(stream.tracker.stats.poses))),
            first_s=session.started + session.status_every_s)


def _log_late_sightings(tracker: Tracker) -> None:
    late = getattr(tracker.fusion, "stats", {})
    if late:
        log.info("fusion: %d sightings fused, %d of them late (folded in), %d steps re-applied after them",
                 sum(tracker.stats.estimates.values()) + tracker.stats.frames, late["late sighting"],
                 late["replayed sighting"])


def record_live(config: TrackerConfig, out: str | Path, source: SourceParams | None = None, *,
                duration_s: float | None = None, stop: threading.Event | None = None,
                status: Callable[[LiveStatus], None] | None = None, status_every_s: float = 2.0,
                overwrite: bool = False, clock: Callable[[], float] = time.time) -> LiveResult:
    """Record the config's cameras into the recording folder ``out`` (contracts §3: frames,
    ``index.csv``, ``clock.csv``, ``recording.json`` with the source URLs, and ``camera_info/``
    copied from the config where it names one) and ``run.json`` (the session runtime's record). Rows
    are flushed as they come, so whatever ends the session (``duration_s``, ``stop``, Ctrl-C,
    SIGTERM), everything recorded so far is kept."""
    source = source or config_params(config).source
    urls = live_camera_urls(config)
    recorder = _Recorder(out, config, urls, overwrite)
    live = LiveCameras(urls, source, on_frame=recorder.frame, on_clock=recorder.clock, queue=False, clock=clock)
    rates = StatusRates(list(urls), [])
    session = Session(duration_s=duration_s, stop=stop, status_every_s=status_every_s,
                      status=None if status is None else lambda: status(
                          rates.snapshot(live.stats(), live.pending(), {})),
                      record=RunSpec(recorder.path / RUN_FILE, "record", {"source": source}, {"config": config.path},
                                     {"cameras": urls}))

    def step(timeout_s: float) -> None:
        session.stop_event.wait(timeout_s)
        if live.failure is not None:
            raise live.failure

    try:
        live.start()
        log.info("recording %d camera(s) into %s", len(urls), recorder.path)
        session.run(step, 0.05)
    finally:
        live.stop()
        recorder.close()
    if live.failure is not None:
        raise live.failure
    session.finish({"frames": recorder.frames})
    return LiveResult(None, live.stats(), {}, recorder.path, session.elapsed_s, session.interrupted, None,
                      ended_by=session.ended_by)
