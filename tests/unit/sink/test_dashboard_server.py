"""The dashboard's server over real HTTP sockets on 127.0.0.1: every endpoint, the event stream,
the actions and their guards, downloads, client limits, and what the tiles draw on a rendered
scene (world marker and the paper's cube at known poses, detected by the real detector)."""

import json
import logging
import socket
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import requests
from sink_helpers import INTRINSICS

from cubetrack.core.geometry import make_T, position_quat_from_T, transform_points
from cubetrack.core.layout import paper_cube_layout
from cubetrack.core.records import CameraHealth, CameraView, TrackedPose
from cubetrack.detect.detector import Detector, DetectorParams
from cubetrack.sink.base import OutputError, Outputs
from cubetrack.sink.dashboard.draw import floor_footprint
from cubetrack.sink.dashboard.server import DashboardError, DashboardServer, DashboardSink, Download, folder_downloads
from cubetrack.sink.dashboard.state import DashboardParams

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scenes import Camera, cube_solid, marker_on_paper

CUBE_T = make_T(cv2.Rodrigues(np.array([0.0, 0.0, np.radians(25)]))[0], [0.45, 0.25, 0.055])


@pytest.fixture(scope="module")
def rendered(request):
    """cam-a's view (1, 0, 1) -> origin of the world marker and robot "robot 1!"'s cube: the JPEG
    and what the detector finds in it."""
    from sink_helpers import look_at

    T_world_cam = look_at(np.array([1.0, 0.0, 1.0]), [0, 0, 0])
    layout = paper_cube_layout()
    solids = [marker_on_paper(np.eye(4), "DICT_4X4_50", 0, 0.25, 0.03), cube_solid(layout, 0.11, CUBE_T)]
    jpeg = Camera(INTRINSICS, T_world_cam, solids).jpeg(90)
    gray = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    detections = Detector(DetectorParams()).detect(gray)
    return jpeg, detections


@pytest.fixture
def server(session_info):
    srv = DashboardServer("127.0.0.1", 0, DashboardParams(client_timeout_s=2.0),
                          camera_urls={"cam-a": "http://10.0.0.1/stream"})
    srv.state.open_session(session_info)
    yield srv
    srv.close()


def get(srv, path, **kw):
    return requests.get(srv.url.rstrip("/") + path, timeout=10, **kw)


def post(srv, path, body=None, **kw):
    kw.setdefault("json", {} if body is None else body)
    return requests.post(srv.url.rstrip("/") + path, timeout=10, **kw)


def feed_scene(srv, rendered, now_s):
    jpeg, detections = rendered
    position, q = position_quat_from_T(CUBE_T)
    srv.state.pose(TrackedPose("robot 1!", now_s, position, q, ("cam-a",), ("top", "front"), 0.01))
    cube = tuple(d for d in detections if d.marker_id == 1)
    srv.state.camera_view(CameraView("cam-a", 42, now_s, jpeg, cube))
    srv.state.camera_health(CameraHealth("cam-a", now_s, True, 7.5, 100, 2, 1, 3, 1.7e9, 12.5, 0.004, len(jpeg)))
    return cube


def test_the_page_and_its_assets_come_from_the_server_only(server):
    page = get(server, "/")
    assert page.status_code == 200 and page.headers["Content-Type"].startswith("text/html")
    assert '<script src="/static/dashboard.js">' in page.text and 'href="/static/dashboard.css"' in page.text
    for name, kind in (("dashboard.js", "text/javascript"), ("dashboard.css", "text/css")):
        r = get(server, f"/static/{name}")
        assert r.status_code == 200 and r.headers["Content-Type"].startswith(kind) and len(r.text) > 500
    for text in (page.text, get(server, "/static/dashboard.js").text, get(server, "/static/dashboard.css").text):
        # nothing fetched from elsewhere (the SVG namespace is a name, not a fetch)
        assert "https://" not in text and "cdn" not in text.lower()
        assert text.replace("http://www.w3.org/2000/svg", "").count("http://") == 0
    assert get(server, "/static/state.py").status_code == 404
    assert get(server, "/static/../state.py").status_code == 404
    assert get(server, "/nothing").status_code == 404


