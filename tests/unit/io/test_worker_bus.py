"""Automatic camera claiming (cubetrack.io.worker_bus): the share rule every worker computes alike,
and the take / give-up decisions that keep one reader per camera as workers come and go; the same
for fusion shards and robots, and the per-robot keys of the sightings."""

from __future__ import annotations

import itertools
import math

import pytest

from cubetrack.core.errors import ConfigError
from cubetrack.io.worker_bus import (
    ROBOT_CLAIMS_KEY,
    SHARD_POOL_KEY,
    SIGHTINGS_KEY,
    ClaimBoard,
    Claims,
    claim_changes,
    claim_key,
    robot_sightings_key,
    share_cameras,
    sighting_key,
)

CAMERAS = [f"cam{i}" for i in range(1, 8)]


@pytest.mark.parametrize("workers", [1, 2, 3, 4, 7, 9])
def test_every_camera_has_one_owner_and_shares_differ_by_at_most_one(workers):
    pool = [f"host-{100 + i}" for i in range(workers)]
    owner = share_cameras(CAMERAS, pool)
    assert set(owner) == set(CAMERAS) and set(owner.values()) <= set(pool)
    loads = [list(owner.values()).count(w) for w in pool]
    assert max(loads) - min(loads) <= 1


def test_the_share_does_not_depend_on_the_order_workers_are_seen():
    pool = ["b-2", "a-1", "c-3"]
    answers = {tuple(sorted(share_cameras(CAMERAS, p).items())) for p in itertools.permutations(pool)}
    assert len(answers) == 1
    assert share_cameras(CAMERAS, []) == {}


def test_a_worker_leaving_moves_few_cameras_besides_its_own():
    pool = [f"w{i}" for i in range(4)]
    cameras = [f"cam{i}" for i in range(40)]
    before = share_cameras(cameras, pool)
    after = share_cameras(cameras, pool[1:])
    moved = [c for c in cameras if before[c] != "w0" and after[c] != before[c]]
    assert all(after[c] != "w0" for c in cameras)
    assert len(moved) <= 4, moved  # the cap makes a few move; a plain modulo would move most


def simulate(workers, named=None, rounds=6):
    """Workers that each see every token (the bus), applying claim_changes in turn."""
    named = named or {}
    held = {w: set() for w in workers}
    for _ in range(rounds):
        for w in workers:
            holders = {}
            for v, cams in itertools.chain(held.items(), named.items()):
                for c in cams:
                    holders.setdefault(c, set()).add(v)
            take, give = claim_changes(w, CAMERAS, held[w], workers, holders)
            held[w] = (held[w] - give) | take
    return held


def test_workers_starting_together_end_with_disjoint_fair_shares():
    held = simulate(["h-10", "h-11", "h-12"])
    cams = [c for cs in held.values() for c in cs]
    assert sorted(cams) == sorted(CAMERAS)  # each camera read once
    assert max(map(len, held.values())) - min(map(len, held.values())) <= 1


def test_a_camera_claimed_by_a_named_worker_is_not_shared():
    held = simulate(["h-10", "h-11"], named={"fixed-1": {"cam1", "cam2"}})
    cams = sorted(c for cs in held.values() for c in cs)
    assert cams == sorted(set(CAMERAS) - {"cam1", "cam2"})


def test_a_camera_still_claimed_by_another_is_not_taken_and_a_double_claim_is_resolved():
    # a dead worker's cameras are free once its token is gone, not before
    take, give = claim_changes("b", ["cam1"], set(), ["b"], {"cam1": {"a"}})  # "a" is a named worker
    assert take == set() and give == set()
    take, give = claim_changes("b", ["cam1"], set(), ["b"], {})
    assert take == {"cam1"} and give == set()
    # both claimed cam1 before seeing each other: the greater name gives way
    holders = {"cam1": {"a", "b"}}
    assert claim_changes("b", ["cam1"], {"cam1"}, ["a", "b"], holders)[1] == {"cam1"}
    owner = share_cameras(["cam1"], ["a", "b"])["cam1"]
    assert claim_changes("a", ["cam1"], {"cam1"}, ["a", "b"], holders)[1] == (set() if owner == "a" else {"cam1"})


