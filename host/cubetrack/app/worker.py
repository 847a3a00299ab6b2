"""``cubetrack worker``: the per-camera half of tracking, published on Zenoh (docs/scaling.md).

A worker reads its cameras (:class:`cubetrack.source.LiveCameras`), stamps each frame with its
capture time through the camera's ``/time`` round trips and does the tracker's per-frame work
(:meth:`cubetrack.app.tracker.FrameWorker.work`: decode, detect, the camera's pose), then
publishes one sighting message per frame (:mod:`cubetrack.core.sighting_wire`) under
``cubetrack/sightings/<camera>``. The fusion (:mod:`cubetrack.app.fusion_service`) subscribes to
``cubetrack/sightings/*``. A worker holds no fusion state, so detection searches whole frames
(there is no prediction to search around) and per-camera estimates are made by the fusion, from
the corners, when it asks for one (as in one process: only then). Each running worker holds a
Zenoh liveliness token ``cubetrack/workers/<host>-<pid>``; the fusion reports workers coming and
going (a killed worker's token goes when its connection drops).

Zenoh: the fusion listens on ``tcp/127.0.0.1:7450`` and workers connect there (loopback by
default); either may start first, restart, or come and go.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
import socket
import threading
import time
from dataclasses import dataclass
from typing import Callable, Sequence

from cubetrack.app.config import config_params
from cubetrack.app.live import live_camera_urls, live_intrinsics
from cubetrack.app.tracker import CameraPoseSource, FrameResult, StageParams, Tracker, TrackStats
from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.core.errors import ConfigError
from cubetrack.core.sighting_wire import SightingMessage, WireClock, WireHealth, encode_sighting
from cubetrack.io.config import TrackerConfig
from cubetrack.sink.zenoh_session import ZenohEndpoints, open_session
from cubetrack.source.clock import ClockSync
from cubetrack.source.streams import CameraStats, ClockReading, LiveCameras, SourceParams

log = logging.getLogger(__name__)

SIGHTINGS_KEY = "cubetrack/sightings"  # one camera's sightings: cubetrack/sightings/<camera>
WORKERS_KEY = "cubetrack/workers"  # a liveliness token per running worker: cubetrack/workers/<host>-<pid>
FUSE_PORT = 7450


def fuse_endpoints(listen: tuple[str, ...] = (), connect: tuple[str, ...] = (), mode: str = "peer",
                   config_file=None) -> ZenohEndpoints:
    """The fusion's session: a peer listening on ``tcp/127.0.0.1:7450`` unless told otherwise."""
    default = () if connect or config_file is not None else (f"tcp/127.0.0.1:{FUSE_PORT}",)
    return ZenohEndpoints(mode, listen or default, connect, config_file)


def worker_endpoints(listen: tuple[str, ...] = (), connect: tuple[str, ...] = (), mode: str = "peer",
                     config_file=None) -> ZenohEndpoints:
    """A worker's session: a peer connecting to the fusion at ``tcp/127.0.0.1:7450`` (retried
    until it is there) unless told otherwise."""
    default = () if listen or config_file is not None else (f"tcp/127.0.0.1:{FUSE_PORT}",)
    return ZenohEndpoints(mode, listen, connect or default, config_file)


def sighting_key(camera: str) -> str:
    """The key expression ``camera``'s sightings are published under."""
    if not camera or re.search(r"[/*$#?\s]", camera):
        raise ConfigError(f"camera name {camera!r} cannot be a Zenoh key chunk (no '/', '*', '$', '#', '?' or spaces)")
    return f"{SIGHTINGS_KEY}/{camera}"


