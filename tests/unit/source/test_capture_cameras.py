"""Cameras read through OpenCV's VideoCapture (usb:, v4l2:, rtsp:, file:) on the live source: a video
file written here (real JPEG-coded frames in an AVI) stands in for a USB camera through the same
capture path, on its own thread, merged into the one queue; URLs by scheme, and one-line errors."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
import simplejpeg
from conftest import collect

from cubetrack.core.errors import ConfigError, SourceError
from cubetrack.source.camera_url import CameraKind, parse_camera_url
from cubetrack.source.clock import ClockFitMethod, ClockSync
from cubetrack.source.streams import LiveCameras, SourceParams

FPS = 10.0
PARAMS = SourceParams(clock_period_s=0.25, frames_per_camera=100, arrival_latency_s=0.05)


def write_video(path, frames: int, fps: float = FPS):
    """An MJPEG AVI whose frame i shows a white square at x = 8 * i (so each frame is known)."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (160, 120))
    for i in range(frames):
        image = np.zeros((120, 160, 3), np.uint8)
        image[40:80, 8 * i:8 * i + 20] = 255
        writer.write(image)
    writer.release()
    return path


def square_x(jpeg: bytes) -> int:
    gray = simplejpeg.decode_jpeg(jpeg, "GRAY")[:, :, 0]
    return int(np.argmax(gray[60] > 128))


def test_a_video_file_plays_in_real_time_through_the_capture_path(tmp_path):
    video = write_video(tmp_path / "cam.avi", 12)
    with LiveCameras({"usbcam": f"file:{video}"}, PARAMS) as live:
        frames, clocks = collect(live, 6.0, until=lambda f, c: len(f) >= 12)
        time.sleep(0.3)
        stats = live.stats()["usbcam"]
    assert [f.seq for f in frames] == list(range(1, 13))
    assert [square_x(f.jpeg) for f in frames] == [8 * i for i in range(12)]  # every frame, in order
    assert simplejpeg.decode_jpeg_header(frames[0].jpeg)[2] == "Gray"
    gaps = np.diff([f.device_time_s for f in frames])
    assert np.allclose(gaps, 1 / FPS, atol=1e-3)  # media times
    sync = ClockSync()
    for c in clocks:
        sync.add_round_trip(c.sample.host_send_s, c.sample.device_time_s, c.sample.host_recv_s)
    first = clocks[0].sample
    assert sync.method is ClockFitMethod.ROUND_TRIP and first.host_recv_s - first.host_send_s < 0.01
    # played in real time: each frame handed over within a few ms of its media time on the host clock
    lateness = [f.host_time_s - sync.to_host(f.device_time_s) for f in frames]
    assert min(lateness) >= -0.002 and np.median(lateness) < 0.05
    assert stats.timing.startswith("video file") and not stats.connected
    assert stats.last_error.startswith("end of the video file") and stats.frames == 12


def test_a_file_started_in_the_past_skips_what_a_live_camera_would_not_send(tmp_path):
    video = write_video(tmp_path / "cam.avi", 15)
    with LiveCameras({"cam": f"file:{video}?at={time.time() - 0.55}"}, PARAMS) as live:
        frames, _ = collect(live, 5.0, until=lambda f, c: f and square_x(f[-1].jpeg) == 8 * 14)
    xs = [square_x(f.jpeg) for f in frames]
    assert xs[-1] == 8 * 14 and 8 * 4 <= xs[0] <= 8 * 6  # frames 0..4 had passed (100 ms slack)


def test_a_slow_files_frame_read_late_is_sent_while_it_is_the_newest(tmp_path):
    """At 2 fps a frame read 0.2 s late is still the camera's newest (the next is due 0.3 s later):
    sent, as a live camera's driver would; one read after the next was due is skipped."""
    video = write_video(tmp_path / "cam.avi", 4, fps=2.0)
    with LiveCameras({"cam": f"file:{video}?at={time.time() - 0.7}"}, PARAMS) as live:
        frames, _ = collect(live, 5.0, until=lambda f, c: f and square_x(f[-1].jpeg) == 8 * 3)
    assert [square_x(f.jpeg) for f in frames] == [8, 16, 24]  # frame 0 (0.7 s late) skipped, frame 1 (0.2 s) sent


