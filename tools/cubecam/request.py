"""The node's HTTP request reading and routing (contracts §1), with the firmware's outcomes.

Incremental and bounded like ``firmware/core/http.cpp``: a request head (request line and
headers) over :data:`~cubecam.mjpeg.MAX_REQUEST_HEAD` bytes is 431, anything that is not
``METHOD SP target SP HTTP/1.0|1.1`` followed by ``name: value`` lines is 400, empty lines
before the request line are ignored, a request body is never read. Routing: an unknown path
is 404 whatever the method, a known path with another method than GET is 405.
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass

from cubecam.mjpeg import MAX_REQUEST_HEAD, MAX_STREAM_FPS, MAX_TARGET

_TCHAR = set(b"!#$%&'*+-.^_`|~0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ")
_MAX_METHOD = 7


class ParseStatus(enum.Enum):
    INCOMPLETE = "incomplete"
    COMPLETE = "complete"
    MALFORMED = "malformed"
    HEAD_TOO_LARGE = "head too large"


class _State(enum.Enum):
    METHOD = 0
    TARGET = 1
    VERSION = 2
    LINE_FEED = 3
    HEADER_START = 4
    HEADER_NAME = 5
    HEADER_VALUE = 6
    DONE = 7


class RequestParser:
    """Feed bytes until :attr:`status` is no longer INCOMPLETE; later bytes are ignored."""

    def __init__(self) -> None:
        self.status = ParseStatus.INCOMPLETE
        self._state = _State.METHOD
        self._after_lf = _State.HEADER_START
        self._head_bytes = 0
        self._method = bytearray()
        self._target = bytearray()
        self._version = bytearray()
        self._header_name_len = 0

    @property
    def method(self) -> str:
        return self._method.decode("ascii", "replace")

    @property
    def target(self) -> str:
        return self._target.decode("ascii", "replace")

    def feed(self, data: bytes) -> ParseStatus:
        for c in data:
            if self.status is not ParseStatus.INCOMPLETE:
                break
            self._head_bytes += 1
            if self._head_bytes > MAX_REQUEST_HEAD:
                self.status = ParseStatus.HEAD_TOO_LARGE
                break
            self.status = self._step(c)
        return self.status

    def _end_of_line(self) -> ParseStatus:
        if self._state is _State.VERSION:
            if bytes(self._version) not in (b"HTTP/1.1", b"HTTP/1.0"):
                return ParseStatus.MALFORMED
            self._state = _State.HEADER_START
            return ParseStatus.INCOMPLETE
        if self._state is _State.HEADER_START:
            self._state = _State.DONE
            return ParseStatus.COMPLETE
        if self._state is _State.HEADER_VALUE:
            self._state = _State.HEADER_START
            return ParseStatus.INCOMPLETE
        return ParseStatus.MALFORMED

    def _step(self, c: int) -> ParseStatus:
        st = self._state
        if st is _State.LINE_FEED:
            if c != 0x0A:
                return ParseStatus.MALFORMED
            self._state = self._after_lf
            return self._end_of_line()
        if c in (0x0D, 0x0A):
            if st is _State.METHOD and not self._method:
                return ParseStatus.INCOMPLETE  # empty lines before the request line (RFC 9112 2.2)
            if st not in (_State.VERSION, _State.HEADER_START, _State.HEADER_VALUE):
                return ParseStatus.MALFORMED
            if c == 0x0A:
                return self._end_of_line()
            self._after_lf = st
            self._state = _State.LINE_FEED
            return ParseStatus.INCOMPLETE
        if st is _State.METHOD:
            if c == 0x20 and self._method:
                self._state = _State.TARGET
                return ParseStatus.INCOMPLETE
            if c not in _TCHAR or len(self._method) >= _MAX_METHOD:
                return ParseStatus.MALFORMED
            self._method.append(c)
            return ParseStatus.INCOMPLETE
        if st is _State.TARGET:
            if c == 0x20 and self._target:
                self._state = _State.VERSION
                return ParseStatus.INCOMPLETE
            if c <= 0x20 or c >= 0x7F:
                return ParseStatus.MALFORMED
            self._target.append(c)
            return ParseStatus.INCOMPLETE
        if st is _State.VERSION:
            if len(self._version) >= 8:
                return ParseStatus.MALFORMED
            self._version.append(c)
            return ParseStatus.INCOMPLETE
        if st is _State.HEADER_START:
            self._header_name_len = 0
            self._state = _State.HEADER_NAME
            return self._step(c)
        if st is _State.HEADER_NAME:
            if c == 0x3A and self._header_name_len > 0:
                self._state = _State.HEADER_VALUE
                return ParseStatus.INCOMPLETE
            if c not in _TCHAR:
                return ParseStatus.MALFORMED
            self._header_name_len += 1
            return ParseStatus.INCOMPLETE
        if st is _State.HEADER_VALUE:
            if (c < 0x20 and c != 0x09) or c == 0x7F:
                return ParseStatus.MALFORMED
            return ParseStatus.INCOMPLETE
        return ParseStatus.MALFORMED


class Route(enum.Enum):
    INDEX = "/"
    STREAM = "/stream"
    CAPTURE = "/capture"
    STATUS = "/status"
    TIME = "/time"
    ERROR = ""


@dataclass(frozen=True, slots=True)
class RouteDecision:
    route: Route
    status: int = 200
    fps_cap: float | None = None  # /stream?fps=N


_ROUTES = {r.value: r for r in Route if r is not Route.ERROR}
_TENTHS = re.compile(r"^(\d{1,6})(?:\.(\d))?$")


def parse_fps(text: str) -> float | None:
    """``30``, ``7.5`` -> frames per second; None unless 0 < fps <= 30 with at most one decimal."""
    m = _TENTHS.match(text)
    if not m:
        return None
    tenths = int(m.group(1)) * 10 + int(m.group(2) or 0)
    if tenths == 0 or tenths > MAX_STREAM_FPS * 10:
        return None
    return tenths / 10.0


def route(parser: RequestParser) -> RouteDecision:
    """The answer to a finished request head."""
    if parser.status is ParseStatus.HEAD_TOO_LARGE:
        return RouteDecision(Route.ERROR, 431)
    if parser.status is not ParseStatus.COMPLETE:
        return RouteDecision(Route.ERROR, 400)
    target = parser.target
    if len(target) > MAX_TARGET or not target.startswith("/"):
        return RouteDecision(Route.ERROR, 404)
    path, _, query = target.partition("?")
    r = _ROUTES.get(path)
    if r is None:
        return RouteDecision(Route.ERROR, 404)
    if parser.method != "GET":
        return RouteDecision(Route.ERROR, 405)
    fps_cap = None
    if r is Route.STREAM and query:
        for item in query.split("&"):
            name, eq, value = item.partition("=")
            if name == "fps" and eq:
                fps_cap = parse_fps(value)
                if fps_cap is None:
                    return RouteDecision(Route.ERROR, 400)
                break
    return RouteDecision(r, 200, fps_cap)
