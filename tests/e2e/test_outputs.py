"""``cubetrack demo`` with every output at once, each watched by its consumer while it runs:
a VRPN client, a ROS 2 subscriber (through a Zenoh router standing in for rmw_zenohd), the
Foxglove WebSocket client, the official Foxglove client library (@foxglove/ws-protocol, from a
Node.js script: tests/e2e/foxglove_client), a Zenoh JSON subscriber; then the MCAP file it wrote, and ``cubetrack
track`` replaying the demo's recording with an ``[[outputs]]`` table in the config."""

import base64
import json
import queue
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests" / "unit" / "sink"))  # the consumers written for the unit tests

from foxglove_client import LiveClient, decode, read_mcap  # noqa: E402
from sink_helpers import free_port, open_router, peer  # noqa: E402
from vrpn_client import TrackerClient  # noqa: E402

from cubetrack.cli.main import main  # noqa: E402

pytestmark = pytest.mark.slow
NODE_CLIENT = REPO / "tests" / "e2e" / "foxglove_client"
NODE_TOPICS = ("/robots/robot/pose", "/tf", "/scene", "/cameras/cam1/image", "/cameras/cam1/annotations",
               "/cameras/cam1/calibration", "/cameras/cam1/health")
POSE_KEY = ("0/robot/pose/geometry_msgs::msg::dds_::PoseStamped_/"
            "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8")


def retry(make, timeout_s=120.0):
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return make()
        except (OSError, TimeoutError, ConnectionError):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)


def node_client_missing() -> str | None:
    """Why the official Foxglove client cannot run here, None when it can."""
    if shutil.which("node") is None:
        return "node (Node.js) is not installed: the official Foxglove client library runs on it"
    if not (NODE_CLIENT / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        return f"@foxglove/ws-protocol is not installed: run tests/install.sh (npm ci in {NODE_CLIENT})"
    return None


class Consumers:
    """Every consumer, connected while the demo runs (the servers start before the simulation)."""

    def __init__(self, router: str, vrpn_port: int, foxglove_port: int, folder: Path):
        self.vrpn = None
        self.foxglove = None
        self.errors: list[str] = []
        self.ros = peer(router)
        self.ros_samples: queue.Queue = queue.Queue()
        self.ros.declare_subscriber("0/**", self.ros_samples.put)
        self.json_samples: queue.Queue = queue.Queue()
        self.ros.declare_subscriber("cubetrack/**", self.json_samples.put)
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._vrpn, args=(vrpn_port,), daemon=True),
                        threading.Thread(target=self._foxglove, args=(foxglove_port,), daemon=True)]
        for t in self.threads:
            t.start()
        # its output to files: a pipe nobody reads while the demo runs would hold the client up
        self.node_files = (folder / "node_client.out", folder / "node_client.err")
        with open(self.node_files[0], "w") as stdout, open(self.node_files[1], "w") as stderr:
            self.node = None if node_client_missing() else subprocess.Popen(
                ["node", "client.mjs", f"ws://127.0.0.1:{foxglove_port}", "--topics", ",".join(NODE_TOPICS),
                 "--timeout", "300"], cwd=NODE_CLIENT, stdout=stdout, stderr=stderr)
        self.node_output: tuple[int, str, str] | None = None  # exit code, stdout, stderr

    def _vrpn(self, port):
        try:
            self.vrpn = retry(lambda: TrackerClient(port, "robot"))
        except Exception as exc:
            self.errors.append(f"vrpn: {exc!r}")

    def _foxglove(self, port):
        try:
            client = retry(lambda: LiveClient(port))
            client.poll(lambda c: self.stop.is_set() or "/robots/robot/pose" in c.messages, timeout_s=240)
            self.foxglove = client
        except Exception as exc:
            self.errors.append(f"foxglove: {exc!r}")

    def close(self):
        self.stop.set()
        for t in self.threads:
            t.join(10)
        self.ros.close()
        if self.node is not None:
            try:
                self.node.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.node.kill()
                self.node.wait()
            self.node_output = (self.node.returncode, *(f.read_text() for f in self.node_files))


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("outputs")
    router, router_locator = open_router()
    vrpn_port, foxglove_port = free_port(), free_port()
    consumers = Consumers(router_locator, vrpn_port, foxglove_port, out)
    try:
        code = main(["demo", "--out", str(out / "demo"), "--duration", "3", "--vrpn", f"127.0.0.1:{vrpn_port}",
                     "--foxglove", f"127.0.0.1:{foxglove_port}", "--mcap", str(out / "demo.mcap"),
                     "--ros2", "--zenoh", "--zenoh-connect", router_locator])
        time.sleep(0.5)
    finally:
        consumers.close()
    yield code, out, consumers, router_locator
    router.close()


def drain(q: queue.Queue) -> list:
    items = []
    while not q.empty():
        items.append(q.get())
    return items


