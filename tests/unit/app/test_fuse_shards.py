"""A fleet's fusion split by robot (issue 28): a worker publishes a frame per robot it holds markers
of (cubetrack.app.worker.body_messages), and a fusion with ``robots`` (a shard) receives, decodes and
fuses only its robots' share, through real loopback Zenoh sessions, with the poses a single process
makes of the same sightings. The sightings are benchmarks/fleet.py's simulated fleet."""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest

from cubetrack.app.config import load_config
from cubetrack.app.fusion_service import frame_result, run_fusion
from cubetrack.app.live import live_intrinsics
from cubetrack.app.tracker import Tracker
from cubetrack.app.worker import body_messages, fuse_endpoints, worker_endpoints
from cubetrack.core.errors import ConfigError
from cubetrack.core.records import CubeSighting, Detection, Frame, FrameJob, FrameOutcome, FrameResult
from cubetrack.io.config import read_extrinsics
from cubetrack.io.sighting_wire import SightingMessage, decode_sighting, encode_sighting
from cubetrack.io.worker_bus import sighting_key
from cubetrack.sink.zenoh_session import open_session
from cubetrack.source.clock import ClockSync
from cubetrack.source.streams import CameraStats
from tests.helpers.benchmarks import load_benchmark


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_frame_is_published_once_per_robot_with_that_robots_detections():
    frame = Frame("cam1", 4, 10.0, 11.0, b"")
    job = FrameJob(frame, 10.5, None, frozenset())
    a, b = (Detection(i, np.zeros((4, 2)), 1.0, "DICT_4X4_50") for i in (1, 7))
    sightings = tuple(CubeSighting("cam1", robot, 4, 10.5, 11.0, (d,), None, np.eye(4), None)
                      for robot, d in (("r1", a), ("r2", b)))
    result = FrameResult(job, FrameOutcome.FULL_FRAME, sightings, dropped={"too small": 2})
    clock, stats = ClockSync(), CameraStats(connected=True)
    split = body_messages(result, clock, stats, False)
    assert [(m.body, [d.marker_id for d in m.detections], dict(m.dropped)) for m in split] == [
        ("r1", [1], {"too small": 2}), ("r2", [7], {})]  # the frame's drops counted once
    empty = body_messages(FrameResult(job, FrameOutcome.FULL_FRAME, (), dropped={"x": 1}), clock, stats, False)
    assert [(m.body, m.detections, dict(m.dropped)) for m in empty] == [(None, (), {"x": 1})]


@pytest.fixture(scope="module")
def fleet_messages(tmp_path_factory):
    """A 2-robot, 4-camera fleet (one cell) and 1.5 s of its frames at 10 fps, as (robot or None,
    encoded message) in capture order (so that any batching of them is fused in that order)."""
    fleet_bench = load_benchmark("fleet")
    fleet = fleet_bench.Fleet(2, 4, 10.0, 3, 0.3, 0.0)
    config, extrinsics = fleet_bench.write_fleet(fleet, tmp_path_factory.mktemp("fleet"))
    cameras = fleet_bench.cameras_of(fleet, 0, 1)
    out: list[tuple[str | None, bytes]] = []
    for seq in range(15):
        for camera in cameras:
            t_s = 1.7e9 + (seq + camera.phase) / fleet.fps
            found = fleet_bench.frame_detections(fleet, camera.markers, camera.T_cam_world, t_s, camera.rng)
            for body, dets in found.items() or [(None, ())]:
                out.append((body, encode_sighting(SightingMessage(camera.name, seq, t_s, t_s, t_s + 0.05,
                                                                  "full frame", dets, body=body))))
    assert {b for b, _ in out} >= {"r1", "r2"}
    return config, extrinsics, sorted(out, key=lambda m: decode_sighting(m[1]).capture_time_s)


def single_process(config_path, extrinsics_path, messages) -> dict[str, list]:
    config, settings = load_config(config_path)
    tracker = Tracker(live_intrinsics(config), config.world, config.robots, read_extrinsics(extrinsics_path),
                      settings.stages)
    poses: dict[str, list] = {}
    for _, data in messages:
        m = decode_sighting(data)
        for p in tracker.fuse(frame_result(tracker, m), m.arrival_time_s):
            poses.setdefault(p.robot, []).append((p.time_s, p.position_m))
    return poses


def test_shards_fuse_only_their_robots_and_make_the_single_process_poses(fleet_messages, tmp_path):
    config_path, extrinsics_path, messages = fleet_messages
    config, settings = load_config(config_path)
    extrinsics = read_extrinsics(extrinsics_path)
    ports, stop, results = [free_port(), free_port()], threading.Event(), {}
    shards = [threading.Thread(target=lambda i=i, robot=robot: results.setdefault(i, run_fusion(
        config, extrinsics, tmp_path / f"shard{i}", fuse_endpoints(
            listen=(f"tcp/127.0.0.1:{ports[i]}",), connect=tuple(f"tcp/127.0.0.1:{p}" for p in ports[:i])),
        settings.stages, stop=stop, robots=[robot]))) for i, robot in enumerate(("r1", "r2"))]
    for shard in shards:
        shard.start()
    bus = open_session(worker_endpoints(connect=tuple(f"tcp/127.0.0.1:{p}" for p in ports)), "test")
    try:
        keys = {(decode_sighting(d).camera, b) for b, d in messages}
        publishers = {key: bus.declare_publisher(sighting_key(*key)) for key in keys}
        deadline = time.monotonic() + 60  # until each robot's publishers reach its shard's subscriber
        while not all(p.matching_status.matching for (_, body), p in publishers.items() if body is not None):
            assert time.monotonic() < deadline, "the shards' subscriptions did not reach the publisher"
            time.sleep(0.05)
        for body, data in messages:
            publishers[(decode_sighting(data).camera, body)].put(data)
        expected = single_process(config_path, extrinsics_path, messages)
        deadline = time.monotonic() + 60
        while not all(len(lines(tmp_path / f"shard{i}" / f"{r}.jsonl")) >= len(expected[r])
                      for i, r in enumerate(("r1", "r2"))):
            assert time.monotonic() < deadline, "the shards did not fuse every sighting"
            time.sleep(0.05)
    finally:
        stop.set()
        for shard in shards:
            shard.join(60)
        bus.close()
    for i, robot in enumerate(("r1", "r2")):
        other = "r2" if robot == "r1" else "r1"
        mine = sum(1 for b, _ in messages if b == robot)
        assert results[i].received == sum(results[i].heard.values()) == mine  # nothing of the other robot's
        assert results[i].bad_messages == 0
        assert dict(results[i].stats.poses) == {robot: len(expected[robot])}
        assert not (tmp_path / f"shard{i}" / f"{other}.jsonl").exists()  # its outputs are its robot's only
        got = lines(tmp_path / f"shard{i}" / f"{robot}.jsonl")
        assert [p["time"] for p in got] == pytest.approx([t for t, _ in expected[robot]], abs=1e-6)
        np.testing.assert_allclose([p["position"] for p in got], [x for _, x in expected[robot]], atol=1e-6)
        assert [(robot, True)] == [(r, taken) for _, r, taken in results[i].claims[:1]]


def lines(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def test_an_unknown_robot_is_one_clear_line(fleet_messages, tmp_path):
    config_path, extrinsics_path, _ = fleet_messages
    config, settings = load_config(config_path)
    with pytest.raises(ConfigError, match="no robot r9"):
        run_fusion(config, read_extrinsics(extrinsics_path), tmp_path, fuse_endpoints(), settings.stages,
                   robots=["r9"])
