"""ROS 2 over Zenoh, checked on real sessions against rmw_zenoh's documented wire format.

A Zenoh router on 127.0.0.1 stands in for ``rmw_zenohd``; a plain peer plays the ROS side.
Expected keys and tokens are written out literally from ros2/rmw_zenoh ``docs/design.md``
(key format, token format, mangling, QoS examples); payloads are decoded by ``rosbags`` and
compared byte for byte with what rosbags itself serialises; attachments are decoded with
Zenoh's own deserialiser.
"""

import queue
import re
import struct
import time

import numpy as np
import pytest
import xxhash
from rosbags.typesys import Stores, get_typestore
from sink_helpers import peer, rejoined, tracked, wait_connected

from cubetrack.core.geometry import R_from_quat_xyzw
from cubetrack.sink import rmw_zenoh
from cubetrack.sink.base import OutputError
from cubetrack.sink.ros2 import Ros2Params, Ros2Profile, Ros2Sink
from cubetrack.sink.zenoh_session import ros_endpoints

JAZZY = get_typestore(Stores.ROS2_JAZZY)
POSE_HASH = "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
ODOM_HASH = "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
TF_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


class Listener:
    """A consumer session: every sample under ``keys`` and every liveliness change, queued."""

    def __init__(self, router: str, keys: str = "**"):
        self.session = peer(router)
        self.samples: queue.Queue = queue.Queue()
        self.tokens: queue.Queue = queue.Queue()
        self.sub = self.session.declare_subscriber(keys, self.samples.put)
        self.live = self.session.liveliness().declare_subscriber("@ros2_lv/**", self.tokens.put, history=True)

    def take(self, n: int, timeout_s: float = 15.0) -> list:
        out, deadline = [], time.monotonic() + timeout_s
        while len(out) < n:
            sample = self.samples.get(timeout=max(0.01, deadline - time.monotonic()))
            if not str(sample.key_expr).startswith("probe/"):  # see wait_connected
                out.append(sample)
        return out

    def token_keys(self, n: int, timeout_s: float = 15.0) -> set[str]:
        keys, deadline = set(), time.monotonic() + timeout_s
        while len(keys) < n:
            sample = self.tokens.get(timeout=max(0.01, deadline - time.monotonic()))
            keys.add(str(sample.key_expr))
        return keys

    def close(self):
        self.session.close()


def ros_sink(router, listener: "Listener | None" = None, **params) -> Ros2Sink:
    """The sink with rmw_zenoh's session settings, pointed at the test's router (and reaching
    ``listener`` before it returns)."""
    sink = Ros2Sink(Ros2Params(**params), ros_endpoints(connect=(router,)))
    if listener is not None:
        wait_connected(listener.session, sink.zenoh)
    return sink


def unpack(attachment: bytes) -> tuple[int, int, bytes]:
    """The attachment decoded with zenoh-ext's deserialiser (what rmw_zenoh's C++ side uses)."""
    import zenoh
    from zenoh.ext import Int64, z_deserialize

    return z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(attachment))


def by_key(samples) -> dict:
    out = {}
    for s in samples:
        out.setdefault(str(s.key_expr), []).append(s)
    return out


