"""``cubetrack fuse``: the fusion half of tracking, fed by ``cubetrack worker`` processes over
Zenoh (docs/scaling.md).

It subscribes to ``cubetrack/sightings/*`` (:mod:`cubetrack.app.worker`), turns each message
back into the per-frame work's result (each robot's own detections, and its per-camera
estimate from the corners when the fusion asks for one) and runs the tracker's fusion
(:meth:`cubetrack.app.tracker.Tracker.fuse`) and the outputs on the session runtime
(:mod:`cubetrack.app.session`), exactly as ``track --live`` does: sightings that arrived together
are fused oldest capture first, late ones are folded in by the fusion, a fixed lag's poses leave
when their time is up and ``[fusion] output_rate_hz`` adds each robot's predicted pose. It reports
which cameras it hears from (and which it does not).
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
from typing import Any

from cubetrack.app.config import config_params, parameter_tables
from cubetrack.app.live import live_intrinsics
from cubetrack.app.outputs import open_outputs
from cubetrack.app.session import PoseStream, RunSpec, Session, idle_wait_s
from cubetrack.app.tracker import StageParams, Tracker, TrackStats
from cubetrack.app.watch_log import attach_watch_log
from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.core.records import CameraHealth, Frame, FrameJob, FrameOutcome, FrameResult
from cubetrack.io.config import TrackerConfig
from cubetrack.io.run import RUN_FILE
from cubetrack.io.sighting_wire import SightingMessage, SightingWireError, decode_sighting
from cubetrack.io.worker_bus import SIGHTINGS_KEY, WORKERS_KEY
from cubetrack.sink.base import Sink
from cubetrack.sink.zenoh_session import ZenohEndpoints, open_session
from cubetrack.source.health import HEALTH_EVERY_S

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
    has no intrinsics or pose for): the tracker's :meth:`~cubetrack.app.tracker.FrameProcessor.sightings`
    of the message's detections, with estimates for the robots whose fusion asks."""
    camera = message.camera
    T_world_cam = message.T_world_cam if message.T_world_cam is not None else tracker.T_world_cam.get(camera)
    if camera not in tracker.intrinsics or T_world_cam is None:
        return None
    frame = Frame(camera, message.seq, message.device_time_s, message.arrival_time_s, b"")
    job = FrameJob(frame, message.capture_time_s, None,
                   frozenset(r.name for r in tracker.robots if tracker.fusion.needs_estimate(r.name)))
    sightings = tracker.processor.sightings(job, message.detections, T_world_cam)
    return FrameResult(job, FrameOutcome(message.outcome), sightings, dropped=message.dropped)


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


class _Inbox:
    """The sightings the Zenoh threads deliver, taken by the fusion's thread: each decoded, the
    ones of a known camera fused oldest capture first (second copies of a frame dropped), each
    camera's health passed on every ``HEALTH_EVERY_S``; and the workers' liveliness tokens."""

    def __init__(self, stream: PoseStream, cameras: Sequence[str]):
        self.stream, self.tracker = stream, stream.tracker
        self.messages: collections.deque[bytes] = collections.deque()
        self.wake = threading.Event()
        self.heard = {c: Heard() for c in cameras}
        self.workers: set[str] = set()
        self.bad = self.duplicates = 0

    def receive(self, sample: Any) -> None:  # a Zenoh thread
        self.messages.append(bytes(sample.payload))
        self.wake.set()

    def worker_event(self, sample: Any) -> None:  # a Zenoh thread: a worker's liveliness token came or went
        name = str(sample.key_expr).removeprefix(f"{WORKERS_KEY}/")
        if str(sample.kind).endswith("DELETE"):
            self.workers.discard(name)
            log.warning("fuse: worker %s left", name)
        else:
            self.workers.add(name)
            log.info("fuse: worker %s joined", name)

    def step(self, timeout_s: float) -> None:
        self.wake.wait(timeout_s)
        self.wake.clear()
        self.fuse()

    def _decoded(self) -> list[SightingMessage]:
        messages = []
        while self.messages:
            try:
                messages.append(decode_sighting(self.messages.popleft()))
            except SightingWireError as exc:
                self.bad += 1
                if self.bad == 1 or self.bad % 1000 == 0:
                    log.warning("fuse: %s (%d refused so far)", exc, self.bad)
        return sorted(messages, key=lambda m: m.capture_time_s)

    def fuse(self) -> None:
        for message in self._decoded():
            result = frame_result(self.tracker, message)
            if result is None:
                self.bad += 1
                log.warning("fuse: sighting of camera %r, which the config and extrinsics do not know", message.camera)
                continue
            h = self.heard[message.camera]
            if not h.first_copy(message):
                self.duplicates += 1
                continue
            self.stream.fuse(result)
            h.messages += 1
            h.last_heard_s = time.monotonic()
            now_s = self.stream.clock()
            if h.health is None or now_s - h.health.time_s >= HEALTH_EVERY_S:
                h.health = camera_health(message, h.health, now_s)
                self.stream.outputs.camera_health(h.health)

    def line(self, elapsed_s: float) -> str:
        """The status line: the workers, the cameras heard from (sightings so far) and those silent."""
        now = time.monotonic()
        live = [f"{c} {h.messages}" for c, h in self.heard.items() if now - h.last_heard_s < SILENT_AFTER_S]
        silent = [c for c, h in self.heard.items() if not now - h.last_heard_s < SILENT_AFTER_S]
        poses = " ".join(f"{r} {n} poses" for r, n in self.tracker.stats.poses.items())
        return (f"{elapsed_s:5.0f}s {len(self.workers)} worker(s), hearing {', '.join(live) or 'no camera'}"
                + (f" | silent: {', '.join(silent)}" if silent else "") + (f" | {poses}" if poses else "")
                + (f" | refused {self.bad}" if self.bad else "")
                + (f" | duplicates {self.duplicates}" if self.duplicates else ""))


