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

MAX_HEAD_BYTES = 16384  # a response head longer than this is refused
MAX_HEADERS = 100
MAX_CHUNK_LINE = 1024
_SO_TIMESTAMPNS = 35 if sys.platform.startswith("linux") else None  # SCM_TIMESTAMPNS too (asm-generic/socket.h)
_TIMESPEC = struct.Struct("@qq")
_ANC_SPACE = socket.CMSG_SPACE(_TIMESPEC.size) if hasattr(socket, "CMSG_SPACE") else 0


class HttpError(Exception):
    """The peer answered something that is not a usable HTTP response (one line on what)."""


class _Chunked:
    """Incremental ``Transfer-Encoding: chunked`` decoder."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._left = 0  # bytes of the current chunk still to come
        self._crlf = False  # the CRLF after a chunk's data is due
        self.done = False

    def feed(self, data: bytes) -> bytes:
        buf = self._buf
        buf += data
        out = bytearray()
        while buf and not self.done:
            if self._left:
                take = min(self._left, len(buf))
                out += buf[:take]
                del buf[:take]
                self._left -= take
                self._crlf = self._left == 0
                continue
            nl = buf.find(b"\n")
            if nl < 0:
                if len(buf) > MAX_CHUNK_LINE:
                    raise HttpError("bad chunked encoding (chunk size line too long)")
                break
            line = bytes(buf[:nl]).strip()
            del buf[:nl + 1]
            if self._crlf:
                self._crlf = False
                if line:
                    raise HttpError("bad chunked encoding (no line end after a chunk)")
                continue
            size_text = line.split(b";", 1)[0].strip()
            try:
                size = int(size_text, 16)
            except ValueError:
                raise HttpError(f"bad chunked encoding (chunk size {size_text[:20]!r})") from None
            if size < 0:
                raise HttpError("bad chunked encoding (negative chunk size)")
            if size == 0:
                self.done = True
            self._left = size
        return bytes(out)


class HttpGet:
    """``GET url`` on a non-blocking socket. Register :attr:`sock` with a selector for
    :attr:`events` (they change as the exchange goes on: write while connecting, then read) and
    call :meth:`handle` when it is ready; it returns the body bytes that came (b"" for none yet)
    and raises OSError or :class:`HttpError` when the exchange fails. :attr:`head` is the
    response (status, headers with lower-case names) once its head is in; :attr:`ended` is True
    once the body is complete (Content-Length reached, last chunk, or the server closed).
    ``sent_s`` is ``clock()`` taken just before the request was written; ``received_s`` the
    receive time of the last byte read (see the module doc). Resolving a host name blocks; camera nodes are normally given by address. :attr:`filled`: the last read filled
    the buffer (more may be waiting)."""

    def __init__(self, url: str, headers: dict[str, str], clock: Callable[[], float] = time.time,
                 read_bytes: int = 65536):
        u = urlsplit(url)
        if u.scheme != "http" or not u.hostname:
            raise ValueError(f"{url}: only http:// URLs are supported")
        port = u.port or 80
        path = (u.path or "/") + (f"?{u.query}" if u.query else "")
        lines = [f"GET {path} HTTP/1.1", f"Host: {u.hostname}:{port}",
                 *(f"{k}: {v}" for k, v in headers.items()), "", ""]
        self._request = "\r\n".join(lines).encode("latin-1")
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
        self._head = bytearray()
        self._length: int | None = None  # body bytes still to come (Content-Length), None: until close
        self._chunked: _Chunked | None = None
        try:
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self.kernel_stamps:
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
        if not data:
            if self.head is None:
                raise HttpError("the server closed the connection without an answer")
            if self._chunked is not None or self._length:
                raise HttpError("the server closed the connection inside the body")
            self.ended = True
            return b""
        if self.head is None:
            data = self._read_head(data)
            if self.head is None:
                return b""
        if self._chunked is not None:
            data = self._chunked.feed(data)
            self.ended = self._chunked.done
        elif self._length is not None:
            data = data[:self._length]
            self._length -= len(data)
            self.ended = self._length == 0
        return data

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

    def _read_head(self, data: bytes) -> bytes:
        self._head += data
        end = self._head.find(b"\r\n\r\n")
        skip = 4
        if end < 0:
            end, skip = self._head.find(b"\n\n"), 2
        if end < 0:
            if len(self._head) > MAX_HEAD_BYTES:
                raise HttpError(f"response head longer than {MAX_HEAD_BYTES} bytes")
            return b""
        if end > MAX_HEAD_BYTES:
            raise HttpError(f"response head longer than {MAX_HEAD_BYTES} bytes")
        lines = bytes(self._head[:end]).decode("latin-1").splitlines()
        rest = bytes(self._head[end + skip:])
        self._head = bytearray()
        status = lines[0].split(None, 2)
        if len(status) < 2 or not status[0].startswith("HTTP/") or not status[1].isdigit():
            raise HttpError(f"not an HTTP response ({lines[0][:40]!r})")
        if len(lines) > MAX_HEADERS + 1:
            raise HttpError(f"more than {MAX_HEADERS} response headers")
        headers: dict[str, str] = {}
        for line in lines[1:]:
            name, sep, value = line.partition(":")
            if not sep:
                raise HttpError(f"malformed response header ({line[:40]!r})")
            headers[name.strip().lower()] = value.strip()
        self.head = (int(status[1]), headers)
        if "chunked" in headers.get("transfer-encoding", "").lower():
            self._chunked = _Chunked()
        elif (length := headers.get("content-length", "")).isdigit():
            self._length = int(length)
            self.ended = self._length == 0
        return rest
