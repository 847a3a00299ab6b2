"""The MJPEG part parser of a camera node's ``/stream`` (contracts §1): bytes in as each read
returns, whole checked parts out (:class:`MjpegParser`); the live source
(:mod:`cubetrack.source.streams`) feeds it. No sockets here."""

from __future__ import annotations

import logging
import math
import re
from collections import Counter
from dataclasses import dataclass

log = logging.getLogger(__name__)


_SOI = b"\xff\xd8"
_EOI = b"\xff\xd9"


@dataclass(frozen=True, slots=True, eq=False)
class MjpegPart:
    """One whole, plausible part: X-Frame (None when the server sends none), X-Timestamp in
    seconds (NaN when the server sends none and the parser does not require it), the JPEG bytes
    and the part headers (names lower-cased)."""

    seq: int | None
    device_time_s: float
    jpeg: bytes
    headers: dict[str, str]


def boundary_from_content_type(content_type: str) -> str | None:
    """The boundary of a ``multipart/x-mixed-replace;boundary=...`` Content-Type (quotes, spaces and
    a leading ``--`` that some servers include are removed); None when there is none."""
    m = re.search(r"""boundary\s*=\s*("([^"]*)"|[^;,\s]+)""", content_type, re.IGNORECASE)
    if not m:
        return None
    value = m.group(2) if m.group(2) is not None else m.group(1)
    value = value.strip().lstrip("-")
    return value or None


