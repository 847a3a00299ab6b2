"""``cubetrack fuse``: the fusion half of tracking, fed by ``cubetrack worker`` processes over
Zenoh (docs/scaling.md).

It subscribes to ``cubetrack/sightings/*`` (:mod:`cubetrack.app.worker`), turns each message
back into the per-frame work's result (each robot's own detections, and its per-camera
estimate from the corners when the fusion asks for one) and runs the tracker's fusion
(:meth:`cubetrack.app.tracker.Tracker.fuse`) and the outputs, exactly as ``track --live`` does:
sightings that arrived together are fused oldest capture first, late ones are folded in by the
fusion. It reports which cameras it hears from (and which it does not).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cubetrack.app.config import config_params
from cubetrack.app.live import HEALTH_EVERY_S, idle_wait_s, live_intrinsics
from cubetrack.app.outputs import open_outputs
from cubetrack.app.tracker import FrameJob, FrameOutcome, FrameResult, StageParams, Tracker, TrackStats
from cubetrack.app.worker import SIGHTINGS_KEY, WORKERS_KEY
from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.core.records import CameraHealth, Frame, TrackedPose
from cubetrack.core.sighting_wire import SightingMessage, SightingWireError, decode_sighting
from cubetrack.io.config import TrackerConfig
from cubetrack.sink.base import Sink
from cubetrack.sink.zenoh_session import ZenohEndpoints, open_session

log = logging.getLogger(__name__)

SILENT_AFTER_S = 2.0  # a camera not heard from for this long is reported silent
RECENT_FRAMES = 64  # per camera, the frames remembered to drop a second worker's copy of a frame


@dataclass(slots=True)
class Heard:
    """What the fusion heard from one camera."""

    messages: int = 0
    last_heard_s: float = math.nan  # time.monotonic()
    health: CameraHealth | None = None
    recent: collections.deque = field(default_factory=lambda: collections.deque(maxlen=RECENT_FRAMES))

    def first_copy(self, message: SightingMessage) -> bool:
        """Whether ``message`` is the first of its frame (two workers can read one camera for
        a moment while a claim changes hands: the second copy of a frame is dropped)."""
        frame = (message.seq, message.device_time_s)
        if frame in self.recent:
            return False
        self.recent.append(frame)
        return True


@dataclass(frozen=True, slots=True)
class FuseResult:
    """What a fusion session did. ``heard``: camera -> messages; ``bad_messages``: refused;
    ``duplicates``: second copies of a frame (from two workers reading one camera)."""

    stats: TrackStats
    heard: dict[str, int]
    bad_messages: int
    outputs: dict[str, tuple[Path, Path]]
    duration_s: float
    interrupted: bool
    duplicates: int = 0


def frame_result(tracker: Tracker, message: SightingMessage) -> FrameResult | None:
    """The per-frame work's result a sighting message stands for (None: a camera the fusion
    has no intrinsics or pose for): the tracker's :meth:`~cubetrack.app.tracker.FrameWorker.sightings`
    of the message's detections, with estimates for the robots whose fusion asks."""
    camera = message.camera
    T_world_cam = message.T_world_cam if message.T_world_cam is not None else tracker.T_world_cam.get(camera)
    if camera not in tracker.intrinsics or T_world_cam is None:
        return None
    frame = Frame(camera, message.seq, message.device_time_s, message.arrival_time_s, b"")
    job = FrameJob(frame, message.capture_time_s, None,
                   frozenset(r.name for r in tracker.robots if tracker.fusion.needs_estimate(r.name)))
    sightings = tracker.worker.sightings(job, message.detections, T_world_cam)
    return FrameResult(job, FrameOutcome(message.outcome), sightings)


def camera_health(message: SightingMessage, previous: CameraHealth | None, now_s: float) -> CameraHealth:
    """The outputs' health snapshot of a camera from its latest message (frames/s since the
    previous snapshot)."""
    h, c = message.health, message.clock
    fps = math.nan
    if previous is not None and now_s > previous.time_s:
        fps = (h.frames - previous.frames) / (now_s - previous.time_s)
    synced = c.method == "round-trip"
    return CameraHealth(message.camera, now_s, h.connected, fps, h.frames, h.dropped, h.bad, h.reconnects,
                        c.offset_s if synced else math.nan, c.drift * 1e6 if synced else math.nan,
                        message.arrival_time_s - message.capture_time_s)


