"""Local cameras and other VideoCapture sources (``usb:N``, ``v4l2:/dev/videoN``, ``rtsp://``, and
``file:`` standing in for a USB camera in tests), each read through OpenCV's ``VideoCapture`` on a
thread of its own: ``read()`` blocks until the device has a frame, so it must never run on the
selector loop that reads the HTTP cameras (:class:`cubetrack.source.streams.LiveCameras` owns
these readers and merges their frames into its one queue).

Per frame: the image is encoded as a grayscale JPEG (detection works on gray; the pipeline, the
recording and the worker processes carry JPEGs): 0.72 ms per VGA frame and 1.88 ms per
1280x720 frame, colour would be 1.52 / 4.10 ms (``benchmarks/capture_encode.py``, 2 cores), and
stamped (:mod:`cubetrack.source.timing`):

- the driver's timestamp (``CAP_PROP_POS_MSEC``: the V4L2 backend gives the buffer's timestamp,
  on the host's monotonic clock for UVC webcams) when it is plausible (within 2 s before now);
  the reader then sends monotonic<->Unix round trips of this host as the camera's clock samples;
- otherwise (RTSP, devices without stamps) the monotonic time the read returned, de-jittered
  (:class:`~cubetrack.source.timing.ArrivalEnvelope`: the lower envelope of the read times
  against the frame count), the assumed latency declared in the clock samples;
- a video file: its media time (``CAP_PROP_POS_MSEC`` of the frame read) from its start, played
  in real time; frames whose time has already passed are skipped, as a live camera would not
  deliver them.

USB and V4L2 devices are asked for MJPEG (``FOURCC MJPG``, which is how webcams reach 30 fps at
larger sizes over USB 2) at the URL's ``width``/``height``/``fps`` where given; what the device
gives instead is logged. A device that cannot be opened at the start is a
:class:`~cubetrack.core.errors.SourceError`; one lost later is reopened with back-off.
"""

from __future__ import annotations

import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import simplejpeg

from cubetrack.core.cameras import ClockSample
from cubetrack.core.errors import SourceError
from cubetrack.core.records import Frame
from cubetrack.source.camera_url import CameraKind, CameraUrl
from cubetrack.source.timing import ArrivalEnvelope, CameraTiming, monotonic_sample, timing_note

log = logging.getLogger(__name__)

MAX_DRIVER_AGE_S = 2.0  # a driver timestamp older than this (or in the future) is not trusted
MAX_FILE_LATE_S = 0.1  # a file's frame read later than this after its media time (and after the next one's) is skipped


@dataclass(frozen=True, slots=True)
class CaptureSettings:
    """What a capture reader needs of the ``[source]`` section (seconds; quality 1..100)."""

    latency_s: float
    jpeg_quality: int
    clock_period_s: float
    backoff_initial_s: float
    backoff_max_s: float
    envelope_frames: int = 0  # without driver stamps: frames of the arrival envelope (0: the read time itself)


@dataclass(frozen=True, slots=True)
class CaptureTaps:
    """Where a capture reader's events go (:class:`~cubetrack.source.streams.LiveCameras`' own
    queueing and counting, thread-safe)."""

    frame: Callable[[Frame], None]
    clock: Callable[[str, ClockSample], None]
    count: Callable[..., None]


def open_capture(name: str, spec: CameraUrl) -> Any:
    """An opened ``cv2.VideoCapture`` for ``spec``, MJPEG at the asked size and rate where it is a
    device; SourceError (one line) when it cannot be opened."""
    if spec.kind is CameraKind.USB:
        backend = cv2.CAP_V4L2 if sys.platform.startswith("linux") else cv2.CAP_ANY
        capture = cv2.VideoCapture(int(spec.target), backend)
    elif spec.kind is CameraKind.V4L2:
        capture = cv2.VideoCapture(spec.target, cv2.CAP_V4L2)
    else:
        capture = cv2.VideoCapture(spec.target, cv2.CAP_FFMPEG)
    if not capture.isOpened():
        capture.release()
        raise SourceError(f"camera {name}: cannot open {spec.url} — {_open_advice(spec)}")
    if spec.kind in (CameraKind.USB, CameraKind.V4L2):
        capture.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*"MJPG"))
        for prop, value in ((cv2.CAP_PROP_FRAME_WIDTH, spec.width), (cv2.CAP_PROP_FRAME_HEIGHT, spec.height),
                            (cv2.CAP_PROP_FPS, spec.fps)):
            if value:
                capture.set(prop, value)
        log.info("camera %s: %s gives %dx%d at %.1f fps", name, spec.url, capture.get(cv2.CAP_PROP_FRAME_WIDTH),
                 capture.get(cv2.CAP_PROP_FRAME_HEIGHT), capture.get(cv2.CAP_PROP_FPS))
    return capture


def _open_advice(spec: CameraUrl) -> str:
    if spec.kind is CameraKind.USB:
        return "is a camera plugged in with that number? (ls /dev/video*; usb:0 is the first)"
    if spec.kind is CameraKind.V4L2:
        return f"does {spec.target} exist and may this user read it? (group video)"
    if spec.kind is CameraKind.RTSP:
        return "is the camera on, the URL right, and its RTSP port reachable?"
    return "is it a video file OpenCV's FFmpeg backend reads?"


