"""Camera nodes in software: every camera of a recording (or a folder of JPEGs) served with
the firmware's HTTP API (contracts §1), for developing and testing clients without hardware.

::

    with Emulator("rec/", loop=True) as emu:
        url = emu.urls["cam1"]            # http://127.0.0.1:<port>/stream

Each camera gets its own listening socket (its own port, or its own 127.0.0.x address) and
serves several clients at once, one thread per connection, at most ``max_clients`` (more get
503, as on the node). Frames are released on the recorded timeline (see
:mod:`cubecam.replay`); a stream client always gets the newest frame, so a slow client skips
frames and never receives old ones. The accepted sockets get a small send buffer
(``send_buffer_bytes``) so that "newest" is not defeated by kernel buffering.

Faults (:class:`Faults`) make the node misbehave in the ways a Wi-Fi camera does: added
latency and jitter, frames dropped at capture (gaps in X-Frame), a bandwidth cap in bytes/s
shared by the camera's clients (the GS2200M manages some 100 kB/s), a disconnect every N s, a
stalled connection, and corrupted parts. A camera can be knocked on its tripod mid-stream
(:mod:`cubecam.bump`: ``bumps`` at given times, :meth:`Emulator.bump` at once).
"""

from __future__ import annotations

import errno
import heapq
import ipaddress
import json
import logging
import random
import select
import socket
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cubecam import __version__, mjpeg
from cubecam.bump import Bump, RotationWarp, camera_intrinsics
from cubecam.errors import EmulatorError
from cubecam.replay import CameraTrack, Release, Timeline, jpeg_size, load_images, load_recording
from cubecam.request import ParseStatus, RequestParser, Route, RouteDecision, route

log = logging.getLogger(__name__)

FIRMWARE_VERSION = f"cubecam-emulator {__version__}"
REQUEST_TIMEOUT_S = 5.0     # a client must finish its request head within this (as the node)
STALL_TIMEOUT_S = 10.0      # a client that accepts no bytes for this long is dropped (as the node)
NET_CHUNK = 1400            # bytes per write when the bandwidth is capped (a GS2200M write)
START_LEAD_S = 0.05         # the first frame is released this long after start()
EMULATED_RSSI_DBM = -45
CORRUPT_KINDS = ("jpeg", "truncate")
FAULT_LOG_ITEMS = 4096      # faults injected remembered per camera (Unix time, kind), for soak tests


@dataclass(frozen=True, slots=True)
class Faults:
    """Misbehaviour to inject; the defaults inject none.

    latency_s: added to every answer and every stream part (after capture), seconds.
    jitter_s: uniform random extra delay in [0, jitter_s] on top of latency_s.
    drop_rate: probability in [0, 1) that a frame is lost at capture (a gap in X-Frame).
    bandwidth_bytes_per_s: cap on the bytes a camera sends per second, shared by its clients.
    disconnect_every_s: a stream connection is cut after this many seconds.
    stall_after_s: a stream connection goes silent after this many seconds ...
    stall_for_s: ... for this long (None: until the client leaves).
    corrupt_every: every N-th part of a stream connection is corrupted ...
    corrupt_kind: ... "jpeg" (garbage JPEG data, framing intact) or "truncate" (the part is
        shorter than its Content-Length, so the client must find the next boundary).
    seed: random seed for drops, jitter and garbage (None: unpredictable).
    """

    latency_s: float = 0.0
    jitter_s: float = 0.0
    drop_rate: float = 0.0
    bandwidth_bytes_per_s: float | None = None
    disconnect_every_s: float | None = None
    stall_after_s: float | None = None
    stall_for_s: float | None = None
    corrupt_every: int | None = None
    corrupt_kind: str = "jpeg"
    seed: int | None = None

    def check(self) -> Faults:
        def bad(what: str) -> EmulatorError:
            return EmulatorError(what)

        if self.latency_s < 0 or self.jitter_s < 0:
            raise bad("latency and jitter must be >= 0 seconds")
        if not 0.0 <= self.drop_rate < 1.0:
            raise bad(f"drop rate must be in [0, 1), got {self.drop_rate}")
        if self.bandwidth_bytes_per_s is not None and not self.bandwidth_bytes_per_s >= 100:
            raise bad(f"bandwidth cap must be at least 100 bytes/s, got {self.bandwidth_bytes_per_s}")
        for name in ("disconnect_every_s", "stall_after_s", "stall_for_s"):
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise bad(f"{name.removesuffix('_s').replace('_', ' ')} must be a positive number of seconds")
        if self.corrupt_every is not None and self.corrupt_every < 1:
            raise bad(f"corrupt every N parts needs N >= 1, got {self.corrupt_every}")
        if self.corrupt_kind not in CORRUPT_KINDS:
            raise bad(f"corrupt kind must be one of {', '.join(CORRUPT_KINDS)}, got {self.corrupt_kind!r}")
        return self


