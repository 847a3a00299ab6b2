"""Hostile camera nodes on 127.0.0.1, for tests of the live source: each KIND misbehaves in one
way a broken or malicious node (or something else at its address) can.

Run as a separate process so that its floods do not share the test's interpreter::

    python hostile_peers.py KIND [KIND ...]

It prints ``KIND PORT`` per kind, then ``ready``, serves until SIGTERM and prints
``sent KIND BYTES`` per kind before it exits. Kinds (for ``/stream``; ``/time`` gets the same
treatment where it makes sense, else a garbage answer):

- endless_header: an HTTP status line, then one header line that never ends;
- many_headers: an HTTP status line, then header lines forever;
- endless_part_header: a good multipart head, then a part whose headers never end;
- huge_part: a part declaring Content-Length 5 GB, then zeros as fast as the socket takes them;
- huge_part_no_length: a part without Content-Length that never ends, as fast as possible;
- short_length: parts whose Content-Length is shorter than their JPEG (20 parts/s);
- long_length: parts whose Content-Length is 10x their JPEG (20 parts/s);
- trickle_body: a good head and part headers, then one byte a second;
- trickle_head: the status line at one byte a second;
- trickle_fast: the status line at one byte every 0.3 s (below every per-read timeout);
- silent: accepts the connection, reads the request, never answers.
"""

from __future__ import annotations

import signal
import socket
import sys
import threading
import time
from collections import Counter

BOUNDARY = b"hostile"
HEAD = (b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace;boundary=hostile\r\n"
        b"Connection: close\r\n\r\n")
DELIM = b"\r\n--hostile\r\n"
JPEG = b"\xff\xd8" + bytes(range(256)) * 12 + b"\xff\xd9"
FLOOD = bytes(1 << 20)
TIME_GARBAGE = b"HTTP/1.1 200 OK\r\nContent-Length: 5\r\nConnection: close\r\n\r\nhello"

stop = threading.Event()
sent: Counter[str] = Counter()
_lock = threading.Lock()


def _send(kind: str, conn: socket.socket, data: bytes) -> None:
    conn.sendall(data)
    with _lock:
        sent[kind] += len(data)


def _flood(kind: str, conn: socket.socket, prefix: bytes, filler: bytes = FLOOD) -> None:
    _send(kind, conn, prefix)
    while not stop.is_set():
        _send(kind, conn, filler)


def _trickle(kind: str, conn: socket.socket, data: bytes, period_s: float) -> None:
    for i in range(10**9):
        if stop.wait(period_s):
            return
        _send(kind, conn, data[i % len(data):i % len(data) + 1])


def _parts(kind: str, conn: socket.socket, length: int) -> None:
    _send(kind, conn, HEAD + DELIM)
    seq = 0
    while not stop.wait(0.05):
        seq += 1
        head = (f"Content-Type: image/jpeg\r\nContent-Length: {length}\r\nX-Timestamp: {seq}.000000\r\n"
                f"X-Frame: {seq}\r\n\r\n")
        _send(kind, conn, head.encode() + JPEG + DELIM)


def serve(kind: str, conn: socket.socket, path: str) -> None:
    part_head = DELIM + b"Content-Type: image/jpeg\r\nX-Timestamp: 1.000000\r\n"
    if path.startswith("/time") and kind not in ("endless_header", "many_headers", "silent") \
            and not kind.startswith("trickle_"):
        _send(kind, conn, TIME_GARBAGE)
        return
    if kind == "endless_header":
        _flood(kind, conn, b"HTTP/1.1 200 OK\r\nX-Junk: ", b"a" * 65536)
    elif kind == "many_headers":
        _flood(kind, conn, b"HTTP/1.1 200 OK\r\n", b"X-Junk: a\r\n" * 4096)
    elif kind == "endless_part_header":
        _flood(kind, conn, HEAD + DELIM + b"X-Pad: ", b"a" * 65536)
    elif kind == "huge_part":
        _flood(kind, conn, HEAD + part_head + b"Content-Length: 5000000000\r\n\r\n\xff\xd8")
    elif kind == "huge_part_no_length":
        _flood(kind, conn, HEAD + part_head + b"\r\n\xff\xd8")
    elif kind == "short_length":
        _parts(kind, conn, 100)
    elif kind == "long_length":
        _parts(kind, conn, 10 * len(JPEG))
    elif kind == "trickle_body":
        _send(kind, conn, HEAD + part_head + b"\r\n")
        _trickle(kind, conn, JPEG, 1.0)
    elif kind == "trickle_head":
        _trickle(kind, conn, HEAD, 1.0)
    elif kind == "trickle_fast":
        _trickle(kind, conn, HEAD, 0.3)
    elif kind == "silent":
        stop.wait()
    else:
        raise ValueError(f"unknown kind {kind!r}")


def _connection(kind: str, conn: socket.socket) -> None:
    try:
        conn.settimeout(5.0)
        request = b""
        while b"\r\n\r\n" not in request and len(request) < 8192:
            chunk = conn.recv(4096)
            if not chunk:
                return
            request += chunk
        conn.settimeout(None)
        path = request.split(b" ", 2)[1].decode("latin-1") if request.count(b" ") >= 2 else "/"
        serve(kind, conn, path)
    except OSError:
        pass  # the client gave up: exactly what these peers want
    finally:
        conn.close()


def _accept(kind: str, server: socket.socket) -> None:
    server.settimeout(0.2)
    while not stop.is_set():
        try:
            conn, _ = server.accept()
        except TimeoutError:
            continue
        threading.Thread(target=_connection, args=(kind, conn), daemon=True).start()


def main(kinds: list[str]) -> int:
    for kind in kinds:
        server = socket.create_server(("127.0.0.1", 0))
        threading.Thread(target=_accept, args=(kind, server), daemon=True).start()
        print(kind, server.getsockname()[1], flush=True)
    print("ready", flush=True)
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    while not stop.wait(0.1):
        pass
    time.sleep(0.1)
    with _lock:
        for kind in kinds:
            print("sent", kind, sent[kind], flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