class CaptureReader:
    """One VideoCapture camera read on a thread of its own: frames and clock samples to ``taps``."""

    def __init__(self, name: str, spec: CameraUrl, settings: CaptureSettings, taps: CaptureTaps):
        self.name, self.spec, self.settings, self.taps = name, spec, settings, taps
        self.capture: Any = None
        self.timing = CameraTiming.MEDIA if spec.kind is CameraKind.FILE else CameraTiming.UNKNOWN
        self.seq = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._next_clock_s = 0.0
        self._file_start_mono = 0.0
        self._file_late_s = MAX_FILE_LATE_S
        self._file_skipped = 0
        self._envelope = ArrivalEnvelope(settings.envelope_frames) if settings.envelope_frames else None

    def start(self) -> None:
        """Open the device (SourceError when it cannot be) and start reading it."""
        self.capture = open_capture(self.name, self.spec)
        if self.spec.kind is CameraKind.FILE:
            at_s = self.spec.at_s or time.time()
            self._file_start_mono = time.monotonic() + (at_s - time.time())
            # a live camera sends its newest frame: one read late is skipped only once the next is due too
            fps = self.capture.get(cv2.CAP_PROP_FPS)
            self._file_late_s = max(MAX_FILE_LATE_S, 1.0 / fps if fps > 0 else 0.0)
        self.taps.count(self.name, connects=1, connected=True)
        self._thread = threading.Thread(target=self._run, name=f"cubetrack-capture-{self.name}", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("camera %s: the capture thread is still in a read after stop (daemon)", self.name)

    def _run(self) -> None:
        backoff = self.settings.backoff_initial_s
        try:
            while not self._stop.is_set():
                if self.capture is None:
                    if self._reopen():
                        backoff = self.settings.backoff_initial_s
                    else:
                        self._stop.wait(backoff)
                        backoff = min(self.settings.backoff_max_s, backoff * 2)
                    continue
                if not self._read_one():
                    self._lost()
        finally:
            if self.capture is not None:
                self.capture.release()
                self.capture = None
            self.taps.count(self.name, connected=False)

    def _reopen(self) -> bool:
        try:
            self.capture = open_capture(self.name, self.spec)
        except SourceError as exc:
            self.taps.count(self.name, last_error=str(exc))
            return False
        self.taps.count(self.name, connects=1, connected=True, last_error="")
        return True

    def _lost(self) -> None:
        """The read failed: the end of a file (reading stops), or a device lost (reopened)."""
        if self.capture is not None:
            self.capture.release()
            self.capture = None
        if self._envelope is not None:
            self._envelope.reset()
        if self.spec.kind is CameraKind.FILE:
            self.taps.count(self.name, connected=False, last_error=f"end of the video file {self.spec.target} "
                            f"({self.seq} frames read, {self._file_skipped} skipped as already past)")
            self._stop.set()
            return
        reason = f"{self.spec.url} stopped giving frames — is the camera still plugged in?"
        log.warning("camera %s: %s; reopening", self.name, reason)
        self.taps.count(self.name, connected=False, reconnects=1, last_error=reason)

    def _read_one(self) -> bool:
        """Read, stamp, encode and hand over one frame; False when the read failed."""
        ok, image = self.capture.read()
        read_mono = time.monotonic()
        if not ok or image is None:
            return False
        pos_s = self.capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        if self.spec.kind is CameraKind.FILE:
            device_s = self._file_start_mono + pos_s
            if read_mono - device_s > self._file_late_s:  # a newer frame is due: a live camera would send that
                self._file_skipped += 1
                return True
            if self._stop.wait(max(0.0, device_s - time.monotonic())):
                return True
            read_mono = time.monotonic()
        else:
            device_s = self._stamp(pos_s, read_mono)
        self._clock_due()
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        jpeg = simplejpeg.encode_jpeg(np.ascontiguousarray(gray)[:, :, None], self.settings.jpeg_quality, "GRAY")
        self.seq += 1
        arrival_s = time.time() - (time.monotonic() - read_mono)
        self.taps.frame(Frame(self.name, self.seq, device_s, arrival_s, jpeg))
        return True

    def _stamp(self, pos_s: float, read_mono: float) -> float:
        """The frame's device time (host monotonic seconds): the driver's stamp when plausible,
        else the time the read returned; the camera's timing is decided on its first frame."""
        plausible = math.isfinite(pos_s) and 0.0 <= read_mono - pos_s <= MAX_DRIVER_AGE_S
        if self.timing is CameraTiming.UNKNOWN:
            self.timing = CameraTiming.DRIVER if plausible else CameraTiming.ARRIVAL
            note = timing_note(self.timing, self.settings.latency_s)
            log.info("camera %s: %s", self.name, note)
            self.taps.count(self.name, timing=note)
        if plausible and self.timing is CameraTiming.DRIVER:
            return pos_s
        return read_mono if self._envelope is None else self._envelope.stamp(read_mono)

    def _clock_due(self) -> None:
        """This host's monotonic<->Unix round trip every ``clock_period_s`` (and before the first
        frame), with the assumed latency declared for a camera stamped on arrival."""
        now = time.monotonic()
        if now < self._next_clock_s:
            return
        if self._next_clock_s == 0.0 and self.timing is CameraTiming.MEDIA:
            self.taps.count(self.name, timing=timing_note(self.timing))
        self._next_clock_s = now + self.settings.clock_period_s
        latency_s = self.settings.latency_s if self.timing is CameraTiming.ARRIVAL else 0.0
        self.taps.clock(self.name, monotonic_sample(latency_s))
