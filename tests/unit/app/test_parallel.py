"""The frame pool of live tracking and replays: worker processes (one or several jobs queued
each) and threads give what the tracker's own frame worker gives, frame by frame; a corrupt
JPEG is a counted outcome, a worker process that dies ends the session with one clear error."""

from __future__ import annotations

import functools
import os
import signal
import threading
import time

import pytest
import test_tracker
from test_tracker import BLUE, INTRINSICS, RED, T_WORLD_CAM, WORLD

from cubetrack.app.tracker import FrameProcessor, StageParams
from cubetrack.core.errors import SourceError
from cubetrack.core.frame_pool import CAMERA_PROCESSES_FROM, FramePool, LiveParams, WorkerKind
from cubetrack.core.records import Frame, FrameJob, FrameOutcome

scenes = test_tracker.scenes  # the rendered frames of the tracker's tests (a fixture)
MAKE_WORKER = functools.partial(FrameProcessor, INTRINSICS, WORLD, (RED, BLUE), T_WORLD_CAM, StageParams())


def jobs(scenes) -> list[FrameJob]:
    out = []
    for k, cam in enumerate(sorted(T_WORLD_CAM)):
        jpeg = scenes["both"][cam]
        out.append(FrameJob(Frame(cam, k, 1.0, 2.0, jpeg), 3.0 + k, None, frozenset({"red", "blue"})))
        out.append(FrameJob(Frame(cam, 10 + k, 1.0, 2.0, jpeg), 4.0 + k, ((0, 0, 320, 240),), frozenset()))
    out.append(FrameJob(Frame("cam1", 99, 1.0, 2.0, b"\xff\xd8 not a jpeg \xff\xd9"), 9.0, None, frozenset()))
    return out


def run_pool(pool: FramePool, wake: threading.Event, todo: list[FrameJob], timeout_s: float = 120.0):
    results, todo = [], list(todo)
    deadline = time.monotonic() + timeout_s
    while (todo or pool.busy()) and time.monotonic() < deadline:
        while todo and pool.idle():
            pool.submit(todo.pop(0))
        wake.wait(0.5)
        wake.clear()
        results += pool.take()
    assert not todo and not pool.busy(), "the pool did not finish"
    return results


def summary(result):
    return (result.outcome, [(s.robot, s.estimate is not None, [(d.marker_id, d.corners_px.tolist())
                                                                 for d in s.detections]) for s in result.sightings])


@pytest.mark.parametrize(("kind", "depth"), [(WorkerKind.THREAD, 1), (WorkerKind.PROCESS, 1), (WorkerKind.PROCESS, 3)])
def test_the_pool_gives_what_the_trackers_worker_gives(scenes, kind, depth):
    todo = jobs(scenes)
    expected = {(j.frame.camera, j.frame.seq): summary(MAKE_WORKER().work(j)) for j in todo}
    wake = threading.Event()
    with FramePool(MAKE_WORKER, 2, kind, wake.set, depth=depth) as pool:
        results = run_pool(pool, wake, todo)
        assert pool.submitted == len(todo) and pool.started % depth == 0
    assert len(results) == len(todo)
    for r in results:
        assert summary(r) == expected[(r.job.frame.camera, r.job.frame.seq)]
        assert r.job.frame.jpeg  # the job comes back whole, JPEG included
    outcomes = {r.outcome for r in results}
    assert {FrameOutcome.FULL_FRAME, FrameOutcome.REGIONS, FrameOutcome.CORRUPT} <= outcomes
    assert any(s.estimate is not None for r in results for s in r.sightings)


def test_a_worker_process_that_dies_ends_the_session_with_one_clear_error(scenes):
    wake = threading.Event()
    with FramePool(MAKE_WORKER, 1, WorkerKind.PROCESS, wake.set) as pool:
        run_pool(pool, wake, jobs(scenes)[:1])
        os.kill(pool._lanes[0].process.pid, signal.SIGKILL)
        deadline = time.monotonic() + 30
        with pytest.raises(SourceError, match="frame worker process ended unexpectedly"):
            while time.monotonic() < deadline:
                pool.take()
                time.sleep(0.05)


