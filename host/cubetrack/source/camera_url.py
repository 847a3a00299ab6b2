"""What a ``[[cameras]] url`` names, by its scheme (docs/live.md, "Cameras by URL"):

- ``http://host[:port]/path``: an MJPEG stream over HTTP, read on the selector loop. A cubetrack
  node answers ``/time`` beside it; a plain MJPEG device (an ESP32-CAM's ``http://host:81/stream``,
  an IP camera) does not, and is found out by the stream itself (:mod:`cubetrack.source.timing`);
- ``usb:N``: the N-th local camera, ``v4l2:/dev/videoN``: a V4L2 device by path, both read through
  OpenCV's ``VideoCapture`` on a thread of their own (:mod:`cubetrack.source.capture`);
- ``rtsp://...``: an RTSP stream through OpenCV's FFmpeg backend (no clock: stamped on arrival);
- ``file:/path/video.avi``: a video file through the same ``VideoCapture`` path as a USB camera,
  played at its own frame rate, for tests and benchmarks (``?at=<unix time>`` releases its first
  frame at that host time, so it plays in step with other sources of the same scene).

``usb:``, ``v4l2:`` and ``file:`` take ``?width=W&height=H&fps=F`` (asked of the device; the
device may give something else, which the health then shows).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

from cubetrack.core.errors import ConfigError

EXAMPLES = ("http://192.168.1.21/stream (a cubetrack node), http://192.168.1.40:81/stream (an ESP32-CAM), "
            "usb:0, v4l2:/dev/video2, rtsp://192.168.1.50/stream1, file:/path/video.avi")


@enum.unique
class CameraKind(enum.Enum):
    """How a camera is read: over HTTP on the selector loop, or through OpenCV's VideoCapture."""

    HTTP = "http"
    USB = "usb"
    V4L2 = "v4l2"
    RTSP = "rtsp"
    FILE = "file"


@dataclass(frozen=True, slots=True)
class CameraUrl:
    """A parsed camera URL. ``target``: the URL (http, rtsp), the device index (usb) or the path
    (v4l2, file); ``width``/``height``/``fps``: asked of a capture device (0: its default);
    ``at_s``: a file's first frame's host Unix time (0: when it is opened)."""

    url: str
    kind: CameraKind
    target: str
    width: int = 0
    height: int = 0
    fps: float = 0.0
    at_s: float = 0.0

    @property
    def captured(self) -> bool:
        """Read through OpenCV's VideoCapture on a thread of its own (not the selector loop)."""
        return self.kind is not CameraKind.HTTP


def parse_camera_url(name: str, url: str) -> CameraUrl:
    """The camera ``name``'s ``url`` parsed; ConfigError (one line, with examples) when the scheme
    is unknown or the rest does not fit it."""
    scheme, sep, rest = url.partition(":")
    scheme = scheme.lower()
    if not sep:
        raise ConfigError(f"camera {name}: url {url!r} has no scheme; expected one of: {EXAMPLES}")
    if scheme in ("http", "rtsp"):
        u = urlsplit(url)
        if not u.hostname:
            raise ConfigError(f"camera {name}: url {url!r} names no host; expected e.g. {EXAMPLES}")
        return CameraUrl(url, CameraKind(scheme), url)
    if scheme not in ("usb", "v4l2", "file"):
        raise ConfigError(f"camera {name}: url {url!r}: unknown scheme {scheme!r}; expected one of: {EXAMPLES}")
    target, _, query = rest.partition("?")
    options = _options(name, url, query)
    kind = CameraKind(scheme)
    if kind is CameraKind.USB and not target.isdigit():
        raise ConfigError(f"camera {name}: url {url!r}: usb: takes a camera number, e.g. usb:0")
    if kind is not CameraKind.USB and not target:
        raise ConfigError(f"camera {name}: url {url!r} names no {'device' if kind is CameraKind.V4L2 else 'file'}")
    if kind is CameraKind.FILE and not Path(target).is_file():
        raise ConfigError(f"camera {name}: url {url!r}: no such video file {target}")
    if kind is not CameraKind.FILE and options.get("at", 0.0):
        raise ConfigError(f"camera {name}: url {url!r}: at= is for file: sources only")
    return CameraUrl(url, kind, target, int(options.get("width", 0)), int(options.get("height", 0)),
                     options.get("fps", 0.0), options.get("at", 0.0))


def _options(name: str, url: str, query: str) -> dict[str, float]:
    """``width``, ``height``, ``fps`` and ``at`` of a capture URL's query, as non-negative numbers."""
    out: dict[str, float] = {}
    for key, value in parse_qsl(query, keep_blank_values=True):
        if key not in ("width", "height", "fps", "at"):
            raise ConfigError(f"camera {name}: url {url!r}: unknown option {key!r}; known: width, height, fps, at")
        try:
            number = float(value)
        except ValueError:
            number = -1.0
        if not number >= 0 or (key in ("width", "height") and number != int(number)):
            raise ConfigError(f"camera {name}: url {url!r}: {key} must be a non-negative number, got {value!r}")
        out[key] = number
    return out
