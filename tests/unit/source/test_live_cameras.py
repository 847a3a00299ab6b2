"""LiveCameras against a real local HTTP server (the emulator, with its faults): frames and
clock samples arrive, every fault is survived and counted, reconnects are logged, the queue
stays bounded, and stop() wakes blocked reads."""

from __future__ import annotations

import dataclasses
import http.server
import itertools
import logging
import statistics
import threading
import time

import cv2
import numpy as np
import pytest
from conftest import FPS, collect

from cubecam.emulator import Emulator, Faults
from cubecam.testdata import synthetic_jpeg
from cubetrack.core.errors import ConfigError
from cubetrack.core.records import Frame
from cubetrack.source.streams import ClockReading, LiveCameras, SourceParams

FAST = SourceParams(connect_timeout_s=1.0, read_timeout_s=1.0, backoff_initial_s=0.05, backoff_max_s=0.4,
                    clock_period_s=0.25)


def wait_until(condition, timeout_s: float = 20.0) -> None:
    """Wait for a state (polled), never for a fixed time; fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "the state waited for never came"
        time.sleep(0.02)


def decodes(frame: Frame) -> bool:
    return cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE) is not None


def test_frames_and_clock_samples_arrive_in_order_with_capture_stamps(images):
    with Emulator(images=images, fps=FPS, name="cam1", loop=True) as emu:
        with LiveCameras(emu.urls, FAST) as live:
            frames, clocks = collect(live, 6.0, until=lambda f, c: len(f) >= 12 and len(c) >= 3)
            stats = live.stats()["cam1"]
    assert len(frames) >= 12 and len(clocks) >= 3
    assert all(isinstance(c, ClockReading) and c.camera == "cam1" for c in clocks)
    seqs = [f.seq for f in frames]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert all(decodes(f) for f in frames)
    # X-Timestamp is the emulated device clock; arrival is the host time the last byte came:
    # on 127.0.0.1 without faults that is within a few ms of capture (no frame of added latency)
    delays = [f.host_time_s - emu.unix_time(f.device_time_s) for f in frames]  # images: device = recorded host
    assert min(delays) > -0.005
    assert statistics.median(delays) < 0.5 / FPS
    assert stats.frames == len(frames) and stats.bad == 0 and stats.connected and stats.reconnects == 0
    assert stats.clock_samples >= 3 and not stats.clock_failures


def test_added_latency_shows_in_the_arrival_times(images):
    with Emulator(images=images, fps=FPS, name="cam1", loop=True, faults=Faults(latency_s=0.2)) as emu:
        with LiveCameras(emu.urls, FAST) as live:
            frames, _ = collect(live, 6.0, until=lambda f, c: len(f) >= 8)
    delays = [f.host_time_s - emu.unix_time(f.device_time_s) for f in frames]
    assert len(frames) >= 8
    assert min(delays) >= 0.2 - 0.005
    assert statistics.median(delays) < 0.2 + 0.5 / FPS


def test_a_camera_that_disconnects_is_reconnected_and_it_is_logged(images, caplog):
    caplog.set_level(logging.WARNING, logger="cubetrack.source.streams")
    with Emulator(images=images, fps=FPS, name="cam1", loop=True, faults=Faults(disconnect_every_s=0.8)) as emu:
        with LiveCameras(emu.urls, FAST) as live:
            frames, _ = collect(live, 4.0)
        stats = live.stats()["cam1"]
    assert stats.reconnects >= 2 and stats.connects >= 3
    assert len(frames) >= 0.6 * 4.0 * FPS  # frames keep coming across reconnects
    assert any("reconnecting" in r.getMessage() and "cam1" in r.getMessage() for r in caplog.records)
    assert stats.bad == 0  # the node closes between parts: nothing half-read


def test_a_stalled_stream_times_out_and_is_reconnected(images, caplog):
    caplog.set_level(logging.WARNING, logger="cubetrack.source.streams")
    faults = Faults(stall_after_s=0.6)  # every connection goes silent after 0.6 s, until the client leaves
    with Emulator(images=images, fps=FPS, name="cam1", loop=True, faults=faults) as emu:
        params = SourceParams(read_timeout_s=0.5, backoff_initial_s=0.05, clock_period_s=0.5)
        with LiveCameras(emu.urls, params) as live:
            frames, _ = collect(live, 4.0)
        stats = live.stats()["cam1"]
    assert stats.reconnects >= 2
    lost = [r.getMessage() for r in caplog.records if "stream lost" in r.getMessage()]
    assert lost and all("stopped for 0.5 s" in m for m in lost)
    assert all("reconnecting in 0.05 s" in m for m in lost)  # each connection worked: no growing back-off
    first_gap = max(b.host_time_s - a.host_time_s for a, b in itertools.pairwise(frames))
    assert first_gap >= 0.5  # the stall was seen ...
    assert frames[-1].host_time_s - frames[0].host_time_s > 2.0  # ... and frames resumed after it


@pytest.mark.parametrize("kind,reason", [("jpeg", "not a whole JPEG"),
                                         ("truncate", "part shorter than its Content-Length")])
def test_corrupt_parts_are_skipped_and_counted_and_the_rest_delivered(images, kind, reason):
    faults = Faults(corrupt_every=3, corrupt_kind=kind, seed=3)
    with Emulator(images=images, fps=FPS, name="cam1", loop=True, faults=faults) as emu:
        with LiveCameras(emu.urls, FAST) as live:
            frames, _ = collect(live, 6.0, until=lambda f, c: len(f) >= 10)
        stats = live.stats()["cam1"]
    assert len(frames) >= 10 and all(decodes(f) for f in frames)
    assert stats.bad_parts[reason] >= 4 and stats.reconnects == 0


def test_a_vanished_server_is_retried_with_backoff_until_it_comes_back(images, caplog):
    caplog.set_level(logging.WARNING, logger="cubetrack.source.streams")
    emu = Emulator(images=images, fps=FPS, name="cam1", loop=True).start()
    url = emu.urls["cam1"]
    port = int(url.split(":")[2].split("/")[0])
    with LiveCameras({"cam1": url}, FAST) as live:
        before, _ = collect(live, 3.0, until=lambda f, c: len(f) >= 3)
        emu.close()
        wait_until(lambda: (s := live.stats()["cam1"]) and not s.connected and s.reconnects >= 3
                   and s.clock_failures["no answer"] >= 1)  # retried while the server is away
        down = live.stats()["cam1"]
        emu = Emulator(images=images, fps=FPS, name="cam1", loop=True, port=port).start()
        try:
            after, _ = collect(live, 6.0, until=lambda f, c: len(f) >= 3 and f[-1].seq >= 3)
        finally:
            emu.close()
    assert len(before) >= 3 and len(after) >= 3
    assert not down.connected and down.reconnects >= 3 and down.clock_failures["no answer"] >= 1
    waits = [float(r.getMessage().split("reconnecting in ")[1].split(" s")[0])
             for r in caplog.records if "reconnecting in" in r.getMessage()]
    assert max(waits) > min(waits)  # back-off grows while the server is away


def test_a_wrong_path_is_an_http_error_and_retried(images):
    with Emulator(images=images, fps=FPS, name="cam1", loop=True) as emu:
        with LiveCameras({"cam1": emu.base_urls["cam1"] + "nostream"}, FAST) as live:
            collect(live, 1.0)
        stats = live.stats()["cam1"]
    assert stats.frames == 0 and stats.reconnects >= 1 and "answered HTTP 404 for /" in stats.last_error


def test_a_consumer_that_falls_behind_keeps_each_cameras_newest_frame_only(tmp_path):
    from cubecam.testdata import CameraSpec, write_recording

    rec = write_recording(tmp_path / "rec", [CameraSpec("a"), CameraSpec("b")], frames=30, fps=10.0)
    woken = threading.Event()
    with Emulator(rec, loop=True) as emu:
        with LiveCameras(emu.urls, SourceParams(clock_period_s=0.25), wake=woken.set) as live:
            # nobody reads, until both cameras' frames have been replaced and clock samples came
            wait_until(lambda: all(s.dropped > 0 for s in live.stats().values())
                       and sum(s.clock_samples for s in live.stats().values()) >= 4)
            assert woken.is_set()
            live.stop()
            clocks = []
            while (e := live.get(0, frames=False)) is not None:  # clock samples pass waiting frames
                clocks.append(e)
            stats = live.stats()
            freshest = live.get(0, newest_first=True)
            events = [freshest]
            while (e := live.get(0)) is not None:
                events.append(e)
    frames = [e for e in events if isinstance(e, Frame)]
    assert isinstance(freshest, Frame) and freshest.host_time_s == max(f.host_time_s for f in frames)
    assert len(clocks) >= 4 and all(isinstance(e, ClockReading) for e in clocks)  # never dropped
    assert sorted(f.camera for f in frames) == ["a", "b"]  # one frame per camera waited
    for f in frames:
        st = stats[f.camera]
        assert st.dropped > 0 and st.dropped >= st.frames - 2  # the others were dropped, per camera
        assert f.seq >= st.frames - 1  # the newest was kept


def test_behind_or_not_an_instants_frames_come_in_arrival_order_and_intervals_are_learnt(tmp_path):
    from cubecam.testdata import CameraSpec, write_recording

    rec = write_recording(tmp_path / "rec", [CameraSpec("a"), CameraSpec("b")], frames=30, fps=10.0)
    with Emulator(rec, loop=True) as emu:
        with LiveCameras(emu.urls, SourceParams(clock_period_s=0.25, behind_intervals=600.0)) as live:
            # nobody reads: each camera's newest waits, its interval learnt from the real arrivals
            wait_until(lambda: all(s.frames >= 6 for s in live.stats().values()))
            live.stop()
            while live.get(0, frames=False) is not None:  # the clock samples
                pass
            waiting = [live._queue[0], live._queue[-1]]  # arrival order: the older, the fresher
            assert [type(e) for e in waiting] == [Frame, Frame]
            intervals_s = [live._intervals.interval_s(name) for name in ("a", "b")]
            kept_up = live.get(0, newest_if_behind=True)  # nothing waited 600 frame intervals: arrival order
            live._queue.appendleft(kept_up)
            live._queued_frames[kept_up.camera] += 1
            live.params = dataclasses.replace(live.params, behind_intervals=0.0)
            behind = live.get(0, newest_if_behind=True)  # behind: the freshest instant, oldest first
    assert all(i is not None and 0.08 < i < 0.125 for i in intervals_s), intervals_s  # 10 fps
    # the emulator serves both cameras' frames of an instant together: one instant, unless this host
    # was so slow to read that they arrived more than a tenth of an interval apart
    one_instant = waiting[1].host_time_s - waiting[0].host_time_s <= 0.1 * intervals_s[1]
    assert kept_up is waiting[0] and behind is waiting[0 if one_instant else 1]


def test_stop_wakes_a_read_blocked_on_a_silent_camera(images):
    with Emulator(images=images, fps=FPS, name="cam1", loop=True, faults=Faults(stall_after_s=0.3)) as emu:
        live = LiveCameras(emu.urls, SourceParams(read_timeout_s=30.0)).start()
        collect(live, 1.0)
        t0 = time.monotonic()
        live.stop()
        assert time.monotonic() - t0 < 5.0  # far below the 30 s read timeout
        assert not any(t.is_alive() for t in live._threads)


def test_several_cameras_are_merged_in_arrival_order(tmp_path):
    from cubecam.testdata import CameraSpec, write_recording

    rec = write_recording(tmp_path / "rec", [CameraSpec("a", boot_offset_s=10.0), CameraSpec("b", boot_offset_s=99.0)],
                          frames=30, fps=10.0)
    with Emulator(rec, loop=True) as emu:
        with LiveCameras(emu.urls, FAST) as live:
            frames, clocks = collect(live, 6.0, until=lambda f, c: len(f) >= 20 and {x.camera for x in c} == {"a", "b"})
    assert {f.camera for f in frames} == {"a", "b"}
    arrivals = [f.host_time_s for f in frames]
    assert arrivals == sorted(arrivals)


def test_unknown_camera_url_schemes_are_refused_naming_the_camera():
    with pytest.raises(ConfigError, match="cam1.*unknown scheme 'ftp'"):
        LiveCameras({"cam1": "ftp://10.0.0.2/stream"})
    with pytest.raises(ConfigError, match="no cameras"):
        LiveCameras({})


class _Esp32Style(http.server.BaseHTTPRequestHandler):
    """An ESP32 CameraWebServer-like stream: HTTP/1.1 chunked encoding, boundary, headers and
    JPEG as separate chunks, X-Timestamp but no X-Frame; /time answers from the same clock."""

    protocol_version = "HTTP/1.1"
    boundary = "123456789000000000000987654321"

    def chunk(self, data: bytes) -> None:
        self.wfile.write(f"{len(data):X}\r\n".encode() + data + b"\r\n")
        self.wfile.flush()

    def do_GET(self):  # noqa: N802
        if self.path == "/time":
            body = f"{time.monotonic():.6f}".encode()
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Connection", "close")
            self.end_headers()
            self.wfile.write(body)
            return
        self.send_response(200)
        self.send_header("Content-Type", f"multipart/x-mixed-replace;boundary={self.boundary}")
        self.send_header("Transfer-Encoding", "chunked")
        self.end_headers()
        try:
            for i in range(8):
                jpeg = synthetic_jpeg(i, 80, 60)
                self.chunk(f"\r\n--{self.boundary}\r\n".encode())
                self.chunk(f"Content-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n"
                           f"X-Timestamp: {time.monotonic():.6f}\r\n\r\n".encode())
                self.chunk(jpeg)
                time.sleep(0.1)
            self.wfile.write(b"0\r\n\r\n")
        except OSError:
            pass

    def log_message(self, *args):
        pass


def test_a_chunked_esp32_style_stream_without_x_frame_is_read_without_added_latency():
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Esp32Style)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{srv.server_address[1]}/stream"
        received = []
        with LiveCameras({"esp": url}, FAST, on_frame=lambda f: received.append((f, time.monotonic()))) as live:
            frames, clocks = collect(live, 5.0, until=lambda f, c: len(f) >= 6 and c)
    finally:
        srv.shutdown()
        srv.server_close()
    assert len(frames) >= 6 and clocks
    assert [f.seq for f in frames[:6]] == list(range(1, 7))  # counted locally
    assert all(decodes(f) for f in frames)
    # the part is complete when its JPEG chunk arrives, not when the next part starts (0.1 s later)
    delays = [arrived - f.device_time_s for f, arrived in received]  # server stamps = monotonic
    assert statistics.median(delays) < 0.05


class _SlowClock(_Esp32Style):
    """The same stream, its /time answered 0.3 s late (three frame intervals)."""

    def do_GET(self):  # noqa: N802
        if self.path == "/time":
            time.sleep(0.3)
        super().do_GET()


def test_a_stream_opens_once_its_camera_has_answered_time_so_no_frame_comes_before_its_clock():
    """Live tracking gives up a frame whose camera's clock is not known yet (it cannot be placed
    in time): the stream is asked for only after the first /time round trip has ended."""
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _SlowClock)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{srv.server_address[1]}/stream"
        events = []
        with LiveCameras({"esp": url}, FAST) as live:
            while sum(isinstance(e, Frame) for e in events) < 3:
                if (event := live.get(5.0)) is None:
                    break
                events.append(event)
    finally:
        srv.shutdown()
        srv.server_close()
    assert isinstance(events[0], ClockReading)
    assert [e.seq for e in events if isinstance(e, Frame)] == [1, 2, 3]  # the stream's first parts, none lost


def test_a_cameras_first_round_trips_go_back_to_back_then_one_per_clock_period(images):
    """The tracker trusts a clock on one narrow round trip or three of any width, and gives up the
    camera's frames until then: the first three are not a clock period apart."""
    slow_period = dataclasses.replace(FAST, clock_period_s=30.0)
    with Emulator(images=images, fps=FPS, name="cam1", loop=True) as emu:
        with LiveCameras(emu.urls, slow_period) as live:
            _, clocks = collect(live, 20.0, until=lambda f, c: len(c) >= 3)
            _, later = collect(live, 1.0)
    assert len(clocks) == 3 and later == []  # three at once, the fourth a period later


