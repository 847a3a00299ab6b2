"""The timing model of a simulated camera node: its clock, when it captures, which frames reach
the host and when, and the ``/time`` round trips the host records (contracts §1 and §3).

Clocks. The host clock is Unix time. Each node's clock counts seconds since the node booted and
runs at its own rate: ``device = (host - boot_host_s) * (1 + drift_ppm * 1e-6)``.

Capture. A node captures on its own clock at ``n / fps + phase`` (plus a small random jitter);
``n`` is the frame counter since boot, so ``seq`` (X-Frame) counts every captured frame.
The stamp (X-Timestamp) is the device time at mid-exposure, the instant the ground truth is
taken at.

Transfer. One frame is on the air at a time. A frame takes ``latency`` (minimum + exponential
jitter, sometimes a spike) from capture to complete arrival. A frame captured while the link is
busy waits; only the newest waiting frame is sent (the node always sends its newest frame), so a
slow transfer skips frames. Independently, a frame is lost with ``drop_rate``. Dropped frames
leave gaps in ``seq``; arrivals are in capture order.

Clock sync. About once a second the host sends ``/time`` at ``host_send``; the request takes an
``up`` delay, the node reads its clock, the answer takes a ``down`` delay: ``host_recv = host_send
+ up + down``. Up and down are asymmetric (30 % / 70 % of the mean round trip, exponential
tails) and sometimes one leg is slow. So the node's time maps to a host time inside
``[host_send, host_recv]``, never exactly the midpoint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cubetrack.core.cameras import ClockSample
from cubetrack.simulate.params import SimulationParams


@dataclass(frozen=True, slots=True)
class DeviceClock:
    """A node's clock: it read 0 at host time ``boot_host_s`` and gains ``drift_ppm`` per million."""

    boot_host_s: float
    drift_ppm: float

    @property
    def rate(self) -> float:
        """Device seconds per host second."""
        return 1.0 + self.drift_ppm * 1e-6

    def device_time_s(self, host_time_s: float | np.ndarray) -> float | np.ndarray:
        """The node's clock at a host (Unix) time, seconds."""
        return (host_time_s - self.boot_host_s) * self.rate

    def host_time_s(self, device_time_s: float | np.ndarray) -> float | np.ndarray:
        """The host (Unix) time at which the node's clock read ``device_time_s``, seconds."""
        return self.boot_host_s + device_time_s / self.rate


@dataclass(frozen=True, slots=True)
class CaptureTruth:
    """One captured frame: its X-Frame, capture instant on both clocks, and arrival on the host
    (``None`` when the frame never arrived: lost, skipped, or after the end of the recording)."""

    seq: int
    capture_host_s: float
    device_time_s: float
    arrival_host_s: float | None

    @property
    def delivered(self) -> bool:
        return self.arrival_host_s is not None


def make_clock(params: SimulationParams, rng: np.random.Generator) -> DeviceClock:
    """A node booted 60 s .. ``uptime_max_s`` before the recording, with a random rate error."""
    uptime = rng.uniform(60.0, params.uptime_max_s)
    drift = rng.normal(0.0, params.drift_ppm) if params.drift_ppm > 0 else 0.0
    return DeviceClock(boot_host_s=params.start_unix_s - uptime, drift_ppm=float(drift))


def _transfer_s(params: SimulationParams, rng: np.random.Generator) -> float:
    latency = params.latency_ms
    if params.latency_jitter_ms > 0:
        latency += rng.exponential(params.latency_jitter_ms)
    if params.spike_rate > 0 and rng.random() < params.spike_rate:
        latency += rng.exponential(params.spike_ms) if params.spike_ms > 0 else 0.0
    return latency * 1e-3


def plan_captures(
    params: SimulationParams,
    clock: DeviceClock,
    phase_s: float,
    rng: np.random.Generator,
    start_host_s: float,
    end_host_s: float,
    max_delivered: int | None = None,
) -> tuple[CaptureTruth, ...]:
    """Every frame a node captures between two host times, with arrival times (or None).

    ``phase_s`` is where the node's capture grid sits on its own clock. With ``max_delivered``
    the plan stops after that many frames have arrived (captures after it are not listed).
    """
    period = 1.0 / params.fps
    d_start = clock.device_time_s(start_host_s)
    d_end = clock.device_time_s(end_host_s)
    n0 = math.ceil((d_start - phase_s) / period + 1e-9)
    n1 = math.floor((d_end - phase_s) / period)
    captures: list[list] = []  # [seq, capture_host, device_time, arrival]
    jitter_cap = 0.25 * period
    for n in range(n0, n1 + 1):
        jitter = rng.normal(0.0, params.capture_jitter_s) if params.capture_jitter_s > 0 else 0.0
        d = n * period + phase_s + float(np.clip(jitter, -jitter_cap, jitter_cap))
        captures.append([n, float(clock.host_time_s(d)), d, None])

    link_free = -math.inf
    pending: list | None = None

    def send(frame: list, at: float) -> float:
        frame[3] = at + _transfer_s(params, rng)
        return frame[3]

    for frame in captures:
        capture = frame[1]
        if pending is not None and link_free <= capture:
            link_free = send(pending, max(link_free, pending[1]))
            pending = None
        if params.drop_rate > 0 and rng.random() < params.drop_rate:
            continue  # lost: never sent
        if link_free <= capture:
            link_free = send(frame, capture)
        else:
            pending = frame  # a waiting older frame, if any, is superseded (skipped)
    if pending is not None:
        send(pending, max(link_free, pending[1]))

    out = []
    count = 0
    for seq, capture, d, arrival in captures:
        if max_delivered is not None and count >= max_delivered:
            break
        if arrival is not None and arrival > end_host_s:
            arrival = None
        count += arrival is not None
        out.append(CaptureTruth(int(seq), capture, d, arrival))
    return tuple(out)


def plan_clock_samples(
    params: SimulationParams,
    clock: DeviceClock,
    rng: np.random.Generator,
    start_host_s: float,
    end_host_s: float,
) -> tuple[ClockSample, ...]:
    """``/time`` round trips about every ``clock_period_s`` between two host times."""
    samples = []
    t = start_host_s + rng.uniform(0.0, params.clock_period_s)
    rtt = params.rtt_ms * 1e-3
    while True:
        up = 0.3 * rtt * (0.5 + 0.5 * rng.exponential(1.0))
        down = 0.7 * rtt * (0.5 + 0.5 * rng.exponential(1.0))
        if params.slow_rtt_rate > 0 and rng.random() < params.slow_rtt_rate:
            extra = rng.exponential(params.slow_rtt_ms * 1e-3) if params.slow_rtt_ms > 0 else 0.0
            if rng.random() < 0.5:
                up += extra
            else:
                down += extra
        if t + up + down > end_host_s:
            break
        samples.append(ClockSample(t, float(clock.device_time_s(t + up)), t + up + down))
        t += params.clock_period_s * rng.uniform(0.95, 1.05)
    return tuple(samples)
