"""``cubetrack worker``: the per-camera half of tracking, published on Zenoh (docs/scaling.md).

A worker reads its cameras (:class:`cubetrack.source.streams.LiveCameras`), stamps each frame with its
capture time through the camera's ``/time`` round trips and does the tracker's per-frame work
(:meth:`cubetrack.app.tracker.FrameProcessor.work`: decode, detect, the camera's pose), then
publishes each frame (:mod:`cubetrack.io.sighting_wire`) as one sighting per robot whose markers it
holds (:func:`body_messages`), gathered over a pass over its cameras (at most ``BATCH_HOLD_S``) into one
message per fusion claiming robots (``cubetrack/shard-sightings/<fusion>/<worker>``) or per unclaimed robot
(``cubetrack/sightings/<worker>/<robot>``), a frame without any under ``cubetrack/sightings/<camera>``
(:class:`cubetrack.io.worker_bus.SightingBatches`: the fusion and its shards subscribe). A worker holds no fusion state,
so detection searches whole frames (there is no prediction to search around) and per-camera
estimates are made by the fusion, from the corners, when it asks for one (as in one process: only
then). Each running worker holds a Zenoh liveliness token ``cubetrack/workers/<host>-<pid>``; the
fusion reports workers coming and going (a killed worker's token goes when its connection drops).

Which worker reads which camera: named (``--cameras``) or automatic. Every worker holds a
liveliness token ``cubetrack/claims/<camera>/<worker>`` per camera it reads; an automatic worker
also holds ``cubetrack/pool/<worker>``. The cameras no named worker claims are shared among the
automatic workers by :func:`cubetrack.io.worker_bus.share_cameras` (the same answer in every worker that sees the same
tokens); a worker takes a camera of its share only once no other worker claims it, gives up
what is no longer its share, and on a double claim the greater worker name gives way. A dead
worker's tokens vanish with its connection, so the others take its cameras over
(docs/scaling.md).

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
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from cubetrack.app.config import config_params
from cubetrack.app.live import live_camera_urls, live_intrinsics
from cubetrack.app.session import Session
from cubetrack.app.tracker import CameraPoseSource, StageParams, Tracker, TrackStats
from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.core.errors import ConfigError
from cubetrack.core.records import Detection, Frame, FrameResult
from cubetrack.fuse.forecast import NO_FORECAST
from cubetrack.io.config import TrackerConfig
from cubetrack.io.sighting_wire import SightingMessage, WireClock, WireHealth, encode_sighting
from cubetrack.io.worker_bus import SIGHTINGS_KEY, WORKERS_KEY, Claims, SightingBatches, claim_key, sighting_key
from cubetrack.sink.zenoh_session import ZenohEndpoints, open_session
from cubetrack.source.clock import ClockSync
from cubetrack.source.streams import CameraStats, ClockReading, LiveCameras, SourceParams

log = logging.getLogger(__name__)

FUSE_PORT = 7450
BUS_LEASE_MS = 3000  # a worker or fusion silent this long (frozen, host gone) is dropped with its claims
CHECK_EVERY_S = 0.2  # how often an automatic worker compares its claims with its share


def fuse_endpoints(listen: tuple[str, ...] = (), connect: tuple[str, ...] = (), mode: str = "peer",
                   config_file=None) -> ZenohEndpoints:
    """The fusion's session: a peer listening on ``tcp/127.0.0.1:7450`` unless told otherwise."""
    default = () if connect or config_file is not None else (f"tcp/127.0.0.1:{FUSE_PORT}",)
    return ZenohEndpoints(mode, listen or default, connect, config_file, lease_ms=BUS_LEASE_MS)


def worker_endpoints(listen: tuple[str, ...] = (), connect: tuple[str, ...] = (), mode: str = "peer",
                     config_file=None) -> ZenohEndpoints:
    """A worker's session: a peer connecting to the fusion at ``tcp/127.0.0.1:7450`` (retried
    until it is there) unless told otherwise. It listens on a free loopback port, which the
    fusion passes on (Zenoh gossip) so that workers connect to each other and see each other's
    claims even while the fusion is away. A peer silent for ``BUS_LEASE_MS`` is dropped (Zenoh's
    default is 10 s): a frozen or unplugged worker's cameras are taken over within about that."""
    default = () if listen or config_file is not None else (f"tcp/127.0.0.1:{FUSE_PORT}",)
    own = () if config_file is not None else ("tcp/127.0.0.1:0",)
    return ZenohEndpoints(mode, listen or own, connect or default, config_file, lease_ms=BUS_LEASE_MS)