def test_topics_keys_attachments_and_payloads_follow_rmw_zenoh(router, session_info):
    listener = Listener(router, "0/**")
    sink = ros_sink(router, listener)
    try:
        sink.open(session_info)
        static = listener.take(1)[0]  # /tf_static goes out at once
        before_ns = time.time_ns()
        for i in range(3):
            sink.pose(tracked("robot 1!", i))
        samples = by_key(listener.take(9))
    finally:
        sink.close()
        listener.close()
    pose_key = f"0/robot_1/pose/geometry_msgs::msg::dds_::PoseStamped_/{POSE_HASH}"
    odom_key = f"0/robot_1/odom/nav_msgs::msg::dds_::Odometry_/{ODOM_HASH}"
    tf_key = f"0/tf/tf2_msgs::msg::dds_::TFMessage_/{TF_HASH}"
    assert str(static.key_expr) == f"0/tf_static/tf2_msgs::msg::dds_::TFMessage_/{TF_HASH}"
    assert set(samples) == {pose_key, odom_key, tf_key}
    gids = set()
    for received in samples.values():
        assert len(received) == 3
        for n, sample in enumerate(received, start=1):
            raw = sample.attachment.to_bytes()
            assert len(raw) == 33 and raw[16] == 16  # int64, int64, LEB128 length 16, 16 bytes
            seq, stamp_ns, gid = unpack(raw)
            assert struct.unpack("<qq", raw[:16]) == (seq, stamp_ns)
            assert seq == n and before_ns <= stamp_ns <= time.time_ns()
            gids.add(gid)
    assert len(gids) == 3  # one GID per publisher

    # payloads: rosbags decodes them, and serialises the decoded message to the same bytes
    for key, typename in ((pose_key, "geometry_msgs/msg/PoseStamped"), (odom_key, "nav_msgs/msg/Odometry"),
                          (tf_key, "tf2_msgs/msg/TFMessage")):
        for sample in samples[key]:
            payload = sample.payload.to_bytes()
            assert payload[:4] == b"\x00\x01\x00\x00"
            msg = JAZZY.deserialize_cdr(payload, typename)
            assert JAZZY.serialize_cdr(msg, typename) == payload
    expected = tracked("robot 1!", 2)
    msg = JAZZY.deserialize_cdr(samples[pose_key][2].payload.to_bytes(), "geometry_msgs/msg/PoseStamped")
    assert msg.header.frame_id == "world"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 100_000_000)
    p, q = msg.pose.position, msg.pose.orientation
    np.testing.assert_allclose([p.x, p.y, p.z, q.x, q.y, q.z, q.w],
                               [*expected.position_m, *expected.quaternion_xyzw])
    tf = JAZZY.deserialize_cdr(samples[tf_key][0].payload.to_bytes(), "tf2_msgs/msg/TFMessage")
    assert [(t.header.frame_id, t.child_frame_id) for t in tf.transforms] == [("world", "robot_1")]
    statics = JAZZY.deserialize_cdr(static.payload.to_bytes(), "tf2_msgs/msg/TFMessage").transforms
    assert [t.child_frame_id for t in statics] == ["cam_a_optical_frame", "cam_b_optical_frame"]  # cam_c uncalibrated
    t = statics[0].transform.translation
    assert (t.x, t.y, t.z) == (1.0, 0.0, 1.0)


def test_odometry_carries_the_covariance_and_the_twist_in_the_robot_frame(router, session_info):
    listener = Listener(router, "0/robot_1/odom/**")
    sink = ros_sink(router, listener)
    try:
        sink.open(session_info)
        pose = tracked("robot 1!", 40)  # yaw 1 rad
        sink.pose(pose)
        sink.pose(tracked("robot 1!", 41, velocity=False))
        first, second = listener.take(2)
    finally:
        sink.close()
        listener.close()
    odom = JAZZY.deserialize_cdr(first.payload.to_bytes(), "nav_msgs/msg/Odometry")
    assert odom.header.frame_id == "world" and odom.child_frame_id == "robot_1"
    np.testing.assert_allclose(odom.pose.covariance.reshape(6, 6), pose.covariance)
    R_world_body = R_from_quat_xyzw(pose.quaternion_xyzw)
    linear = odom.twist.twist.linear
    np.testing.assert_allclose(R_world_body @ [linear.x, linear.y, linear.z], pose.velocity_m_s, atol=1e-12)
    assert abs(linear.y) > 0.1  # really rotated: the robot moves sideways in its own frame
    assert odom.twist.twist.angular.z == pytest.approx(0.5)
    unknown = JAZZY.deserialize_cdr(second.payload.to_bytes(), "nav_msgs/msg/Odometry")
    assert not unknown.pose.covariance.any() and unknown.twist.twist.linear.x == 0.0


