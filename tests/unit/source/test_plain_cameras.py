"""Cameras without a clock on the live source, over real sockets: a plain MJPEG server laid out as
an ESP32-CAM's (tests/helpers/plain_mjpeg.py: chunked, no X-Timestamp, no /time) is recognised
either by /time's 404 or, when /time never answers (the device's one HTTP task is busy
streaming), by its unstamped parts; its frames are stamped on arrival (de-jittered) and the assumed
latency is declared in its clock samples; a node's stream is never taken for one."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from conftest import collect

from cubecam.testdata import synthetic_jpeg
from cubetrack.source.clock import ClockFitMethod, ClockSync
from cubetrack.source.mjpeg import MjpegParser
from cubetrack.source.streams import LiveCameras, SourceParams
from tests.helpers.plain_mjpeg import PART_DELIMITER, PlainMjpegServer

FAST = SourceParams(connect_timeout_s=1.0, read_timeout_s=2.0, backoff_initial_s=0.05, backoff_max_s=0.4,
                    clock_period_s=0.25, clock_timeout_s=0.3, arrival_latency_s=0.08, frames_per_camera=100)


def frames_from_now(n: int, fps: float = 10.0, start_in_s: float = 0.3) -> list[tuple[float, bytes]]:
    t0 = time.time() + start_in_s
    return [(t0 + i / fps, synthetic_jpeg(i, 96, 64)) for i in range(n)]


@pytest.mark.parametrize("time_answer", ["404", "silent"])
def test_a_plain_mjpeg_camera_is_stamped_on_arrival_with_the_assumed_latency_declared(time_answer):
    with PlainMjpegServer(frames_from_now(30), time_answer=time_answer) as cam:
        with LiveCameras({"esp": cam.url}, FAST) as live:
            frames, clocks = collect(live, 8.0, until=lambda f, c: len(f) >= 15 and len(c) >= 3)
            asked = cam.time_requests
            collect(live, 4 * FAST.clock_period_s)
            stats = live.stats()["esp"]
        requests = cam.time_requests
    assert len(frames) >= 15 and len(clocks) >= 3
    assert all(cv2.imdecode(np.frombuffer(f.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE) is not None for f in frames)
    # the device clock is the arrival's, de-jittered (tests/unit/source/test_arrival_envelope.py): never later
    assert all(f.device_time_s <= f.host_time_s for f in frames)
    assert any(f.device_time_s < f.host_time_s for f in frames)
    assert [f.seq for f in frames] == list(range(1, len(frames) + 1))
    sync = ClockSync()
    for c in clocks:
        sync.add_round_trip(c.sample.host_send_s, c.sample.device_time_s, c.sample.host_recv_s)
    assert sync.method is ClockFitMethod.ROUND_TRIP
    assert abs(frames[-1].device_time_s - sync.to_host(frames[-1].device_time_s) - 0.08) < 1e-6
    assert stats.timing == "no clock: stamped on arrival, latency ~80 ms assumed"
    assert stats.bad == 0
    assert requests == asked  # once known to have no clock, /time is not asked again
    if time_answer == "404":
        assert not stats.clock_failures  # a 404 is an answer, not a failure
    else:
        assert stats.clock_failures["no answer"] == 1


def test_a_node_whose_time_fails_is_not_taken_for_a_camera_without_a_clock():
    """Parts with X-Timestamp: a failing /time leaves the frames on the device clock (the tracker
    waits for a round trip), whatever /time does."""
    import http.server
    import threading

    class Node(http.server.BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def log_message(self, *args):
            pass

        def do_GET(self):  # noqa: N802
            if self.path == "/time":
                self.send_error(500)
                return
            self.send_response(200)
            self.send_header("Content-Type", "multipart/x-mixed-replace;boundary=b")
            self.end_headers()
            try:
                for i in range(20):
                    jpeg = synthetic_jpeg(i, 64, 48)
                    self.wfile.write(b"--b\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\nX-Timestamp: %d.5"
                                     b"\r\n\r\n" % (len(jpeg), 100 + i) + jpeg + b"\r\n")
                    self.wfile.flush()
                    time.sleep(0.05)
            except OSError:
                pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Node)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        with LiveCameras({"node": f"http://127.0.0.1:{srv.server_address[1]}/stream"}, FAST) as live:
            frames, clocks = collect(live, 4.0, until=lambda f, c: len(f) >= 10)
            stats = live.stats()["node"]
    finally:
        srv.shutdown()
        srv.server_close()
    assert len(frames) >= 10 and not clocks
    assert all(f.device_time_s == 100 + f.seq - 0.5 for f in frames)
    assert stats.timing == "" and stats.clock_failures["garbage answer"] >= 1


def test_the_parser_keeps_unstamped_parts_only_when_asked():
    jpeg = synthetic_jpeg(1, 64, 48)
    data = (b"Content-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(jpeg) + jpeg + PART_DELIMITER) * 3
    data += b"Content-Length: %d\r\nX-Timestamp: -4\r\n\r\n" % len(jpeg) + jpeg + PART_DELIMITER
    strict = MjpegParser("123456789000000000000987654321")
    assert strict.feed(data) == [] and strict.bad["no X-Timestamp"] == 2  # the first has no delimiter before it
    lenient = MjpegParser("123456789000000000000987654321", require_timestamp=False)
    parts = lenient.feed(data)
    assert len(parts) == 2 and all(np.isnan(p.device_time_s) and p.jpeg == jpeg for p in parts)
    assert lenient.bad["bad X-Timestamp"] == 1  # a malformed stamp is still refused
