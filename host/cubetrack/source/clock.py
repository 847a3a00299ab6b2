"""Camera clock -> host clock (contracts §1 "Clock sync", §3 ``clock.csv``).

A camera node stamps each frame with X-Timestamp, its own clock since boot. The host polls
``/time`` about once a second and keeps (host_send, device_time, host_recv) round trips. The
device time was read somewhere inside [host_send, host_recv], so with the round trip's midpoint
the offset is known to within half the round trip — independent of how long frames take to
arrive. A line host = device + offset + drift * (device - device_ref) is fitted to the fastest
recent round trips, which follows tens of ppm of drift. The drift has a zero-mean prior
(``drift_prior_ppm``): a crystal's rate error is tens of ppm, while two round trips a second apart,
their midpoints each a few milliseconds off, would draw a line thousands of ppm off that runs away
until a faster trip comes (docs/tracking.md, "Session 30"); the prior keeps the line level until the
round trips span enough time to show a drift.

:class:`ClockSync` is causal: it only uses round trips it has been given so far, so a recording
replayed through it stamps frames exactly as the live tracker did. Without round trips it falls
back to frame arrival times (the lower envelope of arrival - device time, i.e. the fastest
transfers), which is biased late by the minimum transfer time; ``method`` says which is in use.
"""

from __future__ import annotations

import enum
import logging
from collections import deque
from dataclasses import dataclass

import numpy as np

from cubetrack.core.params import check, param

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class ClockSyncParams:
    """How a camera's clock is mapped to the host clock."""

    window: int = param(120, "number of most recent round trips (or arrivals) used for the fit")
    fastest_fraction: float = param(0.3, "fraction of the window's fastest round trips the line is fitted to (0..1]")
    max_round_trip_s: float = param(0.05, "round trips slower than this are ignored (they bound the offset too "
                                          "loosely), seconds")
    min_samples: int = param(1, "round trips needed before they are trusted over arrival times (one fast round trip "
                                "already beats arrival times)")
    trusted_width_s: float = param(0.02, "a round trip at most this wide is trusted alone; wider ones only once "
                                         "start_round_trips have come, and only while no narrow one is in the window "
                                         "(a lone trip's midpoint can be half its width off), seconds")
    start_round_trips: int = param(3, "round trips after which they are trusted however wide (a network whose round "
                                      "trips are all slow still gets a clock)")
    drift_prior_ppm: float = param(100.0, "standard deviation of the zero-mean prior on the clock's rate error, parts "
                                          "per million (crystals: tens of ppm); a round trip's midpoint counts as "
                                          "uncertain by its width / sqrt(12), so narrow trips over a long span "
                                          "overrule it; 0: no prior (the drift fitted from the round trips alone; "
                                          "before session 30)")

    def __post_init__(self) -> None:
        check(self.window >= 2 and self.min_samples >= 1 and 0.0 < self.fastest_fraction <= 1.0,
              "need window >= 2, min_samples >= 1 and 0 < fastest_fraction <= 1")
        check(self.trusted_width_s >= 0 and self.start_round_trips >= 1,
              "need trusted_width_s >= 0 and start_round_trips >= 1")
        check(self.max_round_trip_s > 0, "max_round_trip_s must be positive")
        check(self.drift_prior_ppm >= 0, "drift_prior_ppm must not be negative")


@enum.unique
class ClockFitMethod(enum.Enum):
    """What a clock fit rests on: ``/time`` round trips, frame arrival times, or nothing yet."""

    ROUND_TRIP = "round-trip"
    ARRIVAL = "arrival"
    NONE = "none"


@dataclass(frozen=True, slots=True)
class ClockFit:
    """host_time_s = device_time_s + offset_s + drift * (device_time_s - device_ref_s)."""

    offset_s: float
    drift: float
    device_ref_s: float
    method: ClockFitMethod
    uncertainty_s: float

    def to_host(self, device_time_s: float) -> float:
        return device_time_s + self.offset_s + self.drift * (device_time_s - self.device_ref_s)


def fit_line(device_s: np.ndarray, offset_s: np.ndarray, ridge_s2: float = 0.0) -> tuple[float, float, float]:
    """Least-squares offset = a + b (device - ref); returns (a, b, ref). One point: b = 0.
    ``ridge_s2`` (s²) is added to the slope's normal equation: a zero-mean prior on ``b`` with
    variance (the points' variance) / ``ridge_s2``."""
    ref = float(np.mean(device_s))
    x = device_s - ref
    a = float(np.mean(offset_s))  # x is centred: the intercept is the mean offset
    if len(x) < 2 or np.ptp(x) < 1e-6:
        return a, 0.0, ref
    return a, float(np.dot(x, offset_s - a) / (np.dot(x, x) + ridge_s2)), ref


