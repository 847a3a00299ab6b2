"""Live camera sources (architecture: layer "source"): frames and clock samples from camera nodes
over HTTP (contracts §1), delivered in arrival order to one consumer (the tracker, a recorder).

Per camera two HTTP exchanges run, all cameras on one event loop (non-blocking sockets,
:mod:`selectors`; :mod:`cubetrack.source.http_get`), in a thread of its own or, for a process
that does its per-frame work between reads, in the consumer's own thread:

- the **stream**: ``GET <url>`` (the node's ``/stream``), the body handed to
  :class:`~cubetrack.source.mjpeg.MjpegParser` as each read returns, so a frame is never held
  back until the next one comes (see
  ``ecosystem-facts.md`` §8). Each part becomes a :class:`~cubetrack.core.records.Frame` stamped
  with the host time at which its last byte arrived (the kernel's receive time). A malformed
  part is skipped and counted, never fatal; a lost, refused or silent connection is retried
  with exponential back-off (logged);
- the **clock**: ``GET /time`` about once a second (the URL derived from the stream URL),
  giving (host_send, device_time, host_recv) :class:`~cubetrack.core.cameras.ClockSample`
  round trips (:mod:`cubetrack.source.time_poll`). The TCP connection is opened before
  ``host_send`` is taken, so the round trip brackets only the request and its answer. Timeouts
  and garbage answers are counted and dropped. A camera's first stream connection waits for its
  first ``/time`` answer (or its failure, at most ``clock_timeout_s``): a frame that came before
  its camera's clock was known could not be placed in time, and live tracking gives it up.

:class:`LiveCameras` runs them for a set of cameras and merges everything into one bounded,
queue in arrival order. When the consumer falls behind, each camera keeps only its
newest frame (``frames_per_camera``): an older one still waiting is dropped and counted per camera
(a stale frame is worth less than a fresh one). Clock samples are never dropped (they are few and
each one matters).
"""

from __future__ import annotations

import logging
import math
import re
import selectors
import socket
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, cast

from cubetrack.core.cameras import ClockSample
from cubetrack.core.errors import ConfigError, SourceError
from cubetrack.core.params import check, check_at_least, check_positive, param
from cubetrack.core.records import Frame
from cubetrack.source.camera_url import parse_camera_url
from cubetrack.source.capture import CaptureReader, CaptureSettings, CaptureTaps
from cubetrack.source.http_get import HttpError, HttpGet
from cubetrack.source.mjpeg import MjpegParser, boundary_from_content_type
from cubetrack.source.order import FrameIntervals
from cubetrack.source.reasons import (
    broken_frames_reason,
    closed_reason,
    connection_reason,
    content_type_reason,
    http_status_reason,
    timeout_reason,
)
from cubetrack.source.time_poll import _ClockPoll, time_url
from cubetrack.source.timing import (
    ENVELOPE_WARMUP,
    ArrivalEnvelope,
    CameraTiming,
    declared_sample,
    timing_note,
)

log = logging.getLogger(__name__)

