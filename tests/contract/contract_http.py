"""Raw-socket HTTP helpers for the conformance suite: the bytes on the wire are the contract,
so requests are written by hand and answers read without a client library in between."""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass

from cubecam import mjpeg

TIMEOUT_S = 5.0


@dataclass
class Answer:
    status: int
    headers: dict[str, str]
    head: bytes
    body: bytes


def connect(host: str, port: int, rcvbuf: int | None = None) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.settimeout(TIMEOUT_S)
    s.connect((host, port))
    return s


def exchange(host: str, port: int, request: bytes, timeout_s: float = TIMEOUT_S) -> Answer:
    """Send raw request bytes; read the whole answer until the node closes the connection."""
    with connect(host, port) as s:
        s.settimeout(timeout_s)
        try:
            s.sendall(request)
        except OSError:
            pass  # the node may answer (and close) before it has read everything we send
        data = b""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                chunk = s.recv(65536)
            except ConnectionResetError:
                break
            if not chunk:
                break
            data += chunk
        else:
            raise AssertionError(f"the node did not close the connection within {timeout_s} s: {data[:200]!r}")
    head, sep, body = data.partition(b"\r\n\r\n")
    assert sep, f"no complete response head in {data[:300]!r}"
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ", 2)
    headers = {}
    for line in lines[1:]:
        name, _, value = line.partition(":")
        headers[name.strip().lower()] = value.strip()
    return Answer(int(parts[1]), headers, head + sep, body)


def get(host: str, port: int, target: str, timeout_s: float = TIMEOUT_S) -> Answer:
    return exchange(host, port, f"GET {target} HTTP/1.1\r\nHost: {host}\r\n\r\n".encode(), timeout_s)


class StreamClient:
    """A /stream connection read part by part (strict layout, see cubecam.mjpeg.iter_parts)."""

    def __init__(self, host: str, port: int, target: str = "/stream", rcvbuf: int | None = None):
        self.sock = connect(host, port, rcvbuf)
        self.sock.sendall(f"GET {target} HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
        self.file = self.sock.makefile("rb")
        self.status, self.headers, self.head = mjpeg.read_response_head(self.file)
        self._parts = None

    def parts(self):
        if self._parts is None:
            self._parts = mjpeg.iter_parts(self.file)
        return self._parts

    def next_part(self) -> mjpeg.Part:
        part = next(self.parts(), None)
        assert part is not None, "the stream ended"
        return part

    def close(self) -> None:
        try:
            self.file.close()
        finally:
            self.sock.close()

    def __enter__(self) -> StreamClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