def fit_round_trips(host_send_s: np.ndarray, device_s: np.ndarray, host_recv_s: np.ndarray,
                    fastest_fraction: float = 0.3, drift_prior_ppm: float = 0.0) -> ClockFit:
    """Fit the clock line to the fastest round trips (their midpoints), robust to slow ones.
    ``drift_prior_ppm`` > 0: the drift has a zero-mean prior of that standard deviation, each
    midpoint counting as uncertain by its trip's width / sqrt(12) (the node read its clock somewhere
    inside the trip), so the drift stays near 0 until the trips span enough time to show one."""
    host_send_s, device_s, host_recv_s = (np.asarray(a, dtype=float) for a in (host_send_s, device_s, host_recv_s))
    rtt = host_recv_s - host_send_s
    ok = np.isfinite(rtt) & (rtt >= 0)
    host_send_s, device_s, host_recv_s, rtt = host_send_s[ok], device_s[ok], host_recv_s[ok], rtt[ok]
    if rtt.size == 0:
        raise ValueError("no valid round trips (host_recv must not precede host_send)")
    keep = max(min(2, rtt.size), int(np.ceil(fastest_fraction * rtt.size)))  # two points give the drift
    order = np.argsort(rtt, kind="stable")[:keep]
    mid = (host_send_s[order] + host_recv_s[order]) / 2.0
    ridge_s2 = float(np.mean(rtt[order] ** 2)) / 12.0 / (drift_prior_ppm * 1e-6) ** 2 if drift_prior_ppm > 0 else 0.0
    a, b, ref = fit_line(device_s[order], mid - device_s[order], ridge_s2)
    return ClockFit(a, b, ref, ClockFitMethod.ROUND_TRIP, float(np.max(rtt[order]) / 2.0))


def fit_arrivals(device_s: np.ndarray, arrival_s: np.ndarray) -> ClockFit:
    """Fallback without round trips: the line under the (device, arrival - device) points,
    i.e. assuming the fastest frames arrived with no delay. Biased late by the minimum latency."""
    device_s, arrival_s = np.asarray(device_s, dtype=float), np.asarray(arrival_s, dtype=float)
    delay = arrival_s - device_s
    a, b, ref = fit_line(device_s, delay)
    residual = delay - (a + b * (device_s - ref))
    lowest = float(residual.min())
    a += lowest  # lower envelope: shift the line down to the fastest frame
    return ClockFit(a, b, ref, ClockFitMethod.ARRIVAL, float(np.median(residual)) - lowest)


class ClockSync:
    """Causal device->host mapping for one camera; feed round trips and frames as they arrive."""

    def __init__(self, params: ClockSyncParams = ClockSyncParams()):
        self.params = params
        self._trips: deque[tuple[float, float, float]] = deque(maxlen=params.window)
        self._arrivals: deque[tuple[float, float]] = deque(maxlen=params.window)
        self._fit: ClockFit | None = None

    @property
    def method(self) -> ClockFitMethod:
        return self.fit().method

    def add_round_trip(self, host_send_s: float, device_time_s: float, host_recv_s: float) -> None:
        if 0.0 <= host_recv_s - host_send_s <= self.params.max_round_trip_s:
            self._trips.append((host_send_s, device_time_s, host_recv_s))
            self._fit = None

    def add_arrival(self, device_time_s: float, arrival_s: float) -> None:
        self._arrivals.append((device_time_s, arrival_s))
        if not self._trusted():
            self._fit = None

    def _trusted(self) -> bool:
        """Whether the round trips are trusted over arrival times: ``min_samples`` of them, and one
        at most ``trusted_width_s`` wide or ``start_round_trips`` in all (docs/history/accuracy.md, "The
        camera clocks' first seconds": a lone 35 ms trip stamped a camera's first second 15.7 ms late)."""
        p, trips = self.params, self._trips
        if len(trips) < p.min_samples:
            return False
        return len(trips) >= p.start_round_trips or any(recv - send <= p.trusted_width_s for send, _, recv in trips)

    def fit(self) -> ClockFit:
        if self._fit is None:
            if self._trusted():
                narrow = [t for t in self._trips if t[2] - t[0] <= self.params.trusted_width_s]
                s, d, r = (np.array(v) for v in zip(*(narrow or self._trips), strict=True))
                self._fit = fit_round_trips(s, d, r, self.params.fastest_fraction, self.params.drift_prior_ppm)
            elif self._arrivals:  # refitted per frame until a round trip comes: one array, few numpy calls
                arrivals = np.array(self._arrivals)
                self._fit = fit_arrivals(arrivals[:, 0], arrivals[:, 1])
            else:
                self._fit = ClockFit(0.0, 0.0, 0.0, ClockFitMethod.NONE, float("inf"))
        return self._fit

    def to_host(self, device_time_s: float) -> float:
        """Host time (Unix seconds) of a device timestamp with what is known now."""
        return self.fit().to_host(device_time_s)
