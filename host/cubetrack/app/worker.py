"""``cubetrack worker``: the per-camera half of tracking, published on Zenoh (docs/scaling.md).

A worker reads its cameras (:class:`cubetrack.source.streams.LiveCameras`), stamps each frame with its
capture time through the camera's ``/time`` round trips and does the tracker's per-frame work
(:meth:`cubetrack.app.tracker.FrameWorker.work`: decode, detect, the camera's pose), then
publishes one sighting message per frame (:mod:`cubetrack.core.sighting_wire`) under
``cubetrack/sightings/<camera>``. The fusion (:mod:`cubetrack.app.fusion_service`) subscribes to
``cubetrack/sightings/*``. A worker holds no fusion state, so detection searches whole frames
(there is no prediction to search around) and per-camera estimates are made by the fusion, from
the corners, when it asks for one (as in one process: only then). Each running worker holds a
Zenoh liveliness token ``cubetrack/workers/<host>-<pid>``; the fusion reports workers coming and
going (a killed worker's token goes when its connection drops).

Which worker reads which camera: named (``--cameras``) or automatic. Every worker holds a
liveliness token ``cubetrack/claims/<camera>/<worker>`` per camera it reads; an automatic worker
also holds ``cubetrack/pool/<worker>``. The cameras no named worker claims are shared among the
automatic workers by :func:`share_cameras` (the same answer in every worker that sees the same
tokens); a worker takes a camera of its share only once no other worker claims it, gives up
what is no longer its share, and on a double claim the greater worker name gives way. A dead
worker's tokens vanish with its connection, so the others take its cameras over
(docs/scaling.md).

Zenoh: the fusion listens on ``tcp/127.0.0.1:7450`` and workers connect there (loopback by
default); either may start first, restart, or come and go.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import re
import socket
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

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
CLAIMS_KEY = "cubetrack/claims"  # a liveliness token per camera a worker reads: cubetrack/claims/<camera>/<worker>
POOL_KEY = "cubetrack/pool"  # a liveliness token per automatic worker: cubetrack/pool/<worker>
FUSE_PORT = 7450
BUS_LEASE_MS = 3000  # a worker or fusion silent this long (frozen, host gone) is dropped with its claims
SETTLE_S = 1.0  # an automatic worker on the bus listens this long to the others' tokens before it claims
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


def key_chunk(what: str, name: str) -> str:
    """``name`` checked as one chunk of a Zenoh key expression."""
    if not name or re.search(r"[/*$#?\s]", name):
        raise ConfigError(f"{what} name {name!r} cannot be a Zenoh key chunk (no '/', '*', '$', '#', '?' or spaces)")
    return name


def sighting_key(camera: str) -> str:
    """The key expression ``camera``'s sightings are published under."""
    return f"{SIGHTINGS_KEY}/{key_chunk('camera', camera)}"


def claim_key(camera: str, worker: str) -> str:
    """The liveliness token of ``worker`` reading ``camera``."""
    return f"{CLAIMS_KEY}/{key_chunk('camera', camera)}/{worker}"


