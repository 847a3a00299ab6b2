"""Offline tracking: frames (held anywhere) through the :class:`~cubetrack.app.tracker.Tracker`
into sinks, and the workflow that replays a recording folder into ``<out>/<robot>.tum`` and
``.jsonl`` with its run record.

:func:`track_frames` reads no file: frames, intrinsics, the world marker, cube layouts, clock
samples and params in, poses to a sink. :func:`track_recording` turns a tracker config and a
recording folder into those arguments (:mod:`cubetrack.app.config`) and writes the outputs.
"""

from __future__ import annotations

import functools
import gc
import logging
import os
import time
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2

from cubetrack.app.config import config_params, parameter_tables, recording_intrinsics
from cubetrack.app.outputs import open_outputs
from cubetrack.app.session import RunSpec, Session
from cubetrack.app.tracker import FrameProcessor, StageParams, Tracker, TrackStats
from cubetrack.app.watch_log import WatchLog
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample, WorldConfig
from cubetrack.core.errors import ConfigError
from cubetrack.core.frame_pool import FramePool, WorkerKind
from cubetrack.core.layout import CubeLayout
from cubetrack.core.progress import Progress
from cubetrack.core.records import Frame, FrameJob, FrameResult
from cubetrack.fuse.fusion import FilterFusion, FusionMethod
from cubetrack.fuse.smoother import smoothed_poses
from cubetrack.io.config import RobotConfig, TrackerConfig
from cubetrack.io.recording import Recording
from cubetrack.io.run import RUN_FILE
from cubetrack.sink.base import FileSink, Outputs, Sink

log = logging.getLogger(__name__)

__all__ = ["TrackResult", "recording_intrinsics", "replay_workers", "track_frames", "track_recording"]


SMOOTHED_DIR = "smoothed"  # track_recording(smooth=True) writes <out>/smoothed/<robot>.tum and .jsonl
REPLAY_LAG = 4  # a replay plans each frame with the fusion as it was this many frames earlier
MIN_FRAMES_FOR_WORKERS = 600  # shorter replays are done on one thread (worker processes take 1-2 s to start)


class _Replay:
    """The state of one replay (:func:`track_frames`): the frames planned and not fused yet, the
    jobs not handed out, the results done; each frame planned with the fusion as it was
    ``REPLAY_LAG`` frames before it, the planned ones fused in capture order."""

    def __init__(self, tracker: Tracker, output: Sink | Outputs, pool: FramePool | None,
                 clock_samples: Mapping[str, Sequence[ClockSample]]):
        self.tracker, self.output, self.pool = tracker, output, pool
        self.trips = sorted(((s.host_recv_s, camera, s) for camera, samples in clock_samples.items() for s in samples),
                            key=lambda item: (item[0], item[1]))
        self.next_trip = 0
        self.planned: deque[tuple[FrameJob | None, float]] = deque()  # in order, with the time each became available
        self.unsent: deque[FrameJob] = deque()  # planned jobs neither done here nor handed to a worker, oldest first
        self.done: dict[FrameJob, FrameResult] = {}

    def frame(self, frame: Frame) -> None:
        """Take the round trips completed before ``frame`` arrived, exactly as a live run has them
        (the frames held for a camera's first one are planned as they are released), then plan it."""
        tracker = self.tracker
        while self.next_trip < len(self.trips) and self.trips[self.next_trip][0] <= frame.host_time_s:
            _, camera, sample = self.trips[self.next_trip]
            for held, capture_time_s in tracker.released_frames(camera, sample):
                self._make_room()
                self._schedule(tracker.plan(held, capture_time_s), sample.host_recv_s)
            self.next_trip += 1
        self._make_room()
        self._schedule(tracker.admit(frame), frame.host_time_s)

    def drain(self) -> None:
        """Fuse every planned frame."""
        while self.planned:
            self._fuse_first_captured()

    def _hand_out(self) -> None:
        """Free worker slots take the newest unsent jobs (this thread will want the oldest first)."""
        pool = self.pool
        if pool is None:
            return
        if not pool.idle():
            pool.poll()  # results that came free a slot
        while self.unsent and pool.idle():
            pool.submit(self.unsent.pop())

    def _result(self, job: FrameJob) -> FrameResult:
        """``job``'s result: a worker's, else done here; rather than wait for a worker's, this thread
        does the oldest job no worker has, or takes ``job`` back if its worker has not started it,
        or else the newest job a worker has not started (while its worker does ``job``)."""
        done, pool = self.done, self.pool
        while job not in done:
            if pool is not None:
                pool.poll()  # results already there (a slot holds every planned job: nothing else reads them)
                done.update((r.job, r) for r in pool.take())
                if job in done:
                    break
            if self.unsent:
                todo = self.unsent.popleft()
                done[todo] = self.tracker.processor.work(todo)
            elif pool is not None and pool.reclaim(job):  # its worker had not started it (busy, or not given a core)
                done[job] = self.tracker.processor.work(job)
            elif pool is not None and (newer := pool.reclaim_newest()) is not None:  # a worker behind: share
                done[newer] = self.tracker.processor.work(newer)
            elif pool is not None:
                pool.wait(1.0)
        return done.pop(job)

    def _fuse_first_captured(self) -> None:
        """Fuse the planned frame captured first (frames come in arrival order: taking the
        ``REPLAY_LAG`` planned ones in capture order, fewer sightings reach the fusion late, to be
        folded in by re-applying the newer ones)."""
        planned = self.planned
        first = min(range(len(planned)), key=lambda i: _capture_order(planned[i][0]))
        job, now_s = planned[first]
        del planned[first]
        if job is None:
            return
        poses = self.tracker.fuse(self._result(job), now_s)
        # a fixed lag's poses whose time is up once every frame that came before this one did is fused
        poses += self.tracker.release(min((t for _, t in planned), default=now_s))
        for pose in poses:
            self.output.pose(pose)

    def _make_room(self) -> None:
        """Before a frame is planned: fuse what is ``REPLAY_LAG`` frames older."""
        if len(self.planned) == REPLAY_LAG:
            self._fuse_first_captured()

    def _schedule(self, job: FrameJob | None, now_s: float) -> None:
        """Queue a planned frame's work (for a worker or this thread), to be fused ``REPLAY_LAG`` frames later."""
        if job is not None:
            self.unsent.append(job)
            self._hand_out()
        self.planned.append((job, now_s))


