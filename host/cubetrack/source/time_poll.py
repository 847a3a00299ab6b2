"""The ``/time`` poller of a camera node (contracts §1): one round trip (host send, device time,
host receive) per request, the TCP connection opened before the send time is taken so that the
round trip brackets only the request and its answer. The live source
(:mod:`cubetrack.source.streams`) runs :class:`_ClockPoll` on its event loop; :func:`poll_time` is
the blocking one-off."""

from __future__ import annotations

import logging
import re
import selectors
import time
from collections.abc import Callable
from urllib.parse import urljoin

from cubetrack.core.cameras import ClockSample
from cubetrack.source.http_get import HttpGet

log = logging.getLogger(__name__)


def time_url(stream_url: str) -> str:
    """The node's ``/time`` URL beside its stream URL (``http://h:p/stream?fps=5`` -> ``http://h:p/time``)."""
    return urljoin(stream_url, "time")


def parse_time_answer(body: bytes) -> float:
    """Seconds from a ``/time`` body (``<seconds>.<microseconds>``); ValueError for anything else."""
    text = body.decode("ascii").strip()
    if not re.fullmatch(r"\d{1,12}(\.\d{1,9})?", text):
        raise ValueError(f"not a time: {text[:40]!r}")
    return float(text)


class _ClockPoll:
    """One ``/time`` round trip on an event loop: connect within ``timeout_s``, then the request
    and its answer within ``timeout_s``. :meth:`handle` returns the sample once the answer is
    in; raises OSError / :class:`~cubetrack.source.http_get.HttpError` (no answer) or ValueError (a garbage answer)."""

    def __init__(self, url: str, timeout_s: float, clock: Callable[[], float]):
        self.get = HttpGet(url, {"Connection": "close"}, clock, read_bytes=256)
        self.timeout_s = timeout_s
        self.deadline = time.monotonic() + timeout_s
        self.body = bytearray()

    def handle(self) -> ClockSample | None:
        was_connected = self.get.connected
        self.body += self.get.handle()
        if self.get.connected and not was_connected:  # the request went out: the answer's time starts
            self.deadline = time.monotonic() + self.timeout_s
        if len(self.body) > 128:
            raise ValueError("answer longer than 128 bytes")
        if not self.get.ended:
            return None
        status = self.get.head[0] if self.get.head else 0
        if status != 200:
            raise ValueError(f"HTTP {status}")
        return ClockSample(self.get.sent_s, parse_time_answer(bytes(self.body)), self.get.received_s)


def poll_time(url: str, timeout_s: float, clock: Callable[[], float] = time.time) -> ClockSample:
    """One ``/time`` round trip, waited for. The TCP connection is opened before ``host_send`` is
    taken, so the round trip brackets the request and its answer only. Raises OSError /
    :class:`~cubetrack.source.http_get.HttpError` / ValueError."""
    poll = _ClockPoll(url, timeout_s, clock)
    try:
        with selectors.DefaultSelector() as selector:
            selector.register(poll.get.sock, poll.get.events)
            while True:
                left = poll.deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError("timed out")
                if selector.select(left):
                    sample = poll.handle()
                    if sample is not None:
                        return sample
                    selector.modify(poll.get.sock, poll.get.events)
    finally:
        poll.get.close()