def test_state_session_and_cameras(server, rendered):
    feed_scene(server, rendered, time.time())
    state = get(server, "/api/state").json()
    assert set(state) == {"session", "cameras", "topview", "panels", "actions", "files"}
    session = get(server, "/api/session").json()
    assert session == state["session"] and session["state"] == "running" and session["calibrated"] is False
    assert session["world"] == {"dictionary": "DICT_4X4_50", "marker_id": 0, "marker_size_m": 0.25}
    cameras = {c["name"]: c for c in get(server, "/api/cameras").json()}
    assert list(cameras) == ["cam-a", "cam b", "cam_c"]
    a = cameras["cam-a"]
    assert a["url"] == "http://10.0.0.1/stream" and a["status"] == "ok" and a["calibrated"]
    assert a["position_m"] == pytest.approx([1.0, 0.0, 1.0])
    assert a["health"]["reconnects"] == 3 and a["health"]["clock_drift_ppm"] == 12.5
    assert a["view"]["seq"] == 42 and a["view"]["frame"] == "/api/cameras/cam-a/frame.jpg?seq=42"
    assert (cameras["cam b"]["status"], cameras["cam_c"]["calibrated"]) == ("waiting", False)
    one = get(server, "/api/cameras/cam%20b")
    assert one.status_code == 200 and one.json()["name"] == "cam b"
    missing = get(server, "/api/cameras/cam9")
    assert missing.status_code == 404 and "cam-a, cam b, cam_c" in missing.json()["error"]
    assert get(server, "/api/cameras/cam%20b/frame.jpg").status_code == 404  # no frame yet
    assert get(server, "/api/cameras/cam-a/nothing").status_code == 404


def diagonals_meet(quad: np.ndarray) -> np.ndarray:
    """Where a projected square's diagonals cross: the image of its centre."""
    h = [np.cross(np.append(quad[i], 1), np.append(quad[i + 2], 1)) for i in (0, 1)]
    x = np.cross(*h)
    return x[:2] / x[2]


def test_the_view_names_faces_and_puts_cube_and_world_axes_where_they_are(server, rendered):
    _, detections = rendered
    cube = feed_scene(server, rendered, time.time())
    assert len(cube) >= 2  # the scene shows two faces or more
    view = get(server, "/api/cameras/cam-a/view").json()
    assert view["seq"] == 42 and len(view["detections"]) == len(cube)
    T_world_cam = server.state.session.cameras[0].T_world_cam
    cam_pos = T_world_cam[:3, 3]
    layout = paper_cube_layout()
    for d in view["detections"]:
        assert d["robot"] == "robot 1!"
        # the face named is the one whose marker (at the true cube pose) lies under the detection
        i = [m.face for m in layout.markers].index(d["face"])
        centre_world = transform_points(CUBE_T, layout.corners_m[i]).mean(axis=0)
        normal_world = CUBE_T[:3, :3] @ layout.normals[i]
        assert np.dot(normal_world, cam_pos - centre_world) > 0  # it faces the camera
    assert {"top", "front"} <= {d["face"] for d in view["detections"]}
    # predicted cube: five markers, each detected one within a pixel of its projection
    squares = np.array(view["cubes"]["robot 1!"])
    assert squares.shape == (5, 4, 2)
    for d in view["detections"]:
        i = [m.face for m in layout.markers].index(d["face"])
        assert np.abs(squares[i] - np.array(d["corners_px"])).max() < 1.5
    # world axes start at the world marker's centre; its outline matches the detected marker
    world = next(d for d in detections if d.marker_id == 0)
    assert np.linalg.norm(np.array(view["axes"][0]) - diagonals_meet(world.corners_px)) < 1.0
    assert np.abs(np.array(view["world_marker"]) - world.corners_px).max() < 1.5


