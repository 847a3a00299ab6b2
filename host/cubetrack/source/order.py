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

Taken in arrival order, frames still do not reach the fusion in capture order: stamps of cameras
without a clock (the arrival envelope) put 189 of the real footage's 440 frames before one that
arrived earlier, and two workers finish one instant's frames in either order. A late sighting is
folded in but gives no pose of its own, so the instant's last pose misses it (the same sightings
fused newest of each instant first: position median 1.62x). :class:`CaptureOrder` puts the
results back in capture order before the fusion, as a replay does with its few frames of look-ahead.
"""

from __future__ import annotations

import heapq
import itertools
import statistics
from collections import Counter, deque
from collections.abc import Iterable, Sequence

from cubetrack.core.records import Frame, FrameJob, FrameResult

INTERVAL_GAPS = 15  # arrival gaps per camera whose median is its frame interval
INSTANT_INTERVALS = 0.1  # frames that arrived this share of a frame interval apart are of one instant
NEXT_INSTANT_INTERVALS = 0.5  # a capture this share of an interval after a camera's last: its next is later
ORDER_WAIT_INTERVALS = 0.5  # CaptureOrder holds a result at most this share of its camera's frame interval


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



class CaptureOrder:
    """Per-frame results put back in capture order before the fusion. A result is held while an
    older-captured job is still being worked on, or while another camera's frame of the same
    instant may still come: its newest job was captured more than ``NEXT_INSTANT_INTERVALS`` of
    its capture interval before this result, but less than one interval more (unknown interval,
    or further behind: a dropped frame, a stopped camera: not waited for); the wait for other
    cameras ends ``ORDER_WAIT_INTERVALS`` of the result's own camera's interval after its capture.
    Times are capture times on the host clock, seconds."""

    def __init__(self) -> None:
        self._intervals = FrameIntervals()  # on capture times
        self._newest_s: dict[str, float] = {}  # camera -> capture time of its newest job
        self._working: Counter[float] = Counter()  # capture times of jobs not yet done
        self._held: list[tuple[float, int, FrameResult]] = []  # heap: (capture time, tie-break, result)
        self._count = itertools.count()

    def started(self, job: FrameJob) -> FrameJob:
        """``job`` is being worked on (returned, for the caller to hand on)."""
        camera, capture_s = job.frame.camera, job.capture_time_s
        self._intervals.add(camera, capture_s)
        self._newest_s[camera] = max(capture_s, self._newest_s.get(camera, capture_s))
        self._working[capture_s] += 1
        return job

    def held(self) -> int:
        """Results done and not yet handed out."""
        return len(self._held)

    def ready(self, results: Iterable[FrameResult], now_s: float) -> list[FrameResult]:
        """Take the ``results`` of started jobs (in any order; a result of a job never started is
        taken too) and hand out, oldest capture first, every held result nothing older can still
        come before (``now_s``: the time now, on the capture times' clock)."""
        for result in results:
            capture_s = result.job.capture_time_s
            if self._working[capture_s] > 0:
                self._working[capture_s] -= 1
                if not self._working[capture_s]:
                    del self._working[capture_s]
            heapq.heappush(self._held, (capture_s, next(self._count), result))
        out = []
        while self._held and self._may_go(self._held[0][2], now_s):
            out.append(heapq.heappop(self._held)[2])
        return out

    def _may_go(self, result: FrameResult, now_s: float) -> bool:
        """Nothing older is being worked on, and no other camera's frame of this instant is due
        (or the result has waited its longest)."""
        camera, capture_s = result.job.frame.camera, result.job.capture_time_s
        if any(t < capture_s for t in self._working):
            return False  # a started job always ends (a worker that fails ends the session): wait for it
        interval_s = self._intervals.interval_s(camera)
        if interval_s is None or now_s - capture_s >= ORDER_WAIT_INTERVALS * interval_s:
            return True  # a camera's first frame, or waited its longest
        for other, newest_s in self._newest_s.items():
            other_s = self._intervals.interval_s(other)
            if other != camera and other_s is not None and \
                    NEXT_INSTANT_INTERVALS * other_s <= capture_s - newest_s < (1 + NEXT_INSTANT_INTERVALS) * other_s:
                return False  # its frame of this instant is due (one more interval behind: dropped, not waited for)
        return True