def test_liveliness_tokens_announce_the_node_and_each_publisher_and_go_away(router, session_info):
    listener = Listener(router, "nothing/**")
    sink = ros_sink(router)
    zid = sink.zid
    # Zenoh prints a session id as its 128-bit number in hex without leading zeros (rmw_zenoh's
    # keys hold the same text): 32 characters, fewer for one id in 16
    assert re.fullmatch(r"[0-9a-f]{1,32}", zid) and not zid.startswith("0")
    try:
        sink.open(session_info)
        keys = listener.token_keys(7)  # node + 2 x (pose, odom) + tf + tf_static
    finally:
        sink.close()
    node = f"@ros2_lv/0/{zid}/0/0/NN/%/%/cubetrack"
    prefix = f"@ros2_lv/0/{zid}/0/"
    assert node in keys
    publishers = {k.split("/", 5)[5] for k in keys if k.startswith(prefix) and "/MP/" in k}
    assert publishers == {
        f"MP/%/%/cubetrack/%robot_1%pose/geometry_msgs::msg::dds_::PoseStamped_/{POSE_HASH}/::,10:,:,:,,",
        f"MP/%/%/cubetrack/%robot_1%odom/nav_msgs::msg::dds_::Odometry_/{ODOM_HASH}/::,10:,:,:,,",
        f"MP/%/%/cubetrack/%robot_2nd%pose/geometry_msgs::msg::dds_::PoseStamped_/{POSE_HASH}/::,10:,:,:,,",
        f"MP/%/%/cubetrack/%robot_2nd%odom/nav_msgs::msg::dds_::Odometry_/{ODOM_HASH}/::,10:,:,:,,",
        f"MP/%/%/cubetrack/%tf/tf2_msgs::msg::dds_::TFMessage_/{TF_HASH}/::,100:,:,:,,",
        f"MP/%/%/cubetrack/%tf_static/tf2_msgs::msg::dds_::TFMessage_/{TF_HASH}/:1:,1:,:,:,,",
    }
    entity_ids = sorted(int(k.split("/")[4]) for k in keys if "/MP/" in k)
    assert len(set(entity_ids)) == 6
    # each GID is XXH3-128 of the publisher's token (low 64 bits first), as rmw_zenoh derives it
    pose_token = next(k for k in keys if "%robot_1%pose" in k)
    assert rmw_zenoh.gid(pose_token) == xxhash.xxh3_128(pose_token.encode()).digest()[::-1]
    gone = set()
    deadline = time.monotonic() + 5
    while len(gone) < 7 and time.monotonic() < deadline:
        try:
            sample = listener.tokens.get(timeout=0.2)
        except queue.Empty:
            continue
        if str(sample.kind) == "SampleKind.DELETE":
            gone.add(str(sample.key_expr))
    listener.close()
    assert gone == keys


def test_a_recalibrated_cameras_new_pose_goes_out_on_tf_static(router, session_info):
    from cubetrack.core.records import CameraWatchState

    listener = Listener(router, "0/tf_static/**")
    sink = ros_sink(router, listener)
    try:
        sink.open(session_info)
        listener.take(1)
        sink.camera_watch(CameraWatchState("cam b", 1_700_000_000.5, "moved"))  # set aside: no new pose
        sink.camera_watch(rejoined("cam b", [0.1, 1.2, 1.0]))
        (static,) = listener.take(1)
    finally:
        sink.close()
        listener.close()
    tf = JAZZY.deserialize_cdr(static.payload.to_bytes(), "tf2_msgs/msg/TFMessage")
    moved = {t.child_frame_id: t.transform.translation for t in tf.transforms}
    assert set(moved) == {"cam_a_optical_frame", "cam_b_optical_frame"}  # every camera, as a latched message must
    assert [moved["cam_b_optical_frame"].x, moved["cam_b_optical_frame"].y] == pytest.approx([0.1, 1.2])
    assert [moved["cam_a_optical_frame"].x, moved["cam_a_optical_frame"].y] == pytest.approx([1.0, 0.0])


def test_a_late_subscriber_still_gets_the_static_transforms(router, session_info):
    from zenoh import ext

    sink = ros_sink(router)
    late = peer(router)
    got: queue.Queue = queue.Queue()
    try:
        sink.open(session_info)
        time.sleep(0.3)  # published long before anyone listens, like a camera calibrated at start-up
        sub = ext.declare_advanced_subscriber(  # what rmw_zenoh declares for a TRANSIENT_LOCAL subscription
            late, "0/tf_static/**", got.put,
            history=ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
            recovery=ext.RecoveryConfig(heartbeat=True), subscriber_detection=True)
        sample = got.get(timeout=5)
        sub.undeclare()
    finally:
        late.close()
        sink.close()
    msg = JAZZY.deserialize_cdr(sample.payload.to_bytes(), "tf2_msgs/msg/TFMessage")
    assert len(msg.transforms) == 2