@dataclass(frozen=True, slots=True)
class SourceParams:
    """The ``[source]`` section of the tracker config: how live cameras are read."""

    connect_timeout_s: float = param(2.0, "a camera that does not accept the connection within this is "
                                          "retried, seconds")
    read_timeout_s: float = param(3.0, "a stream that sends nothing for this long is dropped and reconnected, seconds")
    backoff_initial_s: float = param(0.25, "first wait before reconnecting a lost stream, seconds "
                                           "(doubles per failure)")
    backoff_max_s: float = param(5.0, "longest wait between reconnection attempts, seconds")
    clock_period_s: float = param(1.0, "interval between /time round trips per camera, seconds")
    clock_timeout_s: float = param(0.5, "a /time round trip not answered within this is dropped, seconds")
    frames_per_camera: int = param(1, "frames of one camera waiting for the consumer; a newer frame pushes the oldest "
                                      "out (dropped, counted): when the host is behind, only the freshest "
                                      "frames are processed")
    max_header_bytes: int = param(2048, "a part whose headers are longer than this is skipped, bytes")
    max_part_bytes: int = param(4 * 1024 * 1024, "a part whose JPEG is larger than this is skipped, bytes")
    read_chunk_bytes: int = param(65536, "largest single socket read, bytes")
    arrival_latency_s: float = param(0.0, "capture -> arrival time assumed for a camera without a clock (a plain "
                                          "MJPEG device, RTSP, a capture device without driver timestamps): its "
                                          "frames are stamped this long before they arrived, seconds")
    arrival_envelope_frames: int = param(64, "a camera without a clock is stamped on the lower envelope of its "
                                             "arrivals against its frame count over this many frames (it captures "
                                             "at a steady rate, transfer only adds delay: "
                                             "cubetrack.source.timing.ArrivalEnvelope); 0: on the arrival itself")
    behind_intervals: float = param(0.25, "track --live takes waiting frames in arrival order, as a replay does, "
                                          "until one has waited longer than this many of its camera's frame "
                                          "intervals (it is behind), then the freshest instant first, its frames "
                                          "in arrival order (cubetrack.source.order)")
    capture_jpeg_quality: int = param(90, "JPEG quality (1..100) frames of usb:/v4l2:/rtsp:/file: cameras are "
                                          "encoded at (grayscale)")

    def __post_init__(self) -> None:
        check_positive(self, "connect_timeout_s", "read_timeout_s", "backoff_initial_s", "backoff_max_s",
                       "clock_period_s", "clock_timeout_s", unit="seconds")
        check(self.backoff_max_s >= self.backoff_initial_s, "backoff_max_s must not be below backoff_initial_s")
        check_at_least(self, 1, "frames_per_camera", "max_header_bytes", "max_part_bytes", "read_chunk_bytes")
        check(0.0 <= self.arrival_latency_s < 10.0, "arrival_latency_s must be in [0, 10) seconds")
        check(self.behind_intervals >= 0.0, f"behind_intervals must not be negative, got {self.behind_intervals}")
        check(1 <= self.capture_jpeg_quality <= 100, "capture_jpeg_quality must be in 1..100")
        check(self.arrival_envelope_frames == 0 or self.arrival_envelope_frames >= ENVELOPE_WARMUP,
              f"arrival_envelope_frames must be 0 (off) or at least {ENVELOPE_WARMUP}")

    def capture_settings(self) -> CaptureSettings:
        """What a VideoCapture camera's reader takes of these."""
        return CaptureSettings(self.arrival_latency_s, self.capture_jpeg_quality, self.clock_period_s,
                               self.backoff_initial_s, self.backoff_max_s, self.arrival_envelope_frames)

    def arrival_envelope(self) -> ArrivalEnvelope | None:
        """A camera without a clock's envelope of arrivals (None: stamped on the arrival itself)."""
        return ArrivalEnvelope(self.arrival_envelope_frames) if self.arrival_envelope_frames else None


# --- the live cameras ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ClockReading:
    """One completed ``/time`` round trip of ``camera``, as delivered by :class:`LiveCameras`."""

    camera: str
    sample: ClockSample


@dataclass(slots=True)
class CameraStats:
    """Counters of one live camera (a copy is handed out by :meth:`LiveCameras.stats`)."""

    url: str = ""
    frames: int = 0
    bytes: int = 0
    bad_parts: Counter = field(default_factory=Counter)  # reason -> count
    connects: int = 0
    reconnects: int = 0
    connected: bool = False
    dropped: int = 0  # frames dropped because the consumer fell behind
    clock_samples: int = 0
    clock_failures: Counter = field(default_factory=Counter)  # reason -> count
    last_round_trip_s: float = float("nan")
    last_error: str = ""
    timing: str = ""  # how its frames are timed and what it lacks (cubetrack.source.timing.timing_note)
    unstamped: int = 0  # frames without X-Timestamp given up before the camera was known to have no clock

    @property
    def bad(self) -> int:
        return sum(self.bad_parts.values())

    def copy(self) -> CameraStats:
        return replace(self, bad_parts=Counter(self.bad_parts), clock_failures=Counter(self.clock_failures))