def test_the_board_follows_tokens_and_ignores_other_keys():
    board = ClaimBoard()
    board.token("cubetrack/pool/h-1", True)
    board.token(claim_key("cam1", "h-1"), True)
    board.token(claim_key("cam1", "h-2"), True)
    board.token("cubetrack/claims/too/many/chunks", True)
    board.token("cubetrack/workers/h-1", True)
    assert board.snapshot() == ({"h-1"}, {"cam1": {"h-1", "h-2"}})
    board.token(claim_key("cam1", "h-1"), False)
    board.token("cubetrack/pool/h-1", False)
    assert board.snapshot() == (set(), {"cam1": {"h-2"}})
    with pytest.raises(ConfigError, match="key chunk"):
        claim_key("cam/1", "h-1")


def test_a_robots_share_of_a_frame_has_its_own_key_that_a_shards_subscription_matches():
    import zenoh

    assert sighting_key("cam1") == "cubetrack/sightings/cam1"
    assert sighting_key("cam1", "r2") == "cubetrack/sightings/cam1/r2"
    mine = zenoh.KeyExpr(robot_sightings_key("r2"))
    assert mine.intersects(zenoh.KeyExpr(sighting_key("cam1", "r2")))
    assert not mine.intersects(zenoh.KeyExpr(sighting_key("cam1", "r22")))
    assert not mine.intersects(zenoh.KeyExpr(sighting_key("cam1")))  # frames without a robot: not a shard's
    every = zenoh.KeyExpr(f"{SIGHTINGS_KEY}/**")
    assert every.intersects(zenoh.KeyExpr(sighting_key("cam1")))
    assert every.intersects(zenoh.KeyExpr(sighting_key("cam1", "r2")))
    with pytest.raises(ConfigError, match="robot name"):
        sighting_key("cam1", "r/2")


def test_the_shards_board_follows_robot_claims_and_not_the_workers():
    board = ClaimBoard(SHARD_POOL_KEY, ROBOT_CLAIMS_KEY)
    board.token(f"{SHARD_POOL_KEY}/s-1", True)
    board.token(claim_key("r1", "s-1", ROBOT_CLAIMS_KEY), True)
    board.token(claim_key("cam1", "w-1"), True)  # a worker's camera claim
    board.token("cubetrack/pool/w-1", True)
    assert board.snapshot() == ({"s-1"}, {"r1": {"s-1"}})
    robots = [f"r{i}" for i in range(5)]
    take, give = claim_changes("s-2", robots, set(), ["s-1", "s-2"], {"r1": {"s-1"}})
    owner = share_cameras(robots, ["s-1", "s-2"])
    assert take == {r for r in robots if owner[r] == "s-2"} - {"r1"} and give == set()


class FakeBus:
    """What Claims uses of a Zenoh session: its peers, and liveliness tokens and subscribers."""

    def __init__(self) -> None:
        self.peers: list[str] = []
        self.tokens: list[str] = []
        self.info = self

    def peers_zid(self) -> list[str]:
        return self.peers

    def routers_zid(self) -> list[str]:
        return []

    def liveliness(self) -> FakeBus:
        return self

    def declare_token(self, key: str) -> FakeToken:
        self.tokens.append(key)
        return FakeToken(self, key)

    def declare_subscriber(self, key: str, callback, history: bool) -> FakeToken:
        return FakeToken(self, None)


class FakeToken:
    def __init__(self, bus: FakeBus, key: str | None):
        self.bus, self.key = bus, key

    def undeclare(self) -> None:
        if self.key is not None:
            self.bus.tokens.remove(self.key)


def test_a_shard_claims_its_share_only_once_on_the_bus_and_gives_way_to_a_smaller_name(monkeypatch):
    monkeypatch.setattr("cubetrack.io.worker_bus.SETTLE_S", 0.0)
    bus, held = FakeBus(), set()
    claims = Claims(bus, "s-2", ["r1", "r2", "r3"], lambda: held, held.add, held.discard,
                    (SHARD_POOL_KEY, ROBOT_CLAIMS_KEY))
    claims.watch()
    assert bus.tokens == [f"{SHARD_POOL_KEY}/s-2"]
    claims.board.token(f"{SHARD_POOL_KEY}/s-2", True)
    claims.rebalance()
    assert held == set()  # alone on the bus (no worker, no other shard): nothing claimed
    bus.peers.append("a peer")
    claims.rebalance()
    assert held == {"r1", "r2", "r3"}
    claims.board.token(f"{SHARD_POOL_KEY}/s-1", True)  # another shard joins and claims its share
    owner = share_cameras(["r1", "r2", "r3"], ["s-1", "s-2"])
    for robot in ("r1", "r2", "r3"):
        claims.board.token(claim_key(robot, "s-2", ROBOT_CLAIMS_KEY), True)
        if owner[robot] == "s-1":
            claims.board.token(claim_key(robot, "s-1", ROBOT_CLAIMS_KEY), True)  # a double claim
    claims.rebalance_if_changed()
    assert held == {r for r in owner if owner[r] == "s-2"}  # s-1's share given up: the greater name gives way
    claims.close()
    assert bus.tokens == []


