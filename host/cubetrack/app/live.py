"""Live tracking and recording from camera nodes over HTTP: :class:`cubetrack.source.streams.LiveCameras`
feeding the same :class:`cubetrack.app.tracker.Tracker` that replays recordings
(:func:`cubetrack.app.track.track_recording`); only the source differs.

- :func:`track_live`: the config's camera URLs -> ``<out>/<robot>.tum`` and ``.jsonl``, written
  and flushed as poses come, optionally recording the session as it goes;
- :func:`record_live`: the config's camera URLs -> a recording folder (contracts §3) that
  ``cubetrack track --recording`` replays.

Both run until ``duration_s`` has passed, ``stop`` is set, or Ctrl-C (KeyboardInterrupt), which
ends the session like the end of the duration: everything received so far is kept and the
result says ``interrupted``. A status callback gets a :class:`LiveStatus` every ``status_every_s``.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import shutil
import statistics
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from cubetrack.app.camera_workers import FORECAST_EVERY_S, CameraProcesses, forecast_of
from cubetrack.app.config import config_params
from cubetrack.app.outputs import open_outputs
from cubetrack.app.parallel import FramePool, LiveParams, WorkerKind, by_capture_time
from cubetrack.app.tracker import FrameResult, FrameWorker, StageParams, Tracker, TrackStats
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample
from cubetrack.core.errors import ConfigError
from cubetrack.core.geometry import quat_xyzw_from_R
from cubetrack.core.records import CameraHealth, CameraView, Frame, TrackedPose
from cubetrack.fuse.base import Fusion
from cubetrack.io.camera_info import read_camera_info
from cubetrack.io.config import TrackerConfig
from cubetrack.io.recording import CameraEntry, RecordingWriter
from cubetrack.sink.base import Sink
from cubetrack.source.clock import ClockFitMethod, ClockSync
from cubetrack.source.streams import CameraStats, ClockReading, LiveCameras, SourceParams

log = logging.getLogger(__name__)


def source_params(config: TrackerConfig) -> SourceParams:
    """The ``[source]`` section of a tracker config (read by :func:`cubetrack.app.config.config_params`)."""
    return config_params(config).source


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
    return {c.name: read_camera_info(c.camera_info) for c in config.cameras}


@dataclass(frozen=True, slots=True)
class LiveStatus:
    """A periodic snapshot of a live session (rates over the last interval)."""

    elapsed_s: float
    frames_per_s: dict[str, float]
    poses_per_s: dict[str, float]
    latency_s: float | None  # median pose latency over the interval (capture -> pose output)
    cameras: dict[str, CameraStats]
    queued: int
    arrival_latency_s: float | None = None  # median over the interval of frame arrival -> pose output

    def line(self) -> str:
        """One status line, e.g. ``12s robot 7.4 poses/s | cam1 7.5 fps ... | latency 4/51 ms | ...``
        (arrival -> pose / capture -> pose, medians)."""
        parts = [f"{self.elapsed_s:5.0f}s"]
        if self.poses_per_s:
            parts.append(" ".join(f"{r} {v:.1f} poses/s" for r, v in self.poses_per_s.items()))
        parts.append(" ".join(f"{c} {v:.1f} fps" for c, v in self.frames_per_s.items()))
        if self.poses_per_s:
            parts.append(f"latency {_ms(self.arrival_latency_s)}/{_ms(self.latency_s)} ms")
        bad = sum(s.bad for s in self.cameras.values())
        reconnects = sum(s.reconnects for s in self.cameras.values())
        dropped = sum(s.dropped for s in self.cameras.values())
        clock = "/".join(str(s.clock_samples) for s in self.cameras.values())
        down = [c for c, s in self.cameras.items() if not s.connected]
        tail = f"bad {bad} reconnects {reconnects} dropped {dropped} clock {clock}"
        if down:
            tail += " down: " + ",".join(down)
        parts.append(tail)
        return " | ".join(parts)


def _ms(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds * 1000:.0f}"


class _Rates:
    """Turns counters into per-interval rates for :class:`LiveStatus`."""

    def __init__(self, live: LiveCameras, robots: list[str]):
        self.live = live
        self.robots = robots
        self.start = time.monotonic()
        self.last = self.start
        self.frames = {c: 0 for c in live.urls}
        self.poses = {r: 0 for r in robots}
        self.latencies: list[float] = []
        self.arrival_latencies: list[float] = []

    def add_poses(self, poses: list[TrackedPose]) -> None:
        for pose in poses:
            if not pose.predicted:
                self.latencies.append(pose.latency_s)
            if pose.arrival_latency_s is not None:
                self.arrival_latencies.append(pose.arrival_latency_s)

    def snapshot(self, poses_total: dict[str, int]) -> LiveStatus:
        now = time.monotonic()
        dt = max(1e-6, now - self.last)
        cams = self.live.stats()
        fps = {c: (s.frames - self.frames[c]) / dt for c, s in cams.items()}
        pps = {r: (poses_total.get(r, 0) - self.poses[r]) / dt for r in self.robots}
        status = LiveStatus(now - self.start, fps, pps, _median(self.latencies), cams, self.live.pending(),
                            _median(self.arrival_latencies))
        self.frames = {c: s.frames for c, s in cams.items()}
        self.poses = {r: poses_total.get(r, 0) for r in self.robots}
        self.latencies, self.arrival_latencies = [], []
        self.last = now
        return status


def _median(values: list[float]) -> float | None:
    return statistics.median(values) if values else None


class SessionMedian:
    """The median of a whole session's latencies (seconds) in fixed memory: counts in bins 0.5 %
    wide on a log scale from 10 µs to 1000 s (values at or below 10 µs count as 0, those above in
    the top bin, about 1000 s), so a session of hours does not keep a float per pose (a list did: +25 MB in 10
    minutes at 16 cameras x 30 fps). :meth:`median` is within 0.25 % of the exact median."""

    LOW_S, HIGH_S, STEP = 1e-5, 1e3, 1.005
    _LOG_STEP = math.log(STEP)
    BINS = 2 + math.ceil(math.log(HIGH_S / LOW_S) / _LOG_STEP)

    def __init__(self) -> None:
        self.counts = [0] * self.BINS
        self.count = 0

    def add(self, value_s: float) -> None:
        i = 0 if value_s <= self.LOW_S else min(self.BINS - 1, 1 + int(math.log(value_s / self.LOW_S) / self._LOG_STEP))
        self.counts[i] += 1
        self.count += 1

    def median(self) -> float | None:
        """The middle bin's centre (None before any value)."""
        if not self.count:
            return None
        seen, half = 0, self.count / 2.0
        for i, n in enumerate(self.counts):  # noqa: B007 (i: the bin found, read after the loop)
            seen += n
            if seen >= half:
                break
        return 0.0 if i == 0 else self.LOW_S * self.STEP ** (i - 0.5)


