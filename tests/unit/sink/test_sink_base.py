"""The sink interface: outputs never block or break the pipeline, and lose only what they count."""

import threading

import numpy as np

from cubetrack.core.records import TrackedPose
from cubetrack.sink.base import Decoupled, FileSink, Outputs, Sink


def pose(i: int, robot: str = "r1") -> TrackedPose:
    return TrackedPose(robot, 100.0 + i, np.array([i, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]), ("cam1",), ("top",), 0.01)


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


def test_a_stalled_sink_costs_the_caller_nothing_and_counts_what_it_lost(tmp_path):
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


def test_a_failing_sink_is_stopped_without_reaching_the_pipeline(tmp_path, caplog):
    broken = Decoupled(Broken())
    with Outputs([FileSink(tmp_path, ("r1",)), broken]) as outputs:
        outputs.pose(pose(0))
        broken._thread.join(5)
        outputs.pose(pose(1))
    assert broken.failed == "peer went away"
    assert len((tmp_path / "r1.jsonl").read_text().splitlines()) == 2
    assert "output broken failed" in caplog.text
