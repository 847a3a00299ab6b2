"""The timing model: clocks, captures, drops, arrivals and /time round trips (contracts §1, §3)."""

from __future__ import annotations

import numpy as np
import pytest

from cubetrack.io.recording import Recording
from cubetrack.simulate import SimulationParams
from cubetrack.simulate.timing import DeviceClock, plan_captures, plan_clock_samples

US = 1e-6  # files store microseconds


def test_device_clock_round_trips_and_drifts():
    clock = DeviceClock(boot_host_s=1000.0, drift_ppm=50.0)
    assert clock.device_time_s(1000.0) == 0.0
    assert clock.device_time_s(2000.0) == pytest.approx(1000.05)
    assert clock.host_time_s(clock.device_time_s(1234.5678)) == pytest.approx(1234.5678, abs=1e-9)


def test_index_rows_follow_the_capture_truth(session):
    rec = Recording.open(session.path)
    for cam in session.cameras:
        rows = rec.index(cam.name)
        delivered = [c for c in cam.captures if c.delivered]
        assert [r.seq for r in rows] == [c.seq for c in delivered]
        for row, c in zip(rows, delivered, strict=True):
            assert row.device_time_s == pytest.approx(c.device_time_s, abs=US)
            assert row.host_time_s == pytest.approx(c.arrival_host_s, abs=US)
            # the stamp is the capture instant on the device clock
            assert cam.clock.host_time_s(row.device_time_s) == pytest.approx(c.capture_host_s, abs=2 * US)


def test_drops_leave_gaps_in_seq_and_arrivals_follow_captures(session):
    p = session.params
    for cam in session.cameras:
        seqs = np.array([c.seq for c in cam.captures])
        assert np.all(np.diff(seqs) == 1)  # every captured frame is counted
        delivered = [c for c in cam.captures if c.delivered]
        written = np.array([c.seq for c in delivered])
        assert np.all(np.diff(written) >= 1)
        assert np.any(np.diff(written) > 1), "expected gaps with drop_rate 0.1"
        arrivals = np.array([c.arrival_host_s for c in delivered])
        captures = np.array([c.capture_host_s for c in delivered])
        assert np.all(np.diff(arrivals) > 0)  # in order, one frame on the air at a time
        assert np.all(arrivals - captures >= p.latency_ms * 1e-3 - 1e-9)
        assert np.all(captures >= p.start_unix_s) and np.all(arrivals <= p.start_unix_s + p.duration_s)
        # the capture grid runs on the device clock at the configured rate
        device = np.array([c.device_time_s for c in cam.captures])
        assert np.median(np.diff(device)) == pytest.approx(1.0 / p.fps, abs=1e-3)


def test_clock_samples_bracket_the_true_device_time(session):
    rec = Recording.open(session.path)
    for cam in session.cameras:
        samples = rec.clock_samples(cam.name)
        assert len(samples) >= session.params.duration_s / session.params.clock_period_s - 2
        for s in samples:
            true_host = cam.clock.host_time_s(s.device_time_s)
            assert s.host_send_s - 2 * US <= true_host <= s.host_recv_s + 2 * US
        # the offset known from the fastest round trip is within half of it
        best = min(samples, key=lambda s: s.host_recv_s - s.host_send_s)
        half = (best.host_recv_s - best.host_send_s) / 2
        mid = (best.host_send_s + best.host_recv_s) / 2
        assert abs(cam.clock.host_time_s(best.device_time_s) - mid) <= half + 2 * US
        # asymmetric network: the device reads its clock before the midpoint on average
        before = [cam.clock.host_time_s(s.device_time_s) < (s.host_send_s + s.host_recv_s) / 2 for s in samples]
        assert np.mean(before) > 0.5


def test_clock_offsets_and_drifts_differ_between_cameras(session):
    boots = [c.clock.boot_host_s for c in session.cameras]
    drifts = [c.clock.drift_ppm for c in session.cameras]
    assert len(set(boots)) == len(boots) and len(set(drifts)) == len(drifts)
    assert all(session.params.start_unix_s - b >= 60.0 for b in boots)


def test_latency_spikes_skip_frames_without_random_loss():
    p = SimulationParams(drop_rate=0.0, spike_rate=0.3, spike_ms=400.0)
    clock = DeviceClock(0.0, 0.0)
    rng = np.random.default_rng(0)
    caps = plan_captures(p, clock, 0.01, rng, 100.0, 160.0)
    delivered = [c for c in caps if c.delivered]
    assert 0 < len(caps) - len(delivered) < len(caps) / 2
    # a skipped frame was superseded: something newer arrived after it was captured
    latencies = np.array([c.arrival_host_s - c.capture_host_s for c in delivered])
    assert latencies.max() > 0.3 and np.median(latencies) < 0.1


def test_no_drops_no_spikes_delivers_every_frame():
    p = SimulationParams(drop_rate=0.0, spike_rate=0.0, latency_jitter_ms=5.0)
    caps = plan_captures(p, DeviceClock(0.0, 10.0), 0.0, np.random.default_rng(1), 100.0, 130.0)
    assert all(c.delivered for c in caps[:-1])
    assert len(caps) == pytest.approx(30 * p.fps, abs=2)


def test_max_delivered_stops_the_plan():
    p = SimulationParams()
    caps = plan_captures(p, DeviceClock(0.0, 0.0), 0.0, np.random.default_rng(1), 100.0, 200.0, max_delivered=25)
    assert sum(c.delivered for c in caps) == 25 and caps[-1].delivered


def test_clock_sample_period():
    p = SimulationParams(clock_period_s=0.5)
    samples = plan_clock_samples(p, DeviceClock(0.0, 0.0), np.random.default_rng(3), 10.0, 40.0)
    sends = np.array([s.host_send_s for s in samples])
    assert np.all(np.abs(np.diff(sends) - 0.5) <= 0.5 * 0.05 + 1e-9)
    assert all(s.host_send_s < s.host_recv_s for s in samples)
