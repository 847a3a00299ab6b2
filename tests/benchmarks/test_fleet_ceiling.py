"""benchmarks/fleet.py --find-ceiling's search (issue 28's measure: the highest rate a configuration keeps up
with at <= 1 % dropped and p95 <= 20 ms), driven by a fake fleet whose capacity is known: the runs themselves are
test_fleet's and the benchmark's business."""

import math

import pytest

from tests.helpers.benchmarks import load_benchmark


def fake_fleet(capacity_per_s: float, per_fps: float = 100.0, p95_ms: float = 8.0):
    """A fleet offering ``per_fps`` sightings/s per fps that keeps up below ``capacity_per_s``: drops above it,
    or (``p95_ms`` above 20) keeps every sighting but too late."""
    calls: list[float] = []

    def measure(fps: float) -> dict:
        calls.append(fps)
        offered = per_fps * fps
        over = offered > capacity_per_s
        return {"offered_per_s": offered, "dropped_pct": 6.0 if over and p95_ms <= 20 else 0.0,
                "latency_ms_p50_p95_p99": [2.0, 900.0 if over else p95_ms, 1000.0],
                "shard_cpu_ms_per_sighting": {0: 0.3}, "shard_threads_ms_per_sighting": {0: {"main": 0.25}},
                "publisher_cpu_ms_per_sighting": 0.02, "load_before": [1.0, 1.0, 1.0]}
    return measure, calls


@pytest.mark.parametrize(("start_fps", "capacity"), [(10.0, 2300.0), (30.0, 2300.0), (10.0, 700.0)])
def test_the_ceiling_is_the_highest_rate_kept_up_within_half_a_step(start_fps, capacity):
    bench = load_benchmark("fleet")
    measure, calls = fake_fleet(capacity)
    c = bench.find_ceiling(measure, start_fps, steps=8)
    assert c["ceiling_per_s"] <= capacity < c["ceiling_per_s"] * (1 + (bench.CEILING_FACTOR - 1) / 2)
    assert c["at"]["kept_up"] and c["at"]["offered_per_s"] == c["ceiling_per_s"]
    assert len(c["steps"]) == len(calls) <= 8
    assert [s["kept_up"] for s in c["steps"]] == [100 * f <= capacity for f in calls]


def test_late_poses_fail_a_rate_as_drops_do_and_no_rate_kept_up_gives_nan():
    bench = load_benchmark("fleet")
    measure, calls = fake_fleet(1500.0, p95_ms=25.0)   # every sighting fused, none in time
    c = bench.find_ceiling(measure, 10.0, steps=3)
    assert math.isnan(c["ceiling_per_s"]) and c["at"] is None
    assert calls == pytest.approx([10.0, 8.0, 6.4])     # stepped down by CEILING_FACTOR each time