class _StreamEnded(Exception):
    """The server ended the stream, answered something that is not a stream, or went silent; the
    message is the whole reason (:mod:`cubetrack.source.reasons`)."""


_STREAM, _CLOCK, _WAKE = "stream", "clock", "wake"
READS_PER_EVENT = 4  # reads of one ready stream before the loop turns to the others
NO_TIME_STATUSES = frozenset({400, 401, 403, 404, 405, 501})  # /time answered so: the device has no /time
# a camera's first round trips go back to back, then one per clock_period_s (as NTP's iburst): the tracker
# trusts a clock on one narrow trip or on this many of any width (ClockSyncParams.start_round_trips), and
# gives up the camera's frames until then
FIRST_ROUND_TRIPS = 3


@dataclass(slots=True, eq=False)
class _Camera:
    """One camera's state on the event loop: its stream connection (or when to reconnect) and
    its ``/time`` round trip in flight (or when the next is due)."""

    name: str
    url: str
    time_url: str
    stream: HttpGet | None = None
    parser: MjpegParser | None = None
    deadline: float = 0.0  # monotonic: the stream times out (connect, answer, or silence)
    reconnect_at: float = 0.0
    backoff: float = 0.0
    got_frame: bool = False
    seq: int = 0
    reported: Counter = field(default_factory=Counter)  # bad parts already counted in the stats
    poll: _ClockPoll | None = None
    poll_at: float = 0.0
    timing: CameraTiming = CameraTiming.UNKNOWN
    clock_failed: bool = False  # a /time round trip failed (no answer): with unstamped parts, no clock
    envelope: ArrivalEnvelope | None = None  # without a clock: its arrivals' envelope (stamps)
    round_trips: int = 0  # /time round trips ended (answered or failed)

    @property
    def clock_told(self) -> bool:
        """The first ``/time`` round trip has ended (a clock, none, or a failure): the stream may open."""
        return self.timing is not CameraTiming.UNKNOWN or self.clock_failed


