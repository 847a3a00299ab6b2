"""Offline tracking: frames (held anywhere) through the :class:`~cubetrack.app.tracker.Tracker`
into sinks, and the workflow that replays a recording folder into ``<out>/<robot>.tum`` and
``.jsonl`` with its run record.

:func:`track_frames` reads no file: frames, intrinsics, the world marker, cube layouts, clock
samples and params in, poses to a sink. :func:`track_recording` turns a tracker config and a
recording folder into those arguments (:mod:`cubetrack.app.config`) and writes the outputs.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from cubetrack.app.config import config_params, parameter_tables, recording_intrinsics
from cubetrack.app.outputs import open_outputs
from cubetrack.app.tracker import StageParams, Tracker, TrackStats
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample, WorldConfig
from cubetrack.core.layout import CubeLayout
from cubetrack.core.progress import Progress
from cubetrack.core.records import Frame
from cubetrack.io.config import RobotConfig, TrackerConfig
from cubetrack.io.recording import Recording
from cubetrack.io.run import RUN_FILE, write_run_record
from cubetrack.sink.base import Outputs, Sink

log = logging.getLogger(__name__)

__all__ = ["TrackResult", "recording_intrinsics", "track_frames", "track_recording"]


def track_frames(frames: Iterable[Frame], intrinsics: Mapping[str, CameraIntrinsics], world: WorldConfig,
                 layouts: Mapping[str, CubeLayout], extrinsics: Mapping[str, CameraExtrinsics] | None,
                 output: Sink | Outputs, params: StageParams = StageParams(), *,
                 clock_samples: Mapping[str, Sequence[ClockSample]] | None = None,
                 progress: Progress | None = None, frame_count: int = 0) -> TrackStats:
    """Track ``frames`` (in host arrival order, as a live run receives them) and hand every fused
    pose to ``output``; returns the run's counters.

    ``layouts``: robot -> cube layout; ``extrinsics`` None with ``[track] camera_poses =
    world-marker``. ``clock_samples`` (camera -> its ``/time`` round trips) are fed in as they
    completed between the frames (by receive time), exactly as a live run has them; a camera
    with round trips has its first frames held until one arrives. ``frame_count`` only sizes
    the progress.
    """
    clock_samples = clock_samples or {}
    synced = frozenset(c for c, samples in clock_samples.items() if samples)
    robots = tuple(RobotConfig(name, layout) for name, layout in layouts.items())
    tracker = Tracker(dict(intrinsics), world, robots, dict(extrinsics) if extrinsics is not None else None,
                      params, synced)
    trips = sorted(((s.host_recv_s, camera, s) for camera, samples in clock_samples.items() for s in samples),
                   key=lambda item: (item[0], item[1]))
    next_trip = 0
    for i, frame in enumerate(frames, start=1):
        # round trips completed before this frame arrived, exactly as a live run has them
        while next_trip < len(trips) and trips[next_trip][0] <= frame.host_time_s:
            for pose in tracker.add_clock_sample(trips[next_trip][1], trips[next_trip][2]):
                output.pose(pose)
            next_trip += 1
        for pose in tracker.process(frame):
            output.pose(pose)
        if progress is not None:
            progress("track", i, frame_count)
    for pose in tracker.finish():
        output.pose(pose)
    return tracker.stats


@dataclass(frozen=True, slots=True)
class TrackResult:
    """What :func:`track_recording` produced: the stats, the files per robot, the frames skipped
    by reason, and the run record."""

    stats: TrackStats
    outputs: dict[str, tuple[Path, Path]]
    skipped: dict[str, int]
    run_record: Path


def track_recording(config: TrackerConfig, recording: Recording,
                    extrinsics: dict[str, CameraExtrinsics] | None, out_dir: str | Path,
                    params: StageParams | None = None, progress: Progress | None = None,
                    sinks: Sequence[Sink] = (), *, extrinsics_path: str | Path | None = None) -> TrackResult:
    """Replay a recording through the tracker, writing ``<out_dir>/<robot>.tum`` and ``.jsonl``,
    feeding ``sinks`` (other outputs) the same poses, and recording how in ``<out_dir>/run.json``
    (``extrinsics_path``: where ``extrinsics`` were read, for that record). ``params`` None: the
    config's sections."""
    params = params or config_params(config).stages
    cameras = recording.camera_names
    clock = {c: recording.clock_samples(c) for c in cameras}
    for camera in cameras:
        if not clock[camera]:
            log.warning("%s: no clock.csv; frames are stamped from their arrival times (late by the transfer time)",
                        camera)
    intrinsics = recording_intrinsics(config, recording)
    out_dir = Path(out_dir)
    run_record = write_run_record(
        out_dir / RUN_FILE, "track", parameter_tables(params),
        {"config": config.path, "recording": recording.path, "extrinsics": extrinsics_path})
    total = sum(len(recording.index(c)) for c in cameras)
    outputs, files = open_outputs(config, intrinsics, extrinsics, out_dir, sinks)
    try:
        stats = track_frames(recording.merged_frames(), intrinsics, config.world,
                             {r.name: r.layout for r in config.robots}, extrinsics, outputs, params,
                             clock_samples=clock, progress=progress, frame_count=total)
    finally:
        outputs.close()
    skipped = dict(recording.skipped)
    if stats.corrupt_frames:
        skipped["corrupt frame"] = stats.corrupt_frames
    return TrackResult(stats, files.outputs, skipped, run_record)
