"""One HTTP/1.1 GET on a non-blocking socket, driven by a caller's ``selectors`` loop: the live
source reads every camera's stream and ``/time`` round trips on one thread this way
(:class:`cubetrack.source.streams.LiveCameras`), so reading never competes with the per-frame
work of its process for the GIL (docs/live.md).

:class:`HttpGet` connects, writes the request, parses the response head (bounded in size, so an
endless or flooding head is an error, not a growing buffer) and hands back the body as it
arrives, de-chunked where the server sends ``Transfer-Encoding: chunked``. Each read is stamped
with the kernel's receive time of the newest data it returned (``SO_TIMESTAMPNS`` on Linux;
elsewhere the time of the read), so a frame's arrival time does not include the time its bytes
waited in the socket while the process was busy. (Data that waited together is stamped with
the newest arrival among it: an upper bound for the older frames, right for the newest.)
"""

from __future__ import annotations

import errno
import os
import selectors
import socket
import struct
import sys
import time
from collections.abc import Callable
from urllib.parse import urlsplit

import h11

MAX_HEAD_BYTES = 16384  # a response head (or a chunk-size line) longer than this is refused
_SO_TIMESTAMPNS = 35 if sys.platform.startswith("linux") else None  # SCM_TIMESTAMPNS too (asm-generic/socket.h)
_TIMESPEC = struct.Struct("@qq")
_ANC_SPACE = socket.CMSG_SPACE(_TIMESPEC.size) if hasattr(socket, "CMSG_SPACE") else 0
_SO_RCVLOWAT = getattr(socket, "SO_RCVLOWAT", None)
MAX_LOW_WATER_BYTES = 65536  # the most a socket is told to gather before it counts as readable


class HttpError(Exception):
    """The peer answered something that is not a usable HTTP response (one line on what)."""


class HttpGet:
    """``GET url`` on a non-blocking socket. Register :attr:`sock` with a selector for
    :attr:`events` (they change as the exchange goes on: write while connecting, then read) and
    call :meth:`handle` when it is ready; it returns the body bytes that came (b"" for none yet)
    and raises OSError or :class:`HttpError` when the exchange fails. :attr:`head` is the
    response (status, headers with lower-case names) once its head is in; :attr:`ended` is True
    once the body is complete (Content-Length reached, last chunk, or the server closed).
    ``sent_s`` is ``clock()`` taken just before the request was written; ``received_s`` the
    receive time of the last byte read (see the module doc). Resolving a host name blocks;
    camera nodes are normally given by address. :attr:`filled`: the last read filled the buffer
    (more may be waiting). The HTTP/1.1 parsing (head, body framing, chunks) is ``h11``'s."""

    def __init__(self, url: str, headers: dict[str, str], clock: Callable[[], float] = time.time,
                 read_bytes: int = 65536):
        u = urlsplit(url)
        if u.scheme != "http" or not u.hostname:
            raise ValueError(f"{url}: only http:// URLs are supported")
        port = u.port or 80
        path = (u.path or "/") + (f"?{u.query}" if u.query else "")
        self._http = h11.Connection(h11.CLIENT, max_incomplete_event_size=MAX_HEAD_BYTES)
        self._request = self._http.send(h11.Request(
            method="GET", target=path, headers=[("Host", f"{u.hostname}:{port}"), *headers.items()]))
        self._http.send(h11.EndOfMessage())
        self.clock = clock
        self.read_bytes = read_bytes
        self.kernel_stamps = clock is time.time and _SO_TIMESTAMPNS is not None
        family, kind, proto, _, address = socket.getaddrinfo(u.hostname, port, type=socket.SOCK_STREAM)[0]
        self.sock = socket.socket(family, kind, proto)
        self.sock.setblocking(False)
        self.events = selectors.EVENT_WRITE
        self.connected = False
        self.head: tuple[int, dict[str, str]] | None = None
        self.ended = False
        self.sent_s = float("nan")
        self.received_s = float("nan")
        self.filled = False
        self._low_water = 1 if _SO_RCVLOWAT is not None else 0  # bytes it gathers before it is readable (0: cannot)
        try:
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self.kernel_stamps and _SO_TIMESTAMPNS is not None:  # (kernel_stamps: it is not None)
                try:
                    self.sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
                except OSError:
                    self.kernel_stamps = False
            code = self.sock.connect_ex(address)
        except OSError:
            self.sock.close()
            raise
        if code not in (0, errno.EINPROGRESS, errno.EWOULDBLOCK):
            self.sock.close()
            raise OSError(code, os.strerror(code))

    def close(self) -> None:
        self.sock.close()

    def wake_after(self, n_bytes: int) -> None:
        """Have a selector report the socket readable only once ``n_bytes`` more bytes have come
        (``SO_RCVLOWAT``; at most ``MAX_LOW_WATER_BYTES``, at least 1), or when the peer closes or
        fails: a caller that knows how much of a message is still to come is then not woken for
        each piece of it. A read still returns whatever is there. Where the platform does not
        have it, the socket stays readable at every byte."""
        want = max(1, min(int(n_bytes), MAX_LOW_WATER_BYTES))
        if not self._low_water or want == self._low_water or _SO_RCVLOWAT is None:
            return
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, _SO_RCVLOWAT, want)
        except OSError:
            self._low_water = 0
            return
        self._low_water = want

    def handle(self) -> bytes:
        if not self.connected:
            code = self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
            if code:
                raise OSError(code, os.strerror(code))
            self.connected = True
            self.sent_s = self.clock()
            sent = self.sock.send(self._request)  # a few hundred bytes: a fresh socket takes them at once
            if sent != len(self._request):
                raise HttpError("the request could not be written at once")
            self.events = selectors.EVENT_READ
            return b""
        data = self._recv()
        self._http.receive_data(data)  # b"": the server closed the connection
        body = bytearray()
        try:
            while not self.ended:
                event = self._http.next_event()
                if event is h11.NEED_DATA:
                    break
                if isinstance(event, h11.Response):
                    self.head = (event.status_code,
                                 {name.decode("latin-1"): value.decode("latin-1") for name, value in event.headers})
                elif isinstance(event, h11.Data):
                    body += event.data
                elif isinstance(event, (h11.EndOfMessage, h11.ConnectionClosed)):
                    if self.head is None:
                        raise HttpError("the server closed the connection without an answer")
                    self.ended = True
        except h11.RemoteProtocolError as exc:
            if self.head is None and not data:
                raise HttpError("the server closed the connection without an answer") from None
            raise HttpError(f"bad HTTP response ({exc})") from None
        return bytes(body)

    def _recv(self) -> bytes:
        if not self.kernel_stamps:
            data = self.sock.recv(self.read_bytes)
            self.received_s = self.clock()
            self.filled = len(data) == self.read_bytes
            return data
        data, ancillary, _flags, _address = self.sock.recvmsg(self.read_bytes, _ANC_SPACE)
        self.filled = len(data) == self.read_bytes
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(payload) >= _TIMESPEC.size:
                seconds, nanoseconds = _TIMESPEC.unpack_from(payload)
                self.received_s = seconds + nanoseconds * 1e-9
                break
        else:
            self.received_s = self.clock()
        return data