def test_the_tile_jpeg_is_scaled_down_with_the_overlay_drawn(server, rendered):
    """Detections green; the predicted cube orange where the fused pose puts it (here 12 cm off
    the cube, as a late prediction would be, so that no face is named); world axes."""
    now = time.time()
    feed_scene(server, rendered, now)
    shifted = CUBE_T.copy()
    shifted[1, 3] -= 0.12
    position, q = position_quat_from_T(shifted)
    server.state.pose(TrackedPose("robot 1!", now + 0.05, position, q, ("cam-a",), (), 0.01))
    r = get(server, "/api/cameras/cam-a/frame.jpg?seq=42")
    assert r.status_code == 200 and r.headers["Content-Type"] == "image/jpeg"
    tile = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)
    assert tile.shape == (240, 320, 3)
    view = get(server, "/api/cameras/cam-a/view").json()
    assert all(d["face"] is None for d in view["detections"])  # the prediction explains none of them
    scale = 320 / 640

    def coloured(points, test) -> float:
        """Fraction of ``points`` (full-resolution px) with a pixel passing ``test`` within 1 px."""
        hits = 0
        for x, y in np.asarray(points) * scale:
            row, col = round(y), round(x)
            patch = tile[row - 1:row + 2, col - 1:col + 2].reshape(-1, 3)
            hits += any(test(p.astype(int)) for p in patch)
        return hits / len(points)

    def edge_points(quads):
        quads = np.asarray(quads, float)
        return [a + t * (b - a) for q in quads for a, b in zip(q, np.roll(q, -1, axis=0), strict=True)
                for t in (0.3, 0.7)]

    green = lambda p: p[1] > 150 and p[1] - max(p[0], p[2]) > 60
    orange = lambda p: p[2] > 150 and p[2] - p[0] > 90
    red = lambda p: p[2] > 150 and p[2] - max(p[0], p[1]) > 90
    assert coloured(edge_points([d["corners_px"] for d in view["detections"]]), green) > 0.8
    top = [m.face for m in paper_cube_layout().markers].index("top")
    assert coloured(edge_points([view["cubes"]["robot 1!"][top]]), orange) > 0.6
    origin, x_tip = np.array(view["axes"][0]), np.array(view["axes"][1])
    assert coloured([origin + t * (x_tip - origin) for t in (0.5, 0.7, 0.9)], red) == 1.0
    # the untouched background stays grey
    assert coloured([[600, 440], [20, 440], [20, 20]], lambda p: p.max() - p.min() > 30) == 0


def test_robots_and_topview(server, rendered):
    now = time.time()
    feed_scene(server, rendered, now)
    robots = {r["name"]: r for r in get(server, "/api/robots").json()}
    assert robots["robot 1!"]["seen_by"] == ["cam-a"] and robots["robot 1!"]["yaw_deg"] == pytest.approx(25.0)
    assert robots["2nd"]["position_m"] is None
    top = get(server, "/api/topview").json()
    cams = {c["name"]: c for c in top["cameras"]}
    assert cams["cam_c"]["position_m"] is None and cams["cam_c"]["fov"] == []
    fov = np.array(cams["cam-a"]["fov"])
    assert len(fov) >= 16
    path = cv2.convexHull(fov.astype(np.float32))
    assert cv2.pointPolygonTest(path, (0.0, 0.0), False) > 0  # cam-a looks at the world origin
    assert cv2.pointPolygonTest(path, (1.0, 0.0), False) < 0  # not at its own feet (tilted 45°)
    x0, y0, x1, y1 = top["bounds"]
    for x, y in np.concatenate([fov, np.array(top["world_marker"])]):
        assert x0 <= x <= x1 and y0 <= y <= y1
    assert top["robots"][0]["position_m"] == pytest.approx(list(CUBE_T[:3, 3]))


def test_floor_footprint_of_a_camera_looking_straight_down_is_its_image_on_the_floor():
    T = make_T(np.diag([1.0, -1.0, -1.0]), [0.5, 0.0, 2.0])  # optical z down, 2 m above the floor
    fov = np.array(floor_footprint(T, INTRINSICS, range_m=10.0))
    # 640 x 480 px at f = 500 px from 2 m: 2.56 m x 1.92 m centred below the camera
    assert fov[:, 0].min() == pytest.approx(0.5 - 1.28, abs=0.01)
    assert fov[:, 0].max() == pytest.approx(0.5 + 1.28, abs=0.01)
    assert fov[:, 1].min() == pytest.approx(-0.96, abs=0.01) and fov[:, 1].max() == pytest.approx(0.96, abs=0.01)
    near = np.array(floor_footprint(T, INTRINSICS, range_m=1.0))
    assert np.hypot(near[:, 0] - 0.5, near[:, 1]).max() == pytest.approx(1.0)


def read_events(response, kinds, timeout_s=10.0):
    """Events of ``kinds`` from a server-sent event stream until each kind was seen."""
    seen, kind, deadline = {}, None, time.monotonic() + timeout_s
    for line in response.iter_lines(decode_unicode=True):
        if line.startswith("event: "):
            kind = line[7:]
        elif line.startswith("data: ") and kind in kinds:
            seen.setdefault(kind, json.loads(line[6:]))
        if set(seen) == set(kinds) or time.monotonic() > deadline:
            break
    return seen


