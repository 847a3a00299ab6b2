"""`cubetrack fuse` (cubetrack.app.fusion_service.run_fusion) on the session runtime: with
[fusion] output_rate_hz it outputs each tracked robot's pose predicted to now at that rate, as
`track --live` does, through the same code (cubetrack.app.session.PoseStream).

A short simulated recording is worked frame by frame as a `cubetrack worker` works it (the same
sighting messages, encoded for the wire) and published on a real loopback Zenoh session at the
recording's pace; the fusion runs on a clock that follows the recording's host clock, so its
predictions fall between the recorded frames and can be checked against the ground truth."""

from __future__ import annotations

import dataclasses
import json
import math
import socket
import threading
import time

import numpy as np
import pytest

from cubetrack.app.config import load_config
from cubetrack.app.fusion_service import run_fusion
from cubetrack.app.live import live_intrinsics
from cubetrack.app.session import PoseStream
from cubetrack.app.tracker import Tracker
from cubetrack.app.worker import fuse_endpoints, sighting_message, worker_endpoints
from cubetrack.fuse.forecast import NO_FORECAST
from cubetrack.io.config import read_extrinsics
from cubetrack.io.recording import Recording
from cubetrack.io.sighting_wire import encode_sighting
from cubetrack.io.trajectory import read_tum
from cubetrack.io.worker_bus import sighting_key
from cubetrack.source.streams import CameraStats
from tests.helpers.scene import simulated_recording

RATE_HZ = 20.0
SPEED = 2.0  # the recording is published at twice its pace


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def worker_messages(config, params, extrinsics, rec: Recording) -> list[tuple[float, str, bytes]]:
    """(arrival time, camera, encoded sighting) of every frame, as a worker with its own clock
    fits publishes them (round trips taken as they completed between the frames)."""
    tracker = Tracker(live_intrinsics(config), config.world, config.robots, extrinsics, params,
                      synced_cameras=frozenset(rec.camera_names))
    trips = sorted((s.host_recv_s, c, s) for c in rec.camera_names for s in rec.clock_samples(c))
    out, k = [], 0
    for frame in rec.merged_frames():
        while k < len(trips) and trips[k][0] <= frame.host_time_s:
            tracker.add_clock_sample(trips[k][1], trips[k][2])
            k += 1
        job = tracker.admit(frame, hold=False, forecast=NO_FORECAST)
        if job is not None:
            result = tracker.processor.work(job)
            message = sighting_message(result, tracker.clocks[frame.camera], CameraStats(connected=True), False)
            out.append((frame.host_time_s, frame.camera, encode_sighting(message)))
    return out


@pytest.fixture(scope="module")
def fused(tmp_path_factory):
    """The fusion's output folder after the recording's sightings were published to it."""
    from cubetrack.sink.zenoh_session import open_session

    work = tmp_path_factory.mktemp("fuse_predicted")
    rec_dir = simulated_recording(work / "rec", 4.0, seed=5)
    config, settings = load_config(rec_dir / "config.toml")
    params = dataclasses.replace(settings.stages, fusion=dataclasses.replace(settings.stages.fusion,
                                                                              output_rate_hz=RATE_HZ))
    extrinsics = read_extrinsics(rec_dir / "true_extrinsics.toml")
    messages = worker_messages(config, params, extrinsics, Recording.open(rec_dir))
    start_s, started = messages[0][0] - 0.5, [math.inf]  # the clock stands still until publishing starts

    def clock() -> float:  # the recording's host clock, run at SPEED
        return start_s + max(0.0, time.monotonic() - started[0]) * SPEED

    port, stop, result = free_port(), threading.Event(), []
    fusion = threading.Thread(target=lambda: result.append(run_fusion(
        config, extrinsics, work / "out", fuse_endpoints(listen=(f"tcp/127.0.0.1:{port}",)), params, stop=stop,
        clock=clock)))
    fusion.start()
    peer = open_session(worker_endpoints(connect=(f"tcp/127.0.0.1:{port}",)), "test")
    try:
        publishers = {c: peer.declare_publisher(sighting_key(c)) for c in Recording.open(rec_dir).camera_names}
        deadline = time.monotonic() + 30
        while not list(peer.info.peers_zid()) and time.monotonic() < deadline:  # until the fusion is there
            time.sleep(0.05)
        time.sleep(1.0)  # and its subscription has reached this peer
        started[0] = time.monotonic()
        for arrival_s, camera, data in messages:
            time.sleep(max(0.0, (arrival_s - clock()) / SPEED))
            publishers[camera].put(data)
        time.sleep(1.0)
    finally:
        stop.set()
        fusion.join(30)
        peer.close()
    assert result, "the fusion did not end"
    return work, rec_dir, result[0], len(messages)