@pytest.mark.parametrize("durability", ["volatile", "transient_local"])
def test_a_late_subscriber_gets_from_our_volatile_topics_what_rmw_zenohs_advanced_publisher_gives(
        router, session_info, durability):
    """rmw_zenoh declares every publisher as a zenoh-ext advanced publisher; for a VOLATILE topic
    with default options: no cache, no publisher detection, no sample-miss detection
    (rmw_publisher_data.cpp 3e19ec73). We declare a plain publisher there. A subscription that
    joins late, declared as rmw_zenoh declares a VOLATILE one (an advanced subscriber without
    history) or a TRANSIENT_LOCAL one (history with late-publisher detection, recovery;
    rmw_subscription_data.cpp 04df82fd), gets the same from both: nothing sent before it joined,
    everything after."""
    from zenoh import CongestionControl, Reliability, ext

    sink = ros_sink(router)
    theirs = peer(router)
    rmw_key = "0/their/pose/geometry_msgs::msg::dds_::PoseStamped_/" + POSE_HASH
    rmw_publisher = ext.declare_advanced_publisher(theirs, rmw_key, reliability=Reliability.RELIABLE,
                                                   congestion_control=CongestionControl.DROP)
    late = peer(router)
    got: queue.Queue = queue.Queue()
    try:
        sink.open(session_info)
        wait_connected(late, sink.zenoh)
        wait_connected(late, theirs)
        for i in range(5):  # before anyone listens
            sink.pose(tracked("robot 1!", i))
            rmw_publisher.put(bytes([i]))
        time.sleep(0.3)
        options = {} if durability == "volatile" else {
            "history": ext.HistoryConfig(detect_late_publishers=True, max_samples=10),
            "recovery": ext.RecoveryConfig(heartbeat=True), "subscriber_detection": True}
        subs = [ext.declare_advanced_subscriber(late, key, got.put, **options)
                for key in ("0/robot_1/pose/**", rmw_key)]
        time.sleep(1.0)  # any history would have been queried and answered by now
        for i in range(5, 8):
            sink.pose(tracked("robot 1!", i))
            rmw_publisher.put(bytes([i]))
        samples = []
        while len(samples) < 6:
            samples.append(got.get(timeout=10))
        time.sleep(0.5)
        while not got.empty():
            samples.append(got.get())
        for sub in subs:
            sub.undeclare()
    finally:
        rmw_publisher.undeclare()
        late.close()
        theirs.close()
        sink.close()
    ours = [unpack(s.attachment.to_bytes())[0] for s in samples if str(s.key_expr).startswith("0/robot_1/")]
    rmw = [s.payload.to_bytes()[0] for s in samples if str(s.key_expr) == rmw_key]
    assert ours == [6, 7, 8]  # sequence numbers: the 6th to 8th poses, none of the first five
    assert rmw == [5, 6, 7]


def test_humble_keys_carry_no_type_hash(router, session_info):
    listener = Listener(router, "7/**")
    sink = ros_sink(router, listener, distro=rmw_zenoh.Distro.HUMBLE, domain_id=7, namespace="lab one")
    try:
        sink.open(session_info)
        sink.pose(tracked("2nd", 0))
        keys = {str(s.key_expr) for s in listener.take(4)}
        tokens = listener.token_keys(7)
    finally:
        sink.close()
        listener.close()
    assert "7/lab_one/robot_2nd/pose/geometry_msgs::msg::dds_::PoseStamped_/TypeHashNotSupported" in keys
    assert "7/tf/tf2_msgs::msg::dds_::TFMessage_/TypeHashNotSupported" in keys
    assert any(t.endswith("/NN/%/%lab_one/cubetrack") for t in tokens)
    assert any("/MP/%/%lab_one/cubetrack/%lab_one%robot_2nd%pose/" in t for t in tokens)


def test_bridge_profile_publishes_bare_topic_keys_without_attachment(router, session_info):
    listener = Listener(router, "**")
    sink = ros_sink(router, listener, profile=Ros2Profile.BRIDGE)
    try:
        sink.open(session_info)
        sink.pose(tracked("robot 1!", 0))
        samples = by_key(listener.take(4))
        assert listener.tokens.empty()
    finally:
        sink.close()
        listener.close()
    assert set(samples) == {"tf_static", "robot_1/pose", "robot_1/odom", "tf"}
    assert all(s.attachment is None for received in samples.values() for s in received)
    JAZZY.deserialize_cdr(samples["robot_1/pose"][0].payload.to_bytes(), "geometry_msgs/msg/PoseStamped")


def test_a_bad_endpoint_or_domain_is_a_one_line_error():
    with pytest.raises(OutputError, match="cannot open the Zenoh session"):
        Ros2Sink(Ros2Params(), ros_endpoints(listen=("tcp/not-an-address",)))
    with pytest.raises(OutputError, match="domain id"):
        Ros2Params(domain_id=999)


def test_the_twist_turns_into_the_body_frame_as_the_rotation_matrix_does():
    from cubetrack.core.geometry import R_from_quat_xyzw
    from cubetrack.sink.ros2 import into_body

    rng = np.random.default_rng(3)
    for _ in range(200):
        q = rng.normal(size=4) * rng.uniform(0.5, 2.0)  # not normalised: normalised first, as the matrix is
        v = rng.normal(size=3)
        assert into_body(q, v) == pytest.approx(R_from_quat_xyzw(q).T @ v, abs=1e-12)
    yaw_90 = np.array([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])  # body x = world y
    assert into_body(yaw_90, np.array([0.0, 1.0, 0.0])) == pytest.approx([1.0, 0.0, 0.0])
