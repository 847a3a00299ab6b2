"""The Foxglove output: the MCAP read back with the ``mcap`` reader and the live server read
by a WebSocket client, each message decoded with the schema its channel carries."""

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from foxglove_client import LiveClient, read_mcap
from sink_helpers import INTRINSICS, rejoined, tracked

from cubetrack.core.records import CameraHealth, CameraView, CameraWatchState, Detection
from cubetrack.sink.base import OutputError
from cubetrack.sink.foxglove import FoxgloveSink, layout, project

REPO = Path(__file__).resolve().parents[3]

TOPICS = {
    "/robots/robot_1/pose": "foxglove.PoseInFrame", "/robots/robot_2nd/pose": "foxglove.PoseInFrame",
    "/tf": "foxglove.FrameTransforms", "/scene": "foxglove.SceneUpdate",
    **{f"/cameras/{c}/{kind}": schema for c in ("cam_a", "cam_b", "cam_c")
       for kind, schema in (("image", "foxglove.CompressedImage"), ("annotations", "foxglove.ImageAnnotations"),
                            ("calibration", "foxglove.CameraCalibration"), ("health", "cubetrack.CameraHealth"))},
}


def jpeg() -> bytes:
    image = np.full((480, 640, 3), 90, np.uint8)
    cv2.rectangle(image, (100, 100), (200, 200), (0, 0, 0), -1)
    return cv2.imencode(".jpg", image)[1].tobytes()


DETECTION = Detection(7, np.array([[100.0, 100], [200, 100], [200, 200], [100, 200]]), 10000.0, "DICT_4X4_50")


def feed(sink, session_info, jpeg_bytes):
    """One session's worth of everything: poses, a view of cam-a, a health snapshot."""
    sink.open(session_info)
    sink.pose(tracked("robot 1!", 0))
    sink.pose(tracked("2nd", 0))
    pose = tracked("robot 1!", 1)
    sink.pose(pose)
    sink.camera_view(CameraView("cam-a", 12, pose.time_s, jpeg_bytes, (DETECTION,)))
    sink.camera_health(CameraHealth("cam-a", pose.time_s, True, 24.0, 100, 1, 0, 0))


def check_messages(messages, session_info, jpeg_bytes):
    """One message of each kind, decoded, says what was sent."""
    pose = tracked("robot 1!", 1)
    _, first = messages["/robots/robot_1/pose"][-1]
    assert first.frame_id == "world"
    assert [first.pose.position.x, first.pose.position.y, first.pose.position.z] == pytest.approx(pose.position_m)
    assert first.pose.orientation.w == pytest.approx(pose.quaternion_xyzw[3])
    children = {t.child_frame_id for _, m in messages["/tf"] for t in m.transforms}
    assert children == {"robot_1", "robot_2nd", "cam_a_optical_frame", "cam_b_optical_frame"}
    entities = {e.id: e for _, m in messages["/scene"] for e in m.entities}
    assert set(entities) == {"robot/robot_1", "robot/robot_2nd", "camera/cam_a", "camera/cam_b"}
    cube = entities["robot/robot_1"].cubes[0]
    assert cube.size.x == pytest.approx(0.11) and cube.size.z > 0.09  # the paper's 11 cm cube
    frustum = entities["camera/cam_a"].lines[0]
    assert len(frustum.points) == 16 and entities["camera/cam_a"].texts[0].text == "cam-a"
    log_time, image = messages["/cameras/cam_a/image"][0]
    assert image.data == jpeg_bytes and image.format == "jpeg" and image.frame_id == "cam_a_optical_frame"
    assert log_time == int(pose.time_s * 1e9)
    _, notes = messages["/cameras/cam_a/annotations"][0]
    assert [t.text for t in notes.texts] == ["7"]
    green, *predicted = notes.points
    assert [(p.x, p.y) for p in green.points] == [(100, 100), (200, 100), (200, 200), (100, 200)]
    assert len(predicted) == 10  # each robot's five marker squares where its last pose puts them
    camera = session_info.cameras[0]
    expected = project(camera, np.array([pose.position_m]))[0]
    centre = np.mean([[p.x, p.y] for square in predicted[:5] for p in square.points], axis=0)
    assert np.linalg.norm(centre - expected) < 15  # around the cube's projected centre
    _, calibration = messages["/cameras/cam_c/calibration"][0]
    assert list(calibration.K) == list(INTRINSICS.K.reshape(-1)) and calibration.width == 640
    _, health = messages["/cameras/cam_a/health"][0]
    assert health["camera"] == "cam-a" and health["frames_per_s"] == 24.0 and health["clock_offset_s"] is None


