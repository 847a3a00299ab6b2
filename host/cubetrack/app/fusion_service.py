"""``cubetrack fuse``: the fusion half of tracking, fed by ``cubetrack worker`` processes over
Zenoh (docs/scaling.md).

It subscribes to ``cubetrack/shard-sightings/<itself>/*`` and ``cubetrack/sightings/**`` (:mod:`cubetrack.app.worker`),
or as a shard to ``cubetrack/sightings/*/<robot>`` of the robots it fuses instead of the latter (named, or claimed
as workers claim cameras: :class:`cubetrack.io.worker_bus.Claims`), turns each message
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
import dataclasses
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
from cubetrack.app.worker import CHECK_EVERY_S, worker_id
from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.core.errors import ConfigError
from cubetrack.core.records import CameraHealth, Frame, FrameJob, FrameOutcome, FrameResult
from cubetrack.fuse.fusion import FilterFusion
from cubetrack.io.config import TrackerConfig
from cubetrack.io.run import RUN_FILE
from cubetrack.io.sighting_wire import SightingMessage, SightingWireError, camera_health, decode_messages
from cubetrack.io.worker_bus import (
    ROBOT_CLAIMS_KEY,
    SHARD_POOL_KEY,
    SHARDS_KEY,
    SIGHTINGS_KEY,
    WORKERS_KEY,
    Claims,
    FusedRobots,
    StateRelay,
    key_chunk,
)
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
        frame = (message.seq, message.device_time_s, message.body)
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
    claims: tuple[tuple[float, str, bool], ...] = ()  # (seconds since the start, robot, taken / given up)
    behind: int = 0  # messages still waiting when the session stopped (fused then): the fusion fell behind
    received: int = 0  # messages the bus delivered (a shard: only its robots')


def frame_result(tracker: Tracker, message: SightingMessage) -> FrameResult | None:
    """The per-frame work's result a sighting message stands for (None: a camera the fusion
    has no intrinsics or pose for): the tracker's :meth:`~cubetrack.app.tracker.FrameProcessor.sightings`
    of the message's detections (only its ``body``'s, when it names one), with estimates for the
    robots whose fusion asks."""
    camera = message.camera
    T_world_cam = message.T_world_cam if message.T_world_cam is not None else tracker.T_world_cam.get(camera)
    if camera not in tracker.intrinsics or T_world_cam is None:
        return None
    frame = Frame(camera, message.seq, message.device_time_s, message.arrival_time_s, b"")
    job = FrameJob(frame, message.capture_time_s, None,
                   frozenset(r.name for r in tracker.robots if tracker.fusion.needs_estimate(r.name)))
    robots = None if message.body is None else tuple(r for r in tracker.robots if r.name == message.body)
    sightings = tracker.processor.sightings(job, message.detections, T_world_cam, robots)
    return FrameResult(job, FrameOutcome(message.outcome), sightings, dropped=message.dropped)


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
        self.bad = self.duplicates = self.received = 0
        self.started = time.monotonic()
        self.claims: list[tuple[float, str, bool]] = []
        self.fusing: set[str] = set()  # the robots this fusion fuses (their predictions: stream.robots)
        self.relay: StateRelay | None = None  # a shard's: the fleet's last states, a taken robot's track goes on from

    def fused(self, robot: str, held: bool) -> None:
        """The fusion took (``held``) or gave up ``robot``: its poses and predictions start or stop."""
        self.fusing = self.fusing | {robot} if held else self.fusing - {robot}
        state = self.relay.last(robot) if held and self.relay else None
        if state and (fusion := filter_fusion(self.tracker)) and fusion.seed(*state):
            log.info("fuse: %s: track from its last state (%.2f s old)", robot, self.stream.clock() - state.time_s)
        self.stream.robots = [r.name for r in self.tracker.robots if r.name in self.fusing]
        self.claims.append((time.monotonic() - self.started, robot, held))
        log.info("fuse: %s robot %s", "fusing" if held else "no longer fusing", robot)

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
            self.received += 1
            try:
                messages.extend(decode_messages(self.messages.popleft()))
            except SightingWireError as exc:
                self.bad += 1
                if self.bad == 1 or self.bad % 1000 == 0:
                    log.warning("fuse: %s (%d refused so far)", exc, self.bad)
        return sorted(messages, key=lambda m: m.capture_time_s)

    def fuse(self) -> None:
        for message in self._decoded():
            if message.body is not None and message.body not in self.fusing:
                continue  # a robot this fusion no longer fuses (or does not know)
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
        """The status line: the robots fused, the workers, the cameras heard from (sightings so far)
        and those silent."""
        now = time.monotonic()
        live = [f"{c} {h.messages}" for c, h in self.heard.items() if now - h.last_heard_s < SILENT_AFTER_S]
        silent = [c for c, h in self.heard.items() if not now - h.last_heard_s < SILENT_AFTER_S]
        poses = " ".join(f"{r} {n} poses" for r, n in self.tracker.stats.poses.items() if r in self.stream.robots)
        robots = self.stream.robots
        return (f"{elapsed_s:5.0f}s fusing {', '.join(robots[:8]) or 'no robot'}{' ...' if len(robots) > 8 else ''}"
                f" | {len(self.workers)} worker(s), hearing {', '.join(live) or 'no camera'}"
                + (f" | silent: {', '.join(silent)}" if silent else "") + (f" | {poses}" if poses else "")
                + (f" | refused {self.bad}" if self.bad else "")
                + (f" | duplicates {self.duplicates}" if self.duplicates else ""))


def filter_fusion(tracker: Tracker) -> FilterFusion | None:
    """The tracker's filter fusion (inside a camera watch too), whose track a shard can take over; else None."""
    fusion = getattr(tracker.fusion, "fusion", tracker.fusion)
    return fusion if isinstance(fusion, FilterFusion) else None