def track_frames(frames: Iterable[Frame], intrinsics: Mapping[str, CameraIntrinsics], world: WorldConfig,
                 layouts: Mapping[str, CubeLayout], extrinsics: Mapping[str, CameraExtrinsics] | None,
                 output: Sink | Outputs, params: StageParams | None = None, *,
                 clock_samples: Mapping[str, Sequence[ClockSample]] | None = None,
                 progress: Progress | None = None, frame_count: int = 0, pool: FramePool | None = None,
                 smoothed: Sink | None = None, session: Session | None = None,
                 watch_log: WatchLog | None = None) -> TrackStats:
    """Track ``frames`` (in host arrival order, as a live run receives them) and hand every fused
    pose to ``output``; returns the run's counters. ``smoothed`` (the filter fusion only): after the
    last frame, also hand it every robot's poses smoothed over the whole recording
    (:mod:`cubetrack.fuse.smoother`); ``output``'s poses are the same with or without it.

    ``layouts``: robot -> cube layout; ``extrinsics`` None with ``[track] camera_poses =
    world-marker``. ``clock_samples`` (camera -> its ``/time`` round trips) are fed in as they
    completed between the frames (by receive time), exactly as a live run has them; a camera
    with round trips has its first frames held until one arrives. ``frame_count`` only sizes
    the progress. ``session``: the runtime the replay's loop runs on (:mod:`cubetrack.app.session`;
    None: one of its own): Ctrl-C or SIGTERM end the replay there, the frames taken so far fused.
    ``watch_log``: with ``[camera_watch] enabled``, what the camera watching decides goes there as
    live (:meth:`cubetrack.app.watch_log.WatchLog.attach`: events, versioned extrinsics, the
    outputs' camera states); give it no executor, so that the re-calibration fits run inline and
    the replay stays reproducible.

    The per-frame work (decode, detection, per-camera estimates) runs on ``pool``'s workers
    (:func:`replay_pool`; None: on this thread) while this thread plans and fuses: a worker's
    free slot takes the newest planned job, and this thread does the oldest job no worker has
    when it needs its result, or would otherwise wait for a worker's, and takes a job back that
    its worker has not started yet (until the workers have started, it does them all). So that the result does not
    depend on how many workers there are or how fast each is, every frame is planned (its
    detection regions, the estimates asked for) with the fusion exactly as it was after the
    frames up to ``REPLAY_LAG`` frames before it, and the results are fused in capture order
    within each window of ``REPLAY_LAG`` planned frames: a replay is the same, bit for bit, with
    one thread or any number of workers, run after run.
    """
    params = params or StageParams()
    if smoothed is not None:
        _check_smoothable(params)
    clock_samples = clock_samples or {}
    synced = frozenset(c for c, samples in clock_samples.items() if samples)
    robots = tuple(RobotConfig(name, layout) for name, layout in layouts.items())
    tracker = Tracker(dict(intrinsics), world, robots, dict(extrinsics) if extrinsics is not None else None,
                      params, synced, defer_views=pool is not None)  # the workers project the cubes into regions
    trail = tracker.fusion if isinstance(tracker.fusion, FilterFusion) else None  # --smooth: the filter's
    if smoothed is not None and trail is not None:
        trail.keep_trail()
    if watch_log is not None:
        watch_log.attach(tracker, output)
    replay = _Replay(tracker, output, pool, clock_samples)
    session = session or Session()
    numbered = enumerate(frames, start=1)

    def step(timeout_s: float) -> None:
        item = next(numbered, None)
        if item is None:
            session.complete()
            return
        replay.frame(item[1])
        if progress is not None:
            progress("track", item[0], frame_count)

    freeze = gc.get_freeze_count() == 0  # (a caller that froze its own objects keeps them frozen)
    if freeze:
        gc.freeze()  # start-up's objects (modules, compiled kernels: ~160,000) leave the replay's collections
    try:
        session.run(step, drained=replay.drain)
    finally:
        if freeze:
            gc.unfreeze()
    for pose in tracker.finish():
        output.pose(pose)
    if smoothed is not None and trail is not None:
        for i, robot in enumerate(layouts, start=1):
            for pose in smoothed_poses(trail.trail(robot, tracker.last_now_s), tracker.last_now_s):
                smoothed.pose(pose)
            if progress is not None:
                progress("smooth", i, len(layouts))
    return tracker.stats


