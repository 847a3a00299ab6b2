"""How a live camera's frames are placed in time, and what the camera lacks for it (docs/live.md,
"Time for cameras without a clock").

Every camera hands the tracker frames stamped on some device clock plus
:class:`~cubetrack.core.cameras.ClockSample` round trips relating that clock to the host's, so
one :class:`~cubetrack.source.clock.ClockSync` per camera maps every frame to its capture time,
live and in a replay alike:

- a cubetrack node: ``X-Timestamp`` on its own clock, real ``/time`` round trips
  (:attr:`CameraTiming.NODE`);
- a local capture device with driver timestamps (V4L2 buffer stamps on the host's monotonic
  clock): round trips between the monotonic and the Unix clock of this host, microseconds wide
  (:attr:`CameraTiming.DRIVER`);
- a camera without a clock (a plain MJPEG device, RTSP, a capture device without stamps): the
  frame's arrival time, de-jittered (:class:`ArrivalEnvelope`: the lower envelope of the arrivals
  against the frame count, as a camera capturing at a steady rate whose frames only ever arrive
  late puts them), with *declared* samples (:func:`declared_sample`) that put the capture an
  assumed latency before that (:attr:`CameraTiming.ARRIVAL`), the ``[source]
  arrival_latency_s`` constant until the fusion estimates it from the clocked cameras.
"""

from __future__ import annotations

import enum
import itertools
import math
import time
from collections import deque
from collections.abc import Callable, Sequence

from cubetrack.core.cameras import ClockSample


@enum.unique
class CameraTiming(enum.Enum):
    """Where a camera's frame times come from."""

    UNKNOWN = "unknown"  # an HTTP camera whose /time and stream have not told yet
    NODE = "node"
    DRIVER = "driver"
    ARRIVAL = "arrival"
    MEDIA = "media"  # a video file played at its media times (tests, benchmarks)


def timing_note(timing: CameraTiming, latency_s: float = 0.0) -> str:
    """One line on how the camera's frames are timed and what it lacks, for the health and status."""
    if timing is CameraTiming.NODE:
        return "clock synced by /time round trips"
    if timing is CameraTiming.DRIVER:
        return "driver timestamps on this host's clock"
    if timing is CameraTiming.ARRIVAL:
        return f"no clock: stamped on arrival, latency ~{latency_s * 1000:.0f} ms assumed"
    if timing is CameraTiming.MEDIA:
        return "video file played at its media times (a stand-in for a camera)"
    return "timing not known yet (waiting for /time or the first frame)"


def declared_sample(host_s: float, latency_s: float) -> ClockSample:
    """A round trip of zero width declaring device clock = host clock + ``latency_s``: a frame
    stamped with its arrival time ``a`` on the device clock maps to capture time ``a - latency_s``."""
    return ClockSample(host_s, host_s + latency_s, host_s)


def monotonic_sample(latency_s: float = 0.0, unix: Callable[[], float] = time.time,
                     monotonic: Callable[[], float] = time.monotonic) -> ClockSample:
    """A real round trip between this host's Unix clock (``unix``) and its monotonic clock (the
    device clock of a local capture device), ``latency_s`` declared on top as in
    :func:`declared_sample`."""
    send_s = unix()
    device_s = monotonic()
    return ClockSample(send_s, device_s + latency_s, unix())


# --- de-jittered arrival stamps ----------------------------------------------------------------

ENVELOPE_WARMUP = 8  # frames after a (re)start counted one capture period apart, before indices are inferred
ENVELOPE_TOLERANCE = 0.25  # periods: a frame this far above the envelope is late, this far below breaks it
ENVELOPE_MISFIT_LIMIT = 8  # a score of early (or late) frames, +2 each and -1 per frame that fits: start again
ENVELOPE_MAX_GAP = 100  # periods without a frame after which the envelope is learnt again