HEALTH_EVERY_S = 1.0  # camera health snapshots for the outputs, per camera
IDLE_WAIT_S = 0.1  # a live loop waits at most this long for work between its periodic duties


class _Health:
    """Each camera's :class:`CameraHealth` for the outputs (the dashboard, Foxglove, Zenoh),
    taken every ``HEALTH_EVERY_S``: the source's counters, frames/s and mean JPEG size over the
    interval, the median transfer latency (arrival - capture) of the frames processed in it, and
    the camera's clock fit (offset and drift, NaN until a ``/time`` round trip is known)."""

    def __init__(self, live: LiveCameras, clocks: dict[str, ClockSync], clock: Callable[[], float]):
        self.live, self.clocks, self.clock = live, clocks, clock
        self.last = time.monotonic()
        self.counts = {c: (0, 0) for c in live.urls}  # frames, bytes at the last snapshot
        self.jpeg_bytes = {c: 0 for c in live.urls}
        self.transfer: dict[str, list[float]] = {c: [] for c in live.urls}

    def frame(self, frame: Frame, capture_time_s: float) -> None:
        self.transfer[frame.camera].append(frame.host_time_s - capture_time_s)

    def snapshots(self) -> list[CameraHealth]:
        now = time.monotonic()
        dt, self.last = max(1e-6, now - self.last), now
        out = []
        for name, s in self.live.stats().items():
            frames, size = self.counts[name]
            if s.frames > frames:
                self.jpeg_bytes[name] = (s.bytes - size) // (s.frames - frames)
            self.counts[name] = (s.frames, s.bytes)
            fit = self.clocks[name].fit() if name in self.clocks else None
            synced = fit is not None and fit.method is ClockFitMethod.ROUND_TRIP
            transfer = _median(self.transfer[name])
            self.transfer[name] = []
            out.append(CameraHealth(name, self.clock(), s.connected, (s.frames - frames) / dt, s.frames, s.dropped,
                                    s.bad, s.reconnects, fit.offset_s if synced else math.nan,
                                    fit.drift * 1e6 if synced else math.nan,
                                    math.nan if transfer is None else transfer, self.jpeg_bytes[name], s.last_error))
        return out


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


