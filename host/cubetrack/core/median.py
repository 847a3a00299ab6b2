"""A streaming median in fixed memory (a live session's latencies, :mod:`cubetrack.app.session`)."""

from __future__ import annotations

import math


class SessionMedian:
    """The median of a whole session's latencies (seconds) in fixed memory: counts in bins 0.5 %
    wide on a log scale from 10 µs to 1000 s (values at or below 10 µs count as 0, those above in
    the top bin, about 1000 s), so a session of hours does not keep a float per pose (a list did: +25 MB in 10
    minutes at 16 cameras x 30 fps). :meth:`median` is within 0.25 % of the exact median."""

    LOW_S, HIGH_S, STEP = 1e-5, 1e3, 1.005
    _LOG_STEP = math.log(STEP)
    BINS = 2 + math.ceil(math.log(HIGH_S / LOW_S) / _LOG_STEP)

    def __init__(self) -> None:
        self.counts = [0] * self.BINS
        self.count = 0

    def add(self, value_s: float) -> None:
        i = 0 if value_s <= self.LOW_S else min(self.BINS - 1, 1 + int(math.log(value_s / self.LOW_S) / self._LOG_STEP))
        self.counts[i] += 1
        self.count += 1

    def median(self) -> float | None:
        """The middle bin's centre (None before any value)."""
        if not self.count:
            return None
        seen, half = 0, self.count / 2.0
        i = 0
        for i, n in enumerate(self.counts):  # noqa: B007 (i: the bin found, read after the loop)
            seen += n
            if seen >= half:
                break
        return 0.0 if i == 0 else self.LOW_S * self.STEP ** (i - 0.5)