def test_the_fusion_outputs_predicted_poses_at_the_output_rate(fused):
    work, rec_dir, result, published = fused
    lines = [json.loads(line) for line in (work / "out" / "robot.jsonl").read_text().splitlines()]
    predicted = [p for p in lines if p.get("predicted")]
    measured = [p for p in lines if not p.get("predicted")]
    assert sum(result.heard.values()) == published and result.bad_messages == 0
    assert len(measured) > 20 and result.stats.poses["robot"] == len(measured)  # predictions are not counted
    times = np.array([p["time"] for p in predicted])
    span_s = measured[-1]["time"] - measured[0]["time"]
    # about RATE_HZ of them over the tracked span (the fusion's clock runs on while it waits for the last)
    assert RATE_HZ * span_s * 0.5 < len(times) < RATE_HZ * (span_s + 30 * SPEED)
    assert np.all(np.diff(np.floor((times + 1e-6) * RATE_HZ)) >= 1)  # one per tick of the rate's grid at most
    assert all(p["latency"] == 0.0 for p in predicted)
    # each prediction made while the robot was tracked lies on the true path (it moves at 0.25 m/s)
    truth = read_tum(rec_dir / "ground_truth.tum")
    inside = times[(times > measured[0]["time"]) & (times < measured[-1]["time"])]
    assert len(inside) > RATE_HZ * span_s * 0.5
    positions = np.array([p["position"] for p in predicted])[(times > measured[0]["time"])
                                                             & (times < measured[-1]["time"])]
    true_positions = np.stack([np.interp(inside, truth.times_s, truth.positions_m[:, k]) for k in range(3)], axis=1)
    errors_m = np.linalg.norm(positions - true_positions, axis=1)
    assert np.median(errors_m) < 0.02 and errors_m.max() < 0.1


def test_the_fusion_predicts_through_the_same_pose_stream_as_track_live(monkeypatch, fused):
    """The predicted poses come from PoseStream.predict: with it switched off, none come."""
    work, rec_dir, _, _ = fused
    calls = []
    stop = threading.Event()

    def predict(self):   # switched off: records the call, predicts nothing; the run ends after a few calls
        calls.append(self)
        if len(calls) >= 3:
            stop.set()

    monkeypatch.setattr(PoseStream, "predict", predict)
    config, settings = load_config(rec_dir / "config.toml")
    params = dataclasses.replace(settings.stages, fusion=dataclasses.replace(settings.stages.fusion,
                                                                              output_rate_hz=RATE_HZ))
    timer = threading.Timer(30.0, stop.set)   # a ceiling for a loaded machine (the service's start-up)
    timer.start()
    run_fusion(config, read_extrinsics(rec_dir / "true_extrinsics.toml"), work / "again",
               fuse_endpoints(listen=(f"tcp/127.0.0.1:{free_port()}",)), params, stop=stop)
    timer.join()
    assert calls and all(isinstance(s, PoseStream) for s in calls)
    assert not [line for line in (work / "again" / "robot.jsonl").read_text().splitlines() if "predicted" in line]