def test_capture_frames_wake_a_consumer_without_a_reading_thread(tmp_path):
    video = write_video(tmp_path / "cam.avi", 8)
    live = LiveCameras({"cam": f"file:{video}"}, PARAMS, thread=False).start()
    try:
        started = time.monotonic()
        frame = None
        while frame is None or not hasattr(frame, "jpeg"):
            frame = live.get(5.0)
            assert time.monotonic() - started < 5.0
        assert time.monotonic() - started < 1.0  # woken by the frame, not by get()'s timeout
    finally:
        live.stop()


def test_an_unopenable_device_is_one_line_at_start():
    with pytest.raises(SourceError, match=r"camera cam1: cannot open usb:97 — is a camera plugged in"):
        LiveCameras({"cam1": "usb:97"}, PARAMS).start()
    with pytest.raises(SourceError, match=r"cannot open v4l2:/dev/video97 — does /dev/video97 exist"):
        LiveCameras({"cam1": "v4l2:/dev/video97"}, PARAMS).start()


@pytest.mark.parametrize("url, kind, target", [
    ("http://10.0.0.2:81/stream", CameraKind.HTTP, "http://10.0.0.2:81/stream"),
    ("rtsp://10.0.0.3/stream1", CameraKind.RTSP, "rtsp://10.0.0.3/stream1"),
    ("usb:0", CameraKind.USB, "0"),
    ("v4l2:/dev/video2", CameraKind.V4L2, "/dev/video2"),
])
def test_camera_urls_by_scheme(url, kind, target):
    spec = parse_camera_url("cam", url)
    assert (spec.kind, spec.target, spec.captured) == (kind, target, kind is not CameraKind.HTTP)


def test_capture_options_are_read_and_checked(tmp_path):
    spec = parse_camera_url("cam", "usb:1?width=1280&height=720&fps=30")
    assert (spec.width, spec.height, spec.fps) == (1280, 720, 30.0)
    video = write_video(tmp_path / "v.avi", 1)
    assert parse_camera_url("cam", f"file:{video}?at=12.5").at_s == 12.5


@pytest.mark.parametrize("url, needle", [
    ("ftp://h/x", "unknown scheme 'ftp'"),
    ("192.168.1.2/stream", "has no scheme"),
    ("localhost:8080/stream", "unknown scheme 'localhost'"),
    ("camera", "has no scheme"),
    ("http:///stream", "names no host"),
    ("usb:first", "usb: takes a camera number"),
    ("usb:0?zoom=2", "unknown option 'zoom'"),
    ("usb:0?width=-5", "width must be a non-negative number"),
    ("usb:0?at=5", "at= is for file: sources only"),
    ("file:/no/such/video.avi", "no such video file"),
])
def test_bad_camera_urls_are_one_line_naming_the_camera(url, needle):
    with pytest.raises(ConfigError, match="camera cam7") as info:
        parse_camera_url("cam7", url)
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_rtsp_goes_through_opencvs_ffmpeg_backend_with_no_new_dependency():
    """The RTSP client is FFmpeg's (libavformat, bundled in opencv-contrib-python-headless): it
    speaks RTSP to the camera's port; a server that hangs up is a one-line error at start."""
    import socket
    import threading

    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]
    requests: list[bytes] = []

    def answer_once() -> None:
        conn, _ = server.accept()
        requests.append(conn.recv(1000))
        conn.close()

    threading.Thread(target=answer_once, daemon=True).start()
    try:
        with pytest.raises(SourceError, match=r"camera ipcam: cannot open rtsp://.* its RTSP port reachable"):
            LiveCameras({"ipcam": f"rtsp://127.0.0.1:{port}/stream1"}, PARAMS).start()
    finally:
        server.close()
    assert requests and requests[0].startswith(f"OPTIONS rtsp://127.0.0.1:{port}/stream1 RTSP/1.0".encode())
