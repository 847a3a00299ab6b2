"""ROS 2 topics over Zenoh, without a ROS install: what ``ros2 topic echo`` shows.

Per robot ``<r>`` (names made valid ROS names, :mod:`cubetrack.sink.names`), in the namespace
``ns`` (default none):

- ``/<ns>/<r>/pose``: ``geometry_msgs/msg/PoseStamped``, the cube frame in the world frame;
- ``/<ns>/<r>/odom``: ``nav_msgs/msg/Odometry``: the same pose with the filter's covariance and
  its twist in the robot frame (zeros where the fusion gives none);
- ``/tf``: ``tf2_msgs/msg/TFMessage``, world -> ``<r>`` at every pose;
- ``/tf_static``: world -> ``<camera>_optical_frame`` for every calibrated camera (the optical
  frame: x right, y down, z forward), published once and kept for late subscribers; again with
  the new pose when the camera watching re-calibrates a camera (issue 27).

Two profiles. ``rmw_zenoh`` (default) talks to ROS 2 nodes that use ``rmw_zenoh_cpp``: keys,
33-byte attachments and liveliness tokens as :mod:`cubetrack.sink.rmw_zenoh` describes, type
hashes of the chosen distro, ``/tf_static`` as rmw_zenoh does TRANSIENT_LOCAL (an advanced
publisher with a cache of 1 and publisher detection). ``bridge`` is for zenoh-bridge-ros2dds
(ROS 2 on DDS): keys are the topic names without the leading ``/``, the same CDR payloads,
no attachment, no tokens; ``/tf_static`` is sent again every ``static_every_s``.
"""

from __future__ import annotations

import enum
import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from cubetrack.core.geometry import position_quat_from_T
from cubetrack.core.records import CameraWatchState, TrackedPose
from cubetrack.sink import cdr, rmw_zenoh
from cubetrack.sink.base import OutputError, SessionInfo, Sink
from cubetrack.sink.names import identifier, identifiers
from cubetrack.sink.zenoh_session import ZenohEndpoints, open_session, ros_endpoints

log = logging.getLogger(__name__)


class Ros2Profile(enum.Enum):
    RMW_ZENOH = "rmw_zenoh"
    BRIDGE = "bridge"


@dataclass(frozen=True, slots=True)
class Ros2Params:
    """``distro`` picks the type hashes (Humble has none); ``domain_id`` is ROS_DOMAIN_ID;
    ``namespace`` prefixes the robot topics (``/lab`` -> ``/lab/<robot>/pose``);
    ``world_frame`` is the frame id of the world; ``node`` the name the topics appear under."""

    profile: Ros2Profile = Ros2Profile.RMW_ZENOH
    distro: rmw_zenoh.Distro = rmw_zenoh.Distro.JAZZY
    domain_id: int = 0
    namespace: str = ""
    world_frame: str = "world"
    node: str = "cubetrack"
    static_every_s: float = 2.0

    def __post_init__(self) -> None:
        if not 0 <= self.domain_id <= 232:
            raise OutputError(f"ROS domain id must be 0..232, got {self.domain_id}")


def ros_namespace(text: str) -> str:
    """``text`` as a ROS namespace: ``""`` -> ``"/"``, ``"lab 1/a"`` -> ``"/lab_1/a"``."""
    return "/" + "/".join(identifier(t, "ns") for t in text.split("/") if t.strip())


# tf2_ros' QoS: dynamic broadcaster keep-last 100; static broadcaster keep-last 1, transient local
TF_QOS = rmw_zenoh.Qos(depth=100)
TF_STATIC_QOS = rmw_zenoh.Qos(depth=1, durability=rmw_zenoh.TRANSIENT_LOCAL)
TOPIC_QOS = rmw_zenoh.Qos(depth=10)


