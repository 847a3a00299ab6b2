"""Camera worker processes' results on their way to the fusion: held back while an older frame
is in work, so that the fusion gets them in capture order; the fusion's forecasts on their way back,
posted to shared memory (cubetrack.app.camera_workers)."""

import math
import multiprocessing
import pickle
import threading
import time
import types

import numpy as np

from cubetrack.app import camera_workers
from cubetrack.app.camera_workers import IN_FLIGHT, WAKE, CameraProcesses, HeldResults
from cubetrack.core.pipes import LatestBytes, PipePoll
from cubetrack.core.records import Frame, FrameJob, FrameOutcome, FrameResult
from cubetrack.fuse.forecast import Forecast


def result(capture_time_s, camera="cam1"):
    frame = Frame(camera, 0, capture_time_s, capture_time_s + 0.01, b"")
    return FrameResult(FrameJob(frame, capture_time_s, None, frozenset()), FrameOutcome.FULL_FRAME, ())


def times(results):
    return [r.job.capture_time_s for r in results]


def test_results_older_than_every_frame_in_work_go_at_once_oldest_first():
    held = HeldResults(hold_s=0.004)
    assert times(held.due([result(2.0), result(1.0)], math.inf, now=10.0)) == [1.0, 2.0]
    assert times(held.due([result(3.0)], 3.5, now=10.0)) == [3.0]
    assert len(held) == 0 and held.wait_s(10.0) == math.inf


def test_a_result_newer_than_a_frame_in_work_waits_for_its_result():
    held = HeldResults(hold_s=0.004)
    assert held.due([result(1.02, "cam2")], 1.01, now=10.0) == []  # cam1's frame of 1.01 is in work
    assert len(held) == 1 and math.isclose(held.wait_s(10.001), 0.003)
    # cam1's result comes; the next frame in work is newer than both: both go, in capture order
    assert times(held.due([result(1.01)], 1.05, now=10.002)) == [1.01, 1.02]
    assert len(held) == 0


def test_only_the_results_older_than_the_frame_in_work_go():
    held = HeldResults(hold_s=0.004)
    assert times(held.due([result(1.0), result(1.03), result(1.02)], 1.025, now=10.0)) == [1.0, 1.02]
    assert times(held.due([], math.inf, now=10.001)) == [1.03]  # the frame in work is done


def test_a_held_result_waits_hold_s_at_most():
    held = HeldResults(hold_s=0.004)
    assert held.due([result(1.02)], 1.01, now=10.0) == []
    assert held.due([result(1.03)], 1.01, now=10.0039) == []
    assert held.wait_s(10.0039) > 0
    assert times(held.due([], 1.01, now=10.004)) == [1.02, 1.03]  # the first waited long enough: all go
    assert held.wait_s(10.004) == math.inf


def test_everything_goes_when_no_worker_process_is_left():
    held = HeldResults(hold_s=0.004)
    assert held.due([result(1.02)], 1.01, now=10.0) == []
    assert times(held.due([], 1.01, now=10.0, everything=True)) == [1.02]


def forecasting_end(capacity=65536):
    """CameraProcesses' forecasting end over one pipe, without processes: (it, the pipe's far end)."""
    context = multiprocessing.get_context("spawn")
    near, far = context.Pipe()
    end = CameraProcesses.__new__(CameraProcesses)
    end._forecasts, end._open, end._taken, end._told = LatestBytes(context, capacity), PipePoll({near: 0}), [0], [0]
    return end, far


def test_a_forecast_is_posted_to_shared_memory_and_no_worker_process_is_woken_for_it():
    end, far = forecasting_end()
    forecast = Forecast({"robot": (1.0, np.eye(4), np.ones(3), np.zeros(3))}, frozenset({"robot"}))
    end.forecast(forecast)
    assert not far.poll(0.05)  # nothing down the pipe: a worker process waiting for frames sleeps on
    version, message = end._forecasts.newer(0)
    assert version == 1 and Forecast.from_plain(pickle.loads(message)).motions["robot"][0] == 1.0
    end._taken[0] = IN_FLIGHT  # a worker process may be waiting for its results to be taken: woken
    end.forecast(None)
    assert far.poll(0.05) and far.recv() == WAKE


def test_a_forecast_too_large_to_post_goes_down_the_pipes():
    end, far = forecasting_end(capacity=16)
    end.forecast(Forecast({"robot": (1.0, np.eye(4), np.ones(3), np.zeros(3))}, frozenset()))
    assert end._forecasts.newer(0) == (0, None)
    assert Forecast.from_plain(far.recv()).motions["robot"][0] == 1.0


