"""What the dashboard shows: one thread-safe model, fed by the session and read by the server.

The session feeds it (through :class:`~cubetrack.sink.dashboard.server.DashboardSink`): the
static facts (:class:`~cubetrack.sink.base.SessionInfo`), each camera's health snapshots and
processed frames, each robot's poses. The workflow around the session (``cubetrack dashboard``)
adds *panels*: JSON documents such as the calibration steps or the recording controls. Every
change is also published as an event (:class:`EventHub`) for the page's event stream.

Every part has one JSON form (:meth:`DashboardState.camera_json`,
:func:`cubetrack.sink.dashboard.server.topview_json`, ...); the page shows nothing else, so whatever
it shows can be read from the JSON endpoints too.

A camera's status (:func:`camera_status`):

``ok``       frames arrive;
``waiting``  nothing heard yet (no health snapshot, connecting, or connected without a frame so far);
``down``     not connected, or connected with only broken frames so far: the reason is the source's
             last error, one line saying what to check (:mod:`cubetrack.source.reasons`);
``stale``    connected but no frame for ``stale_after_s``: the reason says for how long, and the
             last error or what to check.

``down`` and ``stale`` are shown red. Statuses are recomputed by :meth:`DashboardState.tick`
(the server calls it four times a second), so a camera that stops sending turns red within
``stale_after_s`` plus a tick, whether or not its health snapshots keep coming.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from cubetrack.core.geometry import T_from_position_quat
from cubetrack.core.params import check, check_positive, param
from cubetrack.core.records import CameraHealth, CameraView, CameraWatchState, TrackedPose
from cubetrack.sink.base import CameraSetup, SessionInfo

HEALTH_FIELDS = tuple(f.name for f in dataclasses.fields(CameraHealth))


@dataclass(frozen=True, slots=True)
class DashboardParams:
    """The ``[dashboard]`` section: how the dashboard shows a session (``cubetrack dashboard``
    and ``--dashboard``) and how its guided calibration judges a camera and paces the steps."""

    tile_width_px: int = param(320, "camera tiles: frames are scaled down to this width, pixels")
    jpeg_quality: int = param(75, "camera tiles: JPEG quality of the annotated frames, 1-100")
    stale_after_s: float = param(1.0, "a connected camera whose newest frame is older than this is shown red, seconds")
    trail_s: float = param(10.0, "top view: each robot's trail covers this many seconds")
    trail_points: int = param(200, "top view: at most this many points of a trail are sent to the page")
    seen_within_s: float = param(1.0, "a camera sees a robot while it took part in one of its poses "
                                      "within this, seconds")
    views_per_s: float = param(5.0, "camera tiles: at most this many new frames per second are announced per camera")
    poses_per_s: float = param(10.0, "top view: at most this many pose updates per second are announced per robot")
    floor_range_m: float = param(4.0, "top view: a camera's field of view is drawn on the floor up to this "
                                      "distance, metres")
    tick_s: float = param(0.25, "camera statuses are recomputed this often, seconds")
    max_clients: int = param(32, "HTTP connections served at once; more are answered 503")
    client_timeout_s: float = param(10.0, "a client that sends its request or reads the event stream slower than this "
                                          "is dropped, seconds")
    min_marker_side_px: float = param(
        30.0, "calibration: the world marker should appear at least this wide in a camera (square root of its pixel "
        "area); smaller: move the camera closer or print a bigger marker, pixels")
    max_spread_cm: float = param(1.0, "calibration: a camera whose per-frame poses scatter more than this is "
                                      "poor, centimetres")
    max_spread_deg: float = param(0.5, "calibration: ... or more than this, degrees")
    max_reprojection_px: float = param(
        1.0, "calibration: a camera whose detected world-marker corners lie farther (RMS) than this from where its "
        "calibrated pose projects them is poor, pixels")
    min_inlier_fraction: float = param(
        0.7, "calibration: a camera whose calibration kept fewer than this fraction of its world-marker sightings "
        "(the others were outliers) is poor")
    check_frames: int = param(30, "calibration: frames of each camera's calibration recording the reprojection "
                                  "error is measured on")
    check_every_s: float = param(0.5, "outside the collection, each camera's newest frame is searched for the "
                                 "world marker this often, seconds")
    drive_instants: int = param(150, "calibration, drive step: instants to collect before refining: sightings of one "
                                "robot by at least [bundle_adjustment] min_cameras cameras within its max_span_s, each "
                                "sighting counted in one instant (as the bundle adjustment groups them)")

    def __post_init__(self) -> None:
        check(16 <= self.tile_width_px <= 4096, f"tile_width_px must be 16..4096, got {self.tile_width_px}")
        check(1 <= self.jpeg_quality <= 100, f"jpeg_quality must be 1..100, got {self.jpeg_quality}")
        check(self.trail_points >= 2, f"trail_points must be at least 2, got {self.trail_points}")
        check(self.max_clients >= 1, f"max_clients must be at least 1, got {self.max_clients}")
        check_positive(self, "stale_after_s", "trail_s", "seen_within_s", "views_per_s", "poses_per_s",
                       "floor_range_m", "tick_s", "client_timeout_s", "min_marker_side_px", "max_spread_cm",
                       "max_spread_deg", "max_reprojection_px", "check_every_s")
        check(0.0 <= self.min_inlier_fraction <= 1.0,
              f"min_inlier_fraction must be within 0..1, got {self.min_inlier_fraction}")
        check(self.check_frames >= 1 and self.drive_instants >= 1, "check_frames and drive_instants must be at least 1")


def finite(value: float) -> float | None:
    """``value`` as JSON allows it: None for NaN and infinities."""
    return float(value) if math.isfinite(value) else None


def health_json(health: CameraHealth) -> dict:
    """Every field of a health snapshot (NaN -> null)."""
    out = {}
    for name in HEALTH_FIELDS:
        value = getattr(health, name)
        out[name] = finite(value) if isinstance(value, float) else value
    return out


def camera_status(health: CameraHealth | None, last_frame_s: float | None, now_s: float,
                  stale_after_s: float) -> tuple[str, str]:
    """(status, reason) of a camera (see the module doc): from its newest health snapshot and
    the host time its newest frame was seen (None: never)."""
    if health is None:
        if last_frame_s is not None and now_s - last_frame_s <= stale_after_s:
            return "ok", ""
        return "waiting", "no answer from the camera yet"
    if not health.connected:
        if not (health.last_error or health.reconnects or health.frames):
            return "waiting", "connecting"  # the session has just started
        return "down", health.last_error or "not connected"
    if last_frame_s is None:  # connected: broken frames only is as bad as no camera
        if health.bad and health.last_error:
            return "down", health.last_error
        return "waiting", "connected, no frame yet"
    age_s = now_s - last_frame_s
    if age_s > stale_after_s:
        reason = f"no frame for {age_s:.1f} s"
        return "stale", (f"{reason}; last error: {health.last_error}" if health.last_error
                         else f"{reason} — is the node still on and in Wi-Fi range?")
    return "ok", ""


class EventHub:
    """Events for the page's event stream. Each subscriber has a bounded queue; one that falls
    behind loses its oldest events and is told to re-read the state (a ``resync`` event)."""

    def __init__(self, max_events: int = 512):
        self.max_events = max_events
        self._lock = threading.Lock()
        self._subscribers: list[Subscription] = []

    def subscribe(self) -> Subscription:
        sub = Subscription(self.max_events)
        with self._lock:
            self._subscribers.append(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        with self._lock:
            if sub in self._subscribers:
                self._subscribers.remove(sub)

    @property
    def subscribers(self) -> int:
        with self._lock:
            return len(self._subscribers)

    def publish(self, kind: str, data: dict) -> None:
        with self._lock:
            subs = list(self._subscribers)
        for sub in subs:
            sub.put(kind, data)

    def close(self) -> None:
        with self._lock:
            subs, self._subscribers = self._subscribers, []
        for sub in subs:
            sub.close()


class Subscription:
    """One event-stream client's queue (see :class:`EventHub`)."""

    def __init__(self, max_events: int):
        self._events: deque[tuple[str, dict]] = deque()
        self._max = max_events
        self._ready = threading.Condition()
        self.closed = False
        self.lost = 0

    def put(self, kind: str, data: dict) -> None:
        with self._ready:
            if len(self._events) >= self._max:
                self._events.clear()
                self._events.append(("resync", {}))
                self.lost += 1
            self._events.append((kind, data))
            self._ready.notify()

    def take(self, timeout_s: float) -> list[tuple[str, dict]]:
        """The events queued so far, waiting up to ``timeout_s`` for one; [] on timeout or close."""
        with self._ready:
            if not self._events and not self.closed:
                self._ready.wait(timeout_s)
            events = list(self._events)
            self._events.clear()
            return events

    def close(self) -> None:
        with self._ready:
            self.closed = True
            self._ready.notify_all()


