"""The dashboard's HTTP server: the page, its JSON endpoints, its event stream, its actions.

Endpoints (every one answers JSON unless it says otherwise; names in paths are URL-encoded):

=====================================  =====================================================
``GET /``                              the page (``static/index.html``; its CSS and JS under ``/static/``)
``GET /api/state``                     everything below in one document, and the available actions
``GET /api/session``                   the session: running or ended, world marker, calibrated or not
``GET /api/cameras``                   every camera: status and reason, health, newest frame
``GET /api/cameras/<c>``               one camera
``GET /api/cameras/<c>/frame.jpg``     its newest frame scaled down with the overlay drawn (JPEG)
``GET /api/cameras/<c>/view``          the overlay of that frame in full-resolution pixels
``GET /api/robots``                    every robot: pose, yaw, trail, which cameras see it
``GET /api/topview``                   floor, world marker, cameras with field of view, robots
``GET /api/<panel>``                   a panel of the workflow (``calibration``, ``recording``)
``GET /api/files``                     the files the page offers for download
``GET /api/files/<id>``                one of them (as an attachment)
``GET /api/events``                    server-sent events: ``session``, ``camera``, ``view``,
                                       ``robot``, ``panel``, ``resync`` (re-read the state)
``POST /api/<panel>/<action>``         run an action of the workflow with a JSON object body;
                                       answers ``{"ok": true, "result": ..., "panel": ...}``,
                                       409 when the action cannot run now, 404 when unknown
=====================================  =====================================================

The server binds 127.0.0.1 unless told otherwise and warns when it is reachable from other
machines. It serves at most ``max_clients`` connections at once (more get 503), drops clients
slower than ``client_timeout_s``, answers only requests addressed to a loopback name while it
listens on loopback (a web page elsewhere cannot reach it through DNS rebinding), and takes
actions only as JSON from the page's own origin (a cross-site form cannot post one).
"""

from __future__ import annotations

import http.server
import json
import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import quote, unquote, urlsplit

from cubetrack.core.errors import CubetrackError
from cubetrack.core.records import CameraHealth, CameraView, CameraWatchState, TrackedPose
from cubetrack.sink.base import OutputError, SessionInfo, Sink, is_loopback_host
from cubetrack.sink.dashboard.draw import annotated_jpeg, floor_footprint, view_overlay
from cubetrack.sink.dashboard.state import DashboardParams, DashboardState

log = logging.getLogger(__name__)

DEFAULT_PORT = 8770
STATIC = {"index.html": "text/html; charset=utf-8", "dashboard.js": "text/javascript; charset=utf-8",
          "dashboard.css": "text/css; charset=utf-8"}
MAX_BODY_BYTES = 65536
TRAJECTORY_FILES = ("*.tum", "*.jsonl")
KEEP_ALIVE_S = 15.0


class DashboardError(CubetrackError):
    """An action the page asked for cannot run now (answered 409 with this message)."""


Action = Callable[[dict], "dict | None"]


@dataclass(frozen=True, slots=True)
class Download:
    """A file the page offers: ``id`` (its URL part, e.g. ``sessions/20250101-120000/robot.tum``),
    where it is, and the group the page lists it under (a session)."""

    id: str
    path: Path
    group: str


def folder_downloads(folder: Path, group: str, patterns: tuple[str, ...], prefix: str = "") -> list[Download]:
    """The files of ``folder`` matching ``patterns`` (in that order, each sorted by name) as
    downloads under ``group``, their ids ``<prefix><name>``."""
    if not folder.is_dir():
        return []
    return [Download(prefix + path.name, path, group) for pattern in patterns for path in sorted(folder.glob(pattern))
            if path.is_file()]