def worker_id() -> str:
    """This worker's name on the bus: host name and process id (a key chunk)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", f"{socket.gethostname()}-{os.getpid()}")


def share_cameras(cameras: Sequence[str], pool: Iterable[str]) -> dict[str, str]:
    """Camera -> the automatic worker whose share it is: rendezvous hashing (each camera ranks
    the workers by a hash of both names), cameras taken in the given order, each worker capped
    at floor(cameras / workers) or, for the first ones to get there, one more. Every worker
    computes the same answer from the same names; shares differ by at most one camera; a worker
    leaving mostly moves only its own cameras."""
    workers = sorted(set(pool))
    if not workers:
        return {}
    least, extra = divmod(len(cameras), len(workers))  # `extra` workers read one camera more
    load = dict.fromkeys(workers, 0)
    owner = {}
    for camera in cameras:
        ranked = sorted(workers, key=lambda w: (hashlib.blake2b(f"{camera}\0{w}".encode(), digest_size=8).digest(), w),
                        reverse=True)
        more = sum(n > least for n in load.values()) < extra
        owner[camera] = next(w for w in ranked if load[w] < least or (more and load[w] == least))
        load[owner[camera]] += 1
    return owner


def claim_changes(me: str, cameras: Sequence[str], held: Iterable[str], pool: Iterable[str],
                  holders: Mapping[str, Iterable[str]]) -> tuple[set[str], set[str]]:
    """What automatic worker ``me``, holding ``held``, takes and gives up: ``pool`` are the
    automatic workers seen, ``holders`` camera -> the workers claiming it. A camera claimed by
    a named (non-pool) worker is not shared; ``me`` takes a camera of its share only when nobody
    else claims it; it gives up a camera that is no longer its share, or that a smaller-named
    worker also claims."""
    held, pool = set(held), set(pool) | {me}
    others = {c: set(holders.get(c, ())) - {me} for c in cameras}
    free = [c for c in cameras if not others[c] - pool]
    mine = {c for c, w in share_cameras(free, pool).items() if w == me}
    release = {c for c in held if c not in mine or any(w < me for w in others.get(c, ()))}
    take = {c for c in mine - held if not others[c]}
    return take, release


class ClaimBoard:
    """The claim and pool tokens seen on the bus (updated from Zenoh's threads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.pool: set[str] = set()
        self.holders: dict[str, set[str]] = {}
        self.changed = threading.Event()

    def token(self, key: str, alive: bool) -> None:
        """A liveliness token ``key`` appeared (``alive``) or vanished."""
        parts = key.split("/")
        with self._lock:
            if key.startswith(f"{POOL_KEY}/") and len(parts) == 3:
                (self.pool.add if alive else self.pool.discard)(parts[2])
            elif key.startswith(f"{CLAIMS_KEY}/") and len(parts) == 4:
                workers = self.holders.setdefault(parts[2], set())
                (workers.add if alive else workers.discard)(parts[3])
            else:
                return
        self.changed.set()

    def snapshot(self) -> tuple[set[str], dict[str, set[str]]]:
        with self._lock:
            return set(self.pool), {c: set(w) for c, w in self.holders.items()}


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
        raise ConfigError(f"{config.path}: no camera {', '.join(unknown)} (the config has "
                          f"{', '.join(known) or 'none'})")
    return list(cameras) or known


def run_worker(config: TrackerConfig, extrinsics: dict[str, CameraExtrinsics] | None, cameras: Sequence[str],
               endpoints: ZenohEndpoints, params: StageParams | None = None, source: SourceParams | None = None, *,
               duration_s: float | None = None, stop: threading.Event | None = None,
               status: Callable[[str], None] | None = None, status_every_s: float = 2.0,
               clock: Callable[[], float] = time.time) -> WorkerResult:
    """Read ``cameras`` of ``config`` live (none named: claim a share of the free cameras, see
    :func:`claim_changes`) and publish each frame's sighting on Zenoh until ``duration_s``,
    ``stop`` or Ctrl-C. Frames of a camera whose clock is not known yet are given up (counted),
    as in ``track --live``."""
    settings = config_params(config)
    params = params or settings.stages
    source = source or settings.source
    automatic = not cameras
    names = chosen_cameras(config, cameras)
    urls = {n: u for n, u in live_camera_urls(config).items() if n in names}
    keys = {n: sighting_key(n) for n in names}
    intrinsics = {n: i for n, i in live_intrinsics(config).items() if n in names}
    tracker = Tracker(intrinsics, config.world, config.robots, extrinsics, params, synced_cameras=frozenset(urls))
    with_pose = params.track.camera_poses is CameraPoseSource.WORLD_MARKER
    me = worker_id()
    board = ClaimBoard()
    session = open_session(endpoints, "worker")
    tokens = [session.liveliness().declare_token(f"{WORKERS_KEY}/{me}")]
    readers: dict[str, tuple[LiveCameras, object, object]] = {}  # camera -> its reader, publisher, claim token
    last_stats: dict[str, CameraStats] = {}
    claims: list[tuple[float, str, bool]] = []
    wake = threading.Event()
    published = 0
    interrupted = False
    started = time.monotonic()
    on_bus_s: float | None = None  # since when this worker has been connected to another Zenoh node
    next_status = started + status_every_s
    next_check = started

    def take(camera: str) -> None:
        token = session.liveliness().declare_token(claim_key(camera, me))
        live = LiveCameras({camera: urls[camera]}, source, clock=clock, wake=wake.set)
        readers[camera] = (live, session.declare_publisher(keys[camera]), token)
        live.start()
        claims.append((time.monotonic() - started, camera, True))
        log.info("worker %s: reading %s", me, camera)

    def give_up(camera: str) -> None:
        live, publisher, token = readers.pop(camera)
        live.stop()
        last_stats.update(live.stats())
        publisher.undeclare()
        token.undeclare()
        claims.append((time.monotonic() - started, camera, False))
        log.info("worker %s: no longer reading %s", me, camera)

    def rebalance() -> None:
        nonlocal on_bus_s
        info = session.info
        if not (list(info.peers_zid()) or list(info.routers_zid())):
            on_bus_s = None
            return
        on_bus_s = on_bus_s if on_bus_s is not None else time.monotonic()
        if time.monotonic() - on_bus_s < SETTLE_S:
            return
        pool, holders = board.snapshot()
        gained, lost = claim_changes(me, names, readers, pool, holders)
        for camera in sorted(lost):
            give_up(camera)
        for camera in sorted(gained):
            take(camera)

    def handle(camera: str, event) -> None:
        nonlocal published
        if isinstance(event, ClockReading):
            tracker.add_clock_sample(event.camera, event.sample)
        elif (job := tracker.admit(event, hold=False)) is not None:
            job = dataclasses.replace(job, regions=None, estimate_robots=frozenset())
            result = tracker.worker.work(job)
            live, publisher, _ = readers[camera]
            message = sighting_message(result, tracker.clocks[camera], live.stats()[camera], with_pose)
            publisher.put(encode_sighting(message))
            published += 1

    def camera_stats() -> dict[str, CameraStats]:
        return last_stats | {n: s for live, _, _ in readers.values() for n, s in live.stats().items()}

    try:
        if automatic:
            tokens.append(session.liveliness().declare_token(f"{POOL_KEY}/{me}"))
            watchers = [session.liveliness().declare_subscriber(
                f"{key}/**", lambda sample: board.token(str(sample.key_expr), not str(sample.kind).endswith("DELETE")),
                history=True) for key in (POOL_KEY, CLAIMS_KEY)]
            log.info("worker %s: claiming its share of %s", me, ", ".join(names))
        else:
            watchers = []
            for camera in names:
                take(camera)
            log.info("worker %s: %s -> Zenoh %s/*", me, ", ".join(names), SIGHTINGS_KEY)
        try:
            while not ((stop is not None and stop.is_set())
                       or (duration_s is not None and time.monotonic() - started >= duration_s)):
                if automatic and (board.changed.is_set() or time.monotonic() >= next_check):
                    board.changed.clear()
                    next_check = time.monotonic() + CHECK_EVERY_S
                    rebalance()
                busy = False
                for camera, (live, _, _) in list(readers.items()):
                    if (event := live.get(0)) is not None:
                        handle(camera, event)
                        busy = True
                if not busy:
                    wake.wait(0.05 if automatic else 0.1)
                    wake.clear()
                if status is not None and time.monotonic() >= next_status:
                    next_status += status_every_s
                    status(f"{time.monotonic() - started:5.0f}s published {published} | "
                           + (" ".join(f"{n} {s.frames} frames{'' if s.connected else ' (down)'}"
                                       for n, s in camera_stats().items() if n in readers) or "no camera claimed"))
        except KeyboardInterrupt:
            interrupted = True
        for watcher in watchers:
            watcher.undeclare()
    finally:
        for camera in list(readers):
            give_up(camera)
        for token in tokens:
            token.undeclare()
        session.close()
    return WorkerResult(tracker.stats, published, camera_stats(), time.monotonic() - started, interrupted,
                        tuple(claims))