class _Camera:
    """What the state knows of one camera (internal, guarded by the state's lock)."""

    def __init__(self, name: str, url: str = ""):
        self.name = name
        self.url = url
        self.setup: CameraSetup | None = None
        self.health: CameraHealth | None = None
        self.last_frame_s: float | None = None  # host time a new frame was last seen
        self.frames = 0  # frames the newest health snapshot of this session counted
        self.view: CameraView | None = None
        self.view_announced_s = -math.inf
        self.status = ("waiting", "no answer from the camera yet")
        self.status_sent_s = -math.inf
        self.watch: CameraWatchState | None = None  # what the camera watching says of it (issue 27)


class _Robot:
    """One robot's trail and who sees it (internal, guarded by the state's lock)."""

    def __init__(self, name: str):
        self.name = name
        self.last: TrackedPose | None = None
        self.T_world_cube: np.ndarray | None = None
        self.trail: deque[tuple[float, float, float, float]] = deque()  # (time_s, x, y, z)
        self.seen_s: dict[str, float] = {}  # camera -> host time it last took part in a pose
        self.announced_s = -math.inf


class DashboardState:
    """The dashboard's model (see the module doc). Every method is thread-safe; ``clock`` gives
    host Unix time."""

    def __init__(self, params: DashboardParams = DashboardParams(), clock: Callable[[], float] = time.time,
                 camera_urls: dict[str, str] | None = None):
        self.params = params
        self.clock = clock
        self.events = EventHub()
        self._lock = threading.RLock()
        self.session: SessionInfo | None = None
        self.session_state = "starting"
        self.session_started_s: float | None = None
        self._cameras: dict[str, _Camera] = {name: _Camera(name, url) for name, url in (camera_urls or {}).items()}
        self._robots: dict[str, _Robot] = {}
        self._panels: dict[str, dict] = {}

    # --- fed by the session ---

    def open_session(self, session: SessionInfo) -> None:
        """A session starts: its cameras (calibrated or not) and robots. What earlier sessions
        showed (health, last frames, trails) is kept, so nothing blanks between sessions."""
        with self._lock:
            self.session = session
            self.session_state = "running"
            self.session_started_s = self.clock()
            for setup in session.cameras:
                cam = self._camera(setup.name)
                cam.setup = setup
                cam.frames = 0  # a new session counts frames from zero
            for robot in session.robots:
                self._robots.setdefault(robot, _Robot(robot))
            data = self.session_json()
        self.events.publish("session", data)

    def close_session(self) -> None:
        with self._lock:
            self.session_state = "ended"
            data = self.session_json()
        self.events.publish("session", data)

    def camera_health(self, health: CameraHealth) -> None:
        with self._lock:
            cam = self._camera(health.camera)
            if health.frames > cam.frames:
                cam.last_frame_s = max(cam.last_frame_s or -math.inf, health.time_s)
            cam.frames = health.frames
            cam.health = health
            self._update_status(cam, force=True)

    def camera_watch(self, state: CameraWatchState) -> None:
        with self._lock:
            cam = self._camera(state.camera)
            cam.watch = state
            self._update_status(cam, force=True)

    def camera_view(self, view: CameraView) -> None:
        now_s = self.clock()
        with self._lock:
            cam = self._camera(view.camera)
            cam.view = view
            cam.last_frame_s = now_s
            self._update_status(cam)
            if now_s - cam.view_announced_s < 1.0 / self.params.views_per_s:
                return
            cam.view_announced_s = now_s
            data = self.view_meta(cam)
        assert data is not None  # cam.view was just set
        self.events.publish("view", {"camera": view.camera, **data})

    def pose(self, pose: TrackedPose) -> None:
        now_s = self.clock()
        with self._lock:
            robot = self._robots.setdefault(pose.robot, _Robot(pose.robot))
            robot.last = pose
            robot.T_world_cube = T_from_position_quat(pose.position_m, pose.quaternion_xyzw)
            x, y, z = (float(v) for v in pose.position_m)
            if not robot.trail or pose.time_s >= robot.trail[-1][0]:
                robot.trail.append((pose.time_s, x, y, z))
            while robot.trail and robot.trail[0][0] < pose.time_s - self.params.trail_s:
                robot.trail.popleft()
            for camera in pose.cameras:
                robot.seen_s[camera] = now_s
            if now_s - robot.announced_s < 1.0 / self.params.poses_per_s:
                return
            robot.announced_s = now_s
            data = self.robot_json(robot)
        self.events.publish("robot", data)

    def tick(self) -> None:
        """Recompute every camera's status (a camera that went silent turns red here) and
        announce each camera about once a second (its frame age moves on)."""
        with self._lock:
            for cam in self._cameras.values():
                self._update_status(cam)

    # --- fed by the workflow ---

    def set_panel(self, name: str, value: dict) -> None:
        """Replace a panel (a JSON document the workflow owns, e.g. ``calibration``)."""
        with self._lock:
            self._panels[name] = value
        self.events.publish("panel", {"name": name, "value": value})

    def panel(self, name: str) -> dict | None:
        with self._lock:
            return self._panels.get(name)

    @property
    def panel_names(self) -> tuple[str, ...]:
        with self._lock:
            return tuple(self._panels)

    # --- internals ---

    def _camera(self, name: str) -> _Camera:
        cam = self._cameras.get(name)
        if cam is None:
            cam = self._cameras[name] = _Camera(name)
        return cam

    def _update_status(self, cam: _Camera, force: bool = False) -> bool:
        """Recompute ``cam``'s status; announce it when its kind changed, when ``force``d, or a
        second after the last announcement. Returns whether an event went out (caller holds the lock)."""
        now_s = self.clock()
        status = camera_status(cam.health, cam.last_frame_s, now_s, self.params.stale_after_s)
        announce = force or status[0] != cam.status[0] or now_s - cam.status_sent_s >= 1.0
        cam.status = status
        if not announce:
            return False
        cam.status_sent_s = now_s
        self.events.publish("camera", self._camera_json(cam, now_s))
        return True

    # --- JSON ---

    def session_json(self) -> dict:
        with self._lock:
            s = self.session
            out: dict[str, Any] = {"state": self.session_state, "started_s": self.session_started_s,
                   "cameras": list(self._cameras), "robots": list(self._robots)}
            if s is not None:
                out["world"] = {"dictionary": s.world.dictionary, "marker_id": s.world.marker_id,
                                "marker_size_m": s.world.marker_size_m}
                out["calibrated"] = bool(s.cameras) and all(c.T_world_cam is not None for c in s.cameras)
            return out

    def camera_names(self) -> list[str]:
        with self._lock:
            return list(self._cameras)

    def camera_json(self, name: str) -> dict | None:
        """A camera's state as of now: its status is recomputed here, not only at the next tick,
        so an answer never says ``ok`` about a frame older than ``stale_after_s`` (however late
        the tick thread runs on a loaded machine)."""
        with self._lock:
            cam = self._cameras.get(name)
            if cam is None:
                return None
            self._update_status(cam)
            return self._camera_json(cam, self.clock())

    def cameras_json(self) -> list[dict]:
        with self._lock:
            for cam in self._cameras.values():
                self._update_status(cam)
            now_s = self.clock()
            return [self._camera_json(cam, now_s) for cam in self._cameras.values()]

    def _camera_json(self, cam: _Camera, now_s: float) -> dict:
        setup = cam.setup
        T = setup.T_world_cam if setup is not None else None
        return {
            "name": cam.name,
            "url": cam.url,
            "status": cam.status[0],
            "reason": cam.status[1],
            "calibrated": T is not None,
            "position_m": None if T is None else [float(v) for v in T[:3, 3]],
            "frame_age_s": None if cam.last_frame_s is None else max(0.0, now_s - cam.last_frame_s),
            "health": None if cam.health is None else health_json(cam.health),
            "view": self.view_meta(cam),
            "watch": None if cam.watch is None else {"state": cam.watch.state, "progress": cam.watch.progress,
                                                     "message": cam.watch.message, "time_s": cam.watch.time_s},
        }

    @staticmethod
    def view_meta(cam: _Camera) -> dict | None:
        view = cam.view
        if view is None:
            return None
        return {"seq": view.seq, "time_s": view.time_s, "markers": len(view.detections),
                "jpeg_bytes": len(view.jpeg), "frame": f"/api/cameras/{cam.name}/frame.jpg?seq={view.seq}"}

    def view_inputs(self, name: str):
        """What drawing a camera's newest frame needs: (view, camera setup, [(layout, T_world_cube)]
        of the robots seen recently, world), or None without a frame."""
        with self._lock:
            cam = self._cameras.get(name)
            if cam is None or cam.view is None:
                return None
            cubes = []
            if self.session is not None:
                for robot in self._robots.values():
                    layout = self.session.robots.get(robot.name)
                    if layout is not None and robot.T_world_cube is not None and robot.last is not None \
                            and cam.view.time_s - robot.last.time_s <= self.params.seen_within_s:
                        cubes.append((robot.name, layout, robot.T_world_cube))
            world = self.session.world if self.session is not None else None
            return cam.view, cam.setup, cubes, world

    def robot_json(self, robot: _Robot) -> dict:
        now_s = self.clock()
        pose = robot.last
        trail = list(robot.trail)
        step = max(1, math.ceil(len(trail) / self.params.trail_points))
        trail = trail[::-1][::step][::-1]  # keep the newest point
        out = {"name": robot.name, "trail": [[t, x, y] for t, x, y, _ in trail],
               "seen_by": sorted(c for c, s in robot.seen_s.items() if now_s - s <= self.params.seen_within_s)}
        if pose is None or robot.T_world_cube is None:  # (set together)
            return {**out, "time_s": None, "position_m": None, "yaw_deg": None, "quaternion_xyzw": None,
                    "age_s": None, "predicted": False}
        R = robot.T_world_cube[:3, :3]
        return {**out, "time_s": pose.time_s, "position_m": [float(v) for v in pose.position_m],
                "quaternion_xyzw": [float(v) for v in pose.quaternion_xyzw],
                "yaw_deg": math.degrees(math.atan2(R[1, 0], R[0, 0])),
                "age_s": max(0.0, now_s - pose.time_s), "predicted": pose.predicted}

    def robots_json(self) -> list[dict]:
        with self._lock:
            return [self.robot_json(r) for r in self._robots.values()]

    def camera_setups(self) -> list[tuple[CameraSetup | None, str, str]]:
        """(setup, status, name) of every camera, for the top view."""
        with self._lock:
            return [(cam.setup, cam.status[0], cam.name) for cam in self._cameras.values()]