class ArrivalEnvelope:
    """Capture times of a camera without a clock, from its arrival times (docs/live.md, "Time for
    cameras without a clock"). A camera streaming at a steady rate takes frame k at
    ``t0 + k * T`` (its sensor is clocked by a crystal); over MJPEG on TCP a frame arrives after
    it was taken, in order, and every queue on the way (encoding, the device's send buffer,
    Wi-Fi retries, TCP retransmission, this host's scheduling) only adds delay. So the arrivals
    lie on or above the line ``t0 + k * T`` and the line is their lower envelope: fitted as the
    linear-programming bound of Moon, Skelly and Towsley ("Estimation and removal of clock skew
    from network delay measurements", INFOCOM 1999: the line under every point that is highest at
    their mean, an edge of their lower convex hull) over the last ``window`` frames.

    :meth:`stamp` takes each frame's arrival (and the camera's own frame number where it sends
    one) and gives the frame's time on the envelope, never after its arrival. The frame count k is
    the camera's number, else inferred from the envelope: the largest k whose envelope time is not
    after the arrival (with ``ENVELOPE_TOLERANCE`` periods of slack), counted from the last frame's
    so that an error in the period does not add up, and a gap of n periods is n - 1 frames
    dropped. It starts again (:meth:`reset`, counted in ``restarts``) when the caller says
    the stream restarted, and by itself when the arrivals stop fitting: frames arriving before their
    envelope time, or later than the tolerance, again and again (``ENVELOPE_MISFIT_LIMIT``: the
    rate rose, or fell to a rate that is no whole fraction of the old one, or the delay grew for
    good), a gap of ``ENVELOPE_MAX_GAP`` periods, arrivals or numbers going backwards. The first
    ``ENVELOPE_WARMUP`` frames after a start are taken as consecutive (a drop among them makes the
    next frames misfit, and the envelope starts again). A frame that arrives before
    its envelope time once (it came in one read with a delayed one before it) is stamped on
    arrival. A camera that halves its rate (a webcam in dim light) still fits: every other frame
    counts as dropped."""

    def __init__(self, window: int = 64):
        if window < ENVELOPE_WARMUP:
            raise ValueError(f"window must be at least {ENVELOPE_WARMUP} frames")
        self.window = window
        self.restarts = 0
        self._points: deque[tuple[int, float]] = deque(maxlen=window)
        self._seq: int | None = None
        self._line: tuple[float, float] | None = None  # (t0, T): time of frame k = t0 + k * T
        self._late = 0
        self._early = 0

    def reset(self) -> None:
        """Learn the envelope again from the next frame (the stream restarted)."""
        if self._points:
            self.restarts += 1
        self._points.clear()
        self._seq = None
        self._line = None
        self._late = self._early = 0

    @property
    def period_s(self) -> float | None:
        """The capture period the envelope has found (None before two frames)."""
        return None if self._line is None else self._line[1]

    def stamp(self, arrival_s: float, seq: int | None = None) -> float:
        """The time of the frame that arrived at ``arrival_s`` (the camera's number ``seq`` where
        it sends one) on the envelope, on the arrivals' clock: its capture time plus the smallest
        delay (the caller's declared latency stands for that)."""
        k = self._index(arrival_s, seq)
        if k is None:
            self.reset()
            k = 0
        elif k < 0:  # before its envelope time: stamped on arrival, not part of the envelope
            return arrival_s
        self._points.append((k, arrival_s))
        self._seq = seq
        self._line = lower_envelope(self._points)
        if self._line is None:
            return arrival_s
        return min(arrival_s, self._line[0] + self._line[1] * k)

    def _index(self, arrival_s: float, seq: int | None) -> int | None:
        """The frame's count k; -1: it arrived before its envelope time (stamp it on arrival);
        None: the arrivals no longer fit the envelope (start again)."""
        if not self._points:
            return 0
        last_k, last_s = self._points[-1]
        if arrival_s < last_s or (seq is None) != (self._seq is None):
            return None
        step = None if seq is None or self._seq is None else seq - self._seq
        if step is not None and not 0 < step <= ENVELOPE_MAX_GAP:
            return None
        line = self._line
        if line is None or len(self._points) < ENVELOPE_WARMUP:
            return last_k + (step or 1)
        t0, period = line
        if arrival_s - last_s > ENVELOPE_MAX_GAP * period:
            return None
        since = (arrival_s - (t0 + period * last_k)) / period  # periods since the last frame's envelope time
        k = last_k + (step if step is not None else math.floor(since + ENVELOPE_TOLERANCE))
        residual = since - (k - last_k)
        if k <= last_k or residual < -ENVELOPE_TOLERANCE:
            self._early += 2
            return None if self._early >= ENVELOPE_MISFIT_LIMIT else -1
        self._early = max(0, self._early - 1)
        self._late = max(0, self._late + (2 if residual > ENVELOPE_TOLERANCE else -1))
        return None if self._late >= ENVELOPE_MISFIT_LIMIT else k


def lower_envelope(points: Sequence[tuple[int, float]]) -> tuple[float, float] | None:
    """The line ``t = t0 + T k`` on or under every (k, t) point (k increasing) that is highest at
    their mean k: the edge of their lower convex hull spanning it (Moon, Skelly and Towsley's
    linear program). ``(t0, T)``, or None for fewer than two points or no rising edge."""
    hull: list[tuple[int, float]] = []
    for k, t in points:
        while len(hull) >= 2 and _cross(hull[-2], hull[-1], (k, t)) <= 0:
            hull.pop()
        hull.append((k, t))
    if len(hull) < 2:
        return None
    mean_k = sum(k for k, _ in points) / len(points)
    for (k0, t0), (k1, t1) in itertools.pairwise(hull):
        if k1 > mean_k or (k1, t1) == hull[-1]:
            period = (t1 - t0) / (k1 - k0)
            return (t0 - period * k0, period) if period > 0 else None
    return None


def _cross(o: tuple[int, float], a: tuple[int, float], b: tuple[int, float]) -> float:
    """z of (a - o) x (b - o): positive when o, a, b turn left (b above the line o-a)."""
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
