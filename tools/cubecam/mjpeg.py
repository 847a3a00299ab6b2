"""MJPEG-over-HTTP wire text of contracts §1, named once, and a small stream reader.

The bytes match the firmware (``firmware/core/mjpeg.cpp``, ``firmware/core/http.cpp``) so that
clients cannot tell the emulator from a node:

- every answer is ``HTTP/1.1``, has ``Connection: close``, ``Cache-Control: no-cache`` and
  ``Access-Control-Allow-Origin: *``; no chunked encoding (the GS2200M cannot do it): the
  stream body simply ends when the connection closes;
- the stream head is followed at once by the first delimiter ``\\r\\n--<B>\\r\\n``; each part is
  its headers (``Content-Type``, ``Content-Length``, ``X-Timestamp``, ``X-Frame``), a blank
  line, the JPEG, and then the *next* delimiter, so readers that wait for the boundary show
  the frame at once. The byte stream equals "a delimiter before every part".

Every part carries ``Content-Length``: ffmpeg's and OpenCV's reader then read exactly that
many bytes instead of scanning for the boundary.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import BinaryIO

BOUNDARY = "cubecam-mjpeg-boundary"
PART_DELIMITER = f"\r\n--{BOUNDARY}\r\n".encode("ascii")
STREAM_CONTENT_TYPE = f"multipart/x-mixed-replace;boundary={BOUNDARY}"
COMMON_HEADERS = "Connection: close\r\nCache-Control: no-cache\r\nAccess-Control-Allow-Origin: *\r\n"
CAPTURE_DISPOSITION = "Content-Disposition: inline; filename=capture.jpg\r\n"

MAX_REQUEST_HEAD = 2048  # request line + headers; more -> 431
MAX_TARGET = 128         # longer targets match no route -> 404
MAX_STREAM_FPS = 30.0    # /stream?fps=N accepts 0 < N <= 30 with at most one decimal

REASONS = {
    200: "OK",
    400: "Bad Request",
    404: "Not Found",
    405: "Method Not Allowed",
    431: "Request Header Fields Too Large",
    503: "Service Unavailable",
}


def format_timestamp(micros: int) -> str:
    """``<seconds>.<6-digit microseconds>``: the X-Timestamp and ``/time`` format."""
    micros = max(0, int(micros))
    return f"{micros // 1_000_000}.{micros % 1_000_000:06d}"


def parse_timestamp(text: str) -> float:
    """Seconds from an X-Timestamp or ``/time`` body; ValueError when not ``<s>.<6 digits>``."""
    text = text.strip()
    if not re.fullmatch(r"\d+\.\d{6}", text):
        raise ValueError(f"timestamp {text!r} is not <seconds>.<6 digits>")
    return float(text)


def response_head(status: int, content_type: str, content_length: int | None = None, extra: str = "") -> bytes:
    """A response head: status line, Content-Type, optional Content-Length, the common headers,
    ``extra`` (complete ``Name: value\\r\\n`` lines) and the blank line."""
    lines = f"HTTP/1.1 {status} {REASONS.get(status, 'Internal Server Error')}\r\n"
    lines += f"Content-Type: {content_type}\r\n"
    if content_length is not None:
        lines += f"Content-Length: {content_length}\r\n"
    return (lines + COMMON_HEADERS + extra + "\r\n").encode("ascii")


def error_response(status: int) -> bytes:
    """A whole short error answer; the body is ``<status> <reason>\\n``."""
    body = f"{status} {REASONS.get(status, 'Internal Server Error')}\n".encode("ascii")
    extra = "Allow: GET\r\n" if status == 405 else ""
    return response_head(status, "text/plain", len(body), extra) + body


def stream_head() -> bytes:
    """The ``/stream`` response head followed by the first part delimiter."""
    return response_head(200, STREAM_CONTENT_TYPE) + PART_DELIMITER


def frame_headers(seq: int, capture_us: int) -> str:
    return f"X-Timestamp: {format_timestamp(capture_us)}\r\nX-Frame: {int(seq)}\r\n"


def part_header(size: int, seq: int, capture_us: int) -> bytes:
    """A part's headers and blank line; the JPEG and then :data:`PART_DELIMITER` follow."""
    return (f"Content-Type: image/jpeg\r\nContent-Length: {size}\r\n"
            + frame_headers(seq, capture_us) + "\r\n").encode("ascii")


