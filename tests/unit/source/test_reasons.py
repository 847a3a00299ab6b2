"""Why a camera cannot be read, as LiveCameras reports it (``last_error``) over real sockets on
127.0.0.1: refused, silent, the wrong content type, the wrong path, broken JPEGs; each one line
naming the address and what to check, none an exception's own wording."""

from __future__ import annotations

import socket

import pytest
from conftest import FPS, collect

from cubecam.emulator import Emulator, Faults
from cubetrack.source.reasons import broken_frames_reason, connection_reason
from cubetrack.source.streams import LiveCameras, SourceParams
from tests.helpers.webpage import WebPage

FAST = SourceParams(connect_timeout_s=1.0, read_timeout_s=1.0, backoff_initial_s=0.05, backoff_max_s=0.4,
                    clock_period_s=0.25)
RAW = ("Errno", "Error", "host=", "port=", "Traceback", "HTTPConnectionPool")


def last_error(url: str, seconds: float = 2.5) -> str:
    with LiveCameras({"cam": url}, FAST) as live:
        collect(live, seconds)
        stats = live.stats()["cam"]
    assert stats.frames == 0 and stats.last_error
    return stats.last_error


def assert_actionable(reason: str, where: str) -> None:
    assert "\n" not in reason and len(reason) <= 200 and where in reason and " — " in reason, reason
    assert not any(raw in reason for raw in RAW), reason


def test_refused():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nobody listens there
    reason = last_error(f"http://127.0.0.1:{port}/stream")
    assert reason == f"connection refused by 127.0.0.1:{port} — is the node on and on this network?"


def test_a_server_that_takes_the_connection_and_never_answers():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(8)  # connections complete in the kernel's queue; nobody reads them
        port = s.getsockname()[1]
        reason = last_error(f"http://127.0.0.1:{port}/stream")
    assert reason == f"127.0.0.1:{port} took the connection but did not answer within 1 s — is it a camera node?"


def test_a_web_page_instead_of_a_stream():
    with WebPage() as page:
        reason = last_error(page.url)
    assert_actionable(reason, f"127.0.0.1:{page.port}")
    assert "'text/html', not an MJPEG stream" in reason


def test_a_wrong_path(images):
    with Emulator(images=images, fps=FPS, name="cam1", loop=True) as emu:
        url = emu.base_urls["cam1"] + "nostream"
        reason = last_error(url)
    assert_actionable(reason, url.split("/")[2])
    assert "answered HTTP 404 for /nostream — the url should be the node's /stream" in reason


def test_broken_jpegs_only(images):
    faults = Faults(corrupt_every=1, corrupt_kind="jpeg")  # every frame's data garbled, framing intact
    with Emulator(images=images, fps=FPS, name="cam1", loop=True, faults=faults) as emu:
        url = emu.urls["cam1"]
        reason = last_error(url)
    assert_actionable(reason, url.split("/")[2])
    assert "broken frame(s) on this connection (not a whole JPEG) — restart the node" in reason


@pytest.mark.parametrize("exc, expected", [
    (socket.gaierror(-2, "Name or service not known"), "cannot find the address of 'cam7.lab'"),
    (ConnectionResetError(104, "Connection reset by peer"), "cam7.lab:8080 reset the connection"),
    (OSError(113, "No route to host"), "no route to cam7.lab:8080 — is this computer on the node's network?"),
])
def test_other_connection_failures(exc, expected):
    reason = connection_reason(exc, "http://cam7.lab:8080/stream")
    assert expected in reason and " — " in reason and not any(raw in reason for raw in RAW)


def test_the_most_frequent_breakage_is_named():
    reason = broken_frames_reason({"not a whole JPEG": 1, "part too large": 3}, "http://10.0.0.7/stream")
    assert reason.startswith("10.0.0.7:80 sent 4 broken frame(s) on this connection (part too large) — ")
