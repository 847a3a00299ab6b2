"""The bus between ``cubetrack worker`` and ``cubetrack fuse`` (docs/scaling.md): its Zenoh key
expressions and the claim protocol by which automatic workers share the cameras and automatic fusion
shards share the robots (the messages on it are :mod:`cubetrack.io.sighting_wire`'s).

Every worker holds a liveliness token ``cubetrack/claims/<camera>/<worker>`` per camera it reads; an
automatic worker also holds ``cubetrack/pool/<worker>``. The cameras no named worker claims are
shared among the automatic workers by :func:`share_cameras` (the same answer in every worker that
sees the same tokens); :func:`claim_changes` says what a worker takes and gives up, and
:class:`ClaimBoard` follows the tokens seen on the bus. Fusion shards do the same with robots, under
their own keys (``cubetrack/robot-claims/<robot>/<shard>``, ``cubetrack/shard-pool/<shard>``):
:class:`Claims` runs the rule for either.

A worker publishes each frame's share of each robot it holds markers of, gathered over a tick
(:class:`SightingBatches`: at most ``BATCH_HOLD_S``) into one message per robot under
``cubetrack/sightings/<worker>/<robot>`` (:func:`sighting_key`), and a frame with no robot's markers
under ``cubetrack/sightings/<camera>``: a shard subscribes to ``cubetrack/sightings/*/<robot>`` for
each of its robots (:func:`robot_sightings_key`), a fusion of every robot to ``cubetrack/sightings/**``.
"""

from __future__ import annotations

import hashlib
import logging
import math
import queue
import re
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

from cubetrack.core.errors import ConfigError
from cubetrack.core.records import TrackedPose
from cubetrack.io.sighting_wire import (
    FusedState,
    SightingWireError,
    decode_states,
    encode_batch,
    encode_states,
    states_error,
)

SIGHTINGS_KEY = "cubetrack/sightings"  # cubetrack/sightings/<worker>/<robot>: a robot's; /<camera>: empty frames
WORKERS_KEY = "cubetrack/workers"  # a liveliness token per running worker: cubetrack/workers/<host>-<pid>
CLAIMS_KEY = "cubetrack/claims"  # a liveliness token per camera a worker reads: cubetrack/claims/<camera>/<worker>
POOL_KEY = "cubetrack/pool"  # a liveliness token per automatic worker: cubetrack/pool/<worker>
SHARDS_KEY = "cubetrack/shards"  # a liveliness token per running fusion: cubetrack/shards/<host>-<pid>
ROBOT_CLAIMS_KEY = "cubetrack/robot-claims"  # per robot a fusion fuses: cubetrack/robot-claims/<robot>/<shard>
SHARD_POOL_KEY = "cubetrack/shard-pool"  # a liveliness token per automatic fusion shard
SHARD_SIGHTINGS_KEY = "cubetrack/shard-sightings"  # .../<fusion>/<worker>: a tick's sightings of its robots
STATES_KEY = "cubetrack/fused-states"  # cubetrack/fused-states/<shard>: its robots' filter states (each tick)
log = logging.getLogger(__name__)
STATE_EVERY_S = 0.1  # a shard publishes its robots' states at most this often (wall clock), in one message
BATCH_HOLD_S = 0.01  # a worker holds a sighting at most this long to publish it with others of its robot
SETTLE_S = 1.0  # an automatic member on the bus listens this long to the others' tokens before it claims


def key_chunk(what: str, name: str) -> str:
    """``name`` checked as one chunk of a Zenoh key expression."""
    if not name or re.search(r"[/*$#?\s]", name):
        raise ConfigError(f"{what} name {name!r} cannot be a Zenoh key chunk (no '/', '*', '$', '#', '?' or spaces)")
    return name


def sighting_key(source: str, robot: str | None = None) -> str:
    """The key expression ``source``'s sightings of ``robot`` are published under (a worker's: one message per
    robot per tick, :class:`SightingBatches`; older workers published one per camera frame under the camera's
    name); ``robot`` None: camera ``source``'s frames with no robot's markers."""
    key = f"{SIGHTINGS_KEY}/{key_chunk('camera' if robot is None else 'worker', source)}"
    return key if robot is None else f"{key}/{key_chunk('robot', robot)}"


def shard_sightings_key(fusion: str, worker: str = "*") -> str:
    """The key expression under which ``worker`` publishes a tick's sightings of the robots ``fusion`` alone claims,
    in one message (:class:`SightingBatches`); ``worker`` "*": every worker's (what the fusion subscribes to)."""
    source = worker if worker == "*" else key_chunk("worker", worker)
    return f"{SHARD_SIGHTINGS_KEY}/{key_chunk('fusion', fusion)}/{source}"