class StateBus:
    """What StateRelay uses of a Zenoh session: publishers, and a subscriber that sees every put (as Zenoh's does)."""

    def __init__(self) -> None:
        self.puts: list[str] = []
        self.undeclared: list[str] = []
        self.callback = None

    def declare_subscriber(self, key: str, callback) -> FakeToken:
        assert key == "cubetrack/fused-states/*"
        self.callback = callback
        return FakeToken(FakeBus(), None)

    def put(self, key: str, payload: bytes) -> None:
        self.puts.append((key, payload))
        self.callback(type("Sample", (), {"key_expr": key, "payload": payload})())

    def declare_publisher(self, key: str):
        bus = self

        class Publisher:
            def put(self, payload: bytes) -> None:
                bus.put(key, payload)

            def undeclare(self) -> None:
                bus.undeclared.append(key)

        return Publisher()


def test_the_state_relay_publishes_one_message_per_tick_with_every_measured_robot_and_keeps_the_newest(
        monkeypatch, caplog):
    import numpy as np

    from cubetrack.core.records import TrackedPose
    from cubetrack.io.sighting_wire import FusedState, decode_states, encode_state, encode_states
    from cubetrack.io.worker_bus import StateRelay

    clock = [100.0]
    monkeypatch.setattr("cubetrack.io.worker_bus.time.monotonic", lambda: clock[0])

    untracked = {"untracked"}

    def state_of(robot: str) -> tuple | None:
        T = np.eye(4)
        T[:3, 3] = [clock[0], 2.0, 3.0]
        return None if robot in untracked else (robot, clock[0], T, np.ones(3), np.zeros(3), np.eye(12))

    def pose(robot: str, predicted: bool = False) -> TrackedPose:
        return TrackedPose(robot, clock[0], np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), (), (), 0.0,
                           predicted=predicted)

    bus = StateBus()
    relay = StateRelay(bus, "host-1", state_of)
    relay.poses([pose("r1"), pose("r1"), pose("r2", predicted=True), pose("untracked")])
    relay.sent()
    assert [k for k, _ in bus.puts] == ["cubetrack/fused-states/host-1"]   # not for predictions nor untracked
    assert [s.robot for s in decode_states(bus.puts[0][1])] == ["r1"]
    clock[0] += 0.05
    relay.poses([pose("r2")])
    relay.poses([pose("r1")])
    relay.sent()
    assert len(bus.puts) == 1   # within STATE_EVERY_S: r2 and r1 wait for the next tick
    clock[0] += 0.06
    relay.poses([pose("r3")])
    relay.sent()
    assert len(bus.puts) == 2 and [s.robot for s in decode_states(bus.puts[1][1])] == ["r1", "r2", "r3"]
    clock[0] += 0.11
    relay.poses([pose("r3")])
    relay.sent()   # only r3 is fresh, but this message replaces the last: it still holds r1's and r2's states
    assert len(bus.puts) == 3 and [s.robot for s in decode_states(bus.puts[2][1])] == ["r1", "r2", "r3"]
    # r2's track ends here: it leaves the messages, and the relay forgets it until it is measured here again
    untracked.add("r2")
    clock[0] += 0.11
    relay.poses([pose("r3")])
    untracked.discard("r2")
    clock[0] += 0.11
    relay.poses([pose("r3")])
    relay.sent()
    assert [[s.robot for s in decode_states(data)] for _, data in bus.puts[3:]] == [["r1", "r3"], ["r1", "r3"]]
    del bus.puts[3:]
    last = relay.last("r1")
    assert last is not None and last.time_s == clock[0] and last.T_world_cube[0, 3] == clock[0]
    assert relay.last("r4") is None
    # another shard's newer state of r1 wins; an older one does not
    newer = FusedState(*state_of("r1"))._replace(time_s=clock[0] + 1)
    bus.put("cubetrack/fused-states/host-2", encode_states([newer]))
    assert relay.last("r1").time_s == clock[0] + 1
    bus.put("cubetrack/fused-states/host-3", encode_states([newer._replace(time_s=clock[0] - 5)]))
    assert relay.last("r1").time_s == clock[0] + 1
    # a shard before session 15 (one state alone per robot) and a newer envelope: refused, one line per sender
    for _ in range(2):
        bus.put("cubetrack/fused-states/r9", encode_state(newer._replace(robot="r9")))
        bus.put("cubetrack/fused-states/host-4", b"CTFB\x02" + encode_states([newer])[5:])
    assert relay.last("r9") is None and set(relay.latest) == {"host-1", "host-2", "host-3"}
    refused = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert refused == ["fused states from r9 refused: not a fused states message (starts b'CTFS\\x01')",
                       "fused states from host-4 refused: fused states version 2, this reads 1"]
    relay.latest["host-2"] = b"CTFB\x01junk"
    assert relay.last("r1").time_s == clock[0]   # an unreadable message is skipped: host-1's is the newest left
    relay.close()
    assert bus.undeclared == ["cubetrack/fused-states/host-1"]   # the relay's thread ended, its publisher gone


