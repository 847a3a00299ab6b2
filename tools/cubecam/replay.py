"""What the emulator replays: each camera's frames and its device clock, read from a recording
(contracts §3) or a folder of JPEGs, and the shared timeline that releases them.

Timing model. Each camera's device clock maps to the host clock as ``host = a + b * device``
(``b`` carries the recorded drift, e.g. 1 + 40e-6). The mapping comes from the camera's
``clock.csv`` round trips when present (least squares through the midpoints of the fastest
round trip in each stretch of time: slow ones bound the clock loosely),
otherwise from ``index.csv`` (least-squares slope of host arrival time against device time,
offset at the lower envelope, i.e. the fastest arrival). The replay runs on the recorded host
timeline shifted to now: a frame is released when the replayed host time reaches its capture
time ``a + b * device_time``, so cameras stay aligned with each other as they were recorded,
and each camera's ``/time`` answers ``(host_now - a) / b``: the same clock as X-Timestamp,
with the same drift. Looping shifts the whole timeline by one period; device clocks and frame
numbers keep counting up, as a node's do.
"""

from __future__ import annotations

import itertools
import logging
import re
import statistics
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from cubecam.errors import EmulatorError
from cubetrack.core.errors import RecordingError
from cubetrack.io.recording import Recording, check_camera_name

log = logging.getLogger(__name__)

IMAGES_FIRST_DEVICE_TIME_S = 1.0  # --images: the first frame's device time (the node booted 1 s before)
_MIN_SLOPE, _MAX_SLOPE = 0.5, 2.0  # a fitted clock rate outside this is a broken recording
_JPEG_SUFFIXES = (".jpg", ".jpeg")


@dataclass(frozen=True, slots=True)
class SourceFrame:
    """A frame to replay: X-Frame, X-Timestamp (device clock, s) and its JPEG file."""

    seq: int
    device_time_s: float
    path: Path


@dataclass(frozen=True, slots=True)
class ClockMap:
    """``host_s = offset_s + rate * device_s``; ``rate`` = host seconds per device second."""

    offset_s: float
    rate: float = 1.0

    def host(self, device_s: float) -> float:
        return self.offset_s + self.rate * device_s

    def device(self, host_s: float) -> float:
        return (host_s - self.offset_s) / self.rate


@dataclass(frozen=True, slots=True)
class CameraTrack:
    """One camera's replay material. ``frames`` are sorted by seq; ``frame_interval_s`` is the
    median spacing on the device clock (the configured rate the node reports)."""

    name: str
    frames: tuple[SourceFrame, ...]
    clock: ClockMap
    frame_interval_s: float


def jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's SOF segment, None when there is none."""
    i = 2
    n = len(data)
    if n < 4 or data[:2] != b"\xff\xd8":
        return None
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        length = int.from_bytes(data[i + 2:i + 4], "big")
        if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
            if i + 9 > n:
                return None
            h = int.from_bytes(data[i + 5:i + 7], "big")
            w = int.from_bytes(data[i + 7:i + 9], "big")
            return (w, h) if w and h else None
        if marker == 0xDA:
            return None
        i += 2 + length
    return None


def looks_like_jpeg(path: Path) -> bool:
    """Cheap check of a whole JPEG file: SOI at the start and EOI near the end."""
    try:
        with path.open("rb") as f:
            head = f.read(3)
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - 64))
            tail = f.read()
    except OSError:
        return False
    return size > 32 and head == b"\xff\xd8\xff" and b"\xff\xd9" in tail


def _median_interval(times: list[float]) -> float:
    steps = [b - a for a, b in itertools.pairwise(times) if b > a]
    return statistics.median(steps) if steps else 0.1


def _least_squares(x: list[float], y: list[float]) -> tuple[float, float] | None:
    """(intercept, slope) of y over x, None when x does not spread."""
    n = len(x)
    if n < 2:
        return None
    mx = sum(x) / n
    my = sum(y) / n
    sxx = sum((v - mx) ** 2 for v in x)
    if sxx < 1e-6:
        return None
    slope = sum((a - mx) * (b - my) for a, b in zip(x, y, strict=True)) / sxx
    return my - slope * mx, slope