def test_the_demo_serves_vrpn_ros2_zenoh_foxglove_and_writes_mcap(demo):
    from rosbags.typesys import Stores, get_typestore

    code, out, consumers, _ = demo
    assert code == 0 and not consumers.errors
    poses = consumers.vrpn.poses("robot")
    assert len(poses) > 20 and all(sensor == 0 for _, sensor, _, _ in poses)
    ros = [s for s in drain(consumers.ros_samples) if str(s.key_expr) == POSE_KEY]
    assert len(ros) > 20 and all(len(s.attachment.to_bytes()) == 33 for s in ros)
    msg = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(ros[-1].payload.to_bytes(), "geometry_msgs/msg/PoseStamped")
    assert msg.header.frame_id == "world" and abs(msg.pose.orientation.w) <= 1.0
    json_keys = {str(s.key_expr) for s in drain(consumers.json_samples)}
    assert {"cubetrack/robots/robot/pose", "cubetrack/robots/robot/status", "cubetrack/session"} <= json_keys
    assert consumers.foxglove is not None and consumers.foxglove.messages["/robots/robot/pose"]
    channels, messages = read_mcap(out / "demo.mcap")
    assert {"/robots/robot/pose", "/tf", "/scene", "/cameras/cam1/calibration"} <= set(channels)
    assert len(messages["/robots/robot/pose"]) == len(poses)  # the file and the VRPN client saw every pose
    images = messages["/cameras/cam1/image"]
    assert len(images) > 10 and all(m.data[:2] == b"\xff\xd8" and m.format == "jpeg" for _, m in images)
    notes = [m for _, m in messages["/cameras/cam1/annotations"]]
    predicted = [[p for p in m.points if p.outline_color.g < 0.9] for m in notes]  # orange, not green
    detected = [[p for p in m.points if p.outline_color.g >= 0.9] for m in notes]
    assert any(predicted) and all(len(p) % 5 == 0 for p in predicted)  # the predicted cube's five markers
    assert all(len(d) == len(m.texts) for d, m in zip(detected, notes, strict=True))  # each detected marker with its id


def test_the_official_foxglove_client_sees_every_channel_with_a_message_of_each(demo):
    missing = node_client_missing()
    if missing:
        pytest.skip(missing)
    code, out, consumers, _ = demo
    assert code == 0 and consumers.node_output is not None
    returncode, stdout, stderr = consumers.node_output
    arrived = re.findall(r'"topic":"([^"]+)","logTime"', stdout)
    assert returncode == 0, f"{stderr[-2000:]}; first messages on {arrived}"
    lines = [json.loads(line) for line in stdout.splitlines()]
    assert lines[0]["serverInfo"]["name"] == "cubetrack"
    advertised = {c["topic"]: c for line in lines if "advertise" in line for c in line["advertise"]}
    written, _ = read_mcap(out / "demo.mcap")
    assert set(written) <= set(advertised)  # the live server offers every channel the MCAP file holds
    assert {t: (c["schemaName"], c["encoding"]) for t, c in advertised.items() if t in written} == {
        t: (schema, encoding) for t, (schema, _, encoding) in written.items()}
    first = {}
    for line in lines:
        if "message" in line:
            channel = advertised[line["message"]["topic"]]
            schema = channel["schema"]
            raw = base64.b64decode(schema) if channel["schemaEncoding"] == "protobuf" else schema.encode()
            first[channel["topic"]] = decode(channel["schemaName"], channel["schemaEncoding"], raw,
                                             base64.b64decode(line["message"]["data"]))
    assert set(NODE_TOPICS) <= set(first)
    assert first["/robots/robot/pose"].frame_id == "world" and abs(first["/robots/robot/pose"].pose.orientation.w) <= 1
    assert first["/tf"].transforms and first["/scene"].entities
    image = first["/cameras/cam1/image"]
    assert image.format == "jpeg" and image.data[:2] == b"\xff\xd8" and image.frame_id == "cam1_optical_frame"
    assert first["/cameras/cam1/calibration"].width > 0 and len(first["/cameras/cam1/calibration"].K) == 9
    assert first["/cameras/cam1/health"]["camera"] == "cam1"


def test_track_takes_outputs_from_the_config(demo, capsys):
    code, out, _, _ = demo
    demo_dir = out / "demo"
    config = demo_dir / "rec" / "with_outputs.toml"  # beside the original: its relative paths still hold
    config.write_text((demo_dir / "rec" / "config.toml").read_text()
                      + '\n[[outputs]]\ntype = "mcap"\npath = "replay.mcap"\n')
    assert main(["track", "--config", str(config), "--extrinsics", str(demo_dir / "extrinsics.toml"),
                 "--recording", str(demo_dir / "rec"), "--out", str(out / "replay")]) == 0
    assert "output: MCAP file" in capsys.readouterr().err
    channels, messages = read_mcap(demo_dir / "rec" / "replay.mcap")  # relative to the config's folder
    tum = (out / "replay" / "robot.tum").read_text().splitlines()
    assert len(messages["/robots/robot/pose"]) == len(tum) > 20


def test_bad_outputs_are_one_line_errors(demo, tmp_path, capsys):
    _, out, _, _ = demo
    demo_dir = out / "demo"
    args = ["track", "--config", str(demo_dir / "rec" / "config.toml"), "--extrinsics",
            str(demo_dir / "extrinsics.toml"), "--recording", str(demo_dir / "rec"), "--out", str(tmp_path / "x")]
    assert main(args + ["--vrpn", "127.0.0.1:99999"]) == 1
    assert "port 99999 out of range" in capsys.readouterr().err
    config = demo_dir / "rec" / "bad_outputs.toml"
    config.write_text((demo_dir / "rec" / "config.toml").read_text() + '\n[[outputs]]\ntype = "carrier-pigeon"\n')
    assert main(["track", "--config", str(config)] + args[3:]) == 1
    err = capsys.readouterr().err
    assert "outputs[0]: type must be one of zenoh, ros2, vrpn, foxglove, mcap" in err and err.count("\n") == 1