def run_fusion(config: TrackerConfig, extrinsics: dict[str, CameraExtrinsics] | None, out_dir: str | Path,
               endpoints: ZenohEndpoints, params: StageParams | None = None, *, duration_s: float | None = None,
               stop: threading.Event | None = None, status: Callable[[str], None] | None = None,
               status_every_s: float = 2.0, clock: Callable[[], float] = time.time,
               sinks: Sequence[Sink] = ()) -> FuseResult:
    """Fuse the sightings every worker publishes into ``<out_dir>/<robot>.tum`` and ``.jsonl``
    and ``sinks`` until ``duration_s``, ``stop`` or Ctrl-C."""
    params = params or config_params(config).stages
    intrinsics = live_intrinsics(config)
    tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, params)
    outputs, files = open_outputs(config, intrinsics, extrinsics, out_dir, sinks)
    inbox: collections.deque[bytes] = collections.deque()
    wake = threading.Event()
    heard = {c.name: Heard() for c in config.cameras}
    workers: set[str] = set()
    bad = duplicates = 0
    interrupted = False
    started = time.monotonic()
    idle_s = idle_wait_s(params)

    def receive(sample) -> None:  # a Zenoh thread
        inbox.append(bytes(sample.payload))
        wake.set()

    def worker_event(sample) -> None:  # a Zenoh thread: a worker's liveliness token came or went
        name = str(sample.key_expr).removeprefix(f"{WORKERS_KEY}/")
        if str(sample.kind).endswith("DELETE"):
            workers.discard(name)
            log.warning("fuse: worker %s left", name)
        else:
            workers.add(name)
            log.info("fuse: worker %s joined", name)

    def emit(poses: list[TrackedPose], now_s: float) -> None:
        for pose in poses:
            outputs.pose(pose)

    def fuse_inbox() -> None:
        nonlocal bad, duplicates
        messages = []
        while inbox:
            try:
                messages.append(decode_sighting(inbox.popleft()))
            except SightingWireError as exc:
                bad += 1
                if bad == 1 or bad % 1000 == 0:
                    log.warning("fuse: %s (%d refused so far)", exc, bad)
        for message in sorted(messages, key=lambda m: m.capture_time_s):
            result = frame_result(tracker, message)
            if result is None:
                bad += 1
                log.warning("fuse: sighting of camera %r, which the config and extrinsics do not know", message.camera)
                continue
            h = heard[message.camera]
            if not h.first_copy(message):
                duplicates += 1
                continue
            now_s = clock()
            emit(tracker.fuse(result, now_s), now_s)
            h.messages += 1
            h.last_heard_s = time.monotonic()
            if h.health is None or now_s - h.health.time_s >= HEALTH_EVERY_S:
                h.health = camera_health(message, h.health, now_s)
                outputs.camera_health(h.health)

    def line() -> str:
        now = time.monotonic()
        live = [f"{c} {h.messages}" for c, h in heard.items() if now - h.last_heard_s < SILENT_AFTER_S]
        silent = [c for c, h in heard.items() if not now - h.last_heard_s < SILENT_AFTER_S]
        poses = " ".join(f"{r} {n} poses" for r, n in tracker.stats.poses.items())
        return (f"{now - started:5.0f}s {len(workers)} worker(s), hearing {', '.join(live) or 'no camera'}"
                + (f" | silent: {', '.join(silent)}" if silent else "") + (f" | {poses}" if poses else "")
                + (f" | refused {bad}" if bad else "") + (f" | duplicates {duplicates}" if duplicates else ""))

    session = None
    try:
        session = open_session(endpoints, "fuse")
        subscriber = session.declare_subscriber(f"{SIGHTINGS_KEY}/*", receive)
        watcher = session.liveliness().declare_subscriber(f"{WORKERS_KEY}/*", worker_event, history=True)
        log.info("fuse: subscribed to %s/*", SIGHTINGS_KEY)
        next_status = started + status_every_s
        try:
            while not ((stop is not None and stop.is_set())
                       or (duration_s is not None and time.monotonic() - started >= duration_s)):
                wake.wait(idle_s)
                wake.clear()
                fuse_inbox()
                now_s = clock()
                emit(tracker.release(now_s), now_s)  # a fixed lag's poses whose time is up, sightings or not
                if status is not None and time.monotonic() >= next_status:
                    next_status += status_every_s
                    status(line())
        except KeyboardInterrupt:
            interrupted = True
        subscriber.undeclare()
        watcher.undeclare()
        fuse_inbox()
        now_s = clock()
        emit(tracker.finish(now_s), now_s)
    finally:
        if session is not None:
            session.close()
        outputs.close()
    return FuseResult(tracker.stats, {c: h.messages for c, h in heard.items()}, bad, files.outputs,
                      time.monotonic() - started, interrupted, duplicates)