def test_the_event_stream_pushes_changes(server, rendered):
    with requests.get(server.url + "api/events", stream=True, timeout=10) as r:
        assert r.headers["Content-Type"] == "text/event-stream"
        deadline = time.monotonic() + 5
        while server.state.events.subscribers == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        feed_scene(server, rendered, time.time())
        server.state.set_panel("recording", {"mode": "watch"})
        events = read_events(r, {"robot", "view", "camera", "panel"})
    assert events["robot"]["name"] == "robot 1!" and events["view"]["seq"] == 42
    assert events["camera"]["name"] == "cam-a" and events["panel"] == {"name": "recording", "value": {"mode": "watch"}}


def test_closing_the_server_ends_the_event_stream(session_info):
    srv = DashboardServer("127.0.0.1", 0)
    with requests.get(srv.url + "api/events", stream=True, timeout=10) as r:
        threading.Timer(0.3, srv.close).start()
        started = time.monotonic()
        lines = list(r.iter_lines())
    assert time.monotonic() - started < 5 and lines[0] == b"retry: 1000"


def test_panels_and_actions(server):
    calls = []

    def echo(body):
        calls.append(body)
        server.state.set_panel("demo", {"step": "done", "got": body})
        return {"echo": body}

    def busy(body):
        raise DashboardError("not now: busy")

    server.add_actions("demo", {"echo": echo, "busy": busy})
    server.state.set_panel("demo", {"step": "start"})
    assert get(server, "/api/demo").json() == {"step": "start"}
    assert get(server, "/api/state").json()["actions"] == {"demo": ["busy", "echo"]}
    r = post(server, "/api/demo/echo", {"samples": 3})
    assert r.status_code == 200 and r.json() == {"ok": True, "result": {"echo": {"samples": 3}},
                                                 "panel": {"step": "done", "got": {"samples": 3}}}
    r = post(server, "/api/demo/busy")
    assert r.status_code == 409 and r.json()["error"] == "not now: busy"
    r = post(server, "/api/demo/nothing")
    assert r.status_code == 404 and "demo/busy, demo/echo" in r.json()["error"]
    assert post(server, "/api/demo/echo", data=b"[1, 2]", json=None,
                headers={"Content-Type": "application/json"}).status_code == 400
    assert post(server, "/api/demo/echo", data=b"{bad", json=None,
                headers={"Content-Type": "application/json"}).status_code == 400
    assert post(server, "/api/demo/echo", data=b"samples=3", json=None,
                headers={"Content-Type": "application/x-www-form-urlencoded"}).status_code == 415
    assert post(server, "/api/demo/echo", data=b"{}", json=None,
                headers={"Content-Type": "text/plain"}).status_code == 415
    assert post(server, "/api/demo/echo", headers={"Origin": "http://evil.example"}).status_code == 403
    assert post(server, "/api/demo/echo", data=b"{" + b" " * 70000 + b"}", json=None,
                headers={"Content-Type": "application/json"}).status_code == 413
    assert post(server, "/api/demo/echo", headers={"Origin": server.url.rstrip("/")}).status_code == 200
    assert len(calls) == 2  # only the two accepted posts reached the action


def test_requests_for_other_host_names_are_refused_while_on_loopback(server):
    """A web page elsewhere that rebinds its DNS name to 127.0.0.1 still sends its own Host."""
    assert get(server, "/api/state", headers={"Host": f"evil.example:{server.port}"}).status_code == 403
    assert post(server, "/api/x/y", headers={"Host": "evil.example"}).status_code == 403
    assert get(server, "/api/state", headers={"Host": f"localhost:{server.port}"}).status_code == 200


def test_downloads_offer_listed_files_only(server, tmp_path):
    (tmp_path / "s1").mkdir()
    (tmp_path / "s1" / "robot.tum").write_text("1 0 0 0 0 0 0 1\n")
    (tmp_path / "s1" / "robot.jsonl").write_text("{}\n")
    (tmp_path / "secret.txt").write_text("no")
    server.set_downloads(lambda: folder_downloads(tmp_path / "s1", "session s1", ("*.tum", "*.jsonl"), "s1/")
                         + [Download("gone/x.tum", tmp_path / "gone.tum", "old")])
    files = get(server, "/api/files").json()
    assert [(f["id"], f["group"], f["bytes"]) for f in files] == [
        ("s1/robot.tum", "session s1", 16), ("s1/robot.jsonl", "session s1", 3), ("gone/x.tum", "old", None)]
    r = get(server, files[0]["url"])
    assert r.status_code == 200 and r.content == b"1 0 0 0 0 0 0 1\n"
    assert r.headers["Content-Disposition"] == 'attachment; filename="robot.tum"'
    assert get(server, "/api/files/gone/x.tum").status_code == 404
    assert get(server, "/api/files/secret.txt").status_code == 404
    assert get(server, "/api/files/s1/..%2Fsecret.txt").status_code == 404


