"""A replay with frame worker processes (cubetrack.app.track.track_frames with a replay_pool)
gives exactly, bit for bit, what the replay on one thread gives, run after run, while the
workers really do the per-frame work; a worker process that dies ends the replay with one clear
error."""

from __future__ import annotations

import dataclasses
import heapq
import os
import signal

import pytest

from cubetrack.app.config import load_config, recording_intrinsics
from cubetrack.app.track import REPLAY_LAG, replay_pool, track_frames
from cubetrack.core.errors import SourceError
from cubetrack.fuse.fusion import FilterFusion
from cubetrack.io.config import read_extrinsics
from cubetrack.io.recording import Recording
from cubetrack.simulate import SimulationParams, simulate


class Collect:
    def __init__(self):
        self.poses = []

    def pose(self, pose):
        self.poses.append(pose)


@pytest.fixture(scope="module")
def replay(tmp_path_factory):
    """The arguments of track_frames for a short simulated session, frames in memory."""
    rec = tmp_path_factory.mktemp("replay") / "rec"
    simulate(SimulationParams(duration_s=4, cameras=4, fps=15.0, calibration_frames=0, seed=4), rec)
    config, settings = load_config(rec / "config.toml")
    recording = Recording.open(rec)
    frames = list(heapq.merge(*(recording.frames(c) for c in recording.camera_names),
                              key=lambda f: (f.host_time_s, f.camera)))
    return {"frames": frames, "intrinsics": recording_intrinsics(config, recording), "world": config.world,
            "layouts": {r.name: r.layout for r in config.robots},
            "extrinsics": read_extrinsics(rec / "true_extrinsics.toml"), "params": settings.stages,
            "clock": {c: recording.clock_samples(c) for c in recording.camera_names}}


def run(replay, pool=None):
    out = Collect()
    stats = track_frames(replay["frames"], replay["intrinsics"], replay["world"], replay["layouts"],
                         replay["extrinsics"], out, replay["params"], clock_samples=replay["clock"], pool=pool)
    return stats, [(p.robot, p.time_s, p.position_m.tobytes(), p.quaternion_xyzw.tobytes(), p.latency_s,
                    p.cameras, p.markers, p.smoothed, p.smooth_lag_s) for p in out.poses]


def started_pool(replay, workers):
    pool = replay_pool(replay["intrinsics"], replay["world"], replay["layouts"], replay["extrinsics"],
                       replay["params"], workers)
    while not pool.all_started:
        pool.wait(0.5)
        pool.take()
    return pool


def test_worker_processes_replay_bit_for_bit_what_one_thread_replays(replay):
    stats, poses = run(replay)
    assert len(poses) > 50 and stats.region_detections > 0  # the plans (regions) depend on the fusion
    for workers in (1, 2, 3):
        with started_pool(replay, workers) as pool:
            # every frame planned ahead fits in the workers
            assert pool.depth * workers >= REPLAY_LAG
            again, poses_again = run(replay, pool)
            assert pool.submitted > 0.5 * len(replay["frames"])  # the workers did most of the work
        assert poses_again == poses, workers
        assert (again.frames, again.poses, again.region_detections, again.estimates) == \
            (stats.frames, stats.poses, stats.region_detections, stats.estimates)


def test_a_fixed_lag_whose_poses_leave_on_time_replays_the_same_with_workers(replay):
    """With a fixed lag and no margin, most poses leave on time during the replay (before a
    sighting that much newer has come); the release's "now" is the arrival time of the first frame
    not yet fused, not a worker's timing: a worker process gives the same poses, bit for bit."""
    params = replay["params"]
    lagged = {**replay, "params": dataclasses.replace(
        params, filter=dataclasses.replace(params.filter, smooth_lag_s=0.05, smooth_margin_s=0.0))}
    stats, poses = run(lagged)
    on_time = [p for p in poses if p[-1] < 0.05]
    assert len(poses) > 50 and len(on_time) > 0.5 * len(poses)
    with started_pool(lagged, 1) as pool:
        again, poses_again = run(lagged, pool)
        assert pool.submitted > 0.5 * len(replay["frames"])
    assert poses_again == poses and again.poses == stats.poses


def test_the_replay_leaves_start_ups_objects_out_of_its_collections_and_restores_them(replay):
    """track_frames freezes the garbage collector's objects of start-up for the replay (a full
    collection walks ~160,000 of them in a tracker's process) and unfreezes them at its end."""
    import gc

    class Frozen(Collect):
        def pose(self, pose):
            self.poses.append(gc.get_freeze_count())

    assert gc.get_freeze_count() == 0
    out = Frozen()
    track_frames(replay["frames"], replay["intrinsics"], replay["world"], replay["layouts"], replay["extrinsics"],
                 out, replay["params"], clock_samples=replay["clock"])
    assert out.poses and min(out.poses) > 1000 and gc.get_freeze_count() == 0


