"""Which waiting frame a live consumer takes next (docs/live.md, "How the frames are processed").

Frames wait in :class:`~cubetrack.source.streams.LiveCameras`' queue, each camera's newest only.
Taken in arrival order, the frames of one instant (every camera's, arriving within a few ms)
reach the fusion oldest first, as a replay gives them; taken freshest first, the last of them is
often fused before the others, which then come late and give no pose of their own. But when the
consumer is behind, arrival order makes every frame wait for the ones before it. So the consumer
is *behind* when a frame has waited longer than a share of its own camera's frame interval
(``[source] behind_intervals``: "behind" at 6 fps is another wait than at 30 fps), and then takes
the freshest instant first, its frames in arrival order. A camera's interval is the median of its
last arrival gaps (:class:`FrameIntervals`).
"""

from __future__ import annotations

import statistics
from collections import deque
from collections.abc import Iterable, Sequence

from cubetrack.core.records import Frame

INTERVAL_GAPS = 15  # arrival gaps per camera whose median is its frame interval
INSTANT_INTERVALS = 0.1  # frames that arrived this share of a frame interval apart are of one instant


class FrameIntervals:
    """Each camera's frame interval, the median of its last ``gaps`` arrival gaps (a dropped or
    late frame moves the median little; a camera that halves its rate is followed within
    ``gaps / 2`` frames). Unknown before a camera's second frame."""

    def __init__(self, gaps: int = INTERVAL_GAPS):
        self.gaps = gaps
        self._last_s: dict[str, float] = {}
        self._gaps_s: dict[str, deque[float]] = {}
        self._interval_s: dict[str, float] = {}

    def add(self, camera: str, arrival_s: float) -> None:
        """A frame of ``camera`` arrived at ``arrival_s`` (seconds, any clock, never going back)."""
        last_s = self._last_s.get(camera)
        self._last_s[camera] = arrival_s
        if last_s is None or arrival_s <= last_s:
            return
        gaps = self._gaps_s.setdefault(camera, deque(maxlen=self.gaps))
        gaps.append(arrival_s - last_s)
        self._interval_s[camera] = statistics.median(gaps)

    def interval_s(self, camera: str) -> float | None:
        """The camera's frame interval, seconds (None: fewer than two frames so far)."""
        return self._interval_s.get(camera)

    def freshest_instant(self, waiting: Sequence[Frame]) -> Frame:
        """What a consumer that is :meth:`behind` takes of ``waiting`` (in arrival order, not
        empty): the oldest frame of the freshest instant, the frames that arrived within
        ``INSTANT_INTERVALS`` of the freshest's camera's interval of it (the cameras of one instant
        arrive within a few ms: taken in their order, none of them comes to the fusion late)."""
        freshest = waiting[-1]
        width_s = INSTANT_INTERVALS * (self._interval_s.get(freshest.camera) or 0.0)
        return next(f for f in waiting if f.host_time_s >= freshest.host_time_s - width_s)

    def behind(self, waiting: Iterable[Frame], now_s: float, behind_intervals: float) -> bool:
        """Whether a consumer with ``waiting`` frames is behind at ``now_s`` (on the frames'
        ``host_time_s`` clock): some frame has waited longer than ``behind_intervals`` of its
        camera's interval (a camera of unknown interval is not behind)."""
        for frame in waiting:
            interval_s = self._interval_s.get(frame.camera)
            if interval_s is not None and now_s - frame.host_time_s > behind_intervals * interval_s:
                return True
        return False