def chosen_robots(config: TrackerConfig, robots: Sequence[str]) -> list[str]:
    """``robots`` checked against the config and as key chunks (every robot when empty)."""
    known = [r.name for r in config.robots]
    unknown = [r for r in robots if r not in known]
    if unknown:
        raise ConfigError(f"{config.path}: no robot {', '.join(unknown)} (the config has {', '.join(known)})")
    return [key_chunk("robot", r) for r in robots or known]


def _join_bus(zenoh: Any, inbox: _Inbox, session: Session, names: list[str], shard: bool, every: bool) -> list[Any]:
    """This fusion on the bus: its token, the workers' tokens followed, and the robots it fuses:
    every robot from ``cubetrack/sightings/**`` (``every``), ``names`` each from its own key, or
    with ``shard`` its share of ``names`` claimed (checked every ``CHECK_EVERY_S`` and whenever a
    token comes or goes). What to close, in order, at the end."""
    me = worker_id()
    robots = FusedRobots(zenoh, me, inbox.receive, inbox.fused, per_robot=not every)
    declared: list[Any] = [zenoh.liveliness().declare_token(f"{SHARDS_KEY}/{me}")]
    declared.append(zenoh.liveliness().declare_subscriber(f"{WORKERS_KEY}/*", inbox.worker_event, history=True))
    if every:
        declared.append(zenoh.declare_subscriber(f"{SIGHTINGS_KEY}/**", inbox.receive))
    if shard:
        fusion = filter_fusion(inbox.tracker)
        inbox.relay = StateRelay(zenoh, me, fusion.last_state if fusion else lambda robot: None)
        inbox.stream.on_poses = inbox.relay.poses
        declared.append(inbox.relay)
        claims = Claims(zenoh, me, names, lambda: robots.held, robots.take, robots.give_up,
                        (SHARD_POOL_KEY, ROBOT_CLAIMS_KEY))
        claims.watch()
        session.every(CHECK_EVERY_S, claims.rebalance)
        session.each_turn(claims.rebalance_if_changed)
        declared.append(claims)
        log.info("fuse %s: claiming a share of robots %s", me, ", ".join(names))
    else:
        for robot in names:
            robots.take(robot)
    return [robots, *reversed(declared)]


