"""The node firmware (cubecam-native: the firmware core built for the host, tests/helpers/native.py)
against slow-loris clients and clients that never read (issue 12, item 4). The node has four
client slots; such clients hold them until its request timeout (5 s: the request head must be
complete) or its stall timeout (10 s without a byte accepted), then the slots come back.
Nothing here ran on a board."""

from __future__ import annotations

import shutil
import socket
import sys
import threading
import time
from pathlib import Path

import pytest
from slow_clients import drain, non_reading_streams, slow_loris

from cubecam.testdata import write_images

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
from tests.helpers.native import NativeNode, build_native  # noqa: E402

REQUEST_TIMEOUT_S = 5.0  # firmware/cubecam/src/core/http_server.h kRequestTimeoutMs
STALL_TIMEOUT_S = 10.0   # kStallTimeoutMs


@pytest.fixture(scope="module")
def node(tmp_path_factory):
    if shutil.which("g++") is None or shutil.which("make") is None:
        pytest.skip("g++ and make are needed to build cubecam-native (tests/install.sh installs them)")
    build_native()
    images = write_images(tmp_path_factory.mktemp("native-img"), 6, 640, 480)
    with NativeNode(images, fps=30, serial=None) as n:
        yield n


def status_code(node: NativeNode) -> int:
    with socket.create_connection(("127.0.0.1", node.port), timeout=3) as s:
        s.sendall(b"GET /status HTTP/1.1\r\nHost: cam\r\n\r\n")
        head = s.recv(64)
    return int(head.split()[1]) if head.startswith(b"HTTP/1.1 ") else 0


def wait_served(node: NativeNode, t0: float, limit_s: float) -> float:
    while time.monotonic() - t0 < limit_s:
        if status_code(node) == 200:
            return time.monotonic() - t0
        time.sleep(0.1)
    pytest.fail(f"no slot came back within {limit_s} s")


def test_slow_loris_and_non_reading_clients_hold_slots_only_until_the_nodes_timeouts(node):
    stop = threading.Event()
    here = ("127.0.0.1", node.port)
    t0 = time.monotonic()
    lorises = slow_loris(here, 2, 0.5, stop)
    readers = non_reading_streams(here, 2)
    fills: list[socket.socket] = []
    try:
        time.sleep(0.5)
        assert status_code(node) == 503  # four slots held
        first = wait_served(node, t0, REQUEST_TIMEOUT_S + 3.0)  # the slow-loris slots come back ...
        assert REQUEST_TIMEOUT_S - 0.5 < first < REQUEST_TIMEOUT_S + 2.0
        for s in lorises:  # ... closed without an answer
            s.settimeout(2)
            assert s.recv(64) == b""
        # the non-reading streams keep theirs until the stall timeout; two good readers take the rest
        fills = [socket.create_connection(here, timeout=3) for _ in range(2)]
        for f in fills:
            f.sendall(b"GET /stream HTTP/1.1\r\n\r\n")
            assert f.recv(12) == b"HTTP/1.1 200"
            threading.Thread(target=drain, args=(f, stop), daemon=True).start()
        assert status_code(node) == 503
        second = wait_served(node, t0, STALL_TIMEOUT_S + 5.0)
        assert STALL_TIMEOUT_S - 1.0 < second < STALL_TIMEOUT_S + 3.0
        print(f"\ncubecam-native: slow-loris slots back after {first:.1f} s, non-reading streams' after {second:.1f} s")
    finally:
        stop.set()
        for s in lorises + readers + fills:
            s.close()