def worker_id() -> str:
    """This worker's name on the bus: host name and process id (a key chunk)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", f"{socket.gethostname()}-{os.getpid()}")


def sighting_message(result: FrameResult, clock: ClockSync, stats: CameraStats, with_pose: bool) -> SightingMessage:
    """What a worker publishes for one frame's per-frame work: the detections of every robot's
    markers (corners, not the image), the camera pose where it came from the frame itself."""
    frame = result.job.frame
    seen: dict[int, object] = {}
    for sighting in result.sightings:
        for d in sighting.detections:
            seen.setdefault(id(d), d)
    fit = clock.fit()
    pose = result.sightings[0].T_world_cam if with_pose and result.sightings else None
    return SightingMessage(frame.camera, frame.seq, frame.device_time_s, result.job.capture_time_s,
                           frame.host_time_s, result.outcome.value, tuple(seen.values()),
                           WireClock(fit.method.value, fit.offset_s, fit.drift, fit.device_ref_s),
                           WireHealth(stats.connected, stats.frames, stats.dropped, stats.bad, stats.reconnects), pose)


@dataclass(frozen=True, slots=True)
class WorkerResult:
    """What a worker session did: frames worked and published, per camera source counters."""

    stats: TrackStats
    published: int
    cameras: dict[str, CameraStats]
    duration_s: float
    interrupted: bool


def chosen_cameras(config: TrackerConfig, cameras: Sequence[str]) -> list[str]:
    """``cameras`` checked against the config (all of them when empty)."""
    known = [c.name for c in config.cameras]
    unknown = [c for c in cameras if c not in known]
    if unknown:
        raise ConfigError(f"{config.path}: no camera {', '.join(unknown)} (the config has {', '.join(known) or 'none'})")
    return list(cameras) or known


def run_worker(config: TrackerConfig, extrinsics: dict[str, CameraExtrinsics] | None, cameras: Sequence[str],
               endpoints: ZenohEndpoints, params: StageParams | None = None, source: SourceParams | None = None, *,
               duration_s: float | None = None, stop: threading.Event | None = None,
               status: Callable[[str], None] | None = None, status_every_s: float = 2.0,
               clock: Callable[[], float] = time.time) -> WorkerResult:
    """Read ``cameras`` of ``config`` live and publish each frame's sighting on Zenoh until
    ``duration_s``, ``stop`` or Ctrl-C. Frames of a camera whose clock is not known yet are given
    up (counted), as in ``track --live``."""
    settings = config_params(config)
    params = params or settings.stages
    source = source or settings.source
    names = chosen_cameras(config, cameras)
    urls = {n: u for n, u in live_camera_urls(config).items() if n in names}
    keys = {n: sighting_key(n) for n in names}
    intrinsics = {n: i for n, i in live_intrinsics(config).items() if n in names}
    tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, params, synced_cameras=frozenset(urls))
    with_pose = params.track.camera_poses is CameraPoseSource.WORLD_MARKER
    session = open_session(endpoints, "worker")
    publishers = {n: session.declare_publisher(k) for n, k in keys.items()}
    token = session.liveliness().declare_token(f"{WORKERS_KEY}/{worker_id()}")
    live = LiveCameras(urls, source, clock=clock)
    published = 0
    interrupted = False
    started = time.monotonic()
    next_status = started + status_every_s
    try:
        live.start()
        log.info("worker: %s -> Zenoh %s/*", ", ".join(names), SIGHTINGS_KEY)
        try:
            while not ((stop is not None and stop.is_set())
                       or (duration_s is not None and time.monotonic() - started >= duration_s)):
                event = live.get(0.1)
                if isinstance(event, ClockReading):
                    tracker.add_clock_sample(event.camera, event.sample)
                elif event is not None and (job := tracker.admit(event, hold=False)) is not None:
                    job = dataclasses.replace(job, regions=None, estimate_robots=frozenset())
                    result = tracker.worker.work(job)
                    message = sighting_message(result, tracker.clocks[event.camera],
                                               live.stats()[event.camera], with_pose)
                    publishers[event.camera].put(encode_sighting(message))
                    published += 1
                if status is not None and time.monotonic() >= next_status:
                    next_status += status_every_s
                    cams = live.stats()
                    status(f"{time.monotonic() - started:5.0f}s published {published} | "
                           + " ".join(f"{n} {s.frames} frames{'' if s.connected else ' (down)'}"
                                      for n, s in cams.items()))
        except KeyboardInterrupt:
            interrupted = True
    finally:
        live.stop()
        for publisher in publishers.values():
            publisher.undeclare()
        token.undeclare()
        session.close()
    return WorkerResult(tracker.stats, published, live.stats(), time.monotonic() - started, interrupted)