class BatchBus:
    """A bus that records what each declared publisher puts, and passes liveliness tokens to the one watching them."""

    def __init__(self) -> None:
        self.puts: list[tuple[str, bytes]] = []
        self.declared: list[str] = []
        self.undeclared = 0
        self.watched: list[str] = []
        self.callback = None

    def liveliness(self) -> BatchBus:
        return self

    def declare_subscriber(self, key: str, callback, history: bool = False):
        assert history   # the tokens already there count
        self.watched.append(key)
        self.callback = callback
        bus = self

        class Watch:
            def undeclare(self) -> None:
                bus.watched.remove(key)

        return Watch()

    def token(self, key: str, alive: bool) -> None:
        self.callback(type("Sample", (), {"key_expr": key, "kind": "SampleKind.PUT" if alive else "SampleKind.DELETE"}))

    def declare_publisher(self, key: str):
        self.declared.append(key)
        bus = self

        class Publisher:
            def put(self, payload: bytes) -> None:
                bus.puts.append((key, payload))

            def undeclare(self) -> None:
                bus.undeclared += 1

        return Publisher()


def test_a_workers_sightings_go_out_as_one_message_per_robot_per_tick_and_decode_as_sent(monkeypatch):
    import zenoh

    from cubetrack.io.sighting_wire import SightingMessage, decode_messages, encode_sighting
    from cubetrack.io.worker_bus import BATCH_HOLD_S, SightingBatches

    clock = [10.0]
    monkeypatch.setattr("cubetrack.io.worker_bus.time.monotonic", lambda: clock[0])
    sent = {(camera, robot): encode_sighting(SightingMessage(camera, seq, 1.0, 2.0 + seq, 3.0, "full frame", (),
                                                             body=robot))
            for seq, (camera, robot) in enumerate([("cam1", "r1"), ("cam2", "r1"), ("cam2", "r2"), ("cam3", None)])}
    bus = BatchBus()
    batches = SightingBatches(bus, "host-7")
    for (camera, robot), data in sent.items():
        batches.add(camera, robot, data)
    clock[0] += BATCH_HOLD_S / 2
    assert batches.flush(due_only=True) == 0 and bus.puts == []   # not held long enough yet
    clock[0] += BATCH_HOLD_S / 2
    assert batches.flush(due_only=True) == 3 and batches.held_s() == 0.0
    got = {key: decode_messages(payload) for key, payload in bus.puts}
    assert list(got) == ["cubetrack/sightings/host-7/r1", "cubetrack/sightings/host-7/r2", "cubetrack/sightings/cam3"]
    assert [(m.camera, m.body, m.seq) for m in got["cubetrack/sightings/host-7/r1"]] == [("cam1", "r1", 0),
                                                                                      ("cam2", "r1", 1)]
    assert dict(bus.puts)["cubetrack/sightings/host-7/r2"] == sent[("cam2", "r2")]   # one alone: as itself
    shard = zenoh.KeyExpr(robot_sightings_key("r1"))
    assert [k for k in got if shard.intersects(zenoh.KeyExpr(k))] == ["cubetrack/sightings/host-7/r1"]
    batches.add("cam1", "r1", sent[("cam1", "r1")])
    batches.close()   # flushes what is left, then undeclares
    assert len(bus.puts) == 4 and bus.declared.count("cubetrack/sightings/host-7/r1") == 1 and bus.undeclared == 3