def test_without_a_thread_frames_are_read_inside_get_and_stamped_when_they_arrived(images):
    """thread=False (a camera worker process): nothing reads while the consumer is busy, yet the
    frames keep the time their bytes reached this host (the kernel's receive time), not the
    time get() read them; a file given to wake_on() ends get()'s wait."""
    import socket as socket_module

    params = SourceParams(frames_per_camera=50, read_timeout_s=30.0, clock_period_s=0.25)
    faults = Faults(stall_after_s=1.0)  # frames for 1 s, then silence (the connection stays)
    with Emulator(images=images, fps=FPS, name="cam1", loop=True, faults=faults) as emu:
        live = LiveCameras(emu.urls, params, thread=False).start()
        here, there = socket_module.socketpair()
        try:
            live.wake_on(here)
            assert not live._threads
            collect(live, 3.0, until=lambda f, c: len(f) >= 1)  # connected and streaming
            time.sleep(2.0)  # busy: nobody reads; the rest of the frames wait in the socket
            read_from = time.time()
            waited = []
            while (event := live.get(0)) is not None:
                waited.append(event)
            there.send(b"x")
            t0 = time.monotonic()
            # woken by the file, not by a clock sample: a sample that came since the loop above (one
            # every 0.25 s, clock_period_s) is handed out first; without the wake, each get() would end
            # at the next sample, and this loop would not end
            while (reading := live.get(5.0, frames=False)) is not None:
                assert isinstance(reading, ClockReading) and time.monotonic() - t0 < 5.0, reading
            woke_s = time.monotonic() - t0
        finally:
            live.stop()
            here.close()
            there.close()
    stamps = [e.host_time_s for e in waited if isinstance(e, Frame)]
    assert len(stamps) >= 2  # frames that came while nobody read, all kept (frames_per_camera 50)
    assert all(t < read_from - 0.8 for t in stamps)  # they arrived before the stream went silent
    assert woke_s < 1.0