class LiveCameras:
    """Frames and clock samples of several camera nodes, merged in arrival order.

    ``cameras``: name -> stream URL (or :class:`~cubetrack.io.config.CameraConfig` objects).
    Use as a context manager (or :meth:`start` / :meth:`stop`); take events with :meth:`get`:
    :class:`~cubetrack.core.records.Frame` or :class:`ClockReading`. ``on_frame`` / ``on_clock`` are
    called for every frame / round trip before it is queued (a recorder taps here, so it keeps
    frames the consumer drops); an exception in them stops everything and is re-raised by
    :meth:`get`. ``queue=False``: nothing is queued (taps only). ``clock`` gives host times (Unix
    seconds); ``wake`` is called whenever an event is queued, for consumers that wait on more
    than this source.

    Every camera is read on one event loop (non-blocking sockets, :mod:`selectors`, see
    :mod:`cubetrack.source.http_get`): with ``thread=True`` it runs in one thread of its own;
    with ``thread=False`` there is no thread and :meth:`get` reads whatever the sockets hold
    before it answers (for a process that does its per-frame work between reads).
    """

    def __init__(self, cameras: Mapping[str, str] | Iterable[Any], params: SourceParams = SourceParams(), *,
                 on_frame: Callable[[Frame], None] | None = None,
                 on_clock: Callable[[str, ClockSample], None] | None = None,
                 queue: bool = True, clock: Callable[[], float] = time.time,
                 wake: Callable[[], None] | None = None, thread: bool = True):
        if isinstance(cameras, Mapping):
            urls = dict(cameras)
        else:
            urls = {c.name: c.url for c in cast(Iterable[Any], cameras)}  # records with name and url
        if not urls:
            raise ConfigError("no cameras to read")
        specs = {name: parse_camera_url(name, url) for name, url in urls.items()}
        self.urls = urls
        self.params = params
        self.on_frame = on_frame
        self.on_clock = on_clock
        self.queue_enabled = queue
        self.clock = clock
        self.wake = wake
        self.threaded = thread
        self.failure: BaseException | None = None
        self._stats = {name: CameraStats(url=url) for name, url in urls.items()}
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._queue: deque = deque()
        self._queued_frames: Counter[str] = Counter()  # per camera
        self._intervals = FrameIntervals()  # each camera's frame interval (what "behind" is measured in)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._cameras = [_Camera(name, url, time_url(url), backoff=params.backoff_initial_s)
                         for name, url in urls.items() if not specs[name].captured]
        taps = CaptureTaps(self._put_captured, self._put_clock, self._count)
        self._captures = [CaptureReader(name, spec, params.capture_settings(), taps)
                          for name, spec in specs.items() if spec.captured]
        self._selector: selectors.BaseSelector | None = None
        self._waker: tuple[socket.socket, socket.socket] | None = None
        self._next_due = 0.0
        self._woken = False

    # --- lifecycle ---

    def start(self) -> LiveCameras:
        if self._selector is not None:
            return self
        self._selector = selectors.DefaultSelector()
        now = time.monotonic()
        for camera in self._cameras:
            camera.reconnect_at = camera.poll_at = now
        if self.threaded or self._captures:
            self._waker = socket.socketpair()
            for s in self._waker:
                s.setblocking(False)
            self._selector.register(self._waker[0], selectors.EVENT_READ, None)
        try:
            for reader in self._captures:
                reader.start()
        except Exception:
            self.stop()
            raise
        if self.threaded:
            t = threading.Thread(target=self._run, name="cubetrack-cameras", daemon=True)
            self._threads.append(t)
            t.start()
        return self

    def stop(self, timeout_s: float | None = None) -> None:
        """Stop reading (every connection is closed; what was queued can still be taken)."""
        if self._stop.is_set():
            return
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        for reader in self._captures:
            reader.stop(timeout_s if timeout_s is not None else 2.0)
        if self._selector is None:
            return
        if not self._threads:
            self._close_all()
            return
        try:
            if self._waker is not None:
                self._waker[1].send(b"x")
        except OSError:
            pass
        for t in self._threads:
            t.join(timeout_s if timeout_s is not None else self.params.read_timeout_s + 1.0)
        if any(t.is_alive() for t in self._threads):
            log.warning("live cameras: the reading thread is still running after stop (daemon; it ends with its read)")

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    def __enter__(self) -> LiveCameras:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- what the consumer sees ---

    def get(self, timeout_s: float | None = None, frames: bool = True, newest_first: bool = False,
            newest_if_behind: bool = False) -> Frame | ClockReading | None:
        """The next event in arrival order, or None after ``timeout_s`` (or once stopped and drained).
        ``frames=False``: the next clock reading only (frames keep waiting: a consumer with no
        room for a frame still takes the clock samples). ``newest_first``: clock readings first,
        then the frame that arrived last (the freshest, of whichever camera);
        ``newest_if_behind``: arrival order until the consumer is behind (a frame has waited
        longer than ``behind_intervals`` of its camera's frame interval), then clock readings
        first and the oldest frame of the freshest instant (:mod:`cubetrack.source.order`)."""
        if not self.threaded:
            self._read_for(timeout_s, frames)
        with self._cond:
            if self.threaded and not self._has(frames) and not self._stop.is_set():
                self._cond.wait(timeout_s)
            if self.failure is not None:
                raise self.failure
            waiting = [e for e in self._queue if isinstance(e, Frame)] if frames and newest_if_behind else []
            behind = self._intervals.behind(waiting, self.clock(), self.params.behind_intervals)
            if frames and not newest_first and not behind:
                if not self._queue:
                    return None
                item = self._queue.popleft()
            else:
                item = next((e for e in self._queue if isinstance(e, ClockReading)), None)
                if item is None and behind:
                    item = self._intervals.freshest_instant(waiting)
                elif item is None and frames:
                    item = next((e for e in reversed(self._queue) if isinstance(e, Frame)), None)
                if item is None:
                    return None
                self._queue.remove(item)
            if isinstance(item, Frame):
                self._queued_frames[item.camera] -= 1
            return item

    def _loop(self) -> selectors.BaseSelector:
        """The event loop's selector (there from :meth:`start` to :meth:`stop`)."""
        if self._selector is None:
            raise SourceError("the live source is not started")
        return self._selector

    def wake_on(self, fileobj) -> None:
        """Without a thread: :meth:`get` also stops waiting when ``fileobj`` (e.g. a pipe from
        another process, read by the caller) has something to read."""
        self._loop().register(fileobj, selectors.EVENT_READ, _WAKE)

    def _read_for(self, timeout_s: float | None, frames: bool) -> None:
        """Without a thread: read what the sockets hold, then wait up to ``timeout_s`` for an event
        (or for a file given to :meth:`wake_on`)."""
        if self._selector is None or self._stop.is_set():
            return
        self._woken = False
        self._step(0.0)
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._has(frames) and not self._stop.is_set() and not self._woken:
            left = 1.0 if deadline is None else deadline - time.monotonic()
            if left <= 0:
                break
            self._step(left)

    def _has(self, frames: bool) -> bool:
        return bool(self._queue) if frames else any(isinstance(e, ClockReading) for e in self._queue)

    def pending(self) -> int:
        with self._lock:
            return len(self._queue)

    def stats(self) -> dict[str, CameraStats]:
        """A consistent copy of every camera's counters."""
        with self._lock:
            return {name: s.copy() for name, s in self._stats.items()}

    # --- internals: the queue ---

    def _fail(self, exc: BaseException) -> None:
        log.error("live cameras: stopping: %s", exc)
        with self._cond:
            if self.failure is None:
                self.failure = exc
        self._stop.set()
        with self._cond:
            self._cond.notify_all()

    def _put_frame(self, frame: Frame) -> None:
        if self.on_frame is not None:
            try:
                self.on_frame(frame)
            except Exception as exc:  # e.g. the recorder's disk is full: stop, the consumer re-raises
                self._fail(exc)
                return
        with self._cond:
            self._stats[frame.camera].frames += 1
            self._stats[frame.camera].bytes += len(frame.jpeg)
            if not self.queue_enabled:
                return
            self._intervals.add(frame.camera, frame.host_time_s)
            if self._queued_frames[frame.camera] >= self.params.frames_per_camera:
                oldest = next(e for e in self._queue if isinstance(e, Frame) and e.camera == frame.camera)
                self._queue.remove(oldest)
                self._queued_frames[frame.camera] -= 1
                self._stats[frame.camera].dropped += 1
            self._queue.append(frame)
            self._queued_frames[frame.camera] += 1
            self._cond.notify()
        if self.wake is not None:
            self.wake()

    def _put_captured(self, frame: Frame) -> None:
        """A frame of a VideoCapture camera's thread: queued, and the event loop woken (without a
        thread of its own, :meth:`get` waits on the selector)."""
        self._put_frame(frame)
        waker = self._waker
        if waker is not None and not self.threaded:
            try:
                waker[1].send(b"f")
            except OSError:  # closed by stop(), or its buffer full (the loop is woken anyway)
                pass

    def _put_clock(self, camera: str, sample: ClockSample) -> None:
        if self.on_clock is not None:
            try:
                self.on_clock(camera, sample)
            except Exception as exc:
                self._fail(exc)
                return
        with self._cond:
            st = self._stats[camera]
            st.clock_samples += 1
            st.last_round_trip_s = sample.host_recv_s - sample.host_send_s
            if not self.queue_enabled:
                return
            self._queue.append(ClockReading(camera, sample))
            self._cond.notify()
        if self.wake is not None:
            self.wake()

    def _count(self, camera: str, **changes) -> None:
        with self._lock:
            st = self._stats[camera]
            for key, value in changes.items():
                if key in ("bad_parts", "clock_failures"):
                    getattr(st, key).update(value)
                elif isinstance(value, int) and not isinstance(value, bool):
                    setattr(st, key, getattr(st, key) + value)
                else:
                    setattr(st, key, value)

    # --- internals: the event loop ---

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                self._step(1.0)
        except Exception as exc:  # a bug: stop, the consumer re-raises
            self._fail(exc)
        finally:
            self._close_all()

    def _step(self, timeout_s: float) -> None:
        """Read every socket that is ready (waiting up to ``timeout_s`` for one, less when a
        connection's deadline or a round trip is due sooner), then act on what is due."""
        wait = max(0.0, min(timeout_s, self._next_due - time.monotonic()))
        for key, _mask in self._loop().select(wait):
            if key.data is None:  # the waker: stop() was called
                try:
                    cast(socket.socket, key.fileobj).recv(64)
                except OSError:
                    pass
                continue
            if key.data is _WAKE:  # a file of the consumer's: it reads it
                self._woken = True
                continue
            camera, kind = key.data
            if kind is _STREAM:
                self._on_stream(camera)
            else:
                self._on_clock(camera)
        self._due(time.monotonic())

    def _due(self, now: float) -> None:
        """Connect, time out and poll what is due at ``now``; note when the next thing is due."""
        if self._stop.is_set():
            return
        p = self.params
        due = now + 1.0
        for camera in self._cameras:
            if camera.stream is None:
                if now >= camera.reconnect_at and camera.clock_told:
                    self._connect(camera, now)
            elif now >= camera.deadline:
                if camera.parser is not None and camera.parser.awaiting:
                    self._on_stream(camera)  # bytes below the low-water mark woke nobody: read what came
            if camera.stream is not None and now >= camera.deadline:
                what = "connect" if not camera.stream.connected else (
                    "the answer" if camera.stream.head is None else "the next bytes")
                limit = p.connect_timeout_s if what == "connect" else p.read_timeout_s
                self._stream_lost(camera, _StreamEnded(timeout_reason(what, limit, camera.url)))
            if camera.stream is not None:
                due = min(due, camera.deadline)
            elif camera.clock_told:  # else the round trip's end (its deadline, below) opens the stream
                due = min(due, camera.reconnect_at)
            if camera.poll is None and now >= camera.poll_at:
                if camera.timing is CameraTiming.ARRIVAL:
                    self._declare(camera, now)
                else:
                    self._start_poll(camera, now)
            elif camera.poll is not None and now >= camera.poll.deadline:
                self._poll_done(camera, reason="no answer", detail="timed out")
            due = min(due, camera.poll.deadline if camera.poll is not None else camera.poll_at)
        self._next_due = due

    def _register(self, get: HttpGet, data: tuple[_Camera, str]) -> None:
        self._loop().register(get.sock, get.events, data)

    def _unregister(self, get: HttpGet) -> None:
        try:
            self._loop().unregister(get.sock)
        except (KeyError, ValueError):
            pass
        get.close()

    def _connect(self, camera: _Camera, now: float) -> None:
        p = self.params
        camera.got_frame = False
        try:
            get = HttpGet(camera.url, {"Accept": "multipart/x-mixed-replace, */*"}, self.clock, p.read_chunk_bytes)
        except (OSError, ValueError) as exc:
            self._stream_lost(camera, exc)
            return
        camera.stream, camera.deadline = get, now + p.connect_timeout_s
        self._register(get, (camera, _STREAM))

    def _on_stream(self, camera: _Camera) -> None:
        get = camera.stream
        if get is None:
            return
        try:
            for _ in range(READS_PER_EVENT):
                was_connected = get.connected
                data = get.handle()
                if get.connected and not was_connected:  # the request went out: the answer is due
                    camera.deadline = time.monotonic() + self.params.read_timeout_s
                    self._loop().modify(get.sock, get.events, (camera, _STREAM))
                    return
                if camera.parser is None and get.head is not None:
                    self._stream_started(camera, get)
                if data:
                    camera.deadline = time.monotonic() + self.params.read_timeout_s
                    self._parts(camera, data, get.received_s)
                    # a part whose length is known wakes the loop once, when it is whole (not per piece)
                    get.wake_after(camera.parser.awaiting if camera.parser is not None else 0)
                if get.ended:
                    raise _StreamEnded(closed_reason(camera.url))
                if not get.filled:
                    return
        except BlockingIOError:  # nothing more to read now
            return
        except Exception as exc:  # network errors, malformed answers
            self._stream_lost(camera, exc)

    def _stream_started(self, camera: _Camera, get: HttpGet) -> None:
        if get.head is None:
            return
        status, headers = get.head
        if status != 200:
            raise _StreamEnded(http_status_reason(status, camera.url))
        ctype = headers.get("content-type", "")
        if not ctype.lower().startswith("multipart/"):
            raise _StreamEnded(content_type_reason(ctype, camera.url))
        p = self.params
        camera.parser = MjpegParser(boundary_from_content_type(ctype), p.max_header_bytes, p.max_part_bytes,
                                    require_timestamp=False)
        camera.reported = Counter()
        if camera.envelope is not None:  # a new connection: frames in a new phase, maybe at a new rate
            camera.envelope.reset()
        self._count(camera.name, connects=1, connected=True, last_error="")
        log.info("camera %s: streaming from %s", camera.name, camera.url)

    def _parts(self, camera: _Camera, data: bytes, arrived_s: float) -> None:
        parser = camera.parser
        if parser is None:
            return
        for part in parser.feed(data):
            camera.got_frame = True
            device_time_s = part.device_time_s
            if camera.timing is CameraTiming.ARRIVAL:
                device_time_s = self._arrival_stamp(camera, arrived_s, part.seq)
            elif math.isnan(device_time_s):
                if camera.timing is CameraTiming.NODE:
                    parser.bad["no X-Timestamp"] += 1
                    continue
                if not camera.clock_failed:  # /time has not told yet: the frame cannot be placed in time
                    self._count(camera.name, unstamped=1)
                    continue
                self._no_clock(camera, "its stream parts carry no X-Timestamp and /time did not answer")
                device_time_s = self._arrival_stamp(camera, arrived_s, part.seq)
            camera.seq = part.seq if part.seq is not None else camera.seq + 1
            self._put_frame(Frame(camera.name, camera.seq, device_time_s, arrived_s, part.jpeg))
        self._report_bad(camera)

    @staticmethod
    def _arrival_stamp(camera: _Camera, arrived_s: float, seq: int | None) -> float:
        """A frame of a camera without a clock on its device clock: its time on the envelope of the
        arrivals (or its arrival); the declared clock samples put the capture the latency before."""
        return arrived_s if camera.envelope is None else camera.envelope.stamp(arrived_s, seq)

    def _no_clock(self, camera: _Camera, why: str) -> None:
        """The camera has no clock (``why``): its frames are stamped on arrival from now on, and a
        declared clock sample (the assumed latency) is queued now and every ``clock_period_s``."""
        camera.timing = CameraTiming.ARRIVAL
        camera.envelope = self.params.arrival_envelope()
        self._poll_done(camera)
        note = timing_note(camera.timing, self.params.arrival_latency_s)
        log.warning("camera %s: %s: %s", camera.name, why, note)
        self._count(camera.name, timing=note)
        now = time.monotonic()
        camera.poll_at = now
        self._declare(camera, now)

    def _declare(self, camera: _Camera, now: float) -> None:
        camera.poll_at = max(camera.poll_at + self.params.clock_period_s, now)
        self._put_clock(camera.name, declared_sample(self.clock(), self.params.arrival_latency_s))

    def _report_bad(self, camera: _Camera) -> None:
        if camera.parser is None:
            return
        bad = camera.parser.bad
        if bad != camera.reported:
            self._count(camera.name, bad_parts=bad - camera.reported, last_error=broken_frames_reason(bad, camera.url))
            camera.reported = Counter(bad)

    def _stream_lost(self, camera: _Camera, exc: BaseException) -> None:
        """End the camera's connection (if any) and schedule the next attempt with back-off."""
        p = self.params
        if camera.stream is not None:
            self._unregister(camera.stream)
            camera.stream = None
        if camera.parser is not None:
            camera.parser.close()  # a part in progress when the connection ended is counted
            self._report_bad(camera)
            camera.parser = None
        reason = str(exc) if isinstance(exc, _StreamEnded) else connection_reason(exc, camera.url)
        self._count(camera.name, connected=False, last_error=reason)
        if camera.got_frame:  # the connection worked: start the back-off again
            camera.backoff = p.backoff_initial_s
        self._count(camera.name, reconnects=1)
        log.warning("camera %s: stream lost (%s); reconnecting in %.2f s", camera.name, reason, camera.backoff)
        camera.reconnect_at = time.monotonic() + camera.backoff
        camera.backoff = min(p.backoff_max_s, camera.backoff * 2)

    def _start_poll(self, camera: _Camera, now: float) -> None:
        camera.poll_at = max(camera.poll_at + self.params.clock_period_s, now)
        try:
            camera.poll = _ClockPoll(camera.time_url, self.params.clock_timeout_s, self.clock)
        except (OSError, ValueError) as exc:
            self._poll_done(camera, reason="no answer", detail=_describe(exc))
            return
        self._register(camera.poll.get, (camera, _CLOCK))

    def _on_clock(self, camera: _Camera) -> None:
        poll = camera.poll
        if poll is None:
            return
        try:
            sample = poll.handle()
        except BlockingIOError:
            return
        except (OSError, HttpError) as exc:
            self._poll_done(camera, reason="no answer", detail=_describe(exc))
        except (ValueError, UnicodeDecodeError) as exc:
            status = poll.get.head[0] if poll.get.head is not None else 0
            if camera.timing is CameraTiming.UNKNOWN and status in NO_TIME_STATUSES:
                self._no_clock(camera, f"/time answered HTTP {status}")
            else:
                self._poll_done(camera, reason="garbage answer", detail=_describe(exc))
        else:
            if sample is None:
                self._loop().modify(poll.get.sock, poll.get.events, (camera, _CLOCK))
            else:
                self._poll_done(camera)
                if camera.timing is CameraTiming.UNKNOWN:
                    camera.timing = CameraTiming.NODE
                    self._count(camera.name, timing=timing_note(camera.timing))
                self._put_clock(camera.name, sample)

    def _poll_done(self, camera: _Camera, reason: str = "", detail: str = "") -> None:
        """The round trip in flight ended (with a failure ``reason``, counted, or a sample); one of
        the first ``FIRST_ROUND_TRIPS`` is followed by the next at once."""
        if camera.poll is not None:
            self._unregister(camera.poll.get)
            camera.poll = None
            camera.round_trips += 1
            if camera.round_trips < FIRST_ROUND_TRIPS and camera.timing is not CameraTiming.ARRIVAL:
                camera.poll_at = time.monotonic()
        if reason:
            camera.clock_failed = True
            self._count(camera.name, clock_failures=Counter({reason: 1}))
            log.debug("camera %s: /time round trip failed: %s", camera.name, detail)

    def _close_all(self) -> None:
        for camera in self._cameras:
            if camera.stream is not None:
                self._unregister(camera.stream)
                camera.stream = None
            camera.parser = None
            self._poll_done(camera)
            self._count(camera.name, connected=False)
        if self._waker is not None:
            for s in self._waker:
                s.close()
            self._waker = None
        if self._selector is not None:
            self._selector.close()


def _describe(exc: BaseException) -> str:
    """One line on why a connection failed (``[Errno 111] Connection refused``, ``HTTP 404``,
    ``timed out (the next bytes, 3 s)``)."""
    text = re.sub(r"\s+", " ", str(exc)) or type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."