def _check_smoothable(params: StageParams) -> None:
    """Only the filter fusion's tracks can be smoothed (the paper's fusions keep no state)."""
    if params.fusion.method is not FusionMethod.FILTER:
        raise ConfigError(f"smoothing (--smooth) needs [fusion] method = filter, not {params.fusion.method.value}")


def replay_workers(sample_s: float = 0.2) -> int:
    """Frame worker processes a replay starts here by default: one per idle core beyond the
    first (the replay's thread plans, fuses and does the jobs no worker has), the idle cores
    measured over ``sample_s`` from /proc/stat (elsewhere: every core counts as idle). On two
    cores: one worker when both are idle, where that replays about 1.4x as fast as one thread,
    none when other work keeps about a core busy, where a worker makes the replay slower
    (docs/live.md)."""
    cores = os.cpu_count() or 1
    if cores == 1:
        return 0
    before = _cpu_idle_busy()
    time.sleep(sample_s)
    after = _cpu_idle_busy()
    if before is None or after is None or after == before:
        return cores - 1
    idle, busy = after[0] - before[0], after[1] - before[1]
    return min(cores - 1, max(0, round(cores * idle / max(idle + busy, 1)) - 1))


def _cpu_idle_busy() -> tuple[int, int] | None:
    """All cores' idle and busy clock ticks since boot (the first line of /proc/stat), or None."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            ticks = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0)  # idle + iowait
    return idle, sum(ticks[:8]) - idle  # user nice system idle iowait irq softirq steal (guest is in user)


def _capture_order(job: FrameJob | None) -> tuple[float, str, int]:
    """Sort key of a planned frame: capture time, then camera and sequence number (a frame not
    planned, None, first: it is only dropped)."""
    if job is None:
        return (float("-inf"), "", 0)
    return (job.capture_time_s, job.frame.camera, job.frame.seq)


def replay_pool(intrinsics: Mapping[str, CameraIntrinsics], world: WorldConfig, layouts: Mapping[str, CubeLayout],
                extrinsics: Mapping[str, CameraExtrinsics] | None, params: StageParams, workers: int,
                depth: int | None = None) -> FramePool:
    """``workers`` frame worker processes for :func:`track_frames` with these arguments, each
    taking up to ``depth`` jobs at a time (default: their share of the ``REPLAY_LAG`` frames planned
    ahead, so that a worker that keeps up does every job and the replay's thread only plans and
    fuses; one that falls behind has its newest unstarted jobs taken back by that thread). They
    start in the background; close the pool when done."""
    robots = tuple(RobotConfig(name, layout) for name, layout in layouts.items())
    T_world_cam = {name: e.T_world_cam for name, e in (extrinsics or {}).items()}
    make_worker = functools.partial(FrameProcessor, dict(intrinsics), world, robots, T_world_cam, params)
    return FramePool(make_worker, workers, WorkerKind.PROCESS, depth=depth or -(-REPLAY_LAG // workers))


@dataclass(frozen=True, slots=True)
class TrackResult:
    """What :func:`track_recording` produced: the stats, the files per robot, the frames skipped
    by reason, the run record, the smoothed poses' files per robot (with ``smooth``), the
    signal that ended the replay early (Ctrl-C: ``SIGINT``; None: it ran to the end) and, with
    ``[camera_watch] enabled``, what the camera watching kept (its events, status lines and
    versioned extrinsics files; None when the cameras were not watched)."""

    stats: TrackStats
    outputs: dict[str, tuple[Path, Path]]
    skipped: dict[str, int]
    run_record: Path
    smoothed: dict[str, tuple[Path, Path]] = field(default_factory=dict)
    ended_by: str | None = None
    camera_watch: WatchLog | None = None


def track_recording(config: TrackerConfig, recording: Recording,
                    extrinsics: dict[str, CameraExtrinsics] | None, out_dir: str | Path,
                    params: StageParams | None = None, progress: Progress | None = None,
                    sinks: Sequence[Sink] = (), *, extrinsics_path: str | Path | None = None,
                    workers: int | None = None, smooth: bool = False,
                    update_extrinsics: bool = False) -> TrackResult:
    """Replay a recording through the tracker, writing ``<out_dir>/<robot>.tum`` and ``.jsonl``,
    feeding ``sinks`` (other outputs) the same poses, and recording how in ``<out_dir>/run.json``
    (``extrinsics_path``: where ``extrinsics`` were read, for that record). ``smooth``: also
    write every robot's poses smoothed over the whole recording to
    ``<out_dir>/smoothed/<robot>.tum`` and ``.jsonl`` (each JSONL line ``"smoothed": true``; the
    filter fusion only), the causal files unchanged. ``params`` None: the
    config's sections. ``workers``: frame worker processes beside this thread (None:
    :func:`replay_workers`; 0, and for recordings of fewer than ``MIN_FRAMES_FOR_WORKERS``
    frames: none, one thread); the poses are the same whatever their number (:func:`track_frames`).
    With ``[camera_watch] enabled`` the session keeps what the watching learnt as a live one does
    (:mod:`cubetrack.app.watch_log`: ``<out_dir>/camera_watch.jsonl``, the log, run.json, a
    re-calibrated camera's new pose in a versioned extrinsics file beside them, and over
    ``extrinsics_path`` with ``update_extrinsics``), its re-calibration fits inline (reproducible)."""
    if workers is not None and workers < 0:
        raise ConfigError(f"frame worker processes must not be negative, got {workers}")
    params = params or config_params(config).stages
    if smooth:
        _check_smoothable(params)
    cameras = recording.camera_names
    clock = {c: recording.clock_samples(c) for c in cameras}
    for camera in cameras:
        if not clock[camera]:
            log.warning("%s: no clock.csv; frames are stamped from their arrival times (late by the transfer time)",
                        camera)
    intrinsics = recording_intrinsics(config, recording)
    out_dir = Path(out_dir)
    run = RunSpec(out_dir / RUN_FILE, "track", parameter_tables(params),
                  {"config": config.path, "recording": recording.path, "extrinsics": extrinsics_path},
                  {"smoothed": SMOOTHED_DIR} if smooth else {})
    total = sum(len(recording.index(c)) for c in cameras)
    if total < MIN_FRAMES_FOR_WORKERS:
        workers = 0
    elif workers is None:
        workers = replay_workers()
    layouts = {r.name: r.layout for r in config.robots}
    outputs, files = open_outputs(config, intrinsics, extrinsics, out_dir, sinks)
    watch_log = WatchLog(out_dir, extrinsics or {}, extrinsics_path if update_extrinsics else None)
    smoothed = FileSink(out_dir / SMOOTHED_DIR, tuple(layouts)) if smooth else None
    pool = replay_pool(intrinsics, config.world, layouts, extrinsics, params, workers) if workers else None
    opencv_threads = cv2.getNumThreads()
    if pool is not None:
        cv2.setNumThreads(1)  # the worker processes have the other cores (each runs OpenCV on one thread)
    try:
        session = Session(record=run)
        stats = track_frames(recording.merged_frames(), intrinsics, config.world, layouts, extrinsics, outputs,
                             params, clock_samples=clock, progress=progress, frame_count=total, pool=pool,
                             smoothed=smoothed, session=session, watch_log=watch_log)
    finally:
        cv2.setNumThreads(opencv_threads)
        if pool is not None:
            pool.close()
        outputs.close()
        if smoothed is not None:
            smoothed.close()
    skipped = dict(recording.skipped)
    if stats.corrupt_frames:
        skipped["corrupt frame"] = stats.corrupt_frames
    watched = watch_log if watch_log.attached else None
    session.finish({"frames": stats.frames, "of_frames": total, "poses": dict(stats.poses), "skipped": skipped,
                    **(watched.summary() if watched is not None else {})})
    return TrackResult(stats, files.outputs, skipped, run.path, smoothed.outputs if smoothed is not None else {},
                       session.ended_by, watched)
