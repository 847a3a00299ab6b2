import numpy as np
import pytest

from cubetrack.source.clock import ClockFitMethod, ClockSync, ClockSyncParams, fit_arrivals, fit_round_trips

BOOT = 1.7e9  # host Unix time at which the node's clock read 0
DRIFT = 40e-6  # node clock runs 40 ppm slow


def device_to_host(d):
    return BOOT + d * (1 + DRIFT)


def round_trips(rng, n=120, slow_every=7):
    """Samples every ~1 s: asymmetric random one-way delays, some very slow round trips."""
    d0 = 50.0 + np.arange(n) * 1.0
    true_host = device_to_host(d0)
    up = rng.uniform(0.002, 0.006, n)
    down = rng.uniform(0.002, 0.006, n)
    slow = np.arange(n) % slow_every == 0
    up[slow] += rng.uniform(0.05, 0.4, slow.sum())  # spikes on the way up only: asymmetric
    return true_host - up, d0, true_host + down


def test_round_trip_fit_recovers_offset_and_drift_under_jitter_and_spikes():
    rng = np.random.default_rng(3)
    send, dev, recv = round_trips(rng)
    fit = fit_round_trips(send, dev, recv)
    assert fit.method is ClockFitMethod.ROUND_TRIP
    for d in (50.0, 100.0, 169.0):
        assert abs(fit.to_host(d) - device_to_host(d)) < 0.003  # within half the fastest round trips
    assert fit.drift == pytest.approx(DRIFT, abs=2e-5)


def test_slow_round_trips_do_not_move_the_fit():
    """The fit rests on the fastest round trips: the same samples with the slow (asymmetric) ones
    left out give the same clock mapping within 1 ms, although those slow trips pull the plain
    midpoint mean more than 10 ms off (checked first: the scene is one where it matters)."""
    rng = np.random.default_rng(3)
    send, dev, recv = round_trips(rng)
    naive = np.mean((send + recv) / 2 - dev) - np.mean(device_to_host(dev) - dev)
    assert abs(naive) > 0.01  # the slow trips bias an all-sample midpoint this much here
    fast = np.arange(len(dev)) % 7 != 0  # round_trips' slow_every
    with_slow, without = fit_round_trips(send, dev, recv), fit_round_trips(send[fast], dev[fast], recv[fast])
    for d in (50.0, 100.0, 169.0):
        assert abs(with_slow.to_host(d) - without.to_host(d)) < 0.001
        assert abs(with_slow.to_host(d) - device_to_host(d)) < abs(naive) / 4


def test_drift_is_followed_over_an_hour():
    rng = np.random.default_rng(4)
    d0 = np.arange(0, 3600, 10.0)
    host = device_to_host(d0)
    fit = fit_round_trips(host - 0.003 - rng.uniform(0, 0.002, d0.size), d0, host + 0.003)
    assert abs(fit.to_host(3600.0) - device_to_host(3600.0)) < 0.003  # 144 ms of drift followed


def test_arrival_fallback_is_late_by_the_minimum_latency_only():
    rng = np.random.default_rng(5)
    dev = 10.0 + np.arange(300) / 7.5
    latency = 0.04 + rng.exponential(0.02, dev.size)
    fit = fit_arrivals(dev, device_to_host(dev) + latency)
    assert fit.method is ClockFitMethod.ARRIVAL
    err = fit.to_host(30.0) - device_to_host(30.0)
    assert 0.0 <= err < 0.05  # biased late by about the minimum latency (40 ms), not by the mean


def test_clock_sync_switches_from_arrivals_to_round_trips():
    sync = ClockSync(ClockSyncParams(min_samples=3))  # (default is 1)
    assert sync.method is ClockFitMethod.NONE
    sync.add_arrival(10.0, device_to_host(10.0) + 0.05)
    assert sync.method is ClockFitMethod.ARRIVAL
    assert sync.to_host(10.0) == pytest.approx(device_to_host(10.0) + 0.05)
    for d in (11.0, 12.0, 13.0):
        h = device_to_host(d)
        sync.add_round_trip(h - 0.002, d, h + 0.002)
    assert sync.method is ClockFitMethod.ROUND_TRIP
    assert sync.to_host(14.0) == pytest.approx(device_to_host(14.0), abs=1e-4)


