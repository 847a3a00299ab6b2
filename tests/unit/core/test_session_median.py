"""A live session's median latencies in fixed memory (cubetrack.core.median.SessionMedian)."""

import random
import statistics

from cubetrack.core.median import SessionMedian


def test_the_session_median_is_within_a_quarter_percent_of_the_exact_one():
    rng = random.Random(3)
    for scale_s in (0.0002, 0.005, 0.3, 40.0):
        values = [rng.lognormvariate(0.0, 0.8) * scale_s for _ in range(20001)]
        sketch = SessionMedian()
        for v in values:
            sketch.add(v)
        exact = statistics.median(values)
        assert abs(sketch.median() - exact) <= 0.0026 * exact, (scale_s, sketch.median(), exact)


def test_it_keeps_counts_not_values_and_clamps_the_ends():
    sketch = SessionMedian()
    assert sketch.median() is None
    for i in range(100_000):
        sketch.add(0.004 + (i % 7) * 1e-4)
    assert len(sketch.counts) == SessionMedian.BINS < 5000 and sketch.count == 100_000
    low, high = SessionMedian(), SessionMedian()
    for v in (-0.5, 0.0, 1e-6):
        low.add(v)
    high.add(5e6)
    assert low.median() == 0.0
    assert abs(high.median() - 1e3) <= 0.01 * 1e3  # the top bin, about 1000 s