def worker_id() -> str:
    """This worker's name on the bus: host name and process id (a key chunk)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", f"{socket.gethostname()}-{os.getpid()}")


def sighting_message(result: FrameResult, clock: ClockSync, stats: CameraStats, with_pose: bool) -> SightingMessage:
    """One frame's per-frame work as one message: the detections of every robot's markers
    (corners, not the image), the camera pose where it came from the frame itself."""
    frame = result.job.frame
    seen: dict[int, Detection] = {}
    for sighting in result.sightings:
        for d in sighting.detections:
            seen.setdefault(id(d), d)
    fit = clock.fit()
    pose = result.sightings[0].T_world_cam if with_pose and result.sightings else None
    return SightingMessage(frame.camera, frame.seq, frame.device_time_s, result.job.capture_time_s,
                           frame.host_time_s, result.outcome.value, tuple(seen.values()),
                           WireClock(fit.method.value, fit.offset_s, fit.drift, fit.device_ref_s),
                           WireHealth(stats.connected, stats.frames, stats.dropped, stats.bad, stats.reconnects), pose,
                           result.dropped)


def body_messages(result: FrameResult, clock: ClockSync, stats: CameraStats,
                  with_pose: bool) -> list[SightingMessage]:
    """What a worker publishes for one frame: one message per robot whose markers it holds, with
    that robot's detections only (``body``; the frame's drop counts travel with the first), or
    the whole frame's message when it holds no robot's markers (contracts §7)."""
    whole = sighting_message(result, clock, stats, with_pose)
    return [dataclasses.replace(whole, detections=s.detections, body=s.robot, dropped=whole.dropped if i == 0 else {})
            for i, s in enumerate(result.sightings)] or [whole]


@dataclass(frozen=True, slots=True)
class WorkerResult:
    """What a worker session did: frames worked and published, per camera source counters
    (of its last reading of the camera), and each take-over and give-up as (seconds since the
    start, camera, True: taken / False: given up)."""

    stats: TrackStats
    published: int
    cameras: dict[str, CameraStats]
    duration_s: float
    interrupted: bool
    claims: tuple[tuple[float, str, bool], ...] = ()


def chosen_cameras(config: TrackerConfig, cameras: Sequence[str]) -> list[str]:
    """``cameras`` checked against the config (all of them when empty)."""
    known = [c.name for c in config.cameras]
    unknown = [c for c in cameras if c not in known]
    if unknown:
        raise ConfigError(f"{config.path}: no camera {', '.join(unknown)} "
                          f"(the config has {', '.join(known) or 'none'})")
    return list(cameras) or known


class ZenohWorker:
    """The cameras one ``cubetrack worker`` reads and publishes (see the module doc): each claimed
    camera's reader, publisher and claim token, the per-frame work on this thread."""

    def __init__(self, session: Any, tracker: Tracker, urls: dict[str, str], source: SourceParams,
                 clock: Callable[[], float], with_pose: bool):
        self.bus, self.tracker, self.urls, self.source, self.clock = session, tracker, urls, source, clock
        self.with_pose = with_pose
        self.me = worker_id()
        self.readers: dict[str, tuple[LiveCameras, Any]] = {}  # camera -> its reader, its claim token
        self.batches = SightingBatches(session, self.me)
        self.last_stats: dict[str, CameraStats] = {}
        self.claims: list[tuple[float, str, bool]] = []
        self.wake = threading.Event()
        self.published = 0
        self.started = time.monotonic()

    def take(self, camera: str) -> None:
        token = self.bus.liveliness().declare_token(claim_key(camera, self.me))
        live = LiveCameras({camera: self.urls[camera]}, self.source, clock=self.clock, wake=self.wake.set)
        self.readers[camera] = (live, token)
        live.start()
        self.claims.append((time.monotonic() - self.started, camera, True))
        log.info("worker %s: reading %s", self.me, camera)

    def give_up(self, camera: str) -> None:
        live, token = self.readers.pop(camera)
        live.stop()
        self.last_stats.update(live.stats())
        token.undeclare()
        self.claims.append((time.monotonic() - self.started, camera, False))
        log.info("worker %s: no longer reading %s", self.me, camera)

    def step(self, timeout_s: float) -> None:
        """One event of every camera read (waiting up to ``timeout_s`` when none had one), published per robot."""
        busy = False
        for camera, (live, _) in list(self.readers.items()):
            if (event := live.get(0)) is not None:
                self.handle(camera, event)
                busy = True
                self.batches.flush(due_only=True)
        self.batches.flush()
        if not busy:
            self.wake.wait(timeout_s)
            self.wake.clear()

    def handle(self, camera: str, event: Frame | ClockReading) -> None:
        """A clock sample to the camera's clock; a frame's per-frame work (whole frame, no
        estimates: this worker holds no fusion) published as its sighting."""
        if isinstance(event, ClockReading):
            self.tracker.add_clock_sample(event.camera, event.sample)
        elif (job := self.tracker.admit(event, hold=False, forecast=NO_FORECAST)) is not None:
            result = self.tracker.processor.work(job)
            stats = self.readers[camera][0].stats()[camera]
            for message in body_messages(result, self.tracker.clocks[camera], stats, self.with_pose):
                self.batches.add(camera, message.body, encode_sighting(message))
            self.published += 1

    def camera_stats(self) -> dict[str, CameraStats]:
        return self.last_stats | {n: s for live, _ in self.readers.values() for n, s in live.stats().items()}

    def line(self, elapsed_s: float) -> str:
        return (f"{elapsed_s:5.0f}s published {self.published} | "
                + (" ".join(f"{n} {s.frames} frames{'' if s.connected else ' (down)'}"
                            for n, s in self.camera_stats().items() if n in self.readers) or "no camera claimed"))