def _session_over(started: float, duration_s: float | None, stop: threading.Event | None) -> bool:
    if stop is not None and stop.is_set():
        return True
    return duration_s is not None and time.monotonic() - started >= duration_s


def idle_wait_s(params: StageParams) -> float:
    """How long a live loop waits for work at most: ``IDLE_WAIT_S``, or with a fixed lag half its
    ``smooth_margin_s`` (so a held pose whose time is up leaves within that of it, even while no
    frame comes)."""
    fp = params.filter
    return IDLE_WAIT_S if fp.smooth_lag_s == 0 else min(IDLE_WAIT_S, max(0.005, fp.smooth_margin_s / 2))


def predicted_poses(fusion: Fusion, robots: Sequence[str], now_s: float) -> list[TrackedPose]:
    """Each tracked robot's pose predicted to ``now_s`` by the fusion's motion model (none for a
    robot that is not tracked or no longer seen; none from fusions without a motion model)."""
    out = []
    for robot in robots:
        T = fusion.predicted_pose(robot, now_s)
        if T is not None:
            out.append(TrackedPose(robot, now_s, T[:3, 3].copy(), quat_xyzw_from_R(T[:3, :3]), (), (), 0.0,
                                   predicted=True))
    return out


def track_live(config: TrackerConfig, extrinsics: dict[str, CameraExtrinsics] | None, out_dir: str | Path,
               params: StageParams | None = None, source: SourceParams | None = None, *,
               duration_s: float | None = None, record_to: str | Path | None = None,
               stop: threading.Event | None = None, status: Callable[[LiveStatus], None] | None = None,
               status_every_s: float = 2.0, clock: Callable[[], float] = time.time,
               sinks: Sequence[Sink] = (), live_params: LiveParams | None = None) -> LiveResult:
    """Track every robot of ``config`` live from its cameras' URLs, writing ``<out_dir>/<robot>.tum``
    and ``.jsonl`` (flushed per pose). ``record_to``: also record the session there (everything that
    arrived, including frames the tracker had to drop). Frames are stamped with their capture
    time through each camera's ``/time`` round trips, exactly as in a replay of the recording.

    Per-frame work runs on ``[live] workers`` (:mod:`cubetrack.app.parallel`); this thread is
    the one ordered consumer: it plans each frame when a worker is free (the fusion's prediction
    tells detection where to look), fuses each result as soon as it is ready, and takes the
    clock samples. A frame still waiting when its camera's next one arrives is dropped (counted
    per camera); frames of a camera whose clock is not known yet are given up (counted). Each
    pose's latencies are taken when it is handed to the outputs. With ``[fusion]
    output_rate_hz``, each tracked robot's pose predicted to now is output at that rate as well.
    With ``[filter] smooth_lag_s``, poses held for it leave once their time is up on this clock
    (:meth:`~cubetrack.app.tracker.Tracker.release`), frames or not. ``sinks``: other outputs,
    fed the same poses."""
    settings = config_params(config)
    params = params or settings.stages
    source = source or settings.source
    live_params = live_params or settings.live
    urls = live_camera_urls(config)
    intrinsics = live_intrinsics(config)
    tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, params, synced_cameras=frozenset(urls))
    recorder = _Recorder(record_to, config, urls) if record_to is not None else None
    outputs, files = open_outputs(config, intrinsics, extrinsics, out_dir, sinks)
    latencies, arrival_latencies = SessionMedian(), SessionMedian()
    interrupted = False
    started = time.monotonic()
    robots = [r.name for r in config.robots]
    tick_s = 1.0 / params.fusion.output_rate_hz if params.fusion.output_rate_hz > 0 else None
    idle_s = idle_wait_s(params)
    wake = threading.Event()

    def emit(poses: list[TrackedPose], now_s: float) -> None:
        """Output poses the tracker made for ``now_s``, their latencies moved to this moment."""
        delay_s = clock() - now_s
        poses = [pose if pose.predicted else dataclasses.replace(
            pose, latency_s=pose.latency_s + delay_s,
            arrival_latency_s=None if pose.arrival_latency_s is None else pose.arrival_latency_s + delay_s)
            for pose in poses]
        for pose in poses:
            outputs.pose(pose)
            if not pose.predicted:
                latencies.add(pose.latency_s)
            if pose.arrival_latency_s is not None:
                arrival_latencies.add(pose.arrival_latency_s)
        rates.add_poses(poses)

    def take_events() -> None:
        """Clock samples always; frames while a worker is free, the freshest first (the others
        wait in the source, one per camera, until a newer frame replaces them). Until the first
        worker has started, this thread does the per-frame work itself."""
        while (event := live.get(0, frames=pool.idle() > 0 or not pool.ready, newest_first=True)) is not None:
            if isinstance(event, ClockReading):
                emit(tracker.add_clock_sample(event.camera, event.sample), event.sample.host_recv_s)
            elif (job := tracker.admit(event, hold=False)) is not None:
                if pool.ready:
                    pool.submit(job)
                else:
                    fuse(tracker.worker.work(job))

    def fuse(result: FrameResult) -> None:
        now_s = clock()
        emit(tracker.fuse(result, now_s), now_s)
        health.frame(result.job.frame, result.job.capture_time_s)
        if outputs.wants_views:  # the frame and what detection found in it, for outputs that show images
            frame = result.job.frame
            found = tuple(d for sighting in result.sightings for d in sighting.detections)
            outputs.camera_view(CameraView(frame.camera, frame.seq, result.job.capture_time_s, frame.jpeg, found))

    def fuse_results() -> None:
        for result in by_capture_time(pool.take()):
            fuse(result)

    def wake_for_source() -> None:
        """A frame or clock sample came: worth waking for only when a worker could take a frame
        (otherwise the next result wakes this thread; clock samples can wait that long)."""
        if pool.idle() or not pool.ready:
            wake.set()

    next_forecast = [0.0]

    def take_from_cameras(timeout_s: float) -> None:
        """Camera worker processes: wait up to ``timeout_s`` for what they send; their clock
        samples, then their results, oldest capture first; back goes how many were taken and,
        at most every ``FORECAST_EVERY_S``, the fusion's new forecast."""
        results, readings = live.take(timeout_s)
        for reading in readings:
            emit(tracker.add_clock_sample(reading.camera, reading.sample), reading.sample.host_recv_s)
        for result in by_capture_time(results):
            tracker.stats.frames += 1
            fuse(result)
        if results:
            now_s = clock()
            forecast = None
            if now_s >= next_forecast[0]:
                next_forecast[0] = now_s + FORECAST_EVERY_S
                forecast = forecast_of(tracker.fusion, robots, now_s)
            live.forecast(forecast)

    def step(timeout_s: float) -> None:
        """Wait up to ``timeout_s`` for something to do, then do it."""
        if pool is None:
            take_from_cameras(timeout_s)
        else:
            wake.wait(timeout_s)
            wake.clear()
            fuse_results()
            take_events()

    def working() -> bool:
        """Work that had arrived when the session ended is still being done."""
        if pool is None:
            return live.running or live.pending() > 0
        return pool.busy() > 0 or live.pending() > 0

    if live_params.worker_kind is WorkerKind.CAMERA_PROCESS and recorder is not None:
        log.warning("recording: frames are recorded by this process, so they are read here and processed by "
                    "worker threads instead of camera worker processes")
    live_params = dataclasses.replace(live_params, worker_kind=live_params.kind_for(len(urls), recorder is not None))
    if live_params.worker_kind is WorkerKind.CAMERA_PROCESS:
        pool = None
        make_tracker = functools.partial(Tracker, intrinsics, config.world, config.robots, extrinsics, params,
                                         synced_cameras=frozenset(urls))
        live = CameraProcesses(urls, source, make_tracker, live_params.worker_count, tracker.worker.unpack,
                               views=outputs.wants_views, clock=clock)
    else:
        make_worker = functools.partial(FrameWorker, intrinsics, config.world, config.robots, tracker.T_world_cam,
                                        params)
        pool = FramePool(make_worker, live_params.worker_count, live_params.worker_kind, wake.set)
        live = LiveCameras(urls, source, on_frame=recorder.frame if recorder else None,
                           on_clock=recorder.clock if recorder else None, clock=clock, wake=wake_for_source)
    rates = _Rates(live, robots)
    health = _Health(live, tracker.clocks, clock)
    try:
        live.start()
        log.info("live tracking %d camera(s) with %d %s worker(s): %s", len(urls), live_params.worker_count,
                 live_params.worker_kind.value, ", ".join(f"{n} {u}" for n, u in urls.items()))
        next_status = started + status_every_s
        next_health = time.monotonic()
        next_tick = clock()
        try:
            while not _session_over(started, duration_s, stop):
                step(idle_s if tick_s is None else min(idle_s, max(0.0, next_tick - clock())))
                now_s = clock()
                emit(tracker.release(now_s), now_s)
                if tick_s is not None and now_s >= next_tick:
                    next_tick = (math.floor(now_s / tick_s) + 1) * tick_s  # the next tick of the rate's grid
                    emit(predicted_poses(tracker.fusion, robots, now_s), now_s)
                if status is not None and time.monotonic() >= next_status:
                    next_status += status_every_s
                    status(rates.snapshot(dict(tracker.stats.poses)))
                if time.monotonic() >= next_health:
                    next_health += HEALTH_EVERY_S
                    for snapshot in health.snapshots():
                        outputs.camera_health(snapshot)
            live.stop()
            while working():  # what had arrived when the session ended
                step(0.05)
        except KeyboardInterrupt:
            interrupted = True
            log.info("interrupted: finishing with what has arrived")
        live.stop()
        if pool is None:  # the frames the camera worker processes gave up
            tracker.stats.frames_before_clock_sync = live.before_clock()
            tracker.stats.frames += tracker.stats.frames_before_clock_sync
        now_s = clock()
        emit(tracker.finish(now_s), now_s)
        late = getattr(tracker.fusion, "stats", {})
        if late:
            log.info("fusion: %d sightings fused, %d of them late (folded in), %d steps re-applied after them",
                     sum(tracker.stats.estimates.values()) + tracker.stats.frames, late["late sighting"],
                     late["replayed sighting"])
    finally:
        live.stop()
        if pool is None:
            live.close()
        else:
            pool.close()
        outputs.close()
        if recorder is not None:
            recorder.close()
    return LiveResult(tracker.stats, live.stats(), files.outputs,
                      recorder.path if recorder else None, time.monotonic() - started, interrupted,
                      latencies.median(), arrival_latencies.median())


