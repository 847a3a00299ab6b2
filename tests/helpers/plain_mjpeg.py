"""A plain MJPEG camera over HTTP, as an ESP32-CAM or an IP camera serves one: no ``/time``, no
``X-Timestamp``, no ``X-Frame``; for tests and benchmarks of cameras without a clock.

The wire layout is that of Espressif's ESP32-CAM ``CameraWebServer`` example (esp32-camera,
``app_httpd.cpp``, as published): the stream at ``/stream`` (port 81 on the device, beside the web
page on port 80; here any port), ``Content-Type: multipart/x-mixed-replace;boundary=
123456789000000000000987654321``, HTTP/1.1 chunked encoding with each part's headers
(``Content-Type: image/jpeg``, ``Content-Length``) and its JPEG sent as separate chunks and the
delimiter ``\\r\\n--<boundary>\\r\\n`` sent *after* each part (so the first part has none before
it). At its worst the device answers nothing else while it streams (its HTTP server runs the
stream handler on its only task): ``time_answer="silent"`` takes ``/time`` connections and never
answers; ``"404"`` answers 404 as the device does when idle and as IP cameras do.

Frames are ``(release Unix time, JPEG)`` pairs: each is sent when its time comes; a client that
connects late starts at the next frame to come (no backlog), as a live camera does; after the
last frame the connection stays open and silent until :meth:`PlainMjpegServer.close`.
"""

from __future__ import annotations

import bisect
import http.server
import threading
import time
from collections.abc import Sequence

BOUNDARY = "123456789000000000000987654321"
CONTENT_TYPE = f"multipart/x-mixed-replace;boundary={BOUNDARY}"
PART_DELIMITER = f"\r\n--{BOUNDARY}\r\n".encode()


class PlainMjpegServer:
    """Serves ``frames`` (sorted by release time) at ``url`` (``http://127.0.0.1:<port>/stream``)
    until :meth:`close`; a context manager."""

    def __init__(self, frames: Sequence[tuple[float, bytes]], time_answer: str = "404", host: str = "127.0.0.1"):
        if time_answer not in ("404", "silent"):
            raise ValueError("time_answer is '404' or 'silent'")
        self.times = [t for t, _ in frames]
        self.jpegs = [j for _, j in frames]
        self.time_answer = time_answer
        self.closed = threading.Event()
        self.sent = 0
        self.time_requests = 0
        handler = type("Handler", (_Handler,), {"camera": self})
        self.server = http.server.ThreadingHTTPServer((host, 0), handler)
        self.server.daemon_threads = True
        self.url = f"http://{host}:{self.server.server_address[1]}/stream"
        self._thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self.closed.set()
        self.server.shutdown()
        self.server.server_close()

    def __enter__(self) -> PlainMjpegServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def finished(self) -> bool:
        """The last frame's release time has passed."""
        return not self.times or time.time() >= self.times[-1]


class _Handler(http.server.BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    camera: PlainMjpegServer

    def log_message(self, *args: object) -> None:
        pass

    def _chunk(self, data: bytes) -> None:
        self.wfile.write(f"{len(data):X}\r\n".encode() + data + b"\r\n")

    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        cam = self.camera
        if self.path.split("?")[0] != "/stream":
            if self.path.startswith("/time"):
                cam.time_requests += 1
                if cam.time_answer == "silent":
                    cam.closed.wait()
                    return
            self.send_error(404, "Nothing matches the given URI")
            return
        self.send_response(200)
        self.send_header("Content-Type", CONTENT_TYPE)
        self.send_header("Transfer-Encoding", "chunked")
        self.send_header("Access-Control-Allow-Origin", "*")
        self.end_headers()
        self.wfile.flush()
        i = bisect.bisect_left(cam.times, time.time())  # the next frame to come
        try:
            while i < len(cam.times) and not cam.closed.is_set():
                if cam.closed.wait(max(0.0, cam.times[i] - time.time())):
                    break
                newest = bisect.bisect_right(cam.times, time.time()) - 1
                i = max(i, newest)  # a slow client skips to the newest frame
                jpeg = cam.jpegs[i]
                self._chunk(f"Content-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n".encode())
                self._chunk(jpeg)
                self._chunk(PART_DELIMITER)
                self.wfile.flush()
                cam.sent += 1
                i += 1
            cam.closed.wait()  # after the last frame: a camera with nothing new, the connection kept
        except OSError:
            pass
