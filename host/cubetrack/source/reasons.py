"""Why a camera cannot be read, as one line a person can act on.

The live source keeps each camera's last connection or stream error (``CameraStats.last_error``);
the status line, the dashboard and the logs show it. The text names the camera's address and
says what to check, instead of the exception's own wording: ``connection refused by
127.0.0.1:9 — is the node on and on this network?``, not ``[Errno 111] Connection refused``.
"""

from __future__ import annotations

import errno
import re
import socket
from collections.abc import Mapping
from urllib.parse import urlsplit

MAX_CHARS = 200  # a reason is one line of a status display

# errno -> (what happened, what to check); {where} is host:port
_OS_ERRORS = {
    errno.ECONNREFUSED: ("connection refused by {where}", "is the node on and on this network?"),
    errno.ECONNRESET: ("{where} reset the connection", "is the node restarting, or serving too many clients?"),
    errno.EHOSTUNREACH: ("no route to {where}", "is this computer on the node's network?"),
    errno.ENETUNREACH: ("no network to reach {where}", "is this computer connected to the node's network?"),
    errno.EPIPE: ("{where} closed the connection", "is the node restarting?"),
}


def where_of(url: str) -> str:
    """``host:port`` of a camera URL (port 80 when the URL gives none)."""
    parts = urlsplit(url)
    return f"{parts.hostname or url}:{parts.port or 80}"


def one_line(text: str) -> str:
    """``text`` on one line of at most :data:`MAX_CHARS` characters."""
    text = re.sub(r"\s+", " ", text).strip()
    return text if len(text) <= MAX_CHARS else text[:MAX_CHARS - 3] + "..."


def connection_reason(exc: BaseException, url: str) -> str:
    """Why the connection to the camera at ``url`` failed or ended (``exc``), as one line."""
    where = where_of(url)
    if isinstance(exc, socket.gaierror):
        return one_line(f"cannot find the address of {urlsplit(url).hostname!r} — check the camera's url in the config")
    if isinstance(exc, OSError) and exc.errno in _OS_ERRORS:
        happened, check = _OS_ERRORS[exc.errno]
        return one_line(f"{happened.format(where=where)} — {check}")
    if isinstance(exc, OSError):
        return one_line(f"cannot reach {where}: {exc.strerror or exc} — is the node on and on this network?")
    return one_line(f"{where}: {str(exc) or type(exc).__name__} — the url should be a camera node's /stream")


def timeout_reason(what: str, limit_s: float, url: str) -> str:
    """No connection (``what`` = ``connect``), no answer, or a stream that went silent within
    ``limit_s`` seconds."""
    where = where_of(url)
    if what == "connect":
        return f"no answer from {where} within {limit_s:g} s — is the node on and on this network?"
    if what == "the answer":
        return f"{where} took the connection but did not answer within {limit_s:g} s — is it a camera node?"
    return f"the stream from {where} stopped for {limit_s:g} s — is the node still on and in Wi-Fi range?"


def http_status_reason(status: int, url: str) -> str:
    """The camera answered ``status`` instead of 200."""
    path = urlsplit(url).path or "/"
    if status == 503:
        return f"{where_of(url)} is busy (HTTP 503: it serves a few clients at once) — close other viewers of {path}"
    return f"{where_of(url)} answered HTTP {status} for {path} — the url should be the node's /stream"


def content_type_reason(content_type: str, url: str) -> str:
    """The camera answered something that is not an MJPEG stream."""
    shown = content_type.split(";")[0].strip() or "none"
    return one_line(f"{where_of(url)} sent {shown!r}, not an MJPEG stream — the url should be the node's /stream")


def closed_reason(url: str) -> str:
    """The camera ended its stream."""
    return f"{where_of(url)} closed the stream — is the node restarting?"


def broken_frames_reason(bad: Mapping[str, int], url: str) -> str:
    """Broken stream parts of a connection (why -> how many), e.g. frames that are not whole JPEGs."""
    why, _ = max(bad.items(), key=lambda item: item[1])
    return (f"{where_of(url)} sent {sum(bad.values())} broken frame(s) on this connection ({why}) — restart "
            f"the node; if it goes on, reseat its camera board")