def record_live(config: TrackerConfig, out: str | Path, source: SourceParams | None = None, *,
                duration_s: float | None = None, stop: threading.Event | None = None,
                status: Callable[[LiveStatus], None] | None = None, status_every_s: float = 2.0,
                overwrite: bool = False, clock: Callable[[], float] = time.time) -> LiveResult:
    """Record the config's cameras into the recording folder ``out`` (contracts §3: frames,
    ``index.csv``, ``clock.csv``, ``recording.json`` with the source URLs, and ``camera_info/``
    copied from the config where it names one). Rows are flushed as they come, so whatever
    ends the session, everything recorded so far is kept."""
    source = source or source_params(config)
    urls = live_camera_urls(config)
    recorder = _Recorder(out, config, urls, overwrite)
    live = LiveCameras(urls, source, on_frame=recorder.frame, on_clock=recorder.clock, queue=False, clock=clock)
    rates = _Rates(live, [])
    interrupted = False
    started = time.monotonic()
    try:
        live.start()
        log.info("recording %d camera(s) into %s", len(urls), recorder.path)
        next_status = started + status_every_s
        try:
            while not _session_over(started, duration_s, stop):
                time.sleep(0.05)
                if live.failure is not None:
                    raise live.failure
                if status is not None and time.monotonic() >= next_status:
                    next_status += status_every_s
                    status(rates.snapshot({}))
        except KeyboardInterrupt:
            interrupted = True
            log.info("interrupted: keeping what was recorded")
    finally:
        live.stop()
        recorder.close()
    if live.failure is not None:
        raise live.failure
    return LiveResult(None, live.stats(), {}, recorder.path, time.monotonic() - started, interrupted, None)
