"""De-jittered arrival stamps of a camera without a clock (cubetrack.source.timing.ArrivalEnvelope):
synthetic arrivals of a camera capturing at a steady rate, delayed by a random non-negative
jitter (MJPEG over TCP: transfer only ever adds delay), with drops, bursts, rate changes and
restarts. Every test compares the stamps with the capture times the arrivals were made from, and
each fails with stamps on the arrival itself (the jitter is far above the bound asserted)."""

from __future__ import annotations

import numpy as np
import pytest

from cubetrack.source.timing import ENVELOPE_WARMUP, ArrivalEnvelope, lower_envelope

LATENCY_S = 0.012  # the smallest delay: capture -> arrival of an unjittered frame


def arrivals(capture_s: np.ndarray, seed: int, mean_jitter_s: float = 0.004) -> np.ndarray:
    """Arrival times: capture + latency + exponential jitter (p95 three times the mean)."""
    return capture_s + LATENCY_S + np.random.default_rng(seed).exponential(mean_jitter_s, capture_s.size)


def stamp_errors(capture_s: np.ndarray, arrival_s: np.ndarray, envelope: ArrivalEnvelope | None = None,
                 seqs: list[int] | None = None) -> np.ndarray:
    """Stamp - (capture + latency) per frame, seconds."""
    envelope = envelope or ArrivalEnvelope()
    stamps = [envelope.stamp(float(a), None if seqs is None else seqs[i]) for i, a in enumerate(arrival_s)]
    assert all(s <= a for s, a in zip(stamps, arrival_s, strict=True))  # never after the arrival
    return np.array(stamps) - (capture_s + LATENCY_S)


def assert_on_envelope(err: np.ndarray, raw: np.ndarray, period_s: float) -> None:
    """The stamps are on the capture times (+ the smallest delay) where the arrivals can tell:
    frames delayed by less than 0.7 of a period within 3 ms, 95 % of all within a quarter of the
    jitter's 95th percentile (the arrival's own error)."""
    told = raw < 0.7 * period_s
    assert np.max(np.abs(err[told])) < 0.003
    assert np.percentile(np.abs(err), 95) < np.percentile(raw, 95) / 4


def test_jitter_is_removed_at_a_steady_rate():
    capture = 1000.0 + np.arange(300) / 30.0
    arrival = arrivals(capture, 1)
    raw = arrival - (capture + LATENCY_S)
    err = stamp_errors(capture, arrival)
    assert np.percentile(raw, 95) > 0.010
    assert_on_envelope(err[10:], raw[10:], 1 / 30.0)
    assert np.percentile(np.abs(err[10:]), 95) < 0.001
    # a frame later than 3/4 of a period cannot be told from the next one: no worse than its arrival
    assert np.all(err <= raw + 1e-9)


def test_dropped_frames_and_a_burst_after_a_stall_keep_the_envelope():
    """Gaps of 2 and 7 periods (frames lost), and a frame delayed by 2.5 periods with the two
    behind it arriving in the same read: the stamps stay on the envelope (the burst's frames are
    stamped no later than they arrived) and no restart is needed."""
    k = np.array([i for i in range(240) if (i < 20 or i % 23 != 5) and not 100 <= i < 106])
    capture = 50.0 + k / 30.0
    arrival = arrivals(capture, 2)
    burst = int(np.searchsorted(k, 150))
    arrival[burst] = capture[burst] + LATENCY_S + 2.5 / 30.0
    arrival[burst + 1] = arrival[burst + 2] = arrival[burst]
    envelope = ArrivalEnvelope()
    err = stamp_errors(capture, arrival, envelope)
    raw = arrival - (capture + LATENCY_S)
    steady = np.ones(len(k), bool)
    steady[:ENVELOPE_WARMUP + 2] = False
    steady[burst:burst + 3] = False
    assert_on_envelope(err[steady], raw[steady], 1 / 30.0)
    assert np.all(err[burst:burst + 3] <= raw[burst:burst + 3] + 1e-9)
    assert envelope.restarts == 0
    assert envelope.period_s == pytest.approx(1 / 30.0, rel=1e-3)


@pytest.mark.parametrize(("fps_before", "fps_after"), [(30.0, 20.0), (30.0, 15.0), (15.0, 30.0)])
def test_a_rate_change_is_followed(fps_before, fps_after):
    """One rate, then another (a webcam lowering it in dim light, or raising it again): within
    a few dozen frames the stamps are on the new envelope (at half the rate without a restart:
    every other frame counts as dropped)."""
    before = 10.0 + np.arange(150) / fps_before
    after = before[-1] + 0.5 / fps_after + np.arange(1, 201) / fps_after
    capture = np.concatenate([before, after])
    arrival = arrivals(capture, 3)
    raw = arrival - (capture + LATENCY_S)
    envelope = ArrivalEnvelope()
    err = stamp_errors(capture, arrival, envelope)
    assert_on_envelope(err[10:150], raw[10:150], 1 / fps_before)
    assert_on_envelope(err[150 + 40:], raw[150 + 40:], 1 / fps_after)
    assert (envelope.restarts == 0) == (fps_after == fps_before / 2)


def test_a_restart_is_learnt_again():
    """The stream restarts (a reconnect: the caller resets; a camera that restarts its numbering
    or comes back after a long silence: found by itself), each time in a new phase."""
    first = 5.0 + np.arange(120) / 25.0
    second = first[-1] + 0.4123 + np.arange(120) / 25.0  # reconnected, new phase
    third = second[-1] + 9.0 + np.arange(120) / 25.0  # silent 9 s: > ENVELOPE_MAX_GAP periods
    envelope = ArrivalEnvelope()
    err1 = stamp_errors(first, arrivals(first, 4), envelope, list(range(1, 121)))
    envelope.reset()
    err2 = stamp_errors(second, arrivals(second, 5), envelope, list(range(1, 121)))
    err3 = stamp_errors(third, arrivals(third, 6), envelope)  # no numbers from here on: a restart by itself
    for err, capture, seed in ((err1, first, 4), (err2, second, 5), (err3, third, 6)):
        raw = arrivals(capture, seed) - (capture + LATENCY_S)
        assert_on_envelope(err[20:], raw[20:], 1 / 25.0)
    assert envelope.restarts == 2


def test_camera_numbers_place_frames_across_long_delays():
    """With the camera's own frame numbers a frame delayed by more than a period is not taken for
    a later one: its stamp is its own envelope time."""
    capture = 1.0 + np.arange(200) / 30.0
    arrival = arrivals(capture, 7)
    arrival[100] += 0.05  # 1.5 periods late, still before the next frame
    err = stamp_errors(capture, np.maximum.accumulate(arrival), seqs=list(range(200)))
    assert abs(err[100]) < 0.002


def test_the_envelope_is_the_highest_line_under_the_points_at_their_mean():
    points = [(0, 0.0), (1, 1.5), (2, 2.0), (3, 3.6), (4, 4.0)]
    t0, period = lower_envelope(points)
    line = [t0 + period * k for k, _ in points]
    assert all(y <= t + 1e-12 for y, (_, t) in zip(line, points, strict=True))
    assert (t0, period) == pytest.approx((0.0, 1.0))
    assert lower_envelope([(0, 1.0)]) is None


def test_the_window_must_hold_the_warm_up():
    with pytest.raises(ValueError):
        ArrivalEnvelope(2)
