"""The sink interface: outputs never block or break the pipeline, and lose only what they count."""

import threading
import time

import numpy as np

from cubetrack.core.records import CameraView, TrackedPose
from cubetrack.sink.base import Decoupled, FileSink, Outputs, Sink


def pose(i: int, robot: str = "r1") -> TrackedPose:
    return TrackedPose(robot, 100.0 + i, np.array([i, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]), ("cam1",),
                       ("top",), 0.01)


class Gate(Sink):
    """A sink that holds its thread until released (a stalled network peer)."""

    name = "gate"

    def __init__(self):
        self.release = threading.Event()
        self.seen: list[float] = []

    def pose(self, p):
        self.release.wait(10)
        self.seen.append(p.time_s)


class Broken(Sink):
    name = "broken"

    def pose(self, p):
        raise RuntimeError("peer went away")


def test_a_stalled_sink_costs_the_caller_nothing_and_counts_what_it_lost(tmp_path, caplog):
    gate = Gate()
    with Outputs([FileSink(tmp_path, ("r1",)), gate]) as outputs:
        for i in range(300):
            outputs.pose(pose(i))  # returns although the gate holds its thread
        dropped = outputs.dropped()["gate"]
        gate.release.set()
    lines = (tmp_path / "r1.tum").read_text().splitlines()
    assert len(lines) == 300  # the in-line file sink saw everything
    assert dropped > 0 and len(gate.seen) + dropped == 300
    assert gate.seen == sorted(gate.seen) and gate.seen[-1] == 399.0  # the newest kept, in order
    assert f"output gate dropped {dropped} item(s)" in caplog.text  # and the user is told


def test_a_failing_sink_is_stopped_without_reaching_the_pipeline(tmp_path, caplog):
    broken = Decoupled(Broken())
    with Outputs([FileSink(tmp_path, ("r1",)), broken]) as outputs:
        outputs.pose(pose(0))
        broken._thread.join(5)
        outputs.pose(pose(1))
    assert broken.failed == "peer went away"
    assert len((tmp_path / "r1.jsonl").read_text().splitlines()) == 2
    assert "output broken failed" in caplog.text


class Views(Sink):
    """A sink that shows images, at most ``fps`` per camera (0: all)."""

    name = "views"
    in_line = True
    wants_views = True

    def __init__(self, fps: float):
        self.view_interval_s = 1 / fps if fps else 0.0
        self.seen: list[tuple[str, int]] = []

    def pose(self, p):
        pass

    def camera_view(self, view):
        self.seen.append((view.camera, view.seq))


def test_views_are_thinned_per_sink_and_camera_to_the_sink_s_rate():
    every, ten = Views(0), Views(10)
    rng = np.random.default_rng(3)
    with Outputs([every, ten]) as outputs:
        for seq in range(300):  # 10 s of two cameras at 30 fps with a few ms of jitter
            for camera, offset in (("cam1", 0.0), ("cam2", 0.011)):
                t = 100.0 + seq / 30 + offset + rng.uniform(-0.004, 0.004)
                outputs.camera_view(CameraView(camera, seq, t, b"", ()))
        outputs.camera_view(CameraView("cam1", 900, 130.0, b"", ()))  # after a gap of 20 s: due at once
    assert len(every.seen) == 601
    for camera in ("cam1", "cam2"):
        seqs = [s for c, s in ten.seen if c == camera]
        assert 99 <= len(seqs) - (camera == "cam1") <= 101  # 10 per second on average, whatever the jitter
        gaps = np.diff(seqs[:100])
        assert set(gaps.tolist()) <= {2, 3, 4}  # evenly spread, not bursts
    assert ten.seen[-1] == ("cam1", 900)


def test_in_line_outputs_of_the_outputs_process_fail_alone(tmp_path, caplog):
    files = FileSink(tmp_path, ("r1",))
    with Outputs([Broken(), files], all_in_line=True) as outputs:  # as the outputs' process runs them
        broken = outputs.sinks[0]
        for i in range(3):
            outputs.pose(pose(i))  # never raises
    assert broken.failed == "peer went away" and caplog.text.count("output broken failed") == 1
    assert len((tmp_path / "r1.jsonl").read_text().splitlines()) == 3  # the other output saw every pose


class Batching(Sink):
    """A batching sink (as the outputs' process's pipe is) that records each batch it is handed."""

    name = "batching"
    batch_window_s = 0.5

    def __init__(self):
        self.batches: list[list[float]] = []
        self.delivered = threading.Event()

    def deliver(self, items):
        self.batches.append([value.time_s for _, value in items])
        self.delivered.set()

    def pose(self, p):  # only batches reach it
        raise AssertionError("a batching sink is handed batches")


class _StoppedClock:
    """``time`` for sink/base.py with the clock standing still and each sleep recorded and held
    until the test lets it go: what the batching thread waits for is seen as state, not timed."""

    def __init__(self):
        self.sleeps: list[float] = []
        self.go = threading.Event()

    def monotonic(self) -> float:
        return 1000.0

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.go.wait(10)

    def __getattr__(self, name):
        return getattr(time, name)


def test_a_batching_sink_sends_a_lone_item_at_once_and_batches_what_follows_it(monkeypatch):
    from cubetrack.sink import base

    clock = _StoppedClock()
    monkeypatch.setattr(base, "time", clock)
    inner = Batching()
    sink = Decoupled(inner)
    try:
        sink.pose(pose(0))
        assert inner.delivered.wait(10)
        assert clock.sleeps == [], "a lone item after a quiet spell waited for the batching window"
        inner.delivered.clear()
        sink.pose(pose(1))  # within the window of the first batch (the clock stands still)
        deadline = time.monotonic() + 10
        while not clock.sleeps:  # the thread waits out the window ...
            assert time.monotonic() < deadline
            time.sleep(0.01)
        sink.pose(pose(2))  # ... and what comes meanwhile joins the same batch
        clock.go.set()
        assert inner.delivered.wait(10)
    finally:
        clock.go.set()
        sink.close()
    assert inner.batches == [[100.0], [101.0, 102.0]] and clock.sleeps == [Batching.batch_window_s]
