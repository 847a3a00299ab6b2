"""Offline replay of a recording folder through the :class:`~cubetrack.app.tracker.Tracker`,
writing ``<out>/<robot>.tum`` and ``<out>/<robot>.jsonl``."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from cubetrack.app.outputs import open_outputs
from cubetrack.app.tracker import StageParams, Tracker, TrackStats
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics
from cubetrack.core.progress import Progress
from cubetrack.io.camera_info import read_camera_info
from cubetrack.io.config import TrackerConfig, camera_intrinsics_path
from cubetrack.io.recording import Recording
from cubetrack.sink.base import Sink

log = logging.getLogger(__name__)


def recording_intrinsics(config: TrackerConfig, recording: Recording) -> dict[str, CameraIntrinsics]:
    """Intrinsics of every camera of a recording (config's camera_info, else the recording's)."""
    return {
        name: read_camera_info(camera_intrinsics_path(config, name, recording.path))
        for name in recording.camera_names
    }


@dataclass(frozen=True, slots=True)
class TrackResult:
    """What :func:`track_recording` produced: the stats and the files per robot."""

    stats: TrackStats
    outputs: dict[str, tuple[Path, Path]]
    skipped: dict[str, int]


def track_recording(config: TrackerConfig, recording: Recording,
                    extrinsics: dict[str, CameraExtrinsics] | None, out_dir: str | Path,
                    params: StageParams | None = None, progress: Progress | None = None,
                    sinks: Sequence[Sink] = ()) -> TrackResult:
    """Replay a recording through the tracker, writing ``<out_dir>/<robot>.tum`` and ``.jsonl``
    and feeding ``sinks`` (other outputs) the same poses."""
    params = params or StageParams.from_config(config)
    synced = frozenset(c for c in recording.camera_names if recording.clock_samples(c))
    for camera in sorted(set(recording.camera_names) - synced):
        log.warning("%s: no clock.csv; frames are stamped from their arrival times (late by the transfer time)", camera)
    intrinsics = recording_intrinsics(config, recording)
    tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, params, synced)
    total = sum(len(recording.index(c)) for c in recording.camera_names)
    trips = sorted(
        ((s.host_recv_s, camera, s) for camera in recording.camera_names for s in recording.clock_samples(camera)),
        key=lambda item: (item[0], item[1]),
    )
    next_trip = 0
    outputs, files = open_outputs(config, intrinsics, extrinsics, out_dir, sinks)
    try:
        for i, frame in enumerate(recording.merged_frames(), start=1):
            # round trips completed before this frame arrived, exactly as a live run has them
            while next_trip < len(trips) and trips[next_trip][0] <= frame.host_time_s:
                for pose in tracker.add_clock_sample(trips[next_trip][1], trips[next_trip][2]):
                    outputs.pose(pose)
                next_trip += 1
            for pose in tracker.process(frame):
                outputs.pose(pose)
            if progress is not None:
                progress("track", i, total)
        for pose in tracker.finish():
            outputs.pose(pose)
    finally:
        outputs.close()
    skipped = dict(recording.skipped)
    if tracker.stats.corrupt_frames:
        skipped["corrupt frame"] = tracker.stats.corrupt_frames
    return TrackResult(tracker.stats, files.outputs, skipped)