def _envelope_points(device_s: list[float], host_s: list[float]) -> tuple[list[float], list[float]]:
    """The fastest arrival in each of up to 10 stretches of time: arrival delays only ever add,
    so these points follow the capture clock more closely than all points do."""
    pairs = sorted(zip(device_s, host_s, strict=True))
    chunks = min(10, len(pairs) // 5)
    if chunks < 3:
        return [d for d, _ in pairs], [h for _, h in pairs]
    size = len(pairs) / chunks
    picked = [min(pairs[int(i * size):int((i + 1) * size)], key=lambda p: p[1] - p[0]) for i in range(chunks)]
    return [d for d, _ in picked], [h for _, h in picked]


def fit_clock(device_s: list[float], host_s: list[float], lower_envelope: bool, where: str) -> ClockMap:
    """The device->host mapping through (device, host) pairs; see the module docstring.
    ``lower_envelope``: the pairs are arrival times (delays only add), so fit their fastest
    arrivals and put the offset at the fastest one; else a plain least-squares fit."""
    fx, fy = _envelope_points(device_s, host_s) if lower_envelope else (device_s, host_s)
    fit = _least_squares(fx, fy)
    rate = fit[1] if fit is not None else 1.0
    if not _MIN_SLOPE <= rate <= _MAX_SLOPE:
        log.warning("%s: fitted clock rate %.6f is implausible; replaying without drift", where, rate)
        rate = 1.0
    residuals = [h - rate * d for d, h in zip(device_s, host_s, strict=True)]
    offset = min(residuals) if lower_envelope else sum(residuals) / len(residuals)
    return ClockMap(offset, rate)


def fastest_round_trips(samples: list) -> list:
    """The round trips that bound the clock best: the fastest one in each of up to 10 stretches
    of time (at least two). A slow round trip's midpoint can sit tens of ms from the moment the
    node read its clock; a line through all midpoints would carry that into the offset and the
    drift, and so into the replayed timing of every frame."""
    pairs = sorted(samples, key=lambda s: s.device_time_s)
    chunks = min(10, len(pairs) // 3)
    if chunks < 2:
        return sorted(pairs, key=lambda s: s.host_recv_s - s.host_send_s)[:max(2, len(pairs) // 2)]
    size = len(pairs) / chunks
    return [min(pairs[int(i * size):int((i + 1) * size)], key=lambda s: s.host_recv_s - s.host_send_s)
            for i in range(chunks)]


def load_recording(path: str | Path) -> tuple[list[CameraTrack], Counter[str]]:
    """Every camera of a recording, and what was skipped (reason -> count): broken index rows,
    missing or corrupt JPEG files, duplicate frame numbers."""
    try:
        rec = Recording.open(path)
    except RecordingError as exc:
        raise EmulatorError(str(exc)) from None
    skipped: Counter[str] = Counter()
    tracks = []
    for name in rec.camera_names:
        try:
            rows = rec.index(name)
        except RecordingError as exc:
            raise EmulatorError(str(exc)) from None
        folder = rec.camera_dir(name)
        by_seq: dict[int, SourceFrame] = {}
        host_of: dict[int, float] = {}
        for row in sorted(rows, key=lambda r: (r.seq, r.host_time_s)):
            file = folder / row.file
            if not file.exists():
                skipped["missing frame file"] += 1
                log.warning("%s: frame file %s is missing; skipped", folder, row.file)
                continue
            if not looks_like_jpeg(file):
                skipped["corrupt frame file"] += 1
                log.warning("%s: frame file %s is not a whole JPEG; skipped", folder, row.file)
                continue
            if row.seq in by_seq:
                skipped["duplicate frame number"] += 1
                continue
            by_seq[row.seq] = SourceFrame(row.seq, row.device_time_s, file)
            host_of[row.seq] = row.host_time_s
        frames = tuple(by_seq.values())
        if not frames:
            raise EmulatorError(f"{folder}: no readable frame (all {len(rows)} listed frames are missing or corrupt)")
        try:
            samples = rec.clock_samples(name)
        except RecordingError as exc:
            raise EmulatorError(str(exc)) from None
        device = [f.device_time_s for f in frames]
        if len(samples) >= 2:
            fast = fastest_round_trips(samples)
            clock = fit_clock([s.device_time_s for s in fast],
                              [(s.host_send_s + s.host_recv_s) / 2 for s in fast], False, f"{folder}/clock.csv")
        else:
            clock = fit_clock(device, [host_of[f.seq] for f in frames], True, f"{folder}/index.csv")
        tracks.append(CameraTrack(name, frames, clock, _median_interval(device)))
    skipped.update(rec.skipped)
    return tracks, skipped


def load_images(folder: str | Path, fps: float, name: str | None = None) -> tuple[list[CameraTrack], Counter[str]]:
    """A folder of JPEGs (sorted by name) as one camera at ``fps``; corrupt files are skipped."""
    folder = Path(folder)
    if not folder.is_dir():
        raise EmulatorError(f"{folder}: image folder not found")
    if not fps > 0:
        raise EmulatorError(f"--fps must be a positive number of frames per second, got {fps}")
    if name is None:
        name = re.sub(r"[^A-Za-z0-9_.-]", "_", folder.resolve().name) or "cam1"
        if not re.match(r"[A-Za-z0-9_]", name):
            name = "cam_" + name
    try:
        check_camera_name(name)
    except RecordingError as exc:
        raise EmulatorError(str(exc)) from None
    skipped: Counter[str] = Counter()
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in _JPEG_SUFFIXES and p.is_file())
    frames: list[SourceFrame] = []
    for path in files:
        if not looks_like_jpeg(path):
            skipped["corrupt frame file"] += 1
            log.warning("%s: not a whole JPEG; skipped", path)
            continue
        i = len(frames)
        frames.append(SourceFrame(i + 1, IMAGES_FIRST_DEVICE_TIME_S + i / fps, path))
    if not frames:
        raise EmulatorError(f"{folder}: no readable .jpg/.jpeg file ({len(files)} found)")
    return [CameraTrack(name, tuple(frames), ClockMap(0.0, 1.0), 1.0 / fps)], skipped


@dataclass(frozen=True, slots=True)
class Release:
    """One frame of the replay: which camera, when (seconds after the replay's start), what."""

    camera: int
    at_s: float
    seq: int
    device_time_s: float
    path: Path


class Timeline:
    """The replay schedule of all cameras on one host timeline starting at 0."""

    def __init__(self, tracks: list[CameraTrack], loop: bool):
        if not tracks:
            raise EmulatorError("nothing to replay")
        self.tracks = tracks
        self.loop = loop
        self.start_host_s = min(t.clock.host(t.frames[0].device_time_s) for t in tracks)
        end = max(t.clock.host(t.frames[-1].device_time_s) for t in tracks)
        step = max(t.clock.rate * t.frame_interval_s for t in tracks)
        self.period_s = end - self.start_host_s + step

    def device_time(self, camera: int, elapsed_s: float) -> float:
        """Camera's device clock when the replay has run ``elapsed_s`` (never below 0)."""
        return max(0.0, self.tracks[camera].clock.device(self.start_host_s + elapsed_s))

    def releases(self, camera: int) -> Iterator[Release]:
        """Frames of one camera in release order (endless when looping)."""
        track = self.tracks[camera]
        seq_span = track.frames[-1].seq - track.frames[0].seq + 1
        k = 0
        while True:
            shift_s = k * self.period_s
            for f in track.frames:
                at = track.clock.host(f.device_time_s) - self.start_host_s + shift_s
                yield Release(camera, at, f.seq + k * seq_span, f.device_time_s + shift_s / track.clock.rate, f.path)
            if not self.loop:
                return
            k += 1