def test_a_state_the_bus_refuses_is_logged_and_the_relay_goes_on(caplog):
    """A put that raises (a closing or broken Zenoh session) must not end the relay's thread: the
    next state is still published and waiting for the puts never hangs."""
    import numpy as np

    from cubetrack.core.records import TrackedPose
    from cubetrack.io.worker_bus import StateRelay

    class BrokenOnce(StateBus):
        failed = False

        def put(self, key: str, payload: bytes) -> None:
            if not self.failed:   # the first put only
                self.failed = True
                raise RuntimeError("session closed")
            super().put(key, payload)

    bus = BrokenOnce()
    relay = StateRelay(bus, "host-1", lambda robot: (robot, 1.0, np.eye(4), np.ones(3), np.zeros(3), np.eye(12)))
    pose = TrackedPose("r1", 1.0, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), (), (), 0.0)
    relay.poses([pose])
    relay.sent()
    assert bus.puts == [] and "fused states not published: session closed" in caplog.text
    relay._sent_s = -math.inf   # the next states message is due
    relay.poses([pose])
    relay.sent()
    assert [key for key, _ in bus.puts] == ["cubetrack/fused-states/host-1"]
    relay.close()


def test_a_tick_of_the_robots_one_fusion_alone_claims_goes_to_it_in_one_message(monkeypatch):
    """Issue 28 (session 15): a worker puts its sightings of every robot that one fusion alone claims under that
    fusion's own key, one message per tick however many of its robots; a robot claimed by nobody or by two (a claim
    changing hands) under its own key, as before, which the claiming shards subscribe to."""
    import zenoh

    from cubetrack.io.sighting_wire import SightingMessage, decode_messages, encode_sighting
    from cubetrack.io.worker_bus import SHARD_SIGHTINGS_KEY, SightingBatches, shard_sightings_key

    bus = BatchBus()
    batches = SightingBatches(bus, "host-7")
    assert bus.watched == ["cubetrack/robot-claims/**"]
    for robot, fusion in (("r1", "s-1"), ("r2", "s-1"), ("r3", "s-2"), ("r4", "s-1"), ("r4", "s-2")):
        bus.token(claim_key(robot, fusion, ROBOT_CLAIMS_KEY), True)
    sent = [(camera, robot, encode_sighting(SightingMessage(camera, seq, 1.0, 2.0 + seq, 3.0, "full frame", (),
                                                            body=robot)))
            for seq, (camera, robot) in enumerate([("cam1", "r1"), ("cam2", "r2"), ("cam2", "r3"), ("cam3", "r4"),
                                                   ("cam3", "r5")])]
    for camera, robot, data in sent:
        batches.add(camera, robot, data)
    assert batches.flush() == 4
    got = {key: [m.body for m in decode_messages(payload)] for key, payload in bus.puts}
    assert got == {f"{SHARD_SIGHTINGS_KEY}/s-1/host-7": ["r1", "r2"], f"{SHARD_SIGHTINGS_KEY}/s-2/host-7": ["r3"],
                   "cubetrack/sightings/host-7/r4": ["r4"], "cubetrack/sightings/host-7/r5": ["r5"]}
    mine = zenoh.KeyExpr(shard_sightings_key("s-1"))
    assert [k for k in got if mine.intersects(zenoh.KeyExpr(k))] == [f"{SHARD_SIGHTINGS_KEY}/s-1/host-7"]
    every, r1 = zenoh.KeyExpr(f"{SIGHTINGS_KEY}/**"), zenoh.KeyExpr(robot_sightings_key("r1"))
    assert not every.intersects(mine) and not r1.intersects(zenoh.KeyExpr(f"{SHARD_SIGHTINGS_KEY}/s-1/host-7"))
    bus.token(claim_key("r1", "s-1", ROBOT_CLAIMS_KEY), False)   # s-1 gave r1 up (or died): r1's own key again
    batches.add("cam1", "r1", sent[0][2])
    batches.flush()
    assert bus.puts[-1][0] == "cubetrack/sightings/host-7/r1"
    batches.close()
    assert bus.watched == []