class MjpegParser:
    """Incremental parser of a ``multipart/x-mixed-replace`` body (contracts §1 part layout).

    :meth:`feed` takes bytes as they arrive and returns the parts completed by them. Parts are cut by
    ``Content-Length`` (no wait for the next boundary); without one, by the next delimiter. Every
    part is checked: headers within ``max_header_bytes`` and well formed, a Content-Length that is a
    plausible number, X-Timestamp present and a number, the body a whole JPEG (SOI ... EOI) and not
    cut short (a delimiter inside the declared length means the part was truncated: parsing resumes
    at that delimiter, so the next part is not lost). A part failing any check is skipped and
    counted in :attr:`bad` (reason -> count). ``boundary=None``: taken from the first ``--`` line.
    ``require_timestamp=False``: a part without X-Timestamp is kept (NaN time) for the caller to
    judge (a plain MJPEG device sends none); a malformed one is still skipped.
    """

    _SEEK, _HEADERS, _BODY, _SCAN = range(4)

    def __init__(self, boundary: str | None, max_header_bytes: int = 2048, max_part_bytes: int = 4 << 20,
                 require_timestamp: bool = True):
        self.max_header_bytes = max_header_bytes
        self.require_timestamp = require_timestamp
        self.max_part_bytes = max_part_bytes
        self._delim = b"--" + boundary.encode("latin-1") if boundary else None
        self._buf = bytearray()
        self._state = self._SEEK
        self._headers: dict[str, str] = {}
        self._length = 0
        self._scanned = 0  # bytes of the current body already searched for a delimiter
        self.bad: Counter[str] = Counter()
        self.parts = 0

    @property
    def in_part(self) -> bool:
        """Whether a part has started (some of its headers came) and not yet completed."""
        if self._state == self._HEADERS:
            return bool(self._buf.strip())
        return self._state != self._SEEK

    @property
    def awaiting(self) -> int:
        """Bytes still to come before the part being read is whole (its Content-Length less what is
        buffered); 0 when that is not known (between parts, or a part cut by its next delimiter)."""
        return max(0, self._length - len(self._buf)) if self._state == self._BODY else 0

    def close(self) -> None:
        """The stream ended: a part still in progress is counted as truncated."""
        if self.in_part:
            self._bad("part cut off by the end of the stream")
        self._buf.clear()
        self._state = self._SEEK

    def _known_delim(self) -> bytes:
        """The delimiter, known in every state after the first (taken from the first ``--`` line)."""
        if self._delim is None:
            raise AssertionError("the MJPEG delimiter is read before anything else")
        return self._delim

    def feed(self, data: bytes) -> list[MjpegPart]:
        self._buf += data
        out: list[MjpegPart] = []
        while True:
            if self._state == self._SEEK:
                if not self._seek():
                    break
            elif self._state == self._HEADERS:
                if not self._read_headers():
                    break
            elif self._state == self._BODY:
                part, progressed = self._read_body()
                if part is not None:
                    out.append(part)
                if not progressed:
                    break
            else:
                part, progressed = self._scan_body()
                if part is not None:
                    out.append(part)
                if not progressed:
                    break
        return out

    # --- states ---

    def _bad(self, reason: str) -> None:
        self.bad[reason] += 1
        log.debug("skipping a stream part: %s", reason)

    def _at_line_start(self, i: int) -> bool:
        j = i
        while j > 0 and self._buf[j - 1] == 0x2D:  # '-': some servers add dashes to the boundary
            j -= 1
        return j == 0 or self._buf[j - 1] == 0x0A

    def _seek(self) -> bool:
        buf = self._buf
        if self._delim is None:  # no boundary in the Content-Type: the first "--" line defines it
            m = re.search(rb"(?:^|\n)(--[^\r\n]{1,70})\r?\n", buf)
            if m is None:
                if len(buf) > self.max_header_bytes:
                    del buf[: len(buf) - 80]
                return False
            self._delim = m.group(1).rstrip()
        delim = self._delim
        start = 0
        while True:
            i = buf.find(delim, start)
            if i < 0:
                keep = len(delim) + 4
                if len(buf) > keep:
                    del buf[: len(buf) - keep]
                return False
            if not self._at_line_start(i):
                start = i + 1
                continue
            nl = buf.find(b"\n", i + len(delim))
            if nl < 0:
                if len(buf) - i > len(delim) + 80:  # no line end after the delimiter: not one
                    start = i + 1
                    continue
                if i:
                    del buf[:i]
                return False
            rest = bytes(buf[i + len(delim):nl]).strip()
            if rest not in (b"", b"--"):  # a longer word that starts like the boundary
                start = i + 1
                continue
            del buf[: nl + 1]
            if rest == b"--":  # the close delimiter; a stream may still go on after it
                continue
            self._state = self._HEADERS
            return True

    def _read_headers(self) -> bool:
        buf = self._buf
        if buf.startswith(b"\r\n") or buf.startswith(b"\n"):
            end, skip = 0, (2 if buf.startswith(b"\r\n") else 1)
        else:
            end = buf.find(b"\r\n\r\n", 0, self.max_header_bytes + 4)
            skip = end + 4
            if end < 0:
                end = buf.find(b"\n\n", 0, self.max_header_bytes + 2)
                skip = end + 2
        if end < 0 or end > self.max_header_bytes:
            if len(buf) > self.max_header_bytes or end > self.max_header_bytes:
                self._bad("part headers too long")
                self._state = self._SEEK
                return True
            return False
        if end == 0:  # a blank line right after the delimiter: an empty part, or one without headers
            rest = bytes(buf[skip:skip + len(self._known_delim()) + 2])
            if len(rest) < len(self._known_delim()) + 2 and (b"\r\n" + self._known_delim()).startswith(rest):
                return False  # wait: it may be the next delimiter
            del buf[:skip]
            self._state = self._SEEK
            if not (rest.startswith(self._known_delim()) or rest.startswith(b"\r\n" + self._known_delim())):
                self._bad("part without headers")
            return True
        raw = bytes(buf[:end])
        del buf[:skip]
        self._state = self._SEEK  # unless the headers pass
        headers: dict[str, str] = {}
        for line in raw.decode("latin-1").splitlines():
            if not line.strip():
                continue
            name, sep, value = line.partition(":")
            if not sep or not name.strip() or name != name.strip():
                self._bad("malformed part header")
                return True
            headers[name.strip().lower()] = value.strip()
        length = headers.get("content-length")
        if length is not None:
            if not length.isdigit() or not 0 < int(length) <= self.max_part_bytes:
                self._bad("bad Content-Length")
                return True
            self._length = int(length)
            self._state = self._BODY
        else:
            self._length = 0
            self._state = self._SCAN
        self._headers = headers
        self._scanned = 0
        return True

    def _find_delimiter(self, limit: int) -> int:
        """Index of ``\\n--boundary`` at a line start inside buf[:limit], searched once per byte."""
        pattern = b"\n" + self._known_delim()
        start = max(0, self._scanned - len(pattern))
        i = self._buf.find(pattern, start, limit)
        self._scanned = max(self._scanned, limit)
        if i < 0:
            return -1
        return i - 1 if i > 0 and self._buf[i - 1] == 0x0D else i

    def _read_body(self) -> tuple[MjpegPart | None, bool]:
        n = self._length
        cut = self._find_delimiter(min(n, len(self._buf)))
        if cut >= 0:  # the next part began inside this one's declared length: truncated
            del self._buf[:cut]
            self._bad("part shorter than its Content-Length")
            self._state = self._SEEK
            return None, True
        if len(self._buf) < n:
            return None, False
        body = bytes(self._buf[:n])
        del self._buf[:n]
        self._state = self._SEEK
        return self._finish(body), True

    def _scan_body(self) -> tuple[MjpegPart | None, bool]:
        cut = self._find_delimiter(len(self._buf))
        if cut < 0:
            if len(self._buf) > self.max_part_bytes:
                self._bad("part too large")
                del self._buf[: len(self._buf) - len(self._known_delim()) - 4]
                self._state = self._SEEK
                return None, True
            return None, False
        body = bytes(self._buf[:cut])
        del self._buf[:cut]
        self._state = self._SEEK
        return self._finish(body), True

    def _finish(self, body: bytes) -> MjpegPart | None:
        headers = self._headers
        if not (body.startswith(_SOI) and body.rstrip(b"\r\n").endswith(_EOI)):
            self._bad("not a whole JPEG")
            return None
        stamp = headers.get("x-timestamp")
        if stamp is None and self.require_timestamp:
            self._bad("no X-Timestamp")
            return None
        try:
            device_time_s = float("nan") if stamp is None else float(stamp)
        except ValueError:
            device_time_s = float("nan")
        if stamp is not None and not (math.isfinite(device_time_s) and device_time_s >= 0):
            self._bad("bad X-Timestamp")
            return None
        seq_text = headers.get("x-frame")
        if seq_text is not None and not seq_text.isdigit():
            self._bad("bad X-Frame")
            return None
        self.parts += 1
        return MjpegPart(int(seq_text) if seq_text is not None else None, device_time_s, body, headers)