def test_live_params_default_to_one_worker_per_core():
    assert LiveParams().worker_count == (os.cpu_count() or 1)
    assert LiveParams().worker_kind is WorkerKind.AUTO
    assert LiveParams(workers=3).worker_count == 3
    with pytest.raises(Exception, match="workers"):
        LiveParams(workers=-1)


def test_auto_takes_camera_processes_for_many_cameras_unless_recording_or_on_one_core():
    auto = LiveParams(workers=2)
    assert auto.kind_for(CAMERA_PROCESSES_FROM, recording=False) is WorkerKind.CAMERA_PROCESS
    assert auto.kind_for(CAMERA_PROCESSES_FROM - 1, recording=False) is WorkerKind.THREAD
    assert auto.kind_for(16, recording=True) is WorkerKind.THREAD  # the tracker's process writes the recording
    assert LiveParams(workers=1).kind_for(16, recording=False) is WorkerKind.THREAD
    chosen = LiveParams(worker_kind=WorkerKind.PROCESS)
    assert chosen.kind_for(16, recording=False) is WorkerKind.PROCESS
    assert LiveParams(worker_kind=WorkerKind.CAMERA_PROCESS).kind_for(3, recording=True) is WorkerKind.THREAD


def test_a_job_comes_back_whole_as_plain_values():
    """FrameJob.plain (a job between the processes of one tracker) pickles into plain values that
    FrameJob.from_plain turns back into the same job; without the JPEG or the predicted markers when
    asked to leave them out (a camera worker's result: the fusion needs neither)."""
    import pickle

    import numpy as np

    from cubetrack.core.records import Detection

    corners = np.array([[10.0, 20.0], [30.5, 20.0], [30.5, 40.25], [10.0, 40.25]])
    job = FrameJob(Frame("cam2", 7, 1.5, 2.5, b"\xff\xd8jpeg\xff\xd9"), 2.25, ((0, 8, 320, 240), (1, 2, 30, 40)),
                   frozenset({"red", "blue"}), (Detection(3, corners, 420.5, "DICT_4X4_50"),))

    def fields(j: FrameJob) -> tuple:
        f = j.frame
        return ((f.camera, f.seq, f.device_time_s, f.host_time_s, f.jpeg), j.capture_time_s, j.regions,
                j.estimate_robots,
                [(d.marker_id, d.corners_px.tobytes(), d.area_px2, d.dictionary) for d in j.predicted])

    back = FrameJob.from_plain(pickle.loads(pickle.dumps(job.plain())))
    assert fields(back) == fields(job)
    bare = FrameJob.from_plain(pickle.loads(pickle.dumps(job.plain(jpeg=False, predicted=False))))
    assert fields(bare) == ((("cam2", 7, 1.5, 2.5, b""),) + fields(job)[1:4] + ([],))


