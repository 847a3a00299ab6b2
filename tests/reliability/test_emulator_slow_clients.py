"""The camera emulator against slow-loris clients, clients that never read, half-open and
half-closed connections and a connection flood (issue 12, item 4): it has the node's four
client slots, so such clients can hold them -- but only until the node's request and stall
timeouts, after which every slot comes back and a well-behaved client is served again.
The timeouts are shortened here (the emulator's defaults are the node's 5 s and 10 s)."""

from __future__ import annotations

import json
import socket
import threading
import time

import pytest
from slow_clients import non_reading_streams, slow_loris

from cubecam import emulator
from cubecam.emulator import Emulator
from cubecam.testdata import write_images

REQUEST_TIMEOUT_S = 1.0
STALL_TIMEOUT_S = 1.0


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    return write_images(tmp_path_factory.mktemp("img"), 6, 640, 480)


@pytest.fixture
def emu(images, monkeypatch):
    monkeypatch.setattr(emulator, "REQUEST_TIMEOUT_S", REQUEST_TIMEOUT_S)
    monkeypatch.setattr(emulator, "STALL_TIMEOUT_S", STALL_TIMEOUT_S)
    with Emulator(images=images, fps=15, name="cam", loop=True, max_clients=4) as e:
        yield e


def address(emu: Emulator) -> tuple[str, int]:
    host, port = emu.base_urls["cam"].split("//")[1].rstrip("/").rsplit(":", 1)
    return host, int(port)


def status_code(emu: Emulator, timeout: float = 2.0) -> int:
    """The status code a well-behaved client gets for GET /status (0: no answer)."""
    with socket.create_connection(address(emu), timeout=timeout) as s:
        s.sendall(b"GET /status HTTP/1.1\r\nHost: cam\r\n\r\n")
        head = s.recv(64)
    return int(head.split()[1]) if head.startswith(b"HTTP/1.1 ") else 0


def served_again_within(emu: Emulator, seconds: float) -> float:
    """Seconds until GET /status is answered 200 (fails after ``seconds``)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        if status_code(emu) == 200:
            return time.monotonic() - t0
        time.sleep(0.05)
    pytest.fail(f"no slot came back within {seconds} s")


def closed_by_server(s: socket.socket, timeout: float) -> bool:
    s.settimeout(timeout)
    try:
        while s.recv(65536):
            pass
        return True
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


def test_slow_loris_clients_hold_the_slots_only_until_the_request_timeout(emu):
    stop = threading.Event()
    lorises = slow_loris(address(emu), 4, 0.2, stop)
    try:
        time.sleep(0.3)
        assert status_code(emu) == 503  # all four slots are held, as on the node
        assert served_again_within(emu, REQUEST_TIMEOUT_S + 1.5) < REQUEST_TIMEOUT_S + 1.0
        assert all(closed_by_server(s, 1.0) for s in lorises)  # dropped without an answer
    finally:
        stop.set()
        for s in lorises:
            s.close()


def test_connections_that_never_send_a_byte_are_dropped_and_their_slots_return(emu):
    idle = [socket.create_connection(address(emu)) for _ in range(4)]
    try:
        time.sleep(0.2)
        assert status_code(emu) == 503
        served_again_within(emu, REQUEST_TIMEOUT_S + 1.5)
        assert all(closed_by_server(s, 1.0) for s in idle)
    finally:
        for s in idle:
            s.close()


def test_a_stream_client_that_never_reads_loses_its_slot_after_the_stall_timeout(emu):
    readers = non_reading_streams(address(emu), 4)
    try:
        time.sleep(0.3)
        assert status_code(emu) == 503
        waited = served_again_within(emu, STALL_TIMEOUT_S + 3.0)
        assert waited < STALL_TIMEOUT_S + 2.0
        # Each stream stalls on its own (its socket buffers fill at their own pace), so the
        # first slot back does not mean the last is: every one must be dropped soon after.
        deadline = time.monotonic() + STALL_TIMEOUT_S + 1.0
        while emu.stats("cam")["clients"] and time.monotonic() < deadline:
            time.sleep(0.05)
        assert emu.stats("cam")["clients"] == 0  # no stream is left streaming into the void
    finally:
        for s in readers:
            s.close()


def test_a_half_closed_request_is_still_answered_and_its_slot_returns(emu):
    with socket.create_connection(address(emu), timeout=3) as s:
        s.sendall(b"GET /status HTTP/1.1\r\n\r\n")
        s.shutdown(socket.SHUT_WR)  # the client says it sends nothing more
        answer = b""
        while chunk := s.recv(65536):
            answer += chunk
    head, _, body = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 200") and json.loads(body)["name"] == "cam"
    assert served_again_within(emu, 1.0) < 0.5


def test_a_connection_flood_is_refused_without_piling_up_threads(emu):
    """60 connections that send nothing: four get the slots (and are dropped at the request
    timeout, freeing slots for the next idle ones), every other one is refused with 503 at once;
    none hangs, and the emulator's threads go back to what they were."""
    baseline = threading.active_count()
    flood = [socket.create_connection(address(emu), timeout=5) for _ in range(60)]
    outcome = {"503": 0, "closed": 0, "hung": 0}
    try:
        for s in flood:
            s.settimeout(REQUEST_TIMEOUT_S + 2.0)
            try:
                outcome["503" if s.recv(64).startswith(b"HTTP/1.1 503") else "closed"] += 1
            except TimeoutError:
                outcome["hung"] += 1
            except OSError:
                outcome["closed"] += 1
    finally:
        for s in flood:
            s.close()
    assert outcome["hung"] == 0 and outcome["503"] >= 40, outcome
    served_again_within(emu, REQUEST_TIMEOUT_S + 3.0)
    deadline = time.monotonic() + 5.0
    while threading.active_count() > baseline + 1 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert threading.active_count() <= baseline + 1
