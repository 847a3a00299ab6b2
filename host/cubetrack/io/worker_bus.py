"""The bus between ``cubetrack worker`` and ``cubetrack fuse`` (docs/scaling.md): its Zenoh key
expressions and the claim protocol by which automatic workers share the cameras (the messages on it
are :mod:`cubetrack.io.sighting_wire`'s).

Every worker holds a liveliness token ``cubetrack/claims/<camera>/<worker>`` per camera it reads; an
automatic worker also holds ``cubetrack/pool/<worker>``. The cameras no named worker claims are
shared among the automatic workers by :func:`share_cameras` (the same answer in every worker that
sees the same tokens); :func:`claim_changes` says what a worker takes and gives up, and
:class:`ClaimBoard` follows the tokens seen on the bus.
"""

from __future__ import annotations

import hashlib
import re
import threading
from collections.abc import Iterable, Mapping, Sequence

from cubetrack.core.errors import ConfigError

SIGHTINGS_KEY = "cubetrack/sightings"  # one camera's sightings: cubetrack/sightings/<camera>
WORKERS_KEY = "cubetrack/workers"  # a liveliness token per running worker: cubetrack/workers/<host>-<pid>
CLAIMS_KEY = "cubetrack/claims"  # a liveliness token per camera a worker reads: cubetrack/claims/<camera>/<worker>
POOL_KEY = "cubetrack/pool"  # a liveliness token per automatic worker: cubetrack/pool/<worker>


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
