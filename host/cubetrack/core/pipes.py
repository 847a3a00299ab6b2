"""Pipes from other processes, polled with one kept ``select.poll`` object.

``Connection.poll()`` and ``multiprocessing.connection.wait`` set up a selector on every
call (~10 and ~13 us on the 2-core machine of issue 31, against ~0.8 us for a kept poll object's
``poll(0)`` over two pipes), and the live loop polls its pipes several times a frame: the camera
worker processes their forecast pipe after every frame, the tracker's process every worker's
pipe after every message (:mod:`cubetrack.app.camera_workers`). A ``multiprocessing`` connection
reads whole messages from its descriptor with no buffer of its own, so "its descriptor is
readable" is "a message (or the pipe's end) is there", as ``Connection.poll()`` says.
"""

from __future__ import annotations

import ctypes
import math
import select
from collections.abc import Iterator, Mapping, MutableMapping
from multiprocessing.connection import Connection
from multiprocessing.context import BaseContext
from typing import TypeVar

V = TypeVar("V")


class PipePoll(MutableMapping[Connection, V]):
    """Connections (each with a value of the caller's, e.g. its lane) and one poll object kept
    over them: :meth:`ready` is ``multiprocessing.connection.wait`` over them, in the order
    they were added. A connection leaves with ``del``; it may be closed before it leaves."""

    def __init__(self, conns: Mapping[Connection, V] | None = None):
        self._poll = select.poll()
        self._values: dict[Connection, tuple[int, V]] = {}  # connection -> (its descriptor, value)
        self._by_fd: dict[int, Connection] = {}
        self.update(conns or {})

    def __getitem__(self, conn: Connection) -> V:
        return self._values[conn][1]

    def __setitem__(self, conn: Connection, value: V) -> None:
        if conn not in self._values:
            fd = conn.fileno()
            self._poll.register(fd, select.POLLIN)
            self._by_fd[fd] = conn
            self._values[conn] = (fd, value)
        else:
            self._values[conn] = (self._values[conn][0], value)

    def __delitem__(self, conn: Connection) -> None:
        fd, _ = self._values.pop(conn)
        del self._by_fd[fd]
        self._poll.unregister(fd)

    def __iter__(self) -> Iterator[Connection]:
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def ready(self, timeout_s: float | None = 0.0) -> list[Connection]:
        """The connections with something to read (a message, or their end), waiting up to
        ``timeout_s`` (None or inf: for ever) for one; [] after the timeout."""
        if not self._values:
            return []
        ms = None if timeout_s is None or math.isinf(timeout_s) else max(0, math.ceil(timeout_s * 1000.0))
        return [self._by_fd[fd] for fd, _events in self._poll.poll(ms)]  # POLLIN, or the end: POLLHUP, POLLERR


class LatestBytes:
    """The newest of a series of messages from one process to others, in shared memory: a new one
    replaces the last and wakes nobody (a pipe message wakes its reader's ``poll``); each reader
    takes it when it next looks (:meth:`newer`), e.g. a camera worker process before it plans a
    frame. Made before the processes start (its memory and lock go to them as ``Process``
    arguments); a message over ``capacity`` bytes is refused (:meth:`post` returns False)."""

    def __init__(self, context: BaseContext, capacity: int = 65536):
        self.capacity = capacity
        self._head = context.RawArray("q", 2)  # the version (0: nothing posted yet), the length in bytes
        self._data = context.RawArray("B", capacity)
        self._lock = context.Lock()

    def post(self, message: bytes) -> bool:
        """Replace the message (False, nothing posted: over ``capacity``)."""
        if len(message) > self.capacity:
            return False
        with self._lock:
            ctypes.memmove(self._data, message, len(message))
            self._head[1] = len(message)
            self._head[0] += 1
        return True

    def newer(self, version: int) -> tuple[int, bytes | None]:
        """(the newest version, its message) if one newer than ``version`` (0: none seen) was
        posted, else (``version``, None)."""
        if self._head[0] == version:  # read without the lock: a stale read only defers the message to the next look
            return version, None
        with self._lock:
            return self._head[0], ctypes.string_at(ctypes.addressof(self._data), self._head[1])
