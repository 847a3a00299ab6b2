"""A live session's view of its cameras, from the source's counters: the periodic status line
(:class:`LiveStatus`, rates over the last interval by :class:`StatusRates`) and each camera's
:class:`~cubetrack.core.records.CameraHealth` for the outputs (:class:`HealthMeter`). The loops of
:mod:`cubetrack.app.live` take these every ``status_every_s`` and ``HEALTH_EVERY_S``."""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from cubetrack.core.records import CameraHealth, Frame, TrackedPose
from cubetrack.source.clock import ClockFitMethod, ClockSync
from cubetrack.source.streams import CameraStats


@dataclass(frozen=True, slots=True)
class LiveStatus:
    """A periodic snapshot of a live session (rates over the last interval)."""

    elapsed_s: float
    frames_per_s: dict[str, float]
    poses_per_s: dict[str, float]
    latency_s: float | None  # median pose latency over the interval (capture -> pose output)
    cameras: dict[str, CameraStats]
    queued: int
    arrival_latency_s: float | None = None  # median over the interval of frame arrival -> pose output

    def line(self) -> str:
        """One status line, e.g. ``12s robot 7.4 poses/s | cam1 7.5 fps ... | latency 4/51 ms | ...``
        (arrival -> pose / capture -> pose, medians)."""
        parts = [f"{self.elapsed_s:5.0f}s"]
        if self.poses_per_s:
            parts.append(" ".join(f"{r} {v:.1f} poses/s" for r, v in self.poses_per_s.items()))
        parts.append(" ".join(f"{c} {v:.1f} fps" for c, v in self.frames_per_s.items()))
        if self.poses_per_s:
            parts.append(f"latency {_ms(self.arrival_latency_s)}/{_ms(self.latency_s)} ms")
        bad = sum(s.bad for s in self.cameras.values())
        reconnects = sum(s.reconnects for s in self.cameras.values())
        dropped = sum(s.dropped for s in self.cameras.values())
        clock = "/".join(str(s.clock_samples) for s in self.cameras.values())
        down = [c for c, s in self.cameras.items() if not s.connected]
        tail = f"bad {bad} reconnects {reconnects} dropped {dropped} clock {clock}"
        if down:
            tail += " down: " + ",".join(down)
        unclocked = [c for c, s in self.cameras.items() if s.timing.startswith("no clock")]
        if unclocked:
            tail += " no clock: " + ",".join(unclocked)
        parts.append(tail)
        return " | ".join(parts)


def _ms(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds * 1000:.0f}"


class StatusRates:
    """Turns counters into per-interval rates for :class:`LiveStatus`."""

    def __init__(self, cameras: Sequence[str], robots: list[str]):
        self.robots = robots
        self.start = time.monotonic()
        self.last = self.start
        self.frames = {c: 0 for c in cameras}
        self.poses = {r: 0 for r in robots}
        self.latencies: list[float] = []
        self.arrival_latencies: list[float] = []

    def add_poses(self, poses: list[TrackedPose]) -> None:
        for pose in poses:
            if not pose.predicted:
                self.latencies.append(pose.latency_s)
            if pose.arrival_latency_s is not None:
                self.arrival_latencies.append(pose.arrival_latency_s)

    def snapshot(self, cams: dict[str, CameraStats], queued: int, poses_total: dict[str, int]) -> LiveStatus:
        """The rates since the last snapshot, from the source's counters ``cams`` and the session's
        poses so far; ``queued``: frames waiting in the source."""
        now = time.monotonic()
        dt = max(1e-6, now - self.last)
        fps = {c: (s.frames - self.frames[c]) / dt for c, s in cams.items()}
        pps = {r: (poses_total.get(r, 0) - self.poses[r]) / dt for r in self.robots}
        status = LiveStatus(now - self.start, fps, pps, _median(self.latencies), cams, queued,
                            _median(self.arrival_latencies))
        self.frames = {c: s.frames for c, s in cams.items()}
        self.poses = {r: poses_total.get(r, 0) for r in self.robots}
        self.latencies, self.arrival_latencies = [], []
        self.last = now
        return status


def _median(values: list[float]) -> float | None:
    return statistics.median(values) if values else None


HEALTH_EVERY_S = 1.0  # camera health snapshots for the outputs, per camera


class HealthMeter:
    """Each camera's :class:`CameraHealth` for the outputs (the dashboard, Foxglove, Zenoh),
    taken every ``HEALTH_EVERY_S``: the source's counters, frames/s and mean JPEG size over the
    interval, the median transfer latency (arrival - capture) of the frames processed in it, and
    the camera's clock fit (offset and drift, NaN until a ``/time`` round trip is known)."""

    def __init__(self, cameras: Sequence[str], clocks: dict[str, ClockSync], clock: Callable[[], float]):
        self.clocks, self.clock = clocks, clock
        self.last = time.monotonic()
        self.counts = {c: (0, 0) for c in cameras}  # frames, bytes at the last snapshot
        self.jpeg_bytes = {c: 0 for c in cameras}
        self.transfer: dict[str, list[float]] = {c: [] for c in cameras}

    def frame(self, frame: Frame, capture_time_s: float) -> None:
        self.transfer[frame.camera].append(frame.host_time_s - capture_time_s)

    def snapshots(self, cams: dict[str, CameraStats]) -> list[CameraHealth]:
        """Every camera's health from the source's counters ``cams``."""
        now = time.monotonic()
        dt, self.last = max(1e-6, now - self.last), now
        out = []
        for name, s in cams.items():
            frames, size = self.counts[name]
            if s.frames > frames:
                self.jpeg_bytes[name] = (s.bytes - size) // (s.frames - frames)
            self.counts[name] = (s.frames, s.bytes)
            fit = self.clocks[name].fit() if name in self.clocks else None
            synced = fit if fit is not None and fit.method is ClockFitMethod.ROUND_TRIP else None
            transfer = _median(self.transfer[name])
            self.transfer[name] = []
            out.append(CameraHealth(name, self.clock(), s.connected, (s.frames - frames) / dt, s.frames, s.dropped,
                                    s.bad, s.reconnects, synced.offset_s if synced else math.nan,
                                    synced.drift * 1e6 if synced else math.nan,
                                    math.nan if transfer is None else transfer, self.jpeg_bytes[name], s.last_error,
                                    s.timing))
        return out
