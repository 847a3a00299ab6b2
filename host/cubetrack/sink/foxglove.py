"""Everything in Foxglove: a live WebSocket server (``--foxglove``) or an MCAP file (``--mcap``).

Channels (foxglove-sdk well-known schemas, protobuf; names made topic-safe by
:func:`cubetrack.sink.names.identifiers`):

- ``/robots/<r>/pose`` (``foxglove.PoseInFrame``): the cube frame in ``world``
- ``/tf`` (``foxglove.FrameTransforms``): world -> ``<r>`` at every pose; world ->
  ``<c>_optical_frame`` of each calibrated camera (at the start and every ``static_every_s``)
- ``/scene`` (``foxglove.SceneUpdate``): entity ``robot/<r>``: a cube of the layout's size in the
  frame ``<r>`` (frame-locked: it moves with ``/tf``); entity ``camera/<c>``: the camera's field of
  view as a frustum ``frustum_depth_m`` deep, with its name; both at the start and every
  ``static_every_s``
- ``/cameras/<c>/image`` (``foxglove.CompressedImage``): the JPEG as received (live sessions that
  hand out views)
- ``/cameras/<c>/annotations`` (``foxglove.ImageAnnotations``): detected markers (green outlines,
  ids) and the predicted cube's markers (orange)
- ``/cameras/<c>/calibration`` (``foxglove.CameraCalibration``): intrinsics, so the image and 3D
  panels line up
- ``/cameras/<c>/health`` (JSON, schema ``cubetrack.CameraHealth``): the camera's health snapshot

Where a view carries no predicted corners, the cube is projected from the robot's latest
fused pose. The live server binds 127.0.0.1 unless another address is given. With both a server
and an MCAP file, one foxglove-sdk ``Context`` feeds both: each message is built and encoded
once. Per pose only the pose and its transform are sent; what changes slowly (the scene, the
camera transforms and calibrations) is re-sent every ``static_every_s`` for viewers that join late,
and at once with a camera's new pose when the camera watching re-calibrates it (issue 27).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import T_from_position_quat, invert_T, position_quat_from_T, transform_points
from cubetrack.core.params import check
from cubetrack.core.records import CameraHealth, CameraView, CameraWatchState, TrackedPose
from cubetrack.sink.base import CameraSetup, OutputError, SessionInfo, Sink, is_loopback_host
from cubetrack.sink.names import identifiers

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
GREEN = (0.1, 0.9, 0.2, 1.0)
ORANGE = (1.0, 0.55, 0.0, 1.0)
CUBE_COLOUR = (0.2, 0.5, 1.0, 0.8)
CAMERA_COLOUR = (0.9, 0.9, 0.9, 1.0)


@dataclass(frozen=True, slots=True)
class FoxgloveParams:
    world_frame: str = "world"
    frustum_depth_m: float = 0.3
    static_every_s: float = 1.0
    #: camera images (and their annotations) per camera per second at most; 0: every frame.
    #: Each image costs the tracker's process about 0.2 ms (MCAP) to 0.5 ms (live), so 16 cameras
    #: at 30 fps would cost it a fifth of a core for pictures nobody watches at that rate.
    image_fps: float = 10.0

    def __post_init__(self) -> None:
        check(isinstance(self.image_fps, (int, float)) and math.isfinite(self.image_fps) and self.image_fps >= 0,
              f"image_fps must be a number >= 0 (0: every frame), got {self.image_fps!r}")


def camera_frame(camera_id: str) -> str:
    return f"{camera_id}_optical_frame"


def health_schema() -> dict:
    """JSON schema of the health channel (one property per :class:`CameraHealth` field)."""
    kinds = {"str": "string", "bool": "boolean", "int": "integer", "float": ["number", "null"]}
    return {"title": "cubetrack.CameraHealth", "type": "object",
            "properties": {f.name: {"type": kinds[f.type if isinstance(f.type, str) else f.type.__name__]}
                           for f in fields(CameraHealth)}}


def _ts(time_s: float):
    from foxglove.messages import Timestamp

    sec = math.floor(time_s)
    return Timestamp(sec, min(999_999_999, int(round((time_s - sec) * 1e9))))


def _vector3(values):
    from foxglove.messages import Vector3

    x, y, z = (float(v) for v in values)
    return Vector3(x=x, y=y, z=z)


def _quaternion(xyzw):
    from foxglove.messages import Quaternion

    x, y, z, w = (float(v) for v in xyzw)
    return Quaternion(x=x, y=y, z=z, w=w)


def _pose(position_m, quaternion_xyzw):
    from foxglove.messages import Pose

    return Pose(position=_vector3(position_m), orientation=_quaternion(quaternion_xyzw))


def _colour(rgba):
    from foxglove.messages import Color

    return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def frustum_points_cam(camera: CameraSetup, depth_m: float) -> np.ndarray:
    """The four image corners back-projected ``depth_m`` in front of the camera (optical frame)."""
    if camera.intrinsics is None:
        raise ValueError(f"camera {camera.name} has no intrinsics: no frustum")
    K = np.asarray(camera.intrinsics.K, float)
    w, h = camera.intrinsics.width, camera.intrinsics.height
    pixels = np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], float)
    rays = (np.linalg.inv(K) @ pixels.T).T
    return rays * (depth_m / rays[:, 2:3])


def project(camera: CameraSetup, points_world: np.ndarray) -> np.ndarray | None:
    """Pixel positions of ``points_world`` ((N, 3)) in ``camera`` (with its distortion), None
    when any is behind it or the camera is not calibrated."""
    if camera.T_world_cam is None or camera.intrinsics is None:
        return None
    return _Projector(camera.T_world_cam, camera.intrinsics).pixels(points_world)


class _Projector:
    """Pixels of world points in one calibrated camera (with its distortion), its constants
    computed once."""

    def __init__(self, T_world_cam: np.ndarray, intrinsics: CameraIntrinsics):
        self.T_cam_world = invert_T(T_world_cam)
        self.K = np.asarray(intrinsics.K, float)
        self.dist = np.asarray(intrinsics.dist, float)

    def pixels(self, points_world: np.ndarray) -> np.ndarray | None:
        """(N, 2) pixel positions, None when any point is behind the camera."""
        import cv2

        points_cam = transform_points(self.T_cam_world, points_world)
        if np.any(points_cam[:, 2] <= 1e-3):
            return None
        pixels, _ = cv2.projectPoints(points_cam, _ZERO3, _ZERO3, self.K, self.dist)
        return pixels.reshape(-1, 2)


_ZERO3 = np.zeros(3)


class FoxgloveSink(Sink):
    """The channels above, to a live server (``server=(host, port)``), an MCAP file
    (``mcap=path``; written in line, like the trajectory files) or both from one context.
    Opens in the constructor."""

    wants_views = True

    def __init__(self, *, server: tuple[str, int] | None = None, mcap: str | Path | None = None,
                 params: FoxgloveParams = FoxgloveParams(), overwrite: bool = False):
        import foxglove

        if server is None and mcap is None:
            raise ValueError("give server=(host, port), mcap=path or both")
        self.params = params
        self.view_interval_s = 1.0 / params.image_fps if params.image_fps > 0 else 0.0
        self.context = foxglove.Context()
        self.server = self.writer = None
        names, wheres = [], []
        if mcap is not None:
            self.path = Path(mcap)
            try:
                self.writer = foxglove.open_mcap(self.path, allow_overwrite=overwrite, context=self.context)
            except (OSError, RuntimeError) as exc:
                raise OutputError(f"{self.path}: cannot write the MCAP file: {exc}") from None
            names.append("mcap")
            wheres.append(f"MCAP file {self.path}")
        if server is not None:
            host, port = server
            try:
                self.server = foxglove.start_server(name="cubetrack", host=host, port=port, context=self.context)
            except RuntimeError as exc:
                self.close()
                raise OutputError(f"Foxglove server cannot listen on {host}:{port}: "
                                  f"{str(exc).removeprefix('FoxgloveError: ')}") from None
            where = f"Foxglove WebSocket ws://{host}:{self.server.port}"
            if is_loopback_host(host):
                log.info("%s (loopback only)", where)
            else:
                log.warning("%s: reachable from other machines", where)
            names.insert(0, "foxglove")
            wheres.insert(0, where)
        self.name, self.where = " + ".join(names), "; ".join(wheres)
        self.in_line = self.writer is not None  # a file holds everything, like the trajectory files
        self.robots: dict[str, str] = {}
        self.cameras: dict[str, CameraSetup] = {}
        self.camera_ids: dict[str, str] = {}
        self.cube_size_m: dict[str, np.ndarray] = {}
        self.cube_markers_m: dict[str, np.ndarray] = {}
        self.projectors: dict[str, _Projector] = {}
        self.last_pose: dict[str, TrackedPose] = {}
        self.cube_world_m: dict[str, np.ndarray] = {}  # marker corners at the last pose, once a view needed them
        self.channels: dict[str, Any] = {}  # foxglove-sdk channels (no common base class)
        self.static_sent_s = -math.inf
        self.session: SessionInfo | None = None

    @property
    def port(self) -> int:
        if self.server is None:
            raise ValueError("no WebSocket server (an MCAP file only, or closed)")
        return self.server.port

    def _channel(self, topic: str, kind: str):
        channel = self.channels.get(topic)
        if channel is None:
            import foxglove
            from foxglove import channels

            if kind == "health":
                channel = foxglove.Channel(topic, schema=health_schema(), context=self.context)
            else:
                channel = getattr(channels, f"{kind}Channel")(topic, context=self.context)
            self.channels[topic] = channel
        return channel

    def _set_cameras(self, session: SessionInfo) -> None:
        self.session = session
        self.cameras = {c.name: c for c in session.cameras}
        self.projectors = {c.name: _Projector(c.T_world_cam, c.intrinsics) for c in session.cameras
                           if c.T_world_cam is not None and c.intrinsics is not None}

    def camera_watch(self, state: CameraWatchState) -> None:
        """A re-calibrated camera's new pose: its transform, frustum and projection, sent at once."""
        session = None if self.session is None else self.session.rejoined(state)
        if session is not None:
            self._set_cameras(session)
            self._send_static(state.time_s)

    def open(self, session: SessionInfo) -> None:
        self.robots = identifiers(list(session.robots), "robot")
        self.camera_ids = identifiers([c.name for c in session.cameras], "camera")
        self._set_cameras(session)
        for robot, layout in session.robots.items():
            corners = layout.corners_m.reshape(-1, 4, 3)
            self.cube_markers_m[robot] = corners
            self.cube_size_m[robot] = 2 * np.abs(corners.reshape(-1, 3)).max(axis=0)
            self._channel(f"/robots/{self.robots[robot]}/pose", "PoseInFrame")
        for c in session.cameras:
            cid = self.camera_ids[c.name]
            for suffix, kind in (("image", "CompressedImage"), ("annotations", "ImageAnnotations"),
                                 ("calibration", "CameraCalibration"), ("health", "health")):
                self._channel(f"/cameras/{cid}/{suffix}", kind)
        self._channel("/tf", "FrameTransforms")
        self._channel("/scene", "SceneUpdate")
        self._send_static(time.time())

    def _log(self, topic: str, message, time_s: float) -> None:
        self.channels[topic].log(message, log_time=int(time_s * 1e9))

    def _send_static(self, time_s: float) -> None:
        """Camera transforms, calibrations and frusta, the robots' cubes (re-sent so late viewers
        get them)."""
        from foxglove.messages import (
            CameraCalibration,
            CubePrimitive,
            FrameTransform,
            FrameTransforms,
            LinePrimitive,
            LinePrimitiveLineType,
            Point3,
            SceneEntity,
            SceneUpdate,
            TextPrimitive,
        )

        world = self.params.world_frame
        transforms = []
        entities = [SceneEntity(timestamp=_ts(time_s), frame_id=rid, id=f"robot/{rid}", frame_locked=True,
                                cubes=[CubePrimitive(pose=_pose(_ZERO3, (0.0, 0.0, 0.0, 1.0)),
                                                     size=_vector3(self.cube_size_m[robot]),
                                                     color=_colour(CUBE_COLOUR))])
                    for robot, rid in self.robots.items() if robot in self.cube_size_m]
        for name, camera in self.cameras.items():
            cid = self.camera_ids[name]
            if camera.intrinsics is not None:
                intr = camera.intrinsics
                K = np.asarray(intr.K, float)
                P = np.hstack([K, np.zeros((3, 1))])
                self._log(f"/cameras/{cid}/calibration", CameraCalibration(
                    timestamp=_ts(time_s), frame_id=camera_frame(cid), width=intr.width, height=intr.height,
                    distortion_model="plumb_bob", D=[float(v) for v in np.asarray(intr.dist).reshape(-1)],
                    K=[float(v) for v in K.reshape(-1)], R=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                    P=[float(v) for v in P.reshape(-1)]), time_s)
            if camera.T_world_cam is None:
                continue
            position, quaternion = position_quat_from_T(camera.T_world_cam)
            transforms.append(FrameTransform(
                timestamp=_ts(time_s), parent_frame_id=world, child_frame_id=camera_frame(cid),
                translation=_vector3(position), rotation=_quaternion(quaternion)))
            if camera.intrinsics is None:
                continue
            corners = frustum_points_cam(camera, self.params.frustum_depth_m)
            origin = np.zeros(3)
            segments = [p for c in corners for p in (origin, c)]
            segments += [p for i in range(4) for p in (corners[i], corners[(i + 1) % 4])]
            entities.append(SceneEntity(
                timestamp=_ts(time_s), frame_id=world, id=f"camera/{cid}", frame_locked=True,
                lines=[LinePrimitive(type=LinePrimitiveLineType.LineList, pose=_pose(position, quaternion),
                                     thickness=2.0, scale_invariant=True, color=_colour(CAMERA_COLOUR),
                                     points=[Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in segments])],
                texts=[TextPrimitive(pose=_pose(position, quaternion), billboard=True, font_size=14.0,
                                     scale_invariant=True, color=_colour(CAMERA_COLOUR), text=name)]))
        self._log("/tf", FrameTransforms(transforms=transforms), time_s)
        self._log("/scene", SceneUpdate(entities=entities), time_s)
        self.static_sent_s = time_s

    def pose(self, pose: TrackedPose) -> None:
        from foxglove.messages import FrameTransform, FrameTransforms, PoseInFrame

        rid = self.robots.get(pose.robot)
        if rid is None:
            return
        t, world = pose.time_s, self.params.world_frame
        stamp = _ts(t)
        self._log(f"/robots/{rid}/pose", PoseInFrame(timestamp=stamp, frame_id=world, pose=_pose(
            pose.position_m, pose.quaternion_xyzw)), t)
        self._log("/tf", FrameTransforms(transforms=[FrameTransform(
            timestamp=stamp, parent_frame_id=world, child_frame_id=rid, translation=_vector3(pose.position_m),
            rotation=_quaternion(pose.quaternion_xyzw))]), t)
        self.last_pose[pose.robot] = pose
        self.cube_world_m.pop(pose.robot, None)
        if t - self.static_sent_s >= self.params.static_every_s:
            self._send_static(t)

    def camera_view(self, view: CameraView) -> None:
        from foxglove.messages import (
            CompressedImage,
            ImageAnnotations,
            Point2,
            PointsAnnotation,
            PointsAnnotationType,
            TextAnnotation,
        )

        cid = self.camera_ids.get(view.camera)
        if cid is None:
            return
        t = view.time_s
        self._log(f"/cameras/{cid}/image", CompressedImage(timestamp=_ts(t), frame_id=camera_frame(cid),
                                                          data=view.jpeg, format="jpeg"), t)

        def outline(corners, colour):
            return PointsAnnotation(timestamp=_ts(t), type=PointsAnnotationType.LineLoop, thickness=2.0,
                                    outline_color=_colour(colour),
                                    points=[Point2(x=float(x), y=float(y)) for x, y in corners])

        points = [outline(d.corners_px, GREEN) for d in view.detections]
        texts = [TextAnnotation(timestamp=_ts(t), position=Point2(x=float(d.corners_px[0][0]),
                                                                  y=float(d.corners_px[0][1])),
                                text=str(d.marker_id), font_size=14.0, text_color=_colour(GREEN),
                                background_color=_colour((0, 0, 0, 0.5))) for d in view.detections]
        projector = self.projectors.get(view.camera)
        for robot in self.robots:
            corners = view.predicted_corners_px.get(robot)
            if corners is None and robot in self.last_pose and projector is not None:
                corners = projector.pixels(self._cube_world(robot))
            if corners is not None:
                points += [outline(square, ORANGE) for square in np.asarray(corners).reshape(-1, 4, 2)]
        self._log(f"/cameras/{cid}/annotations", ImageAnnotations(timestamp=_ts(t), points=points, texts=texts), t)

    def _cube_world(self, robot: str) -> np.ndarray:
        """The robot's marker corners in the world at its last pose (computed once per pose)."""
        corners = self.cube_world_m.get(robot)
        if corners is None:
            last = self.last_pose[robot]
            corners = self.cube_world_m[robot] = transform_points(T_from_position_quat(
                last.position_m, last.quaternion_xyzw), self.cube_markers_m[robot].reshape(-1, 3))
        return corners

    def camera_health(self, health: CameraHealth) -> None:
        cid = self.camera_ids.get(health.camera)
        if cid is None:
            return
        values = {f.name: getattr(health, f.name) for f in fields(CameraHealth)}
        self._log(f"/cameras/{cid}/health", {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                                             for k, v in values.items()}, health.time_s)

    def close(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None
        if self.writer is not None:
            self.writer.close()
            self.writer = None


def layout(robot_ids: list[str], camera_ids: list[str]) -> str:
    """A Foxglove layout (JSON) that opens everything at once: the 3D scene (cubes, camera
    frusta, poses), one image panel per camera with its annotations, the robots' positions
    over time, and a health table per camera."""
    import foxglove.layouts as fl

    three_d = fl.ThreeDeePanel(title="world", config=fl.ThreeDeeConfig(
        follow_tf="world",
        topics={"/scene": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
                **{f"/robots/{r}/pose": fl.BaseRendererPoseTopicSettings(visible=True, type="axis", axis_scale=0.15)
                   for r in robot_ids}}))
    images = [fl.SplitItem(content=fl.ImagePanel(title=c, config=fl.ImageConfig(image_mode=fl.ImageModeConfig(
        image_topic=f"/cameras/{c}/image", calibration_topic=f"/cameras/{c}/calibration",
        annotations={f"/cameras/{c}/annotations": fl.ImageAnnotationSettings(visible=True)}))))
        for c in camera_ids]
    plot = fl.PlotPanel(title="positions (m)", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value=f"/robots/{r}/pose.pose.position.{axis}", label=f"{r} {axis}")
        for r in robot_ids for axis in "xyz"]))
    health = fl.TabContainer(tabs=[fl.TabItem(title=f"{c} health", content=fl.TablePanel(
        config=fl.TableConfig(topic_path=f"/cameras/{c}/health"))) for c in camera_ids])
    right = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=2, content=fl.SplitContainer(direction="row", items=images)),
        fl.SplitItem(content=plot), fl.SplitItem(content=health)])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=1.2, content=three_d), fl.SplitItem(content=right)])).to_json()