def test_client_limit_and_slow_clients(session_info):
    srv = DashboardServer("127.0.0.1", 0, DashboardParams(max_clients=2, client_timeout_s=2.0))
    try:
        idle = [socket.create_connection(("127.0.0.1", srv.port)) for _ in range(2)]
        for s in idle:
            s.sendall(b"GET /api/state HTTP/1.1\r\n")  # and never the rest
        started = time.monotonic()
        codes = []
        while time.monotonic() - started < 1.5 and 503 not in codes:  # until the server has taken them
            codes.append(get(srv, "/api/session").status_code)
        assert codes[-1] == 503
        while get(srv, "/api/session").status_code != 200:  # the slow clients are dropped
            assert time.monotonic() - started < 6.0
            time.sleep(0.1)
        assert time.monotonic() - started > 1.5  # not before their time was up
        for s in idle:
            s.close()
    finally:
        srv.close()


def test_close_ends_the_connections_it_is_serving_before_it_returns(server, rendered):
    """A connection still being served when the command ends must not outlive close(): its thread may be
    in OpenCV drawing a tile, and a thread ended there by the interpreter's exit aborts the process
    (`cubetrack demo --dashboard` stopped by Ctrl-C with the page open exited -6 before). One client
    sends half a request and waits (its thread blocked for client_timeout_s), one streams events."""
    others = set(threading.enumerate())  # connection threads of earlier tests' servers, still ending, are not ours
    feed_scene(server, rendered, time.time())
    half = socket.create_connection(("127.0.0.1", server.port))
    half.sendall(b"GET /api/state HTTP/1.1\r\n")  # and never the rest
    events = requests.get(server.url + "api/events", stream=True, timeout=10)
    assert events.status_code == 200

    def serving() -> list[threading.Thread]:
        return [t for t in threading.enumerate() if "process_request_thread" in t.name and t not in others]

    deadline = time.monotonic() + 5.0
    while len(serving()) < 2:  # both taken by the server
        assert time.monotonic() < deadline
        time.sleep(0.01)
    started = time.monotonic()
    server.close()
    assert serving() == [] and time.monotonic() - started < 2.0 + 1.0  # cut, not waited out (2 s timeout)
    half.close()
    events.close()


def test_a_port_in_use_is_an_output_error_and_other_addresses_are_warned_about(caplog):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        with pytest.raises(OutputError, match=f"dashboard cannot listen on 127.0.0.1:{taken.getsockname()[1]}"):
            DashboardServer("127.0.0.1", taken.getsockname()[1])
    with caplog.at_level(logging.WARNING, logger="cubetrack.sink.dashboard.server"):
        srv = DashboardServer("0.0.0.0", 0)
        srv.close()
    assert "reachable from other machines" in caplog.text


def test_the_sink_behind_the_session_queue(session_info, rendered):
    srv = DashboardServer("127.0.0.1", 0)
    try:
        outputs = Outputs([DashboardSink(srv)])
        assert outputs.wants_views
        outputs.open(session_info)
        outputs.camera_view(CameraView("cam b", 7, time.time(), rendered[0], ()))
        outputs.close()
        assert srv.state.session_json()["state"] == "ended"
        assert get(srv, "/api/cameras/cam%20b").json()["view"]["seq"] == 7  # still served
    finally:
        srv.close()
    owned = DashboardServer("127.0.0.1", 0)
    sink = DashboardSink(owned, owns_server=True)
    assert sink.where == f"dashboard: {owned.url}"
    sink.open(session_info)
    sink.close()  # the session's end: the page still shows it
    assert get(owned, "/api/session").json()["state"] == "ended"
    sink.close()  # the command's end
    sink.close()  # more is harmless
    with pytest.raises(requests.ConnectionError):
        requests.get(owned.url, timeout=2)
