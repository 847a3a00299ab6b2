"""Camera worker processes' results on their way to the fusion: held back while an older frame
is in work, so that the fusion gets them in capture order; the fusion's forecasts on their way back,
posted to shared memory (cubetrack.app.camera_workers)."""

import math
import multiprocessing
import pickle

import numpy as np

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