@dataclass(frozen=True, slots=True)
class LiveFrame:
    """A released frame: X-Frame, X-Timestamp in microseconds, JPEG, release time (monotonic s)."""

    seq: int
    capture_us: int
    jpeg: bytes
    released_mono: float


class _Stopped(Exception):
    """The emulator is shutting down, or the connection's planned end came."""


class _TokenBucket:
    """Serialises a camera's sends at a byte rate: each chunk leaves when the link is free."""

    def __init__(self, rate: float):
        self.rate = rate
        self._free_at = 0.0
        self._lock = threading.Lock()

    def reserve(self, n: int) -> float:
        """Book n bytes; returns the monotonic time at which they have gone out."""
        with self._lock:
            start = max(time.monotonic(), self._free_at)
            self._free_at = start + n / self.rate
            return self._free_at


class _Camera:
    """One emulated node: its listening socket, newest frame and counters."""

    def __init__(self, emu: Emulator, index: int, track: CameraTrack, address: str, port: int):
        self.emu = emu
        self.index = index
        self.track = track
        self.name = track.name
        self.address = address
        self.port = port
        self.sock: socket.socket | None = None
        self.cond = threading.Condition()
        self.latest: LiveFrame | None = None
        self.frames_sent = 0
        self.frames_dropped = 0
        self.clients = 0
        self.streaming = 0
        self.released: deque[float] = deque(maxlen=64)  # monotonic release times, for the measured rate
        self.connections: set[socket.socket] = set()
        self.bucket = (_TokenBucket(emu.faults.bandwidth_bytes_per_s)
                       if emu.faults.bandwidth_bytes_per_s else None)
        self.width, self.height = 0, 0
        self.faults_injected: deque[tuple[float, str]] = deque(maxlen=FAULT_LOG_ITEMS)

    def _injected(self, kind: str) -> None:
        """Note a fault injected now: "disconnect", "stall" or "corrupt"."""
        with self.cond:
            self.faults_injected.append((time.time(), kind))

    # --- frames ---

    def publish(self, frame: LiveFrame) -> None:
        with self.cond:
            self.latest = frame
            self.released.append(frame.released_mono)
            self.cond.notify_all()

    def wait_newer(self, seq: int, timeout: float) -> LiveFrame | None:
        with self.cond:
            if self.latest is None or self.latest.seq <= seq:
                self.cond.wait(timeout)
            f = self.latest
            return f if f is not None and f.seq > seq else None

    def measured_fps(self) -> float:
        with self.cond:
            times = list(self.released)
        now = time.monotonic()
        recent = [t for t in times if now - t <= 5.0]
        if len(recent) < 2 or now - recent[0] <= 0:
            return 0.0
        return (len(recent) - 1) / (recent[-1] - recent[0]) if recent[-1] > recent[0] else 0.0

    # --- serving ---

    @property
    def base_url(self) -> str:
        host = self.address if ":" not in self.address else f"[{self.address}]"
        return f"http://{host}:{self.port}/"

    def bind(self) -> None:
        try:
            self.sock = socket.create_server((self.address, self.port), backlog=16)
        except OSError as exc:
            what = "is in use" if exc.errno == errno.EADDRINUSE else f"cannot be used: {exc.strerror or exc}"
            raise EmulatorError(
                f"{self.address}:{self.port} {what} (camera {self.name}); choose another --port or address"
            ) from None
        self.port = self.sock.getsockname()[1]
        self.sock.settimeout(0.2)

    def accept_loop(self) -> None:
        stop = self.emu._stop
        assert self.sock is not None
        while not stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except (TimeoutError, BlockingIOError):
                continue
            except OSError:
                if stop.is_set():
                    return
                time.sleep(0.05)
                continue
            with self.cond:
                full = self.clients >= self.emu.max_clients
                if not full:
                    self.clients += 1
                    self.connections.add(conn)
            if full:
                threading.Thread(target=self._refuse, args=(conn,), daemon=True,
                                 name=f"cubecam-{self.name}-503").start()
                continue
            threading.Thread(target=self._serve, args=(conn,), daemon=True, name=f"cubecam-{self.name}-client").start()

    def _refuse(self, conn: socket.socket) -> None:
        try:
            conn.settimeout(1.0)
            conn.sendall(mjpeg.error_response(503))
            _lingering_close(conn)
        except OSError:
            pass
        _close(conn)

    def _serve(self, conn: socket.socket) -> None:
        try:
            conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.emu.send_buffer_bytes)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            decision = self._read_request(conn)
            if decision is not None:
                conn.settimeout(STALL_TIMEOUT_S)
                self._respond(conn, decision)
        except (_Stopped, OSError):
            pass
        except Exception:  # a bug must not take the node down; log it and drop the client
            log.exception("camera %s: error serving a client", self.name)
        finally:
            with self.cond:
                self.clients -= 1
                self.connections.discard(conn)
            _close(conn)

    def _read_request(self, conn: socket.socket) -> RouteDecision | None:
        parser = RequestParser()
        deadline = time.monotonic() + REQUEST_TIMEOUT_S
        while parser.status is ParseStatus.INCOMPLETE:
            left = deadline - time.monotonic()
            if left <= 0 or self.emu._stop.is_set():
                return None  # too slow: hang up without an answer, as the node does
            conn.settimeout(min(left, 0.25))
            try:
                data = conn.recv(1024)
            except TimeoutError:
                continue
            if not data:
                return None
            parser.feed(data)
        return route(parser)

    def _respond(self, conn: socket.socket, d: RouteDecision) -> None:
        if d.route is Route.STREAM:
            self._stream(conn, d.fps_cap)
            return
        if d.route is Route.ERROR:
            out = mjpeg.error_response(d.status)
        elif d.route is Route.TIME:
            body = mjpeg.format_timestamp(self.emu.device_now_us(self.index)).encode("ascii")
            out = mjpeg.response_head(200, "text/plain", len(body)) + body
        elif d.route is Route.CAPTURE:
            f = self.latest
            if f is None:
                out = mjpeg.error_response(503)
            else:
                out = mjpeg.capture_head(len(f.jpeg), f.seq, f.capture_us) + f.jpeg
        elif d.route is Route.STATUS:
            body = (json.dumps(self.status(conn), separators=(",", ":")) + "\n").encode("utf-8")
            out = mjpeg.response_head(200, "application/json", len(body)) + body
        else:
            body = self.index_html().encode("utf-8")
            out = mjpeg.response_head(200, "text/html; charset=utf-8", len(body)) + body
        self._delay(time.monotonic())
        self._send(conn, out, None)
        _lingering_close(conn)

    def status(self, conn: socket.socket | None = None) -> dict:
        ip = self.address
        if conn is not None and ip in ("0.0.0.0", "::", ""):
            ip = conn.getsockname()[0]
        interval_s = self.track.frame_interval_s
        return {
            "name": self.name,
            "firmware_version": FIRMWARE_VERSION,
            "uptime_ms": self.emu.device_now_us(self.index) // 1000,
            "ip": ip,
            "rssi": EMULATED_RSSI_DBM,
            "fps": {"configured": round(1.0 / interval_s, 1) if interval_s > 0 else 0.0,
                    "measured": round(self.measured_fps(), 3)},
            "frames_sent": self.frames_sent,
            "frames_dropped": self.frames_dropped,
            "clients": self.streaming,
            "jpeg_quality": self.emu.jpeg_quality,
            "width": self.width,
            "height": self.height,
            "last_error": "",
        }

    def index_html(self) -> str:
        st = self.status()
        return (
            f'<!doctype html>\n<html><head><meta charset="utf-8"><title>{self.name}</title></head>\n'
            f'<body style="font-family:sans-serif"><h1>{self.name}</h1>\n'
            f'<img src="/stream" alt="live stream" width="{self.width}" height="{self.height}">\n'
            f'<p>{st["fps"]["configured"]:.1f} fps configured, {st["fps"]["measured"]:.3f} measured &middot; '
            f'{st["clients"]} streaming &middot; {st["frames_sent"]} frames sent &middot; '
            f'<a href="/status">status</a> &middot; <a href="/capture">capture</a> &middot; '
            f'emulated by {FIRMWARE_VERSION}</p>\n</body></html>\n'
        )

    def _delay(self, since_mono: float) -> None:
        """Sleep for the latency fault, counted from since_mono."""
        faults = self.emu.faults
        if faults.latency_s <= 0 and faults.jitter_s <= 0:
            return
        extra = faults.latency_s + (self.emu._random(faults.jitter_s) if faults.jitter_s > 0 else 0.0)
        wait = since_mono + extra - time.monotonic()
        if wait > 0 and self.emu._stop.wait(wait):
            raise _Stopped()

    def _send(self, conn: socket.socket, data: bytes, end_mono: float | None) -> None:
        """sendall, chunked through the bandwidth cap; stops at end_mono (a planned disconnect)."""
        stop = self.emu._stop
        if self.bucket is None:
            if end_mono is not None and time.monotonic() >= end_mono:
                raise _Stopped()
            conn.sendall(data)
            return
        view = memoryview(data)
        for i in range(0, len(view), NET_CHUNK):
            chunk = view[i:i + NET_CHUNK]
            done_at = self.bucket.reserve(len(chunk))
            if end_mono is not None:
                done_at_or_end = min(done_at, end_mono)
            else:
                done_at_or_end = done_at
            wait = done_at_or_end - time.monotonic()
            if wait > 0 and stop.wait(wait):
                raise _Stopped()
            if end_mono is not None and time.monotonic() >= end_mono:
                raise _Stopped()
            conn.sendall(chunk)

    def _stream(self, conn: socket.socket, fps_cap: float | None) -> None:
        faults = self.emu.faults
        stop = self.emu._stop
        started = time.monotonic()
        end_mono = started + faults.disconnect_every_s if faults.disconnect_every_s else None
        stall_at = started + faults.stall_after_s if faults.stall_after_s else None
        self._delay(started)
        self._send(conn, mjpeg.stream_head(), end_mono)
        with self.cond:
            self.streaming += 1
        try:
            last_seq = 0
            next_allowed = 0.0
            parts = 0
            while not stop.is_set():
                now = time.monotonic()
                if end_mono is not None and now >= end_mono:
                    return
                if stall_at is not None and now >= stall_at:
                    stall_at = None
                    self._stall(conn, faults.stall_for_s, end_mono)
                    continue
                if _client_left(conn):
                    return
                frame = self.wait_newer(last_seq, 0.1)
                if frame is None:
                    continue
                if fps_cap is not None:
                    wait = next_allowed - time.monotonic()
                    if wait > 0:
                        if stop.wait(wait):
                            return
                        frame = self.latest or frame  # the newest when this client may send again
                    next_allowed = time.monotonic() + 1.0 / fps_cap  # as the node: from this frame's start
                elif last_seq and frame.seq > last_seq + 1:
                    with self.cond:
                        self.frames_dropped += frame.seq - last_seq - 1
                last_seq = frame.seq
                self._delay(frame.released_mono)
                parts += 1
                body = frame.jpeg
                header_size = len(body)
                if faults.corrupt_every and parts % faults.corrupt_every == 0:
                    body = self.emu._corrupt(body, faults.corrupt_kind)
                    self._injected("corrupt")
                part = mjpeg.part_header(header_size, frame.seq, frame.capture_us) + body + mjpeg.PART_DELIMITER
                self._send(conn, part, end_mono)
                with self.cond:
                    self.frames_sent += 1
        finally:
            if end_mono is not None and time.monotonic() >= end_mono and not stop.is_set():
                self._injected("disconnect")
            with self.cond:
                self.streaming -= 1

    def _stall(self, conn: socket.socket, stall_for_s: float | None, end_mono: float | None) -> None:
        """Send nothing for a while (or until the client leaves) while keeping the connection."""
        stop = self.emu._stop
        self._injected("stall")
        until = time.monotonic() + stall_for_s if stall_for_s else None
        conn.settimeout(0.1)
        try:
            while not stop.is_set():
                now = time.monotonic()
                if (until is not None and now >= until) or (end_mono is not None and now >= end_mono):
                    return
                try:
                    if conn.recv(4096) == b"":
                        raise _Stopped()  # the client gave up
                except TimeoutError:
                    pass
            raise _Stopped()
        finally:
            conn.settimeout(STALL_TIMEOUT_S)