def topview_json(state: DashboardState, range_m: float) -> dict:
    """The top view (metres, world frame, z up): world marker corners, each camera's position,
    status and field of view on the floor (:func:`~cubetrack.sink.dashboard.draw.floor_footprint`),
    each robot (see :meth:`DashboardState.robot_json`) and ``bounds`` [xmin, ymin, xmax, ymax]
    that hold all of it."""
    session = state.session
    half = session.world.marker_size_m / 2 if session is not None else 0.125
    marker = [[-half, half], [half, half], [half, -half], [-half, -half]]
    cameras = []
    for setup, status, name in state.camera_setups():
        cam: dict[str, Any] = {"name": name, "status": status, "position_m": None, "fov": []}
        if setup is not None and setup.T_world_cam is not None:
            T = setup.T_world_cam
            cam["position_m"] = [float(v) for v in T[:3, 3]]
            if setup.intrinsics is not None:
                cam["fov"] = floor_footprint(T, setup.intrinsics, range_m)
        cameras.append(cam)
    robots = state.robots_json()
    xs, ys = [p[0] for p in marker], [p[1] for p in marker]
    for cam in cameras:
        for x, y in cam["fov"] + ([cam["position_m"][:2]] if cam["position_m"] else []):
            xs.append(x)
            ys.append(y)
    for robot in robots:
        for _, x, y in robot["trail"]:
            xs.append(x)
            ys.append(y)
    margin = 0.2
    return {"world_marker": marker, "cameras": cameras, "robots": robots,
            "bounds": [min(xs) - margin, min(ys) - margin, max(xs) + margin, max(ys) + margin]}


