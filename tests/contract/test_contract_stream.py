"""Contracts §1, the MJPEG stream: exact part layout, frame numbers and timestamps, rate cap,
several clients, and "newest frame only" for a slow client."""

from __future__ import annotations

import itertools
import re
import socket
import time

import cv2
import numpy as np
from contract_http import StreamClient, connect, get

PART = re.compile(
    rb"Content-Type: image/jpeg\r\nContent-Length: (\d+)\r\nX-Timestamp: (\d+\.\d{6})\r\nX-Frame: (\d+)\r\n\r\n")


def read_exactly(sock: socket.socket, n: int) -> bytes:
    out = b""
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        assert chunk, f"stream ended after {len(out)} of {n} bytes"
        out += chunk
    return out


def read_until(sock: socket.socket, marker: bytes, limit: int = 4096) -> bytes:
    out = b""
    while not out.endswith(marker):
        chunk = sock.recv(1)
        assert chunk, f"stream ended while waiting for {marker!r} after {out[-200:]!r}"
        out += chunk
        assert len(out) <= limit, f"no {marker!r} in {limit} bytes: {out[:200]!r}"
    return out


def test_stream_bytes_follow_the_part_layout_exactly(node):
    with connect(node.host, node.port) as s:
        s.sendall(b"GET /stream HTTP/1.1\r\nHost: x\r\n\r\n")
        head = read_until(s, b"\r\n\r\n")
        m = re.search(rb"\r\nContent-Type: multipart/x-mixed-replace;boundary=([^\r\n;]+)\r\n", head)
        assert m, head
        delimiter = b"\r\n--" + m.group(1) + b"\r\n"
        assert read_exactly(s, len(delimiter)) == delimiter, "the body starts with the first delimiter"
        for _ in range(4):
            header = read_until(s, b"\r\n\r\n", 512)
            pm = PART.fullmatch(header)
            assert pm, f"part header not byte-exact: {header!r}"
            jpeg = read_exactly(s, int(pm.group(1)))
            assert jpeg[:2] == b"\xff\xd8" and jpeg[-2:] == b"\xff\xd9"
            # the next delimiter follows the JPEG at once
            assert read_exactly(s, len(delimiter)) == delimiter


def test_parts_are_whole_jpegs_of_the_frame_size(node):
    with StreamClient(node.host, node.port) as c:
        for _ in range(3):
            part = c.next_part()
            img = cv2.imdecode(np.frombuffer(part.jpeg, np.uint8), cv2.IMREAD_COLOR)
            assert img is not None and img.shape[:2] == (node.height, node.width)


def test_frame_numbers_and_timestamps_increase(node):
    with StreamClient(node.host, node.port) as c:
        parts = [c.next_part() for _ in range(12)]
    frames = [p.frame for p in parts]
    stamps = [p.timestamp_s for p in parts]
    assert all(b > a for a, b in itertools.pairwise(frames)), frames
    assert all(b > a for a, b in itertools.pairwise(stamps)), stamps
    # a fast local client misses nothing at 10 fps: frame spacing is one period
    steps = [b - a for a, b in itertools.pairwise(stamps)]
    assert abs(sorted(steps)[len(steps) // 2] - 1.0 / node.fps) < 0.02, steps


def test_frames_arrive_at_the_node_rate(node):
    with StreamClient(node.host, node.port) as c:
        c.next_part()
        t0 = time.monotonic()
        n = 0
        while time.monotonic() - t0 < 1.5:
            c.next_part()
            n += 1
    rate = n / (time.monotonic() - t0)
    assert 0.6 * node.fps < rate < 1.4 * node.fps, rate


def test_fps_query_caps_the_rate(node):
    with StreamClient(node.host, node.port, "/stream?fps=2") as c:
        parts = [c.next_part() for _ in range(4)]
    stamps = [p.timestamp_s for p in parts]
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    assert all(0.35 < g < 0.8 for g in gaps), gaps


def test_two_clients_at_once_get_the_same_frames(node):
    with StreamClient(node.host, node.port) as a, StreamClient(node.host, node.port) as b:
        fa = {p.frame: p.timestamp_s for p in (a.next_part() for _ in range(8))}
        fb = {p.frame: p.timestamp_s for p in (b.next_part() for _ in range(8))}
    common = set(fa) & set(fb)
    assert len(common) >= 4, (sorted(fa), sorted(fb))
    assert all(fa[k] == fb[k] for k in common), "one frame, one timestamp, whoever reads it"


IN_FLIGHT_LIMIT = 300_000  # bytes socket buffers may hold between a node and a slow client


def test_a_slow_client_skips_to_the_newest_frame(node):
    with StreamClient(node.host, node.port, rcvbuf=8192) as c:
        first = c.next_part()
        time.sleep(2.0)  # 30 frames are captured meanwhile, far more than socket buffers hold
        newest = int(get(node.host, node.port, "/capture").headers["x-frame"])
        # what was already in flight (socket buffers) comes first, then the newest frames
        stale_bytes = 0
        seq = [first.frame]
        while seq[-1] < newest:
            part = c.next_part()
            seq.append(part.frame)
            if part.frame < newest:
                stale_bytes += len(part.jpeg)
            assert len(seq) <= 40, seq
    assert stale_bytes <= IN_FLIGHT_LIMIT, f"{stale_bytes} bytes of old frames queued for a slow client: {seq}"
    assert any(b - a > 1 for a, b in itertools.pairwise(seq)), f"frames were not skipped: {seq}"
    assert all(b > a for a, b in itertools.pairwise(seq)), seq