def robot_sightings_key(robot: str) -> str:
    """The key expression of ``robot``'s sightings from every camera (what a shard subscribes to)."""
    return f"{SIGHTINGS_KEY}/*/{key_chunk('robot', robot)}"


def claim_key(camera: str, worker: str, claims_key: str = CLAIMS_KEY) -> str:
    """The liveliness token of ``worker`` reading ``camera`` (or of a shard fusing a robot:
    ``claims_key`` ROBOT_CLAIMS_KEY)."""
    return f"{claims_key}/{key_chunk('camera' if claims_key == CLAIMS_KEY else 'robot', camera)}/{worker}"


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
    """The claim and pool tokens seen on the bus (updated from Zenoh's threads): the workers' by
    default, the fusion shards' with ``pool_key`` SHARD_POOL_KEY and ``claims_key`` ROBOT_CLAIMS_KEY."""

    def __init__(self, pool_key: str = POOL_KEY, claims_key: str = CLAIMS_KEY) -> None:
        self.pool_key, self.claims_key = pool_key, claims_key
        self._lock = threading.Lock()
        self.pool: set[str] = set()
        self.holders: dict[str, set[str]] = {}
        self.changed = threading.Event()

    def token(self, key: str, alive: bool) -> None:
        """A liveliness token ``key`` appeared (``alive``) or vanished."""
        parts = key.split("/")
        with self._lock:
            if key.startswith(f"{self.pool_key}/") and len(parts) == 3:
                (self.pool.add if alive else self.pool.discard)(parts[2])
            elif key.startswith(f"{self.claims_key}/") and len(parts) == 4:
                workers = self.holders.setdefault(parts[2], set())
                (workers.add if alive else workers.discard)(parts[3])
            else:
                return
        self.changed.set()

    def sole_holder(self, name: str) -> str | None:
        """The one member claiming ``name`` (None: nobody, or several at once)."""
        with self._lock:
            holders = self.holders.get(name)
            return next(iter(holders)) if holders is not None and len(holders) == 1 else None

    def snapshot(self) -> tuple[set[str], dict[str, set[str]]]:
        with self._lock:
            return set(self.pool), {c: set(w) for c, w in self.holders.items()}


class Claims:
    """One automatic member's claims on the bus: a worker's cameras or a fusion shard's robots
    (``keys``: the board's pool and claims keys). It holds the pool token, follows the tokens
    (:class:`ClaimBoard`) and, once connected to another Zenoh node for ``SETTLE_S``, brings what
    the member holds (``held()``) in line with :func:`claim_changes` through the member's ``take``
    and ``give_up`` (which declare and drop the member's claim tokens, :func:`claim_key`)."""

    def __init__(self, bus: Any, me: str, names: Sequence[str], held: Callable[[], Iterable[str]],
                 take: Callable[[str], None], give_up: Callable[[str], None],
                 keys: tuple[str, str] = (POOL_KEY, CLAIMS_KEY)):
        self.bus, self.me, self.names, self.held, self.take, self.give_up = bus, me, names, held, take, give_up
        self.board = ClaimBoard(*keys)
        self.on_bus_s: float | None = None  # since when this member has been connected to another Zenoh node
        self._declared: list[Any] = []

    def watch(self) -> None:
        """Declare the pool token and follow the pool's and claims' tokens."""
        liveliness = self.bus.liveliness()
        self._declared = [liveliness.declare_token(f"{self.board.pool_key}/{self.me}")] + [
            liveliness.declare_subscriber(f"{key}/**", lambda sample: self.board.token(
                str(sample.key_expr), not str(sample.kind).endswith("DELETE")), history=True)
            for key in (self.board.pool_key, self.board.claims_key)]

    def close(self) -> None:
        """Stop following the tokens and drop the pool token (the claims are the member's)."""
        for declared in reversed(self._declared):
            declared.undeclare()
        self._declared = []

    def rebalance(self) -> None:
        """The claims brought in line with this member's share (once on the bus for ``SETTLE_S``)."""
        info = self.bus.info
        if not (list(info.peers_zid()) or list(info.routers_zid())):
            self.on_bus_s = None
            return
        self.on_bus_s = self.on_bus_s if self.on_bus_s is not None else time.monotonic()
        if time.monotonic() - self.on_bus_s < SETTLE_S:
            return
        pool, holders = self.board.snapshot()
        gained, lost = claim_changes(self.me, self.names, self.held(), pool, holders)
        for name in sorted(lost):
            self.give_up(name)
        for name in sorted(gained):
            self.take(name)

    def rebalance_if_changed(self) -> None:
        """:meth:`rebalance` as soon as a claim or pool token came or went."""
        if self.board.changed.is_set():
            self.board.changed.clear()
            self.rebalance()