def capture_head(size: int, seq: int, capture_us: int) -> bytes:
    """The ``/capture`` response head; the JPEG follows."""
    return response_head(200, "image/jpeg", size, CAPTURE_DISPOSITION + frame_headers(seq, capture_us))


# --- reading ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Part:
    """One stream part: its headers (names lower-cased), the JPEG, and the raw header bytes."""

    headers: dict[str, str]
    jpeg: bytes
    raw_header: bytes

    @property
    def frame(self) -> int:
        return int(self.headers["x-frame"])

    @property
    def timestamp_s(self) -> float:
        return parse_timestamp(self.headers["x-timestamp"])


class StreamFormatError(ValueError):
    """The stream does not follow the part layout of contracts §1."""


def read_response_head(f: BinaryIO, limit: int = 8192) -> tuple[int, dict[str, str], bytes]:
    """Read a response head from a buffered binary file: (status, headers lower-cased, raw bytes)."""
    raw = b""
    while True:
        line = f.readline(limit)
        if not line:
            raise StreamFormatError(f"connection closed inside the response head after {raw[:200]!r}")
        raw += line
        if line in (b"\r\n", b"\n"):
            break
        if len(raw) > limit:
            raise StreamFormatError("response head too long")
    lines = raw.decode("latin-1").split("\r\n")
    status_line = lines[0].split(" ", 2)
    if len(status_line) < 2 or not status_line[0].startswith("HTTP/1."):
        raise StreamFormatError(f"bad status line {lines[0]!r}")
    headers = {}
    for text in lines[1:]:
        if text:
            name, _, value = text.partition(":")
            headers[name.strip().lower()] = value.strip()
    return int(status_line[1]), headers, raw


def iter_parts(f: BinaryIO, boundary: str = BOUNDARY, max_jpeg: int = 8 << 20) -> Iterator[Part]:
    """Parts of a multipart stream body (after the response head), strictly per contract:
    each part must start with the delimiter line and carry Content-Length. Stops at EOF."""
    delimiter_line = f"--{boundary}\r\n".encode("ascii")
    while True:
        expect = f.readline(256)
        if not expect:
            return
        if expect != b"\r\n":
            raise StreamFormatError(f"expected CRLF before the delimiter, got {expect[:80]!r}")
        line = f.readline(256)
        if not line:
            return
        if line != delimiter_line:
            raise StreamFormatError(f"expected delimiter {delimiter_line!r}, got {line[:80]!r}")
        raw = b""
        while True:
            line = f.readline(256)
            if not line:
                return  # the stream ended between parts (the normal end: the node closed)
            raw += line
            if line == b"\r\n":
                break
            if not line.endswith(b"\r\n") or len(raw) > 1024:
                raise StreamFormatError(f"bad part header line {line[:80]!r}")
        headers = {}
        for text in raw.decode("latin-1").split("\r\n"):
            if text:
                name, sep, value = text.partition(": ")
                if not sep:
                    raise StreamFormatError(f"bad part header {text!r}")
                headers[name.lower()] = value
        try:
            size = int(headers["content-length"])
        except (KeyError, ValueError):
            raise StreamFormatError(f"part without a valid Content-Length: {raw!r}") from None
        if not 0 < size <= max_jpeg:
            raise StreamFormatError(f"implausible Content-Length {size}")
        jpeg = f.read(size)
        if len(jpeg) < size:
            return  # cut off mid-part: the connection closed
        yield Part(headers, jpeg, raw)
