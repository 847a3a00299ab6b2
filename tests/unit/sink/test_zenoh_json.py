"""The Zenoh JSON output, received by a real Zenoh subscriber session over loopback."""

import json
import math
import queue
import time

import pytest
from sink_helpers import free_port, peer, rejoined, tracked, wait_connected

from cubetrack.core.records import CameraHealth
from cubetrack.sink.base import OutputError
from cubetrack.sink.zenoh_json import ZenohJsonParams, ZenohJsonSink
from cubetrack.sink.zenoh_session import ZenohEndpoints, is_loopback, json_endpoints


def collect(session, keys: str) -> queue.Queue:
    got: queue.Queue = queue.Queue()
    session.declare_subscriber(
        keys, lambda s: got.put((str(s.key_expr), str(s.encoding), json.loads(s.payload.to_bytes()))))
    return got


def drain(got: queue.Queue, until, timeout_s: float = 15.0) -> dict:
    """Samples by key until ``until(samples)`` holds."""
    samples: dict = {}
    deadline = time.monotonic() + timeout_s
    while not until(samples):
        key, encoding, value = got.get(timeout=max(0.01, deadline - time.monotonic()))
        assert encoding.startswith("application/json")
        samples.setdefault(key, []).append(value)
    return samples


class Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self):
        return self.now


def test_a_subscriber_receives_pose_velocity_status_health_and_the_session(session_info):
    locator = f"tcp/127.0.0.1:{free_port()}"
    clock = Clock()
    sink = ZenohJsonSink(ZenohJsonParams(prefix="lab/cubetrack"), json_endpoints(listen=(locator,)), clock=clock)
    consumer = peer(locator)  # connects to the sink's own listener: no router needed
    try:
        got = collect(consumer, "lab/cubetrack/**")
        wait_connected(consumer, sink.zenoh)
        sink.open(session_info)
        for i in range(3):
            sink.pose(tracked("robot 1!", i))
            clock.now += 0.1
        sink.pose(tracked("2nd", 0, velocity=False))
        clock.now += 2.0  # nothing from robot 1 for 2 s: it is lost
        sink.camera_health(CameraHealth("cam b", clock.now, True, 23.5, 100, 2, 0, 1, clock_offset_s=0.25))
        lost = "lab/cubetrack/robots/robot_1/status"
        samples = drain(got, lambda s: any(not st["tracking"] for st in s.get(lost, [])))
        replies = list(consumer.get("lab/cubetrack/session", timeout=5))
        sink.camera_watch(rejoined("cam b", [0.1, 1.2, 1.0]))  # re-calibrated: the session again
        put = drain(got, lambda s: "lab/cubetrack/session" in s)["lab/cubetrack/session"]
        (again,) = list(consumer.get("lab/cubetrack/session", timeout=5))
    finally:
        sink.close()
        consumer.close()
    for doc in (put[-1], json.loads(again.ok.payload.to_bytes())):
        assert [c["position"] for c in doc["cameras"]] == [pytest.approx([1.0, 0.0, 1.0]),
                                                           pytest.approx([0.1, 1.2, 1.0]), None]
    robot = "lab/cubetrack/robots/robot_1"
    poses = samples[f"{robot}/pose"]
    assert [p["time"] for p in poses] == [tracked("robot 1!", i).time_s for i in range(3)]
    assert poses[0]["robot"] == "robot 1!" and poses[0]["cameras"] == ["cam-a", "cam b"]
    assert poses[2]["quaternion_xyzw"] == pytest.approx(list(tracked("robot 1!", 2).quaternion_xyzw), abs=1e-9)
    velocity = samples[f"{robot}/velocity"][0]
    assert velocity["linear_m_s"] == [0.2, 0.0, 0.0] and velocity["angular_rad_s"] == [0.0, 0.0, 0.5]
    assert "lab/cubetrack/robots/robot_2nd/velocity" not in samples  # that fusion gave none
    statuses = samples[f"{robot}/status"]
    assert statuses[0]["tracking"] is True and statuses[-1]["tracking"] is False
    health = samples["lab/cubetrack/cameras/cam_b/health"][0]
    assert health["camera"] == "cam b" and health["frames_per_s"] == 23.5 and health["clock_offset_s"] == 0.25
    assert health["clock_drift_ppm"] is None  # NaN is not JSON
    (reply,) = replies
    doc = json.loads(reply.ok.payload.to_bytes())
    assert [c["name"] for c in doc["cameras"]] == ["cam-a", "cam b", "cam_c"]
    assert doc["cameras"][0]["position"] == pytest.approx([1.0, 0.0, 1.0])
    assert doc["cameras"][2]["position"] is None
    assert doc["robots"][0] == {"name": "robot 1!", "pose": f"{robot}/pose", "velocity": f"{robot}/velocity",
                                "status": f"{robot}/status"}
    assert math.isclose(doc["world"]["marker_size_m"], 0.25)


def test_when_the_port_is_taken_by_a_router_the_output_connects_to_it(router, session_info):
    consumer = peer(router)
    sink = ZenohJsonSink(endpoints=ZenohEndpoints(listen=(router,), fallback_connect=True))
    try:
        got = collect(consumer, "cubetrack/robots/**")
        wait_connected(consumer, sink.zenoh)
        sink.open(session_info)
        sink.pose(tracked("2nd", 1))
        samples = drain(got, lambda s: "cubetrack/robots/robot_2nd/pose" in s)
    finally:
        sink.close()
        consumer.close()
    assert samples["cubetrack/robots/robot_2nd/pose"][0]["robot"] == "2nd"


def test_a_taken_port_without_fallback_is_a_one_line_error(router):
    with pytest.raises(OutputError, match="Address already in use") as err:
        ZenohJsonSink(endpoints=json_endpoints(listen=(router,)))
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("locator,loopback", [
    ("tcp/127.0.0.1:7447", True), ("tcp/localhost:0", True), ("tcp/[::1]:7447", True),
    ("tcp/0.0.0.0:7447", False), ("tcp/[::]:7447", False), ("tcp/192.168.1.5:7447", False),
])
def test_loopback_locators_are_told_apart(locator, loopback):
    assert is_loopback(locator) is loopback