def _close(declared: list[Any]) -> None:
    for item in declared:
        (item.close if isinstance(item, (Claims, FusedRobots, StateRelay)) else item.undeclare)()


def run_fusion(config: TrackerConfig, extrinsics: dict[str, CameraExtrinsics] | None, out_dir: str | Path,
               endpoints: ZenohEndpoints, params: StageParams | None = None, *, duration_s: float | None = None,
               stop: threading.Event | None = None, status: Callable[[str], None] | None = None,
               status_every_s: float = 2.0, clock: Callable[[], float] = time.time,
               sinks: Sequence[Sink] = (), extrinsics_path: str | Path | None = None,
               robots: Sequence[str] = (), shard: bool = False, update_extrinsics: bool = False) -> FuseResult:
    """Fuse the sightings every worker publishes into ``<out_dir>/<robot>.tum`` and ``.jsonl``
    and ``sinks`` until ``duration_s``, ``stop``, Ctrl-C or SIGTERM, on the session runtime
    (:mod:`cubetrack.app.session`) as ``track --live`` is: the same release of a fixed lag's poses,
    the same ``[fusion] output_rate_hz`` predicted poses, ``<out_dir>/run.json`` of the same shape.
    ``robots``: fuse only these (a shard of a fleet; default every robot); ``shard``: claim a share
    of them (of every robot when none are named) as other shards come and go (docs/scaling.md). The
    same camera watching as live (:func:`cubetrack.app.watch_log.attach_watch_log`)."""
    params = params or config_params(config).stages
    names = chosen_robots(config, robots)
    intrinsics = live_intrinsics(config)
    tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, params)
    out_dir = Path(out_dir)
    # named robots: the outputs (files, topics, trackers) are theirs only; a shard's robots change, so all
    mine = config if shard or not robots else dataclasses.replace(config, robots=tuple(
        r for r in config.robots if r.name in names))
    outputs, files = open_outputs(mine, intrinsics, extrinsics, out_dir, sinks)
    zenoh, declared, behind = None, [], 0
    watch_log = attach_watch_log(tracker, outputs, out_dir, extrinsics, extrinsics_path if update_extrinsics else None)
    try:
        stream = PoseStream(tracker, outputs, clock)
        stream.robots = []
        inbox = _Inbox(stream, [c.name for c in config.cameras])
        session = Session(duration_s=duration_s, stop=stop, status_every_s=status_every_s,
                          status=None if status is None else lambda: status(inbox.line(session.elapsed_s)),
                          record=RunSpec(out_dir / RUN_FILE, "fuse", parameter_tables(params),
                                         {"config": config.path, "extrinsics": extrinsics_path},
                                         {"robots": list(robots), "shard": shard}))
        stream.attach(session)
        zenoh = open_session(endpoints, "fuse")
        declared = _join_bus(zenoh, inbox, session, names, shard, not robots and not shard)
        session.run(inbox.step, idle_wait_s(params))
        behind = len(inbox.messages)
        inbox.fuse()
        _close(declared)
        declared = []
        stream.finish()
    finally:
        _close(declared)
        if zenoh is not None:
            zenoh.close()
        if watch_log is not None:
            watch_log.close()
        outputs.close()
    heard = {c: h.messages for c, h in inbox.heard.items()}
    session.finish({**stream.summary(tracker.stats), "heard": heard, "refused": inbox.bad,
                    "duplicates": inbox.duplicates, "behind": behind,
                    **(watch_log.summary() if watch_log is not None else {})})
    return FuseResult(tracker.stats, heard, inbox.bad, files.outputs, session.elapsed_s, session.interrupted,
                      inbox.duplicates, tuple(inbox.claims), behind, inbox.received)