class _Publisher:
    """One ROS 2 publisher on Zenoh: its key, token, GID and sequence numbers."""

    def __init__(self, sink: Ros2Sink, topic: str, ros_type: cdr.RosType, qos: rmw_zenoh.Qos, entity_id: int):
        import zenoh

        p = sink.params
        self.topic = topic
        self.rmw = p.profile is Ros2Profile.RMW_ZENOH
        session = sink.zenoh
        if self.rmw:
            self.key = rmw_zenoh.topic_key(p.domain_id, topic, ros_type, p.distro)
            self.token_key = rmw_zenoh.publisher_token(p.domain_id, sink.zid, 0, entity_id, sink.node_namespace,
                                                       p.node, topic, ros_type, p.distro, qos)
            self.gid = rmw_zenoh.gid(self.token_key)
        else:
            self.key = topic.strip("/")
        self.sequence = 0
        options: dict[str, Any] = dict(reliability=zenoh.Reliability.RELIABLE,
                                       congestion_control=zenoh.CongestionControl.DROP)
        if self.rmw and qos.durability == rmw_zenoh.TRANSIENT_LOCAL:
            from zenoh import ext

            self.publisher = ext.declare_advanced_publisher(
                session, self.key, **options, cache=ext.CacheConfig(qos.depth), publisher_detection=True,
                sample_miss_detection=ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=0.5))
        else:
            self.publisher = session.declare_publisher(self.key, **options)
        self.token = session.liveliness().declare_token(self.token_key) if self.rmw else None

    def put(self, payload: bytes) -> None:
        self.sequence += 1
        attachment = rmw_zenoh.attachment(self.sequence, time.time_ns(), self.gid) if self.rmw else None
        self.publisher.put(payload, attachment=attachment)

    def close(self) -> None:
        if self.token is not None:
            self.token.undeclare()
        self.publisher.undeclare()