def test_the_mcap_file_holds_every_channel_and_reads_back(tmp_path, session_info):
    path = tmp_path / "session.mcap"
    sink = FoxgloveSink(mcap=path)
    assert sink.in_line  # a file: sees everything, in pipeline order
    picture = jpeg()
    feed(sink, session_info, picture)
    sink.close()
    channels, messages = read_mcap(path)
    silent = {f"/cameras/{c}/{k}" for c in ("cam_b", "cam_c") for k in ("image", "annotations", "health")}
    assert {topic: schema for topic, (schema, _, _) in channels.items()} == {  # channels that had messages
        t: s for t, s in TOPICS.items() if t not in silent}
    assert {enc for _, enc, _ in channels.values()} == {"protobuf", "jsonschema"}
    assert channels["/cameras/cam_a/health"][2] == "json"
    check_messages(messages, session_info, picture)
    with pytest.raises(OutputError, match="cannot write the MCAP file"):
        FoxgloveSink(mcap=path)  # never overwrites a recording


def test_a_recalibrated_camera_is_shown_at_its_new_pose_at_once(tmp_path, session_info):
    path = tmp_path / "moved.mcap"
    sink = FoxgloveSink(mcap=path)
    sink.open(session_info)
    now = time.time()  # the watching's states carry the host time, after the session opened
    sink.camera_watch(CameraWatchState("cam-a", now + 0.5, "moved"))  # set aside: no pose to show
    sink.camera_watch(rejoined("cam-a", [1.1, 0.2, 1.0], now + 1.0))
    sink.camera_watch(rejoined("cam-z", [0.0, 0.0, 2.0], now + 1.5))  # not a camera of the session: ignored
    sink.close()
    _, messages = read_mcap(path)
    cam_a = [t.translation for _, m in messages["/tf"] for t in m.transforms
             if t.child_frame_id == "cam_a_optical_frame"]
    assert [[v.x, v.y, v.z] for v in cam_a] == [pytest.approx([1.0, 0.0, 1.0]), pytest.approx([1.1, 0.2, 1.0])]
    frusta = [e.lines[0].pose.position for _, m in messages["/scene"] for e in m.entities if e.id == "camera/cam_a"]
    assert [frusta[-1].x, frusta[-1].y] == pytest.approx([1.1, 0.2])
    cam_b = [t for _, m in messages["/tf"] for t in m.transforms if t.child_frame_id == "cam_b_optical_frame"]
    assert [[t.translation.x, t.translation.y] for t in cam_b] == [pytest.approx([0.0, 1.0])] * 2  # as it was


