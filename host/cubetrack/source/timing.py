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
  frame's arrival time, with *declared* samples (:func:`declared_sample`) that put the capture an
  assumed latency before the arrival (:attr:`CameraTiming.ARRIVAL`), the ``[source]
  arrival_latency_s`` constant until the fusion estimates it from the clocked cameras.
"""

from __future__ import annotations

import enum
import time
from collections.abc import Callable

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