def run_worker(config: TrackerConfig, extrinsics: dict[str, CameraExtrinsics] | None, cameras: Sequence[str],
               endpoints: ZenohEndpoints, params: StageParams | None = None, source: SourceParams | None = None, *,
               duration_s: float | None = None, stop: threading.Event | None = None,
               status: Callable[[str], None] | None = None, status_every_s: float = 2.0,
               clock: Callable[[], float] = time.time) -> WorkerResult:
    """Read ``cameras`` of ``config`` live (none named: claim a share of the free cameras, see
    :func:`cubetrack.io.worker_bus.claim_changes`) and publish each frame's sightings on Zenoh
    (:func:`body_messages`) until ``duration_s``, ``stop``, Ctrl-C or SIGTERM (the session runtime,
    :mod:`cubetrack.app.session`). Frames of a camera whose clock is not known yet are given up
    (counted), as in ``track --live``."""
    if params is None or source is None:
        settings = config_params(config)
        params, source = params or settings.stages, source or settings.source
    automatic = not cameras
    names = chosen_cameras(config, cameras)
    urls = {n: u for n, u in live_camera_urls(config).items() if n in names}
    for n in names:
        for robot in config.robots:
            sighting_key(n), sighting_key(worker_id(), robot.name)  # every name a key chunk, before anything starts
    intrinsics = {n: i for n, i in live_intrinsics(config).items() if n in names}
    tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, params, synced_cameras=frozenset(urls))
    zenoh = open_session(endpoints, "worker")
    with_pose = params.track.camera_poses is CameraPoseSource.WORLD_MARKER
    worker = ZenohWorker(zenoh, tracker, urls, source, clock, with_pose)
    session = Session(duration_s=duration_s, stop=stop, status_every_s=status_every_s,
                      status=None if status is None else lambda: status(worker.line(session.elapsed_s)))
    token = zenoh.liveliness().declare_token(f"{WORKERS_KEY}/{worker.me}")
    claims = Claims(zenoh, worker.me, names, lambda: worker.readers, worker.take, worker.give_up)
    try:
        if automatic:
            claims.watch()
            session.every(CHECK_EVERY_S, claims.rebalance)
            session.each_turn(claims.rebalance_if_changed)
            log.info("worker %s: claiming its share of %s", worker.me, ", ".join(names))
        else:
            for camera in names:
                worker.take(camera)
            log.info("worker %s: %s -> Zenoh %s/*", worker.me, ", ".join(names), SIGHTINGS_KEY)
        session.run(worker.step, 0.05 if automatic else 0.1)
    finally:
        for camera in list(worker.readers):
            worker.give_up(camera)
        worker.batches.close()
        claims.close()
        token.undeclare()
        zenoh.close()
    return WorkerResult(tracker.stats, worker.published, worker.camera_stats(), session.elapsed_s,
                        session.interrupted, tuple(worker.claims))