def run_fusion(config: TrackerConfig, extrinsics: dict[str, CameraExtrinsics] | None, out_dir: str | Path,
               endpoints: ZenohEndpoints, params: StageParams | None = None, *, duration_s: float | None = None,
               stop: threading.Event | None = None, status: Callable[[str], None] | None = None,
               status_every_s: float = 2.0, clock: Callable[[], float] = time.time,
               sinks: Sequence[Sink] = (), extrinsics_path: str | Path | None = None,
               update_extrinsics: bool = False) -> FuseResult:
    """Fuse the sightings every worker publishes into ``<out_dir>/<robot>.tum`` and ``.jsonl``
    and ``sinks`` until ``duration_s``, ``stop``, Ctrl-C or SIGTERM, on the session runtime
    (:mod:`cubetrack.app.session`) as ``track --live`` is: the same release of a fixed lag's poses,
    the same ``[fusion] output_rate_hz`` predicted poses, ``<out_dir>/run.json`` of the same shape,
    the same camera watching (:func:`cubetrack.app.watch_log.attach_watch_log`)."""
    params = params or config_params(config).stages
    intrinsics = live_intrinsics(config)
    tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, params)
    out_dir = Path(out_dir)
    outputs, files = open_outputs(config, intrinsics, extrinsics, out_dir, sinks)
    zenoh = None
    watch_log = attach_watch_log(tracker.fusion, out_dir, extrinsics, extrinsics_path if update_extrinsics else None)
    try:
        stream = PoseStream(tracker, outputs, clock)
        inbox = _Inbox(stream, [c.name for c in config.cameras])
        session = Session(duration_s=duration_s, stop=stop, status_every_s=status_every_s,
                          status=None if status is None else lambda: status(inbox.line(session.elapsed_s)),
                          record=RunSpec(out_dir / RUN_FILE, "fuse", parameter_tables(params),
                                         {"config": config.path, "extrinsics": extrinsics_path}))
        stream.attach(session)
        zenoh = open_session(endpoints, "fuse")
        subscriber = zenoh.declare_subscriber(f"{SIGHTINGS_KEY}/*", inbox.receive)
        watcher = zenoh.liveliness().declare_subscriber(f"{WORKERS_KEY}/*", inbox.worker_event, history=True)
        log.info("fuse: subscribed to %s/*", SIGHTINGS_KEY)
        session.run(inbox.step, idle_wait_s(params))
        subscriber.undeclare()
        watcher.undeclare()
        inbox.fuse()
        stream.finish()
    finally:
        if zenoh is not None:
            zenoh.close()
        if watch_log is not None:
            watch_log.close()
        outputs.close()
    heard = {c: h.messages for c, h in inbox.heard.items()}
    session.finish({**stream.summary(tracker.stats), "heard": heard, "refused": inbox.bad,
                    "duplicates": inbox.duplicates, **(watch_log.summary() if watch_log is not None else {})})
    return FuseResult(tracker.stats, heard, inbox.bad, files.outputs, session.elapsed_s, session.interrupted,
                      inbox.duplicates)