class _Pieces(http.server.BaseHTTPRequestHandler):
    """A stream whose every part (headers, then the JPEG) comes in ``pieces`` writes ``gap_s`` apart,
    as a camera on a slow link sends it; then ``pause_s`` before the next part."""

    protocol_version = "HTTP/1.0"
    pieces, gap_s, pause_s, parts = 8, 0.004, 0.05, 12

    def do_GET(self):  # noqa: N802
        if self.path == "/time":
            _Esp32Style.do_GET(self)  # type: ignore[arg-type]  # the same clock answer
            return
        self.send_response(200)
        self.send_header("Content-Type", "multipart/x-mixed-replace;boundary=frame")
        self.end_headers()
        self.wfile.flush()
        try:
            for i in range(self.parts):
                jpeg = synthetic_jpeg(i, 160, 120)
                part = (f"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n"
                        f"X-Frame: {i + 1}\r\nX-Timestamp: {time.monotonic():.6f}\r\n\r\n").encode() + jpeg + b"\r\n"
                size = -(-len(part) // self.pieces)
                for k in range(0, len(part), size):
                    self.wfile.write(part[k:k + size])
                    self.wfile.flush()
                    time.sleep(self.gap_s)
                time.sleep(self.pause_s)
            time.sleep(30.0)  # then silence, the connection open
        except OSError:
            pass

    def log_message(self, *args):
        pass


def _serve(handler):
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv, f"http://127.0.0.1:{srv.server_address[1]}/stream"


def test_a_part_that_comes_in_pieces_is_read_once_it_is_whole(monkeypatch):
    """A part whose Content-Length is known wakes the reading loop once, when its last byte has
    come (SO_RCVLOWAT), not once per piece; its arrival stamp is its last byte's."""
    from cubetrack.source import http_get

    reads = [0]
    handle = http_get.HttpGet.handle

    def counted(self):
        reads[0] += self._request.startswith(b"GET /stream ")  # the stream's reads (not the clock's)
        return handle(self)

    monkeypatch.setattr(http_get.HttpGet, "handle", counted)
    srv, url = _serve(_Pieces)
    try:
        live = LiveCameras({"cam1": url}, dataclasses.replace(FAST, frames_per_camera=50), thread=False).start()
        try:
            frames, _ = collect(live, 10.0, until=lambda f, c: len(f) >= _Pieces.parts)
        finally:
            live.stop()
    finally:
        srv.shutdown()
        srv.server_close()
    assert [f.seq for f in frames] == list(range(1, _Pieces.parts + 1)) and all(decodes(f) for f in frames)
    # per part: its first piece (headers, the body's start), then the rest when whole (a third read at
    # most when a piece splits the headers), and a few reads to connect; one read per piece without it
    assert reads[0] <= 3 * _Pieces.parts + 4, reads[0]
    lasts = [f.host_time_s - (f.device_time_s - time.monotonic() + time.time()) for f in frames]
    assert min(lasts) >= (_Pieces.pieces - 1) * _Pieces.gap_s  # stamped at the last piece, not the first


class _Trickle(_Pieces):
    """One part trickling in over longer than the read timeout (slower than the low-water mark
    wakes anyone), then silence."""

    pieces, gap_s, pause_s, parts = 6, 0.4, 0.0, 1


def test_a_part_slower_than_the_read_timeout_is_read_and_then_the_silence_times_out(caplog):
    caplog.set_level(logging.WARNING, logger="cubetrack.source.streams")
    srv, url = _serve(_Trickle)
    params = dataclasses.replace(FAST, read_timeout_s=1.0, backoff_initial_s=5.0, backoff_max_s=5.0)
    try:
        live = LiveCameras({"cam1": url}, params, thread=False).start()
        try:
            t0 = time.monotonic()
            frames, _ = collect(live, 8.0, until=lambda f, c: len(f) >= 1)
            took_s = time.monotonic() - t0
            wait_until(lambda: live.get(0.05) is None and live.stats()["cam1"].reconnects >= 1, 10.0)
        finally:
            live.stop()
    finally:
        srv.shutdown()
        srv.server_close()
    # the part took ~2.4 s (> the 1 s read timeout): bytes were coming, so it was read whole, not timed out
    assert len(frames) == 1 and decodes(frames[0]) and took_s > 2.0
    assert any("stopped for 1 s" in r.getMessage() for r in caplog.records)  # then the silence times out