def test_the_live_server_advertises_every_channel_and_serves_each(session_info):
    sink = FoxgloveSink(server=("127.0.0.1", 0))
    assert not sink.in_line
    client = LiveClient(sink.port)
    picture = jpeg()
    try:
        client.poll(lambda c: c.server_info is not None)
        assert client.server_info["name"] == "cubetrack"
        feed(sink, session_info, picture)
        client.poll(lambda c: set(c.topics()) == set(TOPICS))
        subscribed = set()

        def all_arrived(c):
            return {"/robots/robot_1/pose", "/cameras/cam_a/image", "/cameras/cam_a/annotations",
                    "/cameras/cam_a/health", "/cameras/cam_c/calibration"} <= set(c.messages) and \
                any(len(m.transforms) == 2 for _, m in c.messages.get("/tf", [])) and \
                {"robot/robot_1", "camera/cam_a"} <= {e.id for _, m in c.messages.get("/scene", [])
                                                      for e in m.entities}

        for _ in range(40):  # keep the session going until the subscriptions have taken effect
            try:
                client.poll(all_arrived, timeout_s=0.25)
                break
            except TimeoutError:
                feed(sink, session_info, picture)
                subscribed = set(client.messages)
        else:
            pytest.fail(f"only {sorted(subscribed)} arrived")
    finally:
        client.close()
        sink.close()
    advertised = client.topics()
    assert {t: c["schemaName"] for t, c in advertised.items()} == TOPICS
    assert advertised["/robots/robot_1/pose"]["encoding"] == "protobuf"
    assert advertised["/cameras/cam_a/health"]["encoding"] == "json"
    check_messages(client.messages, session_info, picture)


def test_a_port_in_use_is_a_one_line_error():
    sink = FoxgloveSink(server=("127.0.0.1", 0))
    try:
        with pytest.raises(OutputError, match=f"cannot listen on 127.0.0.1:{sink.port}"):
            FoxgloveSink(server=("127.0.0.1", sink.port))
    finally:
        sink.close()


def test_the_layout_in_docs_is_the_generated_one_and_names_real_channels():
    """docs/foxglove-layout.json opens the demo's session (robot ``robot``, cameras cam1..cam3)."""
    text = layout(["robot"], ["cam1", "cam2", "cam3"])
    assert json.loads((REPO / "docs" / "foxglove-layout.json").read_text()) == json.loads(text)
    topics = set()

    def walk(node):
        if isinstance(node, dict):
            for key, value in node.items():
                if key in ("imageTopic", "calibrationTopic", "topicPath") or (key == "value" and "/" in value):
                    topics.add(value.split(".")[0])
                elif key in ("topics", "annotations"):
                    topics.update(value)
                walk(value)
        elif isinstance(node, list):
            for item in node:
                walk(item)

    walk(json.loads(text))
    demo_topics = {"/robots/robot/pose", "/scene", "/tf",
                   *(f"/cameras/cam{i}/{k}" for i in (1, 2, 3)
                     for k in ("image", "annotations", "calibration", "health"))}
    assert topics and topics <= demo_topics
    assert {"/scene", "/robots/robot/pose", "/cameras/cam1/image", "/cameras/cam3/health"} <= topics


def test_one_sink_serves_live_and_records_the_same_messages(tmp_path, session_info):
    path = tmp_path / "both.mcap"
    sink = FoxgloveSink(server=("127.0.0.1", 0), mcap=path)
    assert sink.in_line and sink.name == "foxglove + mcap"
    client = LiveClient(sink.port)
    picture = jpeg()
    try:
        client.poll(lambda c: c.server_info is not None)
        feed(sink, session_info, picture)
        client.poll(lambda c: set(c.topics()) == set(TOPICS))
        for _ in range(40):  # until the subscriptions have taken effect
            try:
                client.poll(lambda c: "/cameras/cam_a/annotations" in c.messages, timeout_s=0.25)
                break
            except TimeoutError:
                sink.pose(tracked("robot 1!", 1))
                sink.camera_view(CameraView("cam-a", 12, tracked("robot 1!", 1).time_s, picture, (DETECTION,)))
    finally:
        client.close()
        sink.close()
    _, recorded = read_mcap(path)
    check_messages(recorded, session_info, picture)
    live, = (m for _, m in client.messages["/cameras/cam_a/annotations"][-1:])
    same = recorded["/cameras/cam_a/annotations"][-1][1]
    assert live.SerializeToString() == same.SerializeToString()  # the same message, encoded once