class FusedRobots:
    """The robots one fusion fuses, on the bus: per robot its claim token
    ``cubetrack/robot-claims/<robot>/<me>`` and, with ``per_robot``, its subscriber to
    ``cubetrack/sightings/*/<robot>`` (a shard; a fusion of every robot subscribes to everything
    once); and, from the start, the subscriber to ``cubetrack/shard-sightings/<me>/*``, where workers put the
    sightings of the robots only this fusion claims (:class:`SightingBatches`). ``changed(robot, held)`` is called
    after each take and give-up."""

    def __init__(self, bus: Any, me: str, receive: Callable[[Any], None], changed: Callable[[str, bool], None],
                 per_robot: bool):
        self.bus, self.me, self.receive, self.changed, self.per_robot = bus, me, receive, changed, per_robot
        self.held: dict[str, tuple[Any, Any]] = {}  # robot -> its claim token, its subscriber (or None)
        self._own = bus.declare_subscriber(shard_sightings_key(me), receive)

    def take(self, robot: str) -> None:
        token = self.bus.liveliness().declare_token(claim_key(robot, self.me, ROBOT_CLAIMS_KEY))
        subscriber = self.bus.declare_subscriber(robot_sightings_key(robot), self.receive) if self.per_robot else None
        self.held[robot] = (token, subscriber)
        self.changed(robot, True)

    def give_up(self, robot: str) -> None:
        token, subscriber = self.held.pop(robot)
        if subscriber is not None:
            subscriber.undeclare()
        token.undeclare()
        self.changed(robot, False)

    def close(self) -> None:
        for robot in list(self.held):
            self.give_up(robot)
        self._own.undeclare()


class SightingBatches:
    """What worker ``me`` (or benchmarks/fleet.py's stand-in for one) publishes, gathered over a tick: the sightings of
    the robots one fusion alone claims under ``cubetrack/shard-sightings/<fusion>/<me>`` (:func:`shard_sightings_key`:
    a tick's sightings of all that fusion's robots in one message), those of any other robot (claimed by nobody, or
    by two fusions while a claim changes hands) under ``cubetrack/sightings/<me>/<robot>``, a camera's frames without
    a robot under ``cubetrack/sightings/<camera>`` (:func:`sighting_key`). The claims are followed from the fusions'
    claim tokens (a :class:`ClaimBoard`). :meth:`flush` puts each key's encoded sighting messages as one Zenoh message
    (one alone as itself, several as a batch: :func:`cubetrack.io.sighting_wire.encode_batch`), through a publisher
    declared per key on first use. Fewer, larger messages: Zenoh's cost is mostly per message, on both sides
    (docs/scaling.md)."""

    def __init__(self, bus: Any, me: str) -> None:
        self.bus, self.me = bus, me
        self.pending: dict[str, list[bytes]] = {}
        self.publishers: dict[str, Any] = {}
        self._since_s = math.inf  # time.monotonic() of the oldest pending message
        self.claims = ClaimBoard(SHARD_POOL_KEY, ROBOT_CLAIMS_KEY)
        self._watch = bus.liveliness().declare_subscriber(f"{ROBOT_CLAIMS_KEY}/**", lambda sample: self.claims.token(
            str(sample.key_expr), not str(sample.kind).endswith("DELETE")), history=True)

    def add(self, camera: str, robot: str | None, data: bytes) -> None:
        """An encoded sighting message of ``camera`` holding ``robot``'s markers (None: no robot's)."""
        fusion = None if robot is None else self.claims.sole_holder(robot)
        key = (sighting_key(camera) if robot is None else sighting_key(self.me, robot) if fusion is None
               else shard_sightings_key(fusion, self.me))
        if not self.pending:
            self._since_s = time.monotonic()
        self.pending.setdefault(key, []).append(data)

    def held_s(self) -> float:
        """How long the oldest pending message has waited (0 when none)."""
        return time.monotonic() - self._since_s if self.pending else 0.0

    def flush(self, due_only: bool = False) -> int:
        """Put what is pending, one message per key (``due_only``: only once the oldest has waited
        ``BATCH_HOLD_S``); how many messages were put."""
        if due_only and self.held_s() < BATCH_HOLD_S:
            return 0
        for key, parts in self.pending.items():
            if key not in self.publishers:
                self.publishers[key] = self.bus.declare_publisher(key)
            self.publishers[key].put(parts[0] if len(parts) == 1 else encode_batch(parts))
        count, self.pending = len(self.pending), {}
        return count

    def close(self) -> None:
        """Flush, then undeclare the publishers and stop following the claims."""
        self.flush()
        for publisher in self.publishers.values():
            publisher.undeclare()
        self.publishers = {}
        self._watch.undeclare()