def test_reversed_round_trip_is_ignored():
    sync = ClockSync()
    sync.add_round_trip(5.0, 1.0, 4.0)
    assert sync.method is ClockFitMethod.NONE


def test_a_lone_wide_round_trip_is_not_trusted_until_a_narrow_one_comes():
    """Realistic scene 717's cam1: a first round trip 35 ms wide whose answer's leg was slow (its
    midpoint 15.7 ms after the node's read), a second of 7 ms a second later. The first alone
    stamped the camera's first second 15.7 ms late; now the frames wait for the narrow trip, and
    once it is in the wide one does not pull the line (a line through both read -14,000 ppm)."""
    sync = ClockSync()
    h = device_to_host(100.0)
    sync.add_round_trip(h - 0.0018, 100.0, h + 0.0331)
    assert sync.method is not ClockFitMethod.ROUND_TRIP
    h = device_to_host(101.0)
    sync.add_round_trip(h - 0.0020, 101.0, h + 0.0050)
    assert sync.method is ClockFitMethod.ROUND_TRIP
    for d in (100.5, 101.0, 102.0):
        assert abs(sync.to_host(d) - device_to_host(d)) < 0.002


def test_round_trips_that_are_all_wide_are_trusted_after_a_few():
    """A network whose round trips are all slow still gets a clock: after ``start_round_trips``."""
    sync = ClockSync()
    for k, d in enumerate((10.0, 11.0, 12.0)):
        assert sync.method is not ClockFitMethod.ROUND_TRIP
        h = device_to_host(d)
        sync.add_round_trip(h - 0.015, d, h + 0.015)
        assert (sync.method is ClockFitMethod.ROUND_TRIP) == (k == 2)
    assert sync.to_host(12.0) == pytest.approx(device_to_host(12.0), abs=1e-3)


def test_two_round_trips_a_second_apart_leave_the_line_level():
    """Realistic scene 6464's cam3 (session 30): its two fastest round trips in the first 3 s, 8.3 and
    6.3 ms wide and a second apart, had their midpoints 2.4 ms after and 0.2 ms before the node's read
    (which leg is slow varies); the line through them (about -2,500 ppm) stamped the next seconds'
    frames up to 10 ms early as it ran away. With the drift's prior the line stays level (the node's
    33 ppm is 0.1 ms over those 3 s)."""
    h0, h1 = device_to_host(100.0), device_to_host(101.04)
    trips = ((h0 - 0.00179, 100.0, h0 + 0.00653), (h1 - 0.00334, 101.04, h1 + 0.00292))
    without = ClockSync(ClockSyncParams(drift_prior_ppm=0.0))
    sync = ClockSync()
    for trip in trips:
        without.add_round_trip(*trip)
        sync.add_round_trip(*trip)
    assert abs(without.fit().drift) > 2000e-6  # the case is one where it matters
    assert abs(sync.fit().drift) < 100e-6
    error, error_without = (abs(s.to_host(104.0) - device_to_host(104.0)) for s in (sync, without))
    assert error < error_without / 3
    assert error < 0.003


def test_the_drift_prior_gives_way_to_narrow_round_trips_over_minutes():
    """A clock 40 ppm off over two minutes of round trips (the window's 120): the prior does not
    hold the line level; the fit follows the drift as without it."""
    rng = np.random.default_rng(6)
    send, dev, recv = round_trips(rng, n=120)
    sync = ClockSync()
    for trip in zip(send, dev, recv, strict=True):
        sync.add_round_trip(*trip)
    assert sync.fit().drift == pytest.approx(DRIFT, abs=2e-5)
    for d in (50.0, 169.0):
        assert abs(sync.to_host(d) - device_to_host(d)) < 0.003
