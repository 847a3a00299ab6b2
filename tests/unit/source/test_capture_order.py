"""Live results put back in capture order before the fusion (cubetrack.source.order.CaptureOrder):
a result waits for an older job still being worked on and for another camera's frame of the same
instant that is due, at most half its own camera's frame interval. Clock of the test's: no sockets."""

from __future__ import annotations

from cubetrack.core.records import Frame, FrameJob, FrameOutcome, FrameResult
from cubetrack.source.order import CaptureOrder

INTERVAL_S = 1 / 6  # the real footage's cameras


def job(camera: str, seq: int, capture_s: float) -> FrameJob:
    return FrameJob(Frame(camera, seq, capture_s, capture_s + 0.01, b"jpeg"), capture_s, None, frozenset())


def result(j: FrameJob) -> FrameResult:
    return FrameResult(j, FrameOutcome.FULL_FRAME)


def warmed(cameras: tuple[str, ...], instants: int = 3, spread_s: float = 0.003) -> tuple[CaptureOrder, float]:
    """A CaptureOrder that has seen ``instants`` whole instants of every camera (``spread_s``
    apart within one), all handed out; the capture time of the next instant."""
    order = CaptureOrder()
    for k in range(instants):
        jobs = [order.started(job(c, k, k * INTERVAL_S + i * spread_s)) for i, c in enumerate(cameras)]
        order.ready([result(j) for j in jobs], k * INTERVAL_S + 0.05)
    assert order.ready([], instants * INTERVAL_S) == [] and order.held() == 0
    return order, instants * INTERVAL_S


def captures(results: list[FrameResult]) -> list[tuple[str, float]]:
    return [(r.job.frame.camera, round(r.job.capture_time_s, 4)) for r in results]


def test_a_result_finished_first_waits_for_the_older_job_still_worked_on():
    order, t = warmed(("a", "b"))
    older, newer = order.started(job("a", 3, t)), order.started(job("b", 3, t + 0.003))
    assert order.ready([result(newer)], t + 0.02) == []  # b's worker was faster
    assert captures(order.ready([result(older)], t + 0.03)) == [("a", round(t, 4)), ("b", round(t + 0.003, 4))]


def test_a_result_waits_for_another_cameras_frame_of_the_same_instant_that_arrives_later():
    order, t = warmed(("a", "b"))
    # b's frame was captured later but arrived (and was stamped) first; a's comes 10 ms after
    b = order.started(job("b", 3, t + 0.003))
    assert order.ready([result(b)], t + 0.02) == []
    a = order.started(job("a", 3, t))
    assert captures(order.ready([result(a)], t + 0.03)) == [("a", round(t, 4)), ("b", round(t + 0.003, 4))]
    assert order.held() == 0


def test_the_newest_frame_of_an_instant_goes_at_once_when_every_camera_has_given_its_own():
    order, t = warmed(("a", "b", "c"))
    jobs = [order.started(job(c, 3, t + i * 0.003)) for i, c in enumerate(("a", "b", "c"))]
    assert len(order.ready([result(j) for j in jobs], t + 0.01)) == 3


def test_a_dropped_frame_is_waited_for_at_most_half_an_interval():
    order, t = warmed(("a", "b"))
    b = order.started(job("b", 3, t + 0.003))  # a's frame of this instant never comes
    assert order.ready([result(b)], t + 0.02) == []
    assert order.held() == 1
    assert captures(order.ready([], t + 0.003 + INTERVAL_S / 2)) == [("b", round(t + 0.003, 4))]


def test_a_stopped_camera_is_not_waited_for():
    order, t = warmed(("a", "b"))
    later = t + 3 * INTERVAL_S  # a sent nothing for three intervals
    b = order.started(job("b", 4, later))
    assert captures(order.ready([result(b)], later + 0.01)) == [("b", round(later, 4))]


def test_a_cameras_first_frame_is_not_held():
    order = CaptureOrder()
    first = order.started(job("a", 0, 1.0))
    assert len(order.ready([result(first)], 1.0)) == 1