class _Server(http.server.ThreadingHTTPServer):
    """A threading HTTP server that serves at most ``max_clients`` connections at once, and whose
    :meth:`end_requests` waits for the connections it is serving (a tile's JPEG is drawn by OpenCV
    in its connection's thread: one still drawing when the interpreter exits is ended inside C++,
    which aborts the process — Ctrl-C with a page open exited -6, "FATAL: exception not rethrown")."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address, handler, dashboard: DashboardServer):
        self.dashboard = dashboard
        self.slots = threading.BoundedSemaphore(dashboard.state.params.max_clients)
        self._serving: dict[threading.Thread, socket.socket] = {}  # each connection's thread -> its socket
        self._serving_lock = threading.Lock()
        self.address_family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        super().__init__(address, handler)

    def process_request(self, request, client_address):
        if not self.slots.acquire(blocking=False):
            try:
                request.sendall(b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: text/plain\r\n"
                                b"Connection: close\r\n\r\ntoo many clients\n")
            except OSError:
                pass
            self.shutdown_request(request)
            return
        super().process_request(request, client_address)

    def process_request_thread(self, request, client_address):
        with self._serving_lock:
            self._serving[threading.current_thread()] = request
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self._serving_lock:
                del self._serving[threading.current_thread()]
            self.slots.release()

    def end_requests(self, timeout_s: float) -> None:
        """Once nothing new is accepted: wait up to ``timeout_s`` for the connections being served to end,
        then cut those still open (a client that does not read: its blocked write returns) and wait as long
        again."""
        for cut in (False, True):
            with self._serving_lock:
                serving = dict(self._serving)
            for request in serving.values() if cut else ():
                try:
                    request.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass  # already closed by its thread
            deadline = time.monotonic() + timeout_s
            for thread in serving:
                thread.join(max(0.0, deadline - time.monotonic()))

    def handle_error(self, request, client_address) -> None:
        if not self.dashboard.closing.is_set():  # a connection cut by end_requests: not an error
            super().handle_error(request, client_address)


class _Handler(http.server.BaseHTTPRequestHandler):
    server: _Server
    server_version = "cubetrack-dashboard"

    def setup(self) -> None:
        # socketserver reads self.timeout in setup(); typeshed declares it a class variable only
        self.timeout = self.server.dashboard.state.params.client_timeout_s  # type: ignore[misc]
        super().setup()

    def log_message(self, format: str, *args) -> None:  # the default writes every request to stderr
        log.debug("%s %s", self.address_string(), format % args)

    # --- answers ---

    def _send(self, status: int, body: bytes, content_type: str, extra: dict | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        for name, value in (extra or {}).items():
            self.send_header(name, value)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, value, status: int = 200) -> None:
        self._send(status, json.dumps(value, allow_nan=False).encode(), "application/json")

    def _error(self, status: int, message: str) -> None:
        self._json({"error": message}, status)

    def _host_allowed(self) -> bool:
        """While listening on loopback, only requests addressed to a loopback name are answered."""
        if not is_loopback_host(self.server.dashboard.host):
            return True
        host = self.headers.get("Host", "")
        name = urlsplit(f"//{host}").hostname or ""
        return is_loopback_host(name)

    # --- GET ---

    def do_HEAD(self) -> None:
        self.do_GET()

    def do_GET(self) -> None:
        if not self._host_allowed():
            return self._error(403, "this dashboard answers only requests to its loopback address")
        dash = self.server.dashboard
        state = dash.state
        path = urlsplit(self.path).path
        parts = [unquote(p) for p in path.split("/")[1:]]
        try:
            if path == "/":
                return self._static("index.html")
            if parts[0] == "static" and len(parts) == 2 and parts[1] in STATIC:
                return self._static(parts[1])
            if parts[0] != "api" or len(parts) < 2:
                return self._error(404, f"no such page: {path}")
            what = parts[1]
            if what == "state" and len(parts) == 2:
                return self._json(dash.state_json())
            if what == "session" and len(parts) == 2:
                return self._json(state.session_json())
            if what == "cameras":
                return self._cameras(parts[2:])
            if what == "robots" and len(parts) == 2:
                return self._json(state.robots_json())
            if what == "topview" and len(parts) == 2:
                return self._json(topview_json(state, state.params.floor_range_m))
            if what == "files":
                return self._files(parts[2:])
            if what == "events" and len(parts) == 2:
                return self._events()
            if len(parts) == 2 and (panel := state.panel(what)) is not None:
                return self._json(panel)
            return self._error(404, f"no such endpoint: {path}")
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            return None

    def _static(self, name: str) -> None:
        body = resources.files("cubetrack.sink.dashboard").joinpath("static", name).read_bytes()
        self._send(200, body, STATIC[name])

    def _cameras(self, rest: list[str]) -> None:
        dash = self.server.dashboard
        if not rest:
            return self._json(dash.state.cameras_json())
        name, what = rest[0], rest[1:]
        camera = dash.state.camera_json(name)
        if camera is None:
            return self._error(404, f"no camera {name!r}; cameras: {', '.join(dash.state.camera_names())}")
        if not what:
            return self._json(camera)
        if what == ["view"] or what == ["frame.jpg"]:
            inputs = dash.state.view_inputs(name)
            if inputs is None:
                return self._error(404, f"camera {name!r} has not sent a frame yet")
            view, setup, cubes, world = inputs
            overlay = view_overlay(view, setup, cubes, world)
            if what == ["view"]:
                return self._json(overlay)
            jpeg = dash.frame_jpeg(view, overlay)
            if jpeg is None:
                return self._error(422, f"camera {name!r}: its newest frame does not decode")
            return self._send(200, jpeg, "image/jpeg")
        return self._error(404, f"no such endpoint: {self.path}")

    def _files(self, rest: list[str]) -> None:
        dash = self.server.dashboard
        files = dash.downloads()
        if not rest:
            return self._json([dash.download_json(f) for f in files])
        wanted = "/".join(rest)
        match = next((f for f in files if f.id == wanted), None)
        if match is None or not match.path.is_file():
            return self._error(404, f"no file {wanted!r} to download")
        body = match.path.read_bytes()
        self._send(200, body, "application/octet-stream",
                   {"Content-Disposition": f'attachment; filename="{match.path.name}"'})

    def _events(self) -> None:
        dash = self.server.dashboard
        sub = dash.state.events.subscribe()
        try:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(b"retry: 1000\n\n")
            self.wfile.flush()
            while not dash.closing.is_set() and not sub.closed:
                events = sub.take(KEEP_ALIVE_S)
                chunks = [f"event: {kind}\ndata: {json.dumps(data, allow_nan=False)}\n\n".encode()
                          for kind, data in events] or [b": keep-alive\n\n"]
                self.wfile.write(b"".join(chunks))
                self.wfile.flush()
        except (OSError, ValueError):
            pass  # the client left (or the server is closing)
        finally:
            dash.state.events.unsubscribe(sub)
            self.close_connection = True

    # --- POST ---

    def do_POST(self) -> None:
        if not self._host_allowed():
            return self._error(403, "this dashboard answers only requests to its loopback address")
        origin = self.headers.get("Origin")
        if origin is not None and urlsplit(origin).netloc != self.headers.get("Host", ""):
            return self._error(403, f"actions are taken only from the dashboard's own page, not from {origin}")
        if self.headers.get("Content-Type", "").split(";")[0].strip().lower() != "application/json":
            return self._error(415, "actions take a JSON object (Content-Type: application/json)")
        length = self.headers.get("Content-Length", "0")
        if not length.isdigit() or int(length) > MAX_BODY_BYTES:
            return self._error(413, f"the body must be a JSON object of at most {MAX_BODY_BYTES} bytes")
        raw = self.rfile.read(int(length)) if int(length) else b"{}"
        try:
            body = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            return self._error(400, f"the body is not JSON: {exc}")
        if not isinstance(body, dict):
            return self._error(400, "the body must be a JSON object")
        parts = [unquote(p) for p in urlsplit(self.path).path.split("/")[1:]]
        if len(parts) != 3 or parts[0] != "api":
            return self._error(404, f"no such action: {self.path}")
        self._json(*self.server.dashboard.run_action(parts[1], parts[2], body))


class DashboardServer:
    """The dashboard's server and model (:class:`DashboardState`), serving from the constructor
    on (a port in use is an :class:`~cubetrack.sink.base.OutputError`) until :meth:`close`.

    The workflow adds panels (``state.set_panel``), actions (:meth:`add_actions`) and files to
    download (:meth:`set_downloads`); sessions feed it through :class:`DashboardSink`.
    ``camera_urls``: the config's cameras, shown before a session has started.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, params: DashboardParams = DashboardParams(),
                 *, camera_urls: dict[str, str] | None = None, clock: Callable[[], float] = time.time):
        self.state = DashboardState(params, clock, camera_urls)
        self.closing = threading.Event()
        self._actions: dict[str, dict[str, Action]] = {}
        self._downloads: Callable[[], list[Download]] = list
        self._frames: dict[str, tuple[int, int, bytes]] = {}  # camera -> (seq, overlay hash, JPEG)
        self._frames_lock = threading.Lock()
        try:
            self._http = _Server((host, port), _Handler, self)
        except (OSError, OverflowError) as exc:
            reason = getattr(exc, "strerror", None) or str(exc)
            raise OutputError(f"dashboard cannot listen on {host}:{port}: {reason}") from None
        self.host = host
        self.port = self._http.server_address[1]
        shown = f"[{host}]" if ":" in host else host
        self.url = f"http://{shown}:{self.port}/"
        if is_loopback_host(host):
            log.info("dashboard on %s (loopback only)", self.url)
        else:
            log.warning("dashboard listening on %s: reachable from other machines, and anyone who reaches it "
                        "can start recordings and save extrinsics", self.url)
        self._threads = [threading.Thread(target=self._http.serve_forever, kwargs={"poll_interval": 0.2},
                                          name="cubetrack-dashboard-http", daemon=True),
                         threading.Thread(target=self._tick, name="cubetrack-dashboard-tick", daemon=True)]
        for t in self._threads:
            t.start()

    def _tick(self) -> None:
        while not self.closing.wait(self.state.params.tick_s):
            self.state.tick()

    # --- the workflow's hooks ---

    def add_actions(self, panel: str, actions: dict[str, Action]) -> None:
        """``POST /api/<panel>/<name>`` runs ``actions[name](body)``; a :class:`DashboardError`
        it raises is answered 409 with its message."""
        self._actions.setdefault(panel, {}).update(actions)

    def set_downloads(self, downloads: Callable[[], list[Download]]) -> None:
        self._downloads = downloads

    def downloads(self) -> list[Download]:
        return list(self._downloads())

    @staticmethod
    def download_json(f: Download) -> dict:
        size = f.path.stat().st_size if f.path.is_file() else None
        return {"id": f.id, "name": f.path.name, "group": f.group, "bytes": size,
                "url": "/api/files/" + "/".join(quote(part, safe="") for part in f.id.split("/"))}

    def run_action(self, panel: str, name: str, body: dict) -> tuple[dict, int]:
        """(answer, HTTP status) of one action."""
        action = self._actions.get(panel, {}).get(name)
        if action is None:
            known = sorted(f"{p}/{a}" for p, acts in self._actions.items() for a in acts)
            return {"error": f"no action {panel}/{name}; actions: {', '.join(known) or 'none here'}"}, 404
        try:
            result = action(body)
        except DashboardError as exc:
            return {"error": str(exc), "panel": self.state.panel(panel)}, 409
        except CubetrackError as exc:
            return {"error": str(exc), "panel": self.state.panel(panel)}, 400
        return {"ok": True, "result": result, "panel": self.state.panel(panel)}, 200

    def state_json(self) -> dict:
        state = self.state
        return {"session": state.session_json(), "cameras": state.cameras_json(),
                "topview": topview_json(state, state.params.floor_range_m),
                "panels": {name: state.panel(name) for name in state.panel_names},
                "actions": {panel: sorted(acts) for panel, acts in self._actions.items()},
                "files": [self.download_json(f) for f in self.downloads()]}

    def frame_jpeg(self, view: CameraView, overlay: dict) -> bytes | None:
        """The tile's JPEG of ``view`` with ``overlay``, drawn once per frame and overlay."""
        key = hash(json.dumps(overlay, sort_keys=True))
        with self._frames_lock:
            cached = self._frames.get(view.camera)
            if cached is not None and cached[:2] == (view.seq, key):
                return cached[2]
        params = self.state.params
        jpeg = annotated_jpeg(view, overlay, params.tile_width_px, params.jpeg_quality)
        if jpeg is not None:
            with self._frames_lock:
                self._frames[view.camera] = (view.seq, key, jpeg)
        return jpeg

    def close(self) -> None:
        """Stop serving (idempotent): event streams end, the port is released."""
        if self.closing.is_set():
            return
        self.closing.set()
        self.state.events.close()
        self._http.shutdown()
        self._http.server_close()
        for t in self._threads:
            t.join(2.0)
        self._http.end_requests(1.0)


class DashboardSink(Sink):
    """A session's output to a :class:`DashboardServer`. :meth:`close` ends the session (the
    page keeps showing it); with ``owns_server`` (``track --dashboard``, ``demo --dashboard``)
    a second :meth:`close`, the command's own when it ends, stops the server too. Without it the
    server outlives every session (``cubetrack dashboard`` runs one session after another)."""

    name = "dashboard"
    wants_views = True

    def __init__(self, server: DashboardServer, owns_server: bool = False):
        self.server = server
        self.owns_server = owns_server
        self.where = f"dashboard: {server.url}"
        self._open = False

    def open(self, session: SessionInfo) -> None:
        self._open = True
        self.server.state.open_session(session)

    def pose(self, pose: TrackedPose) -> None:
        self.server.state.pose(pose)

    def camera_health(self, health: CameraHealth) -> None:
        self.server.state.camera_health(health)

    def camera_view(self, view: CameraView) -> None:
        self.server.state.camera_view(view)

    def camera_watch(self, state: CameraWatchState) -> None:
        self.server.state.camera_watch(state)

    def close(self) -> None:
        if self._open:
            self._open = False
            self.server.state.close_session()
        elif self.owns_server:
            self.server.close()