def _client_left(conn: socket.socket) -> bool:
    """Whether the client closed its side (what it sends after the request is discarded)."""
    try:
        readable, _, _ = select.select([conn], [], [], 0)
        if not readable:
            return False
        return conn.recv(4096, socket.MSG_DONTWAIT) == b""
    except BlockingIOError:
        return False
    except OSError:
        return True


def _is_loopback(address: str) -> bool:
    try:
        return ipaddress.ip_address(address).is_loopback
    except ValueError:
        return address == "localhost"


def _close(conn: socket.socket) -> None:
    try:
        conn.close()
    except OSError:
        pass


def _lingering_close(conn: socket.socket) -> None:
    """Half-close, then read what the client still sends (briefly), so that unread request
    bytes do not make the kernel reset the connection and discard the answer."""
    try:
        conn.shutdown(socket.SHUT_WR)
        conn.settimeout(0.2)
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline and conn.recv(4096):
            pass
    except OSError:
        pass


class Emulator:
    """Camera nodes replaying a recording (``recording``) or a folder of JPEGs (``images`` at
    ``fps``). Construct (reads and checks the frames), then :meth:`start` or use as a context
    manager. ``port`` is the first camera's port (0: any free port per camera), the next
    cameras get port+1, ...; with ``addresses`` each camera binds its own address instead, all
    on ``port`` (``"auto"``: ``host``, then the next addresses). ``skipped`` counts the frames left
    out (reason -> count)."""

    def __init__(self, recording: str | Path | None = None, *, images: str | Path | None = None,
                 fps: float | None = None, name: str | None = None, host: str = "127.0.0.1", port: int = 0,
                 addresses: list[str] | str | None = None, loop: bool = False, faults: Faults | None = None,
                 max_clients: int = 4, jpeg_quality: int = 80, send_buffer_bytes: int = 8 * 1024,
                 bumps: tuple[Bump, ...] = ()):
        if (recording is None) == (images is None):
            raise EmulatorError("give either a recording folder or an image folder")
        if images is not None:
            tracks, self.skipped = load_images(images, fps if fps is not None else 10.0, name)
        elif recording is not None:
            tracks, self.skipped = load_recording(recording)
        if not 1 <= max_clients <= 64:
            raise EmulatorError(f"max clients must be 1..64, got {max_clients}")
        if not 0 <= port <= 65535:
            raise EmulatorError(f"port must be 0..65535, got {port}")
        self.faults = (faults or Faults()).check()
        self.loop = loop
        self.max_clients = max_clients
        self.jpeg_quality = jpeg_quality
        self.send_buffer_bytes = send_buffer_bytes
        self.timeline = Timeline(tracks, loop)
        if addresses == "auto":
            try:
                first = ipaddress.ip_address(host)
                addresses = [str(first + i) for i in range(len(tracks))]
            except ValueError:
                raise EmulatorError(f"{host!r} is not an IP address; 'auto' addresses count up from it") from None
        if addresses:
            if len(addresses) < len(tracks):
                raise EmulatorError(
                    f"{len(tracks)} cameras need {len(tracks)} addresses, got {len(addresses)}: {','.join(addresses)}")
            places = [(addresses[i], port) for i in range(len(tracks))]
        else:
            places = [(host, port + i if port else 0) for i in range(len(tracks))]
            if port and port + len(tracks) - 1 > 65535:
                raise EmulatorError(f"ports {port}..{port + len(tracks) - 1} run past 65535")
        self._cameras = [_Camera(self, i, t, a, p) for i, (t, (a, p)) in enumerate(zip(tracks, places, strict=True))]
        self._stop = threading.Event()
        self.finished = threading.Event()  # set when a non-looping replay released its last frame
        self._threads: list[threading.Thread] = []
        self._rng = random.Random(self.faults.seed)
        self._rng_lock = threading.Lock()
        self._start_mono: float | None = None
        self._unix_minus_mono = 0.0
        self._recording = None if recording is None else Path(recording)
        self._scheduled = sorted((b for b in bumps if b.at_s is not None), key=lambda b: b.at_s or 0.0)
        self._warps: dict[str, tuple[np.ndarray, RotationWarp]] = {}
        self.bumped: list[tuple[float, Bump]] = []  # (Unix time, bump) of every bump applied: the truth
        for b in bumps:
            self._bump_warp(b)  # a bad camera name or a recording without its intrinsics fails here, not mid-run
        for cam in self._cameras:
            try:
                first_jpeg = cam.track.frames[0].path.read_bytes()
            except OSError:
                first_jpeg = b""
            cam.width, cam.height = jpeg_size(first_jpeg) or (0, 0)

    # --- lifecycle ---

    def start(self) -> Emulator:
        if self._start_mono is not None:
            return self
        try:
            for cam in self._cameras:
                cam.bind()
        except EmulatorError:
            for cam in self._cameras:
                if cam.sock is not None:
                    cam.sock.close()
            raise
        self._unix_minus_mono = time.time() - time.monotonic()
        self._start_mono = time.monotonic() + START_LEAD_S
        for cam in self._cameras:
            self._spawn(cam.accept_loop, f"cubecam-{cam.name}-accept")
        self._spawn(self._replay_loop, "cubecam-replay")
        for cam in self._cameras:
            log.info("camera %s served at %s", cam.name, cam.base_url)
            if not _is_loopback(cam.address):
                log.warning("camera %s listens on %s, reachable from the network: anyone there can watch it; "
                            "bind 127.0.0.1 to keep it on this machine", cam.name, cam.base_url)
        return self

    def _spawn(self, target, name: str) -> None:
        t = threading.Thread(target=target, name=name, daemon=True)
        t.start()
        self._threads.append(t)

    def close(self) -> None:
        self._stop.set()
        for cam in self._cameras:
            if cam.sock is not None:
                _close(cam.sock)
            with cam.cond:
                conns = list(cam.connections)
                cam.cond.notify_all()
            for conn in conns:
                try:
                    conn.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
        for t in self._threads:
            t.join(timeout=2.0)

    def __enter__(self) -> Emulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def wait_finished(self, timeout: float | None = None) -> bool:
        """Wait until a non-looping replay has released its last frame."""
        return self.finished.wait(timeout)

    # --- what clients see ---

    @property
    def cameras(self) -> tuple[str, ...]:
        return tuple(c.name for c in self._cameras)

    def faults_injected(self) -> dict[str, list[tuple[float, str]]]:
        """Camera name -> the faults injected so far (the last FAULT_LOG_ITEMS): (Unix time, kind)."""
        out = {}
        for c in self._cameras:
            with c.cond:
                out[c.name] = list(c.faults_injected)
        return out

    @property
    def base_urls(self) -> dict[str, str]:
        """Camera name -> ``http://host:port/`` (valid after start)."""
        return {c.name: c.base_url for c in self._cameras}

    @property
    def urls(self) -> dict[str, str]:
        """Camera name -> stream URL, as a tracker config's ``url`` (valid after start)."""
        return {c.name: c.base_url + "stream" for c in self._cameras}

    def unix_time(self, recorded_host_s: float) -> float:
        """When (Unix time on this machine, ``time.time()``) the replay reaches a recorded host time
        (the recording's ``host_time`` clock; the first pass when looping). Valid after start.

        The replay is the recorded host timeline shifted by a constant: a frame whose device time
        maps to recorded host time h (through the camera's clock fit, see :mod:`cubecam.replay`) is
        released at ``unix_time(h)``, and ``/time`` answers the device time that maps to now. So a
        reference on the recorded clock (e.g. ``ground_truth.tum``) is moved onto the live clock by
        adding ``unix_time(h) - h``, the same for every h.
        """
        if self._start_mono is None:
            raise EmulatorError("the emulator has not been started")
        return recorded_host_s - self.timeline.start_host_s + self._start_mono + self._unix_minus_mono

    def device_now_us(self, camera: int) -> int:
        """A camera's device clock now, microseconds (the clock of X-Timestamp and /time)."""
        start = self._start_mono if self._start_mono is not None else time.monotonic()
        return int(round(self.timeline.device_time(camera, time.monotonic() - start) * 1e6))

    def stats(self, camera: str) -> dict:
        """A camera's /status document."""
        for c in self._cameras:
            if c.name == camera:
                return c.status()
        raise EmulatorError(f"no camera {camera!r} (has {', '.join(self.cameras)})")

    def bump(self, bump: Bump) -> None:
        """Turn a camera now (``bump.at_s`` is ignored): its frames from the next one on are
        resampled as the turned camera sees them (:mod:`cubecam.bump`); a second bump adds to the first."""
        R, warp = self._bump_warp(bump)
        self._warps[bump.camera] = R, warp
        self.bumped.append((time.time(), bump))
        log.warning("%s", bump.describe())

    # --- internals ---

    def _bump_warp(self, bump: Bump) -> tuple[np.ndarray, RotationWarp]:
        if bump.camera not in self.cameras:
            raise EmulatorError(f"bump: no camera {bump.camera!r} (has {', '.join(self.cameras)})")
        if self._recording is None:
            raise EmulatorError("bump: needs a recording (its camera_info says how to turn the frames)")
        before = self._warps.get(bump.camera)
        R = bump.R_old_new if before is None else before[0] @ bump.R_old_new
        return R, RotationWarp(camera_intrinsics(self._recording, bump.camera), R, self.jpeg_quality)

    def _random(self, scale: float) -> float:
        with self._rng_lock:
            return self._rng.uniform(0.0, scale)

    def _corrupt(self, jpeg: bytes, kind: str) -> bytes:
        if kind == "truncate":
            return jpeg[: max(1, len(jpeg) // 2)]
        with self._rng_lock:
            garbage = self._rng.randbytes(len(jpeg) - len(jpeg) // 4)
        return jpeg[: len(jpeg) // 4] + garbage

    def _replay_loop(self) -> None:
        assert self._start_mono is not None
        stop = self._stop
        sources = [self.timeline.releases(i) for i in range(len(self._cameras))]
        heap: list[tuple[float, int, Release]] = []
        for i, src in enumerate(sources):
            r = next(src, None)
            if r is not None:
                heap.append((r.at_s, i, r))
        heapq.heapify(heap)
        cache: dict[Path, bytes] = {}
        cacheable = self.loop and sum(len(c.track.frames) for c in self._cameras) <= 2000
        while heap and not stop.is_set():
            at_s, i, r = heapq.heappop(heap)
            wait = self._start_mono + at_s - time.monotonic()
            if wait > 0 and stop.wait(wait):
                return
            nxt = next(sources[i], None)
            if nxt is not None:
                heapq.heappush(heap, (nxt.at_s, i, nxt))
            if self.faults.drop_rate > 0 and self._random(1.0) < self.faults.drop_rate:
                continue  # lost at capture: a gap in X-Frame
            data = cache.get(r.path)
            if data is None:
                try:
                    data = r.path.read_bytes()
                except OSError as exc:
                    self.skipped["unreadable frame file"] += 1
                    log.warning("%s: %s; skipped", r.path, exc)
                    continue
                if cacheable:
                    cache[r.path] = data
            cam = self._cameras[i]
            while self._scheduled and (self._scheduled[0].at_s or 0.0) <= at_s:
                self.bump(self._scheduled.pop(0))
            if cam.name in self._warps:
                data = self._warps[cam.name][1](data)
            cam.publish(LiveFrame(r.seq, int(round(r.device_time_s * 1e6)), data, self._start_mono + at_s))
        if not stop.is_set():
            self.finished.set()


def skipped_summary(skipped: Counter[str]) -> str:
    """``3 skipped (2 corrupt frame file, 1 bad index row)`` or ``0 skipped``."""
    total = sum(skipped.values())
    if not total:
        return "0 skipped"
    return f"{total} skipped (" + ", ".join(f"{n} {why}" for why, n in sorted(skipped.items())) + ")"