class StateRelay:
    """A fleet's fused states on the bus, so that a robot's new shard takes its track over from the last
    state its old shard published (docs/scaling.md, "When a shard dies"). :meth:`poses`, given the poses
    this fusion makes, publishes at most every ``STATE_EVERY_S``, once a robot has a measured pose since the
    last, one message under ``cubetrack/fused-states/<me>`` holding the filter state (``state_of(robot)``: the
    fusion's, or None) of every robot measured here and still tracked (:func:`cubetrack.io.sighting_wire.encode_states`:
    one message per shard and tick, not one per robot, since Zenoh's cost is mostly per message and every shard
    receives every shard's states); every states message on the bus is kept, undecoded, as its shard's latest (a
    Zenoh thread stores the bytes; another message or version is refused, one line per sender); :meth:`last`
    decodes a robot's newest. The puts run on a thread of the relay's own: a put in a process whose Zenoh threads
    call back into Python waits for the interpreter's lock, milliseconds on a busy machine (measured in a shard:
    2-3 ms a put at load ~20, docs/scaling.md), which the fusion's thread must not."""

    def __init__(self, bus: Any, me: str, state_of: Callable[[str], tuple | None]) -> None:
        self.bus, self.state_of = bus, state_of
        self.key = f"{STATES_KEY}/{key_chunk('fusion', me)}"
        self.latest: dict[str, bytes] = {}  # sender -> its latest states message
        self._refused: set[str] = set()  # senders whose messages were refused (logged once each)
        self._fresh: set[str] = set()  # robots with a measured pose since the last states message
        self._measured: set[str] = set()  # robots measured here and still tracked: each states message holds them all
        self._sent_s = -math.inf
        self._outbox: queue.Queue[bytes | None] = queue.Queue()
        self._subscriber = bus.declare_subscriber(f"{STATES_KEY}/*", self._receive)
        self._sender = threading.Thread(target=self._send, name="state-relay", daemon=True)
        self._sender.start()

    def _send(self) -> None:  # the relay's thread
        publisher = None
        while (data := self._outbox.get()) is not None:
            try:
                publisher = publisher or self.bus.declare_publisher(self.key)
                publisher.put(data)
            except Exception as exc:  # a closing or broken session: the states are lost, the fusion goes on
                log.warning("fused states not published: %s", exc)
            finally:
                self._outbox.task_done()
        if publisher is not None:
            publisher.undeclare()
        self._outbox.task_done()

    def _receive(self, sample: Any) -> None:  # a Zenoh thread
        sender, data = str(sample.key_expr).rsplit("/", 1)[-1], bytes(sample.payload)
        if (error := states_error(data)) is None:
            self.latest[sender] = data
        elif sender not in self._refused:
            self._refused.add(sender)
            log.warning("fused states from %s refused: %s", sender, error)

    def poses(self, poses: Sequence[TrackedPose]) -> None:
        """Publish the states of every robot measured here, once ``STATE_EVERY_S`` has passed since the last
        states message and one of them has a measured pose since it."""
        self._fresh.update(p.robot for p in poses if not p.predicted)
        now = time.monotonic()
        if self._fresh and now - self._sent_s >= STATE_EVERY_S:
            # every robot measured here, not only the fresh ones: a shard's newest message replaces its older
            # ones (:attr:`latest`), so a robot left out would lose the state a take-over starts from
            self._measured |= self._fresh
            states = [FusedState(*state) for robot in sorted(self._measured) if (state := self.state_of(robot))]
            self._measured = {state.robot for state in states}  # one no longer tracked here leaves until measured again
            self._fresh, self._sent_s = set(), now
            if states:
                self._outbox.put(encode_states(states))

    def sent(self) -> None:
        """Wait until every state handed over so far is put."""
        self._outbox.join()

    def last(self, robot: str) -> FusedState | None:
        """The newest state of ``robot`` heard on the bus, from any shard (None: none, or not readable)."""
        newest = None
        for data in list(self.latest.values()):
            try:
                states = decode_states(data)
            except SightingWireError:
                continue
            for state in states:
                if state.robot == robot and (newest is None or state.time_s > newest.time_s):
                    newest = state
        return newest

    def close(self) -> None:
        self._outbox.put(None)
        self._sender.join()
        self._subscriber.undeclare()