def test_a_packed_result_comes_back_whole_through_pickle(scenes):
    """What a worker process sends (cubetrack.io.frame_wire.pack_result) is unpacked into the result it made: every
    detection's id, corners, area and dictionary, the estimate, the error; the camera pose and
    intrinsics are the unpacking side's own (calibrated) or the frame's (world-marker mode)."""
    import dataclasses
    import pickle

    from cubetrack.app.tracker import CameraPoseSource, TrackParams
    from cubetrack.io.frame_wire import pack_result, unpack_result

    uncalibrated = dataclasses.replace(StageParams(), track=TrackParams(camera_poses=CameraPoseSource.WORLD_MARKER))
    for params in (StageParams(), uncalibrated):
        sender = FrameProcessor(INTRINSICS, WORLD, (RED, BLUE), T_WORLD_CAM, params)
        receiver = FrameProcessor(INTRINSICS, WORLD, (RED, BLUE), T_WORLD_CAM, params)
        sightings = 0
        for job in jobs(scenes):
            result = sender.work(job)
            packed = pickle.loads(pickle.dumps(pack_result(result, sender.T_world_cam)))
            back = unpack_result(job, packed, receiver.intrinsics, receiver.T_world_cam)
            assert (back.job, back.outcome, back.error) == (job, result.outcome, result.error)
            assert len(back.sightings) == len(result.sightings)
            for a, b in zip(back.sightings, result.sightings, strict=True):
                assert (a.camera, a.robot, a.seq, a.capture_time_s, a.arrival_time_s) == \
                    (b.camera, b.robot, b.seq, b.capture_time_s, b.arrival_time_s)
                assert [(d.marker_id, d.corners_px.tobytes(), d.area_px2, d.dictionary) for d in a.detections] == \
                    [(d.marker_id, d.corners_px.tobytes(), d.area_px2, d.dictionary) for d in b.detections]
                assert (a.estimate is None) == (b.estimate is None)
                if a.estimate is not None:
                    assert a.estimate.T_world_cube.tobytes() == b.estimate.T_world_cube.tobytes()
                assert a.T_world_cam.tobytes() == b.T_world_cam.tobytes()
                assert a.intrinsics is receiver.intrinsics[a.camera]
                if params is uncalibrated:
                    assert a.T_world_cam is not receiver.T_world_cam.get(a.camera)
                else:
                    assert a.T_world_cam is receiver.T_world_cam[a.camera]
                sightings += 1
        assert sightings >= 4
    assert back.outcome is FrameOutcome.CORRUPT and back.error  # the last job: the corrupt JPEG


def test_the_newest_job_its_worker_has_not_started_is_taken_back(scenes):
    """FramePool.reclaim_newest: the job handed out last that the worker process has not started
    comes back, then the one before it; none once the newest left is the one it started."""
    todo = jobs(scenes)[:4]
    with FramePool(MAKE_WORKER, 1, WorkerKind.PROCESS, depth=4) as pool:
        while not pool.all_started:
            pool.wait(0.5)
        assert pool.reclaim_newest() is None  # nothing handed out
        os.kill(pool.process_ids[0], signal.SIGSTOP)  # the worker cannot start anything now
        try:
            for job in todo:
                pool.submit(job)
            assert pool.reclaim(todo[2])
            assert pool.reclaim_newest() is todo[3] and pool.reclaim_newest() is todo[1]  # todo[2] taken back already
        finally:
            os.kill(pool.process_ids[0], signal.SIGCONT)
        deadline = time.monotonic() + 60
        while pool.busy() and time.monotonic() < deadline:
            pool.wait(0.5)
        assert [r.job for r in pool.take()] == [todo[0]] and pool.idle() == 4
        assert pool.reclaim_newest() is None


def test_a_job_its_worker_has_not_started_is_taken_back(scenes):
    """FramePool.reclaim: jobs queued at a worker process that has not started them come back
    (the worker answers None and frees their slots; no result comes); a job it started or
    finished does not."""
    todo = jobs(scenes)[:3]
    with FramePool(MAKE_WORKER, 1, WorkerKind.PROCESS, depth=3) as pool:
        while not pool.all_started:
            pool.wait(0.5)
        first = todo[0]
        pool.submit(first)
        while pool.busy():
            pool.wait(0.5)
        assert [r.job for r in pool.take()] == [first] and not pool.reclaim(first)  # done already
        os.kill(pool.process_ids[0], signal.SIGSTOP)  # the worker cannot start anything now
        try:
            for job in todo[1:]:
                pool.submit(job)
            assert pool.idle() == 1
            assert pool.reclaim(todo[2]) and pool.reclaim(todo[1]) and not pool.reclaim(todo[1])
        finally:
            os.kill(pool.process_ids[0], signal.SIGCONT)
        deadline = time.monotonic() + 60
        while pool.busy() and time.monotonic() < deadline:
            pool.wait(0.5)
        assert pool.idle() == 3 and pool.take() == []  # both slots free again, no result for either
        pool.submit(todo[1])  # the worker goes on with new jobs
        while pool.busy() and time.monotonic() < deadline:
            pool.wait(0.5)
        assert [r.job for r in pool.take()] == [todo[1]]