class ScriptedCameras:
    """LiveCameras as work_cameras uses it, without sockets: each get() returns the next of the
    frames released so far; ``batches`` are released one per sleep of the loop (``log`` says when)."""

    def __init__(self, log, batches):
        self.log, self.batches, self.waiting = log, list(batches), []

    def __call__(self, urls, source, clock, thread):
        return self

    def start(self):
        return self

    def wake_on(self, conn):
        pass

    def get(self, timeout_s, frames=True, newest_if_behind=False):
        self.log.append("get" if timeout_s == 0 else "wait")  # wait: until a frame comes (here: none)
        return self.waiting.pop(0) if self.waiting else None

    def slept(self):
        self.log.append("sleep")
        if self.batches:
            self.waiting += self.batches.pop(0)

    def stop(self):
        pass

    def stats(self):
        return {}


class ScriptedTracker:
    """The parts of a Tracker that work_cameras calls: every frame admitted and worked (``log``)."""

    robots = ()
    T_world_cam: dict = {}

    def __init__(self, log):
        self.log, self.stats = log, types.SimpleNamespace(frames=0, frames_before_clock_sync=0)
        self.processor = types.SimpleNamespace(work=self.work)

    def admit(self, frame, hold, forecast):
        return FrameJob(frame, frame.device_time_s, None, frozenset())

    def work(self, job):
        self.log.append(f"work {job.frame.seq}")
        return FrameResult(job, FrameOutcome.FULL_FRAME, ())

    def count(self, result):
        pass


def run_worker_loop(monkeypatch, tick_s, batches, stop_after_works):
    """work_cameras over scripted cameras on a thread; the far end of its pipe sends None (stop)
    once ``stop_after_works`` frames were worked (0: once the loop sleeps). The log of gets, sleeps
    and works, and whether the loop ended."""
    log: list[str] = []
    cameras = ScriptedCameras(log, batches)

    class Inbox(PipePoll):  # a sleep of the loop: a wait on its pipe that may last
        def ready(self, timeout_s=0.0):
            if timeout_s is None or timeout_s > 0:
                cameras.slept()
            return super().ready(timeout_s)

    monkeypatch.setattr(camera_workers, "LiveCameras", cameras)
    monkeypatch.setattr(camera_workers, "PipePoll", Inbox)
    monkeypatch.setattr(camera_workers, "pack_result", lambda result, T_world_cam: ())
    near, far = multiprocessing.Pipe()
    loop = threading.Thread(target=camera_workers.work_cameras, daemon=True,
                            args=(far, {}, None, ScriptedTracker(log), False, time.time, [math.inf], [0], 0),
                            kwargs={"tick_s": tick_s})
    loop.start()
    messages: list[tuple] = []
    while len([m for m in messages if m[0] == "result"]) < stop_after_works and near.poll(30.0):
        messages.append(pickle.loads(near.recv_bytes()))
    for _ in range(3000):
        if stop_after_works or "sleep" in log:
            break
        time.sleep(0.01)
    near.send(None)
    loop.join(30.0)
    return log, not loop.is_alive()


def frame(seq):
    return Frame("cam1", seq, 1.0 + seq / 30.0, 1.0 + seq / 30.0, b"")


def test_a_ticking_worker_loop_works_every_frame_that_came_in_one_wake(monkeypatch):
    log, ended = run_worker_loop(monkeypatch, 0.001, [[], [frame(1), frame(2), frame(3)], [frame(4)]], 4)
    works = [k for k, entry in enumerate(log) if entry.startswith("work")]
    assert ended and [log[k] for k in works] == ["work 1", "work 2", "work 3", "work 4"]
    assert "sleep" not in log[works[0]:works[2]]  # the three frames of one sleep: back to back
    assert "sleep" in log[works[2]:works[3]]  # the fourth came in the next sleep
    assert log[:works[0]].count("sleep") == 2  # nothing had come in the first sleep


def test_a_message_ends_a_ticks_sleep(monkeypatch):
    """A stop sent while the loop sleeps out a tick of 60 s ends it within the 30 s the test waits
    (so does the wake for room for results): the loop sleeps on its pipe, not for the tick."""
    log, ended = run_worker_loop(monkeypatch, 60.0, [], 0)
    assert ended and log.count("sleep") == 1
