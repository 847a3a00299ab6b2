"""Poses, velocities, robot status and camera health as JSON on Zenoh.

Key expressions (``<prefix>`` default ``cubetrack``; robot and camera names made key-safe by
:func:`cubetrack.sink.names.identifiers`, the real names are inside the JSON), each value JSON (encoding
``application/json``):

- ``<prefix>/robots/<r>/pose``: the JSONL object of contracts §5 (time, robot, position,
  quaternion_xyzw, cameras, markers, latency, ...)
- ``<prefix>/robots/<r>/velocity``: ``{"time", "robot", "frame": "world", "linear_m_s": [3],
  "angular_rad_s": [3]}`` when the fusion estimates it
- ``<prefix>/robots/<r>/status``: ``{"time", "robot", "tracking", "poses_per_s", "last_pose_time",
  "cameras"}`` about once a second
- ``<prefix>/cameras/<c>/health``: a :class:`cubetrack.core.records.CameraHealth` (NaN -> null)
- ``<prefix>/session``: world marker, cameras (pose in the world, intrinsics), robots and the key
  names; also answered as a query; put again with a camera's new pose when the camera watching
  re-calibrates it (issue 27)

``tracking`` turns false when a robot's last pose is older than ``lost_after_s``; status is
sent with poses and with camera health (live sessions), so a lost robot is reported as such.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from cubetrack.core.geometry import position_quat_from_T
from cubetrack.core.records import CameraHealth, CameraWatchState, TrackedPose
from cubetrack.io.trajectory import pose_to_json
from cubetrack.sink.base import SessionInfo, Sink
from cubetrack.sink.names import identifier, identifiers
from cubetrack.sink.zenoh_session import ZenohEndpoints, json_endpoints, open_session

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class ZenohJsonParams:
    """``prefix``: first chunk(s) of every key; ``status_every_s``: seconds between status
    messages per robot; ``lost_after_s``: a robot without a pose for this long is not tracking."""

    prefix: str = "cubetrack"
    status_every_s: float = 1.0
    lost_after_s: float = 1.0


def _key_prefix(text: str) -> str:
    return "/".join(identifier(t, "k") for t in text.split("/") if t.strip()) or "cubetrack"


def _json(value) -> bytes:
    return json.dumps(value, allow_nan=False).encode("utf-8")


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


class _RobotStatus:
    """Pose count and last pose of one robot, for its status message."""

    def __init__(self) -> None:
        self.last_pose_s: float | None = None  # host clock when the last pose was sent
        self.last_time_s: float | None = None  # the last pose's own time
        self.cameras: tuple[str, ...] = ()
        self.count = 0
        self.sent_s = 0.0
        self.sent_count = 0


class ZenohJsonSink(Sink):
    """Publishes JSON on Zenoh (module doc). The session opens in the constructor."""

    name = "zenoh"

    def __init__(self, params: ZenohJsonParams = ZenohJsonParams(), endpoints: ZenohEndpoints | None = None,
                 clock=time.time):
        self.params = params
        self.prefix = _key_prefix(params.prefix)
        self.clock = clock
        endpoints = endpoints or json_endpoints()
        self.zenoh = open_session(endpoints, "Zenoh output")
        self.where = (f"Zenoh JSON under {self.prefix}/** (listening on {', '.join(endpoints.listen) or '-'}"
                      f"{', connecting to ' + ', '.join(endpoints.connect) if endpoints.connect else ''})")
        self.robot_ids: dict[str, str] = {}
        self.camera_ids: dict[str, str] = {}
        self.status: dict[str, _RobotStatus] = {}
        self.publishers: dict[str, Any] = {}  # zenoh publishers
        self.session_doc: bytes = b"{}"
        self.session: SessionInfo | None = None
        self.queryable = None

    def _put(self, key: str, value: dict) -> None:
        import zenoh

        publisher = self.publishers.get(key)
        if publisher is None:
            publisher = self.publishers[key] = self.zenoh.declare_publisher(
                key, encoding=zenoh.Encoding.APPLICATION_JSON, congestion_control=zenoh.CongestionControl.DROP)
        publisher.put(_json(value))

    def open(self, session: SessionInfo) -> None:
        import zenoh

        self.robot_ids = identifiers(list(session.robots), "robot")
        self.camera_ids = identifiers([c.name for c in session.cameras], "camera")
        self.status = {robot: _RobotStatus() for robot in session.robots}
        key = f"{self.prefix}/session"
        self._put_session(session)
        self.queryable = self.zenoh.declare_queryable(
            key, lambda query: query.reply(key, self.session_doc, encoding=zenoh.Encoding.APPLICATION_JSON))
        log.info("Zenoh output: JSON under %s/** (robots: %s)", self.prefix,
                 ", ".join(f"{self.prefix}/robots/{r}" for r in self.robot_ids.values()))

    def camera_watch(self, state: CameraWatchState) -> None:
        """A re-calibrated camera's new pose: the session document again, put and answered."""
        session = None if self.session is None else self.session.rejoined(state)
        if session is not None:
            self._put_session(session)

    def _put_session(self, session: SessionInfo) -> None:
        """The session document (world, cameras, robots and their keys), put and kept for queries."""
        self.session = session
        cameras = []
        for c in session.cameras:
            entry: dict[str, Any] = {"name": c.name,
                                     "health_key": f"{self.prefix}/cameras/{self.camera_ids[c.name]}/health",
                                     "position": None, "quaternion_xyzw": None, "intrinsics": None}
            if c.T_world_cam is not None:
                position, quaternion = position_quat_from_T(c.T_world_cam)
                entry["position"], entry["quaternion_xyzw"] = position.tolist(), quaternion.tolist()
            if c.intrinsics is not None:
                entry["intrinsics"] = {"width": c.intrinsics.width, "height": c.intrinsics.height,
                                       "K": np.asarray(c.intrinsics.K).tolist(),
                                       "distortion": np.asarray(c.intrinsics.dist).reshape(-1).tolist()}
            cameras.append(entry)
        robots = [{"name": r, **{k: f"{self.prefix}/robots/{self.robot_ids[r]}/{k}"
                                 for k in ("pose", "velocity", "status")}} for r in session.robots]
        doc = {"world": asdict(session.world), "cameras": cameras, "robots": robots}
        self.session_doc = _json(doc)
        self._put(f"{self.prefix}/session", doc)

    def pose(self, pose: TrackedPose) -> None:
        robot_id = self.robot_ids.get(pose.robot)
        if robot_id is None:
            return
        base = f"{self.prefix}/robots/{robot_id}"
        self._put(f"{base}/pose", pose_to_json(pose))
        if pose.velocity_m_s is not None and pose.angular_velocity_rad_s is not None:
            self._put(f"{base}/velocity", {
                "time": round(float(pose.time_s), 6), "robot": pose.robot, "frame": "world",
                "linear_m_s": [_finite(v) for v in pose.velocity_m_s],
                "angular_rad_s": [_finite(v) for v in pose.angular_velocity_rad_s]})
        status = self.status[pose.robot]
        now = self.clock()
        status.last_pose_s, status.last_time_s, status.cameras = now, pose.time_s, pose.cameras
        status.count += 1
        self._send_status(pose.robot, now)

    def _send_status(self, robot: str, now: float, force: bool = False) -> None:
        status = self.status[robot]
        if not force and now - status.sent_s < self.params.status_every_s:
            return
        span = now - status.sent_s if status.sent_s else None
        rate = (status.count - status.sent_count) / span if span else None
        tracking = status.last_pose_s is not None and now - status.last_pose_s <= self.params.lost_after_s
        self._put(f"{self.prefix}/robots/{self.robot_ids[robot]}/status", {
            "time": round(now, 6), "robot": robot, "tracking": tracking,
            "poses_per_s": None if rate is None else round(rate, 3),
            "last_pose_time": None if status.last_time_s is None else round(status.last_time_s, 6),
            "cameras": list(status.cameras) if tracking else []})
        status.sent_s, status.sent_count = now, status.count

    def camera_health(self, health: CameraHealth) -> None:
        camera_id = self.camera_ids.get(health.camera) or identifier(health.camera, "camera")
        self._put(f"{self.prefix}/cameras/{camera_id}/health",
                  {k: (_finite(v) if isinstance(v, float) else v) for k, v in asdict(health).items()})
        now = self.clock()
        for robot in self.status:
            self._send_status(robot, now)

    def close(self) -> None:
        if self.zenoh.is_closed():
            return
        now = self.clock()
        for robot in self.status:
            self._send_status(robot, now, force=True)
        for publisher in self.publishers.values():
            publisher.undeclare()
        if self.queryable is not None:
            self.queryable.undeclare()
        self.zenoh.close()
