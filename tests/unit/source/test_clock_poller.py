"""The /time poller: round trips against the emulator bracket the node's clock; timeouts and
garbage answers from a misbehaving server are counted and never become clock samples."""

from __future__ import annotations

import http.server
import threading
import time

import pytest
from conftest import FPS, collect

from cubecam.emulator import Emulator
from cubetrack.source.streams import LiveCameras, SourceParams
from cubetrack.source.time_poll import parse_time_answer, poll_time, time_url


@pytest.mark.parametrize("stream,expected", [
    ("http://192.168.1.21/stream", "http://192.168.1.21/time"),
    ("http://127.0.0.1:8080/stream?fps=5", "http://127.0.0.1:8080/time"),
    ("http://cam.local/node1/stream", "http://cam.local/node1/time"),
    ("http://cam.local/", "http://cam.local/time"),
])
def test_time_url_sits_beside_the_stream(stream, expected):
    assert time_url(stream) == expected


@pytest.mark.parametrize("body,value", [(b"12.345678", 12.345678), (b" 7.000001\r\n", 7.000001), (b"42", 42.0)])
def test_time_answers_are_parsed(body, value):
    assert parse_time_answer(body) == value


@pytest.mark.parametrize("body", [b"", b"hello", b"-1.5", b"nan", b"1e9", b"12:30:00", b"1.2.3", b"\xff\xfe",
                                  b"9" * 40])
def test_garbage_time_answers_are_refused(body):
    with pytest.raises((ValueError, UnicodeDecodeError)):
        parse_time_answer(body)


def test_a_round_trip_brackets_the_nodes_clock(images):
    with Emulator(images=images, fps=FPS, name="cam1", loop=True) as emu:
        time.sleep(0.3)
        samples = [poll_time(time_url(emu.urls["cam1"]), 1.0) for _ in range(5)]
    for s in samples:
        assert s.host_send_s <= s.host_recv_s < s.host_send_s + 0.5
        # the emulator's device clock, mapped back to this machine's Unix time, was read in between
        read_at = emu.unix_time(s.device_time_s)  # images: device clock = recorded host clock
        assert s.host_send_s - 0.002 <= read_at <= s.host_recv_s + 0.002


class _Garbage(http.server.BaseHTTPRequestHandler):
    """Answers /time with whatever the server's ``answers`` list says next (round robin)."""

    def do_GET(self):  # noqa: N802
        srv = self.server
        with srv.lock:
            kind = srv.answers[srv.count % len(srv.answers)]
            srv.count += 1
        if kind == "slow":
            time.sleep(1.0)
            kind = "1.000000"
        if kind == "500":
            self.send_error(500)
            return
        body = kind.encode("latin-1")
        self.send_response(200)
        self.send_header("Content-Type", "text/plain")
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Connection", "close")
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@pytest.fixture
def garbage_server():
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Garbage)
    srv.lock = threading.Lock()
    srv.count = 0
    srv.answers = ["hello", "", "500", "slow", "-3", "12:00"]
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    yield srv
    srv.shutdown()
    srv.server_close()


def test_a_server_answering_garbage_gives_no_clock_sample_and_every_failure_is_counted(garbage_server):
    url = f"http://127.0.0.1:{garbage_server.server_address[1]}/stream"
    params = SourceParams(clock_period_s=0.1, clock_timeout_s=0.3, read_timeout_s=0.5, backoff_initial_s=0.1)
    with LiveCameras({"cam1": url}, params) as live:
        frames, clocks = collect(live, 2.0)
        stats = live.stats()["cam1"]
    assert frames == [] and clocks == []
    assert stats.clock_samples == 0
    assert stats.clock_failures["garbage answer"] >= 3 and stats.clock_failures["no answer"] >= 1
    # its "stream" is no stream: the same round robin answers it with text, HTTP 500 or too late
    assert stats.reconnects >= 1 and any(
        why in stats.last_error for why in ("not an MJPEG stream", "HTTP 500", "did not answer within"))
