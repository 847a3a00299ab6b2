"""The order a live consumer takes waiting frames in (cubetrack.source.order): arrival order while
no frame has waited longer than ``behind_intervals`` of its own camera's frame interval; once one
has (the consumer is behind), the freshest instant first, its frames in arrival order. Frames are
put in the queue directly, on a clock of the test's: no sockets."""

from __future__ import annotations

import pytest

from cubetrack.core.errors import ConfigError
from cubetrack.core.records import Frame
from cubetrack.source.order import FrameIntervals
from cubetrack.source.streams import LiveCameras, SourceParams


def frame(camera: str, seq: int, arrival_s: float) -> Frame:
    return Frame(camera, seq, arrival_s, arrival_s, b"jpeg")


class Clock:
    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


def queued(fps: dict[str, float], frames: int, spread_s: float = 0.004,
           params: SourceParams | None = None) -> tuple[LiveCameras, Clock]:
    """A LiveCameras (never started) that has had ``frames`` frames of each camera at its ``fps``,
    the cameras of one instant arriving ``spread_s`` apart in the order given, none taken: each
    camera's last waits."""
    clock = Clock()
    live = LiveCameras({name: f"http://127.0.0.1:9/{name}" for name in fps}, params or SourceParams(), clock=clock)
    arrivals = sorted((k / rate + i * spread_s, name, k) for i, (name, rate) in enumerate(fps.items())
                      for k in range(frames))
    for arrival_s, name, k in arrivals:
        live._put_frame(frame(name, k, arrival_s))
    clock.now_s = arrivals[-1][0]
    return live, clock


def test_a_cameras_interval_is_the_median_of_its_arrival_gaps():
    intervals = FrameIntervals()
    intervals.add("a", 0.0)
    assert intervals.interval_s("a") is None  # one frame: no gap yet
    arrivals = [0.1, 0.2, 0.4, 0.5, 0.63, 0.7, 0.8]  # one frame dropped (0.3), one late (0.63)
    for t in arrivals:
        intervals.add("a", t)
    assert intervals.interval_s("a") == pytest.approx(0.1)
    assert intervals.interval_s("b") is None


def test_a_camera_that_halves_its_rate_is_followed():
    intervals = FrameIntervals(gaps=15)
    for k in range(30):
        intervals.add("a", k / 30)
    for k in range(1, 9):  # past half the window at the new rate
        intervals.add("a", 29 / 30 + k / 15)
    assert intervals.interval_s("a") == pytest.approx(1 / 15)


def test_a_consumer_keeping_up_at_6_fps_gets_an_instants_frames_in_arrival_order():
    # four webcams at 6 fps (the real footage's rate), the host 30 ms into the instant's work: the
    # frames waited 0.2-0.25 of their interval, so the oldest comes first, as in a replay (the 15 ms
    # rule of the camera processes and the worker threads' freshest-first took the last one first)
    live, clock = queued({"a": 6.0, "b": 6.0, "c": 6.0, "d": 6.0}, frames=5)
    clock.now_s += 0.03
    taken = [live.get(0, newest_if_behind=True) for _ in range(4)]
    assert [f.camera for f in taken] == ["a", "b", "c", "d"]


def test_a_consumer_behind_at_30_fps_gets_the_freshest_frame_first():
    # the oldest waited 2 ms + 3 x 4 ms of the cameras' spread: past a quarter of a 33 ms interval; the
    # cameras are 4 ms apart, more than a tenth of the interval: each is an instant of its own
    live, clock = queued({"a": 30.0, "b": 30.0, "c": 30.0, "d": 30.0}, frames=5)
    clock.now_s += 0.002
    assert live.get(0, newest_if_behind=True).camera == "d"
    live, clock = queued({"a": 30.0, "b": 30.0, "c": 30.0, "d": 30.0}, frames=5, spread_s=0.001)
    clock.now_s += 0.002  # the oldest waited 5 ms: not behind yet, arrival order
    assert live.get(0, newest_if_behind=True).camera == "a"


def test_behind_is_measured_in_each_cameras_own_interval():
    live, clock = queued({"slow": 5.0, "fast": 30.0}, frames=6)
    while live.get(0) is not None:  # take what waited
        pass
    live._put_frame(frame("slow", 6, 1.2))
    live._put_frame(frame("fast", 36, 1.2 + 0.04))
    clock.now_s = 1.2 + 0.045  # slow waited 45 ms (0.225 of its 200 ms), fast 5 ms (0.15 of its 33 ms)
    assert live.get(0, newest_if_behind=True).camera == "slow"
    live._put_frame(frame("slow", 7, 1.4))
    live._put_frame(frame("fast", 37, 1.41))  # replaces fast's frame that waited
    clock.now_s = 1.42  # fast waited 10 ms, past a quarter of its 33 ms; slow 20 ms, 0.1 of its interval
    assert live.get(0, newest_if_behind=True).camera == "fast"


def test_behind_the_freshest_instant_comes_first_its_frames_in_arrival_order():
    live, clock = queued({"a": 6.0, "b": 6.0, "c": 6.0}, frames=5)
    while live.get(0) is not None:
        pass
    live._put_frame(frame("a", 5, 1.0))  # of an instant before
    live._put_frame(frame("b", 5, 1.1))  # the freshest instant, its frames 4 ms apart
    live._put_frame(frame("c", 5, 1.104))
    clock.now_s = 1.11  # a waited 110 ms, past a quarter of its 167 ms interval: behind
    assert [live.get(0, newest_if_behind=True).camera for _ in range(3)] == ["b", "c", "a"]


def test_a_camera_of_unknown_interval_is_not_behind():
    live, clock = queued({"a": 6.0, "b": 6.0}, frames=1)  # one frame each: no interval yet
    clock.now_s += 10.0
    assert live.get(0, newest_if_behind=True).camera == "a"


def test_freshest_first_and_arrival_order_are_still_there_to_ask_for():
    live, clock = queued({"a": 6.0, "b": 6.0}, frames=5)
    assert live.get(0, newest_first=True).camera == "b"  # not behind, but the freshest was asked for
    live, clock = queued({"a": 6.0, "b": 6.0}, frames=5)
    clock.now_s += 1.0  # far behind, but arrival order was asked for
    assert live.get(0).camera == "a"


@pytest.mark.parametrize("behind_intervals, first", [(0.0, "b"), (float("inf"), "a")])
def test_behind_intervals_spans_always_the_freshest_instant_to_arrival_order(behind_intervals, first):
    live, clock = queued({"a": 6.0, "b": 6.0}, frames=5, spread_s=0.05,  # b's instant is not a's
                         params=SourceParams(behind_intervals=behind_intervals))
    clock.now_s += 0.001
    assert live.get(0, newest_if_behind=True).camera == first


def test_a_negative_behind_intervals_is_a_config_error():
    with pytest.raises(ConfigError, match="behind_intervals"):
        SourceParams(behind_intervals=-0.5)