class SlowPool:
    """A pool of one worker slot whose job is done only when the replay waits for it (a worker
    far slower than the replay's thread); it keeps the jobs it got."""

    def __init__(self, worker):
        self.worker, self.jobs, self.busy, self.ready = worker, [], None, []

    def idle(self):
        return int(self.busy is None)

    def submit(self, job):
        self.jobs.append(job)
        self.busy = job

    def poll(self):
        pass

    def reclaim(self, job):
        return False  # the worker started it

    def reclaim_newest(self):
        return None  # it holds one job, started

    def wait(self, timeout_s):
        self.ready.append(self.worker.work(self.busy))
        self.busy = None

    def take(self):
        out, self.ready = self.ready, []
        return out


def test_the_replay_does_the_oldest_jobs_itself_rather_than_wait_for_a_slow_worker(replay):
    from cubetrack.app.tracker import FrameProcessor
    from cubetrack.io.config import RobotConfig

    stats, poses = run(replay)
    robots = tuple(RobotConfig(name, layout) for name, layout in replay["layouts"].items())
    worker = FrameProcessor(replay["intrinsics"], replay["world"], robots,
                         {name: e.T_world_cam for name, e in replay["extrinsics"].items()}, replay["params"])
    pool = SlowPool(worker)
    again, poses_again = run(replay, pool)
    assert poses_again == poses and again.region_detections == stats.region_detections
    # the slot took the newest planned job each time it was free; this thread did the REPLAY_LAG - 1
    # jobs planned after it before waiting for it (deterministic here: no timing involved), so the
    # worker got about one job in REPLAY_LAG
    jobs, frames = len(pool.jobs), len(replay["frames"])
    assert 0.8 * frames / REPLAY_LAG < jobs < 1.2 * frames / REPLAY_LAG, (jobs, frames)
    assert pool.busy is None and pool.take() == []  # every result the worker made was fused


def test_a_worker_process_that_dies_ends_the_replay_with_one_clear_error(replay):
    with started_pool(replay, 2) as pool:
        os.kill(pool.process_ids[0], signal.SIGKILL)
        with pytest.raises(SourceError, match="frame worker process ended unexpectedly"):
            run(replay, pool)


@pytest.mark.parametrize(("cores", "idle", "busy", "workers"), [
    (2, 200, 0, 1),  # both cores idle: one worker beside the replay's thread
    (2, 90, 110, 0),  # another job keeps a core busy: none (a worker would slow the replay)
    (2, 160, 40, 1),
    (4, 400, 0, 3),
    (4, 200, 200, 1),
    (1, 100, 0, 0),
    (2, None, None, 1),  # no /proc/stat: every core counts as idle
])
def test_a_replay_takes_a_worker_per_idle_core_beyond_the_first(monkeypatch, cores, idle, busy, workers):
    from cubetrack.app import track

    samples = iter([(1000, 5000), None if idle is None else (1000 + idle, 5000 + busy)])
    monkeypatch.setattr(track.os, "cpu_count", lambda: cores)
    monkeypatch.setattr(track, "_cpu_idle_busy", lambda: next(samples))
    assert track.replay_workers(sample_s=0.0) == workers


def test_frames_that_arrive_out_of_capture_order_within_the_replay_window_are_fused_in_capture_order(
        replay, monkeypatch):
    """Pairs of frames of two cameras handed over in the reverse of their capture order (their
    arrival times swapped, no clock round trip between them) reach the fusion in capture order:
    each is fused as the robot's newest (and gives its pose), not folded in late."""
    import dataclasses
    import statistics

    offset_s = {c: statistics.median((s.host_send_s + s.host_recv_s) / 2 - s.device_time_s for s in samples)
                for c, samples in replay["clock"].items()}  # each camera's clock onto the host's

    def captured_s(frame):
        return frame.device_time_s + offset_s[frame.camera]

    frames = list(replay["frames"])
    trips = sorted(s.host_recv_s for samples in replay["clock"].values() for s in samples)
    swapped, i = 0, 0
    while i + 1 < len(frames):
        a, b = frames[i], frames[i + 1]
        quiet = not any(a.host_time_s <= t <= b.host_time_s for t in trips)
        if a.camera != b.camera and quiet and captured_s(a) < captured_s(b) - 0.01:
            frames[i] = dataclasses.replace(b, host_time_s=a.host_time_s)
            frames[i + 1] = dataclasses.replace(a, host_time_s=b.host_time_s)
            swapped += 1
            i += 2
        else:
            i += 1
    assert swapped > 20
    late = []
    add = FilterFusion.add

    def counting_add(fusion, sighting, now_s):
        keys = fusion._keys[sighting.robot]
        late.append(bool(keys) and sighting.capture_time_s < keys[-1][0])
        return add(fusion, sighting, now_s)

    monkeypatch.setattr(FilterFusion, "add", counting_add)
    run(replay)
    late_in_order, late[:] = sum(late), []
    run(dict(replay, frames=frames))
    # (a few pairs also were out of order already, so the swap moves one frame beyond the window)
    assert sum(late) - late_in_order <= swapped // 10