class Ros2Sink(Sink):
    """Publishes every robot's pose as ROS 2 topics (module doc). The Zenoh session opens in
    the constructor, so a bad endpoint fails before the pipeline starts."""

    name = "ros2"

    def __init__(self, params: Ros2Params = Ros2Params(), endpoints: ZenohEndpoints | None = None):
        self.params = params
        self.zenoh = open_session(endpoints or ros_endpoints(), "ROS 2 output")
        self.zid = str(self.zenoh.zid())
        self.node_namespace = ros_namespace(params.namespace)
        self.world_frame = identifier(params.world_frame, "world")
        self.node_token = None
        self.robots: dict[str, tuple[str, _Publisher, _Publisher]] = {}  # robot -> (frame, pose, odom)
        self.publishers: list[_Publisher] = []
        self.tf: _Publisher | None = None
        self.tf_static: _Publisher | None = None
        self.static_payload: bytes | None = None
        self.session: SessionInfo | None = None
        self.static_sent_s = 0.0
        endpoints = endpoints or ros_endpoints()
        self.where = (f"ROS 2 ({params.profile.value}, {params.distro.value}, domain {params.domain_id}) over Zenoh "
                      f"via {', '.join(endpoints.connect) or str(endpoints.config_file)}")

    def _publisher(self, topic: str, ros_type: cdr.RosType, qos: rmw_zenoh.Qos) -> _Publisher:
        publisher = _Publisher(self, topic, ros_type, qos, entity_id=len(self.publishers) + 1)
        self.publishers.append(publisher)
        return publisher

    def open(self, session: SessionInfo) -> None:
        p = self.params
        if p.profile is Ros2Profile.RMW_ZENOH:
            self.node_token = self.zenoh.liveliness().declare_token(
                rmw_zenoh.node_token(p.domain_id, self.zid, 0, self.node_namespace, p.node))
        prefix = self.node_namespace.rstrip("/")
        for robot, frame in identifiers(list(session.robots), "robot").items():
            self.robots[robot] = (frame, self._publisher(f"{prefix}/{frame}/pose", cdr.POSE_STAMPED, TOPIC_QOS),
                                  self._publisher(f"{prefix}/{frame}/odom", cdr.ODOMETRY, TOPIC_QOS))
        self.tf = self._publisher("/tf", cdr.TF_MESSAGE, TF_QOS)
        self.tf_static = self._publisher("/tf_static", cdr.TF_MESSAGE, TF_STATIC_QOS)
        self._statics(session)
        log.info("ROS 2 output (%s, %s, domain %d): %s", p.profile.value, p.distro.value, p.domain_id,
                 ", ".join(pub.topic for pub in self.publishers))

    def _statics(self, session: SessionInfo) -> None:
        """``/tf_static`` of ``session``'s calibrated cameras, sent now (and kept to send again)."""
        self.session = session
        now = time.time()
        cameras = identifiers([c.name for c in session.cameras], "camera")
        statics = []
        for camera in session.cameras:
            if camera.T_world_cam is not None:
                position, quaternion = position_quat_from_T(camera.T_world_cam)
                statics.append(cdr.Transform(now, self.world_frame, camera_frame(cameras[camera.name]),
                                             position, quaternion))
        self.static_payload = cdr.tf_message(statics)
        self._send_static(now)

    def camera_watch(self, state: CameraWatchState) -> None:
        """A re-calibrated camera's new pose goes out on ``/tf_static`` at once (latched: a
        late subscriber gets the new one)."""
        session = None if self.session is None else self.session.rejoined(state)
        if session is not None:
            self._statics(session)

    def _send_static(self, now_s: float) -> None:
        assert self.tf_static is not None and self.static_payload is not None  # set by open()
        self.tf_static.put(self.static_payload)
        self.static_sent_s = now_s

    def pose(self, pose: TrackedPose) -> None:
        if pose.robot not in self.robots:
            return
        frame, pose_pub, odom_pub = self.robots[pose.robot]
        world = self.world_frame
        pose_pub.put(cdr.pose_stamped(pose.time_s, world, pose.position_m, pose.quaternion_xyzw))
        linear = None if pose.velocity_m_s is None else into_body(pose.quaternion_xyzw, pose.velocity_m_s)
        angular = None if pose.angular_velocity_rad_s is None else into_body(pose.quaternion_xyzw,
                                                                             pose.angular_velocity_rad_s)
        odom_pub.put(cdr.odometry(pose.time_s, world, frame, pose.position_m, pose.quaternion_xyzw,
                                  _finite(pose.covariance), _finite(linear), _finite(angular)))
        assert self.tf is not None  # set by open(), which names the robots
        self.tf.put(cdr.tf_message([cdr.Transform(pose.time_s, world, frame, pose.position_m,
                                                  pose.quaternion_xyzw)]))
        now = time.time()
        if self.params.profile is Ros2Profile.BRIDGE and now - self.static_sent_s >= self.params.static_every_s:
            self._send_static(now)

    def close(self) -> None:
        if self.zenoh.is_closed():
            return
        for publisher in self.publishers:
            publisher.close()
        self.publishers = []
        if self.node_token is not None:
            self.node_token.undeclare()
            self.node_token = None
        self.zenoh.close()


def camera_frame(camera_id: str) -> str:
    """The tf frame of a camera's optical frame (x right, y down, z forward)."""
    return f"{camera_id}_optical_frame"


def into_body(quaternion_xyzw: np.ndarray, vector_world: np.ndarray) -> np.ndarray:
    """A world-frame vector in the body frame the quaternion (body in world) turns: the inverse
    rotation, ``v + 2 u x (u x v - w v)`` with ``(u, w)`` the normalised quaternion, in plain floats
    (a rotation matrix from scipy cost several times more, per pose)."""
    x, y, z, w = (float(c) for c in quaternion_xyzw)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    vx, vy, vz = (float(c) for c in vector_world)
    ax, ay, az = y * vz - z * vy - w * vx, z * vx - x * vz - w * vy, x * vy - y * vx - w * vz  # u x v - w v
    return np.array([vx + 2 * (y * az - z * ay), vy + 2 * (z * ax - x * az), vz + 2 * (x * ay - y * ax)])


def _finite(values: np.ndarray | None) -> np.ndarray | None:
    """None unless every value is finite: a ROS consumer cannot use NaN."""
    return values if values is not None and np.all(np.isfinite(values)) else None
