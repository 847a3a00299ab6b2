"""The guide behind the dashboard's calibration panel (cubetrack.app.dashboard): the reprojection
check on rendered frames, the verdicts and their advice, recordings with a silent camera, and the
actions' guards over HTTP (nothing runs out of order)."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import requests
from sink_helpers import INTRINSICS, look_at

from cubetrack.app.config import load_config
from cubetrack.app.dashboard import DashboardApp
from cubetrack.calib.check import world_marker_reprojection
from cubetrack.core.cameras import WorldConfig
from cubetrack.core.errors import RecordingError
from cubetrack.core.geometry import make_T
from cubetrack.core.records import Frame
from cubetrack.io.camera_info import write_camera_info
from cubetrack.io.recording import CameraEntry, Recording, RecordingWriter
from cubetrack.sink.dashboard.calibration import calibration_advice, missing_advice
from cubetrack.sink.dashboard.server import DashboardServer
from cubetrack.sink.dashboard.state import DashboardParams

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scenes import Camera, marker_on_paper

WORLD = WorldConfig("DICT_4X4_50", 0, 0.25)


@pytest.fixture(scope="module")
def marker_frames():
    """Five frames of the world marker from 1.4 m (1 m up, 1 m out), and the camera's true pose."""
    T_world_cam = look_at(np.array([1.0, 0.0, 1.0]), [0, 0, 0])
    cam = Camera(INTRINSICS, T_world_cam, [marker_on_paper(np.eye(4), "DICT_4X4_50", 0, 0.25, 0.03)])
    rng = np.random.default_rng(1)
    frames = [Frame("cam1", i, float(i), float(i), cam.jpeg(90, noise_std=2.0, rng=rng)) for i in range(5)]
    return frames, T_world_cam


def test_the_reprojection_check_measures_how_far_a_pose_is_off(marker_frames):
    frames, T = marker_frames
    rms_px, side_px, used = world_marker_reprojection(frames, T, INTRINSICS, WORLD, max_frames=3)
    assert used == 3 and rms_px < 0.5
    # the marker's 25 cm seen from 1.41 m at f = 500 px, foreshortened by the 45° view: sqrt(area)
    assert side_px == pytest.approx(500 * 0.25 / math.sqrt(2) * 2 ** -0.25, rel=0.1)
    off = T.copy()
    off[:3, 3] += [0.0, 0.01, 0.0]  # one centimetre sideways: 500 px * 0.01 m / 1.41 m = 3.5 px
    rms_off, _, _ = world_marker_reprojection(frames, off, INTRINSICS, WORLD)
    assert 2.5 < rms_off < 5.0
    empty = [Frame("cam1", 0, 0.0, 0.0, b"not a jpeg")]
    rms, side, used = world_marker_reprojection(empty, T, INTRINSICS, WORLD)
    assert used == 0 and math.isnan(rms) and math.isnan(side)


def test_a_good_calibration_gets_no_advice_and_each_poor_figure_its_own():
    p = DashboardParams()
    assert calibration_advice(0.2, 0.05, 0.1, 45.0, 30, 30, p) == []
    small = calibration_advice(0.2, 0.05, 0.1, 18.0, 30, 30, p)
    assert len(small) == 1 and "18 px" in small[0] and "bigger marker" in small[0] and "closer" in small[0]
    jitter = calibration_advice(2.5, 0.05, 0.1, 45.0, 30, 30, p)
    assert len(jitter) == 1 and "2.50 cm" in jitter[0] and "focus" in jitter[0]
    assert "0.90°" in calibration_advice(0.2, 0.9, 0.1, 45.0, 30, 30, p)[0]
    far = calibration_advice(0.2, 0.05, 2.4, 45.0, 30, 30, p)
    assert len(far) == 1 and "2.40 px away" in far[0] and "camera_info" in far[0]
    unseen = calibration_advice(0.2, 0.05, math.nan, math.nan, 30, 30, p)
    assert len(unseen) == 1 and "not found in its frames" in unseen[0]
    outliers = calibration_advice(0.2, 0.05, 0.1, 45.0, 12, 30, p)
    assert len(outliers) == 1 and "only 12 of 30" in outliers[0] and "collect again" in outliers[0]
    assert len(calibration_advice(3.0, 2.0, 3.0, 10.0, 5, 30, p)) == 4


def test_advice_for_a_camera_that_could_not_be_calibrated():
    down = missing_advice("", "down", "connection refused")
    assert down == [("the camera sent no usable frames: check its power, its Wi-Fi and its url in the config "
                     "(last error: connection refused)")]
    assert "never saw the whole world marker" in missing_advice(
        "camera 'cam2': world marker DICT_4X4_50 id 0 found in 0 of 30 frames", "ok", "")[0]
    assert "too rarely" in missing_advice("found in 3 of 30 frames, need at least 5", "ok", "")[0]


def test_a_recording_with_a_silent_camera_is_read_without_it(tmp_path, marker_frames):
    frames, _ = marker_frames
    with RecordingWriter(tmp_path / "rec", [CameraEntry("cam1", "u1"), CameraEntry("cam2", "u2")]) as w:
        for f in frames:
            w.add_frame("cam1", f.seq, f.device_time_s, f.host_time_s, f.jpeg)
    recording, left_out = Recording.open(tmp_path / "rec").with_frames()
    assert recording.camera_names == ("cam1",) and len(recording.index("cam1")) == 5
    assert list(left_out) == ["cam2"] and "no frames recorded for cam2" in left_out["cam2"]
    with RecordingWriter(tmp_path / "none", [CameraEntry("cam1", "u1")]):
        pass
    with pytest.raises(RecordingError, match="no camera recorded a frame"):
        Recording.open(tmp_path / "none").with_frames()


@pytest.fixture
def app(tmp_path):
    """A dashboard app over a config of two cameras nobody serves (no session is started)."""
    write_camera_info(INTRINSICS, tmp_path / "cam.yaml")
    (tmp_path / "cube.toml").write_text('dictionary = "DICT_4X4_50"\n\n[[markers]]\nface = "top"\nid = 1\nsize = 0.08\n'
                                        "position = [0.0, 0.0, 0.055]\nquaternion_xyzw = [0.0, 0.0, 0.0, 1.0]\n")
    (tmp_path / "lab.toml").write_text(
        '[world]\ndictionary = "DICT_4X4_50"\nmarker_id = 0\nmarker_size = 0.25\n\n'
        '[[cameras]]\nname = "cam1"\nurl = "http://127.0.0.1:9/stream"\ncamera_info = "cam.yaml"\n\n'
        '[[cameras]]\nname = "cam2"\nurl = "http://127.0.0.1:9/s2"\ncamera_info = "cam.yaml"\n\n'
        '[[robots]]\nname = "robot"\nlayout = "cube.toml"\n')
    config, settings = load_config(tmp_path / "lab.toml")
    server = DashboardServer("127.0.0.1", 0)
    yield DashboardApp(config, settings, server, tmp_path / "out", tmp_path / "extrinsics.toml"), server
    server.close()


def post(server, path, body=None):
    return requests.post(server.url.rstrip("/") + path, json=body or {}, timeout=10)


def test_the_actions_run_only_in_their_step(app):
    guide, server = app
    panel = requests.get(server.url + "api/calibration", timeout=10).json()
    assert panel["step"] == "check" and panel["actions"] == ["collect"] and panel["target_samples"] == 200
    assert [c["name"] for c in panel["cameras"]] == ["cam1", "cam2"]
    assert panel["cameras"][0]["sees_marker"] is None  # nothing checked yet
    for action in ("save", "drive", "refine", "stop", "cancel"):
        r = post(server, f"/api/calibration/{action}")
        assert r.status_code == 409 and r.json()["error"] == "not now: the calibration is at step 'check'"
    assert post(server, "/api/calibration/collect", {"samples": "many"}).status_code == 400
    assert post(server, "/api/calibration/collect", {"samples": 0}).status_code == 400
    assert post(server, "/api/recording/stop").status_code == 409
    r = post(server, "/api/calibration/collect", {"samples": 30})
    assert r.status_code == 200 and r.json()["panel"]["step"] == "collecting"
    assert r.json()["result"]["recording"].startswith(str(guide.out_dir / "calibration"))
    assert r.json()["panel"]["target_samples"] == 30
    # its session has not started (nothing runs sessions here): no samples can come, so no stop yet
    assert r.json()["panel"]["actions"] == ["cancel"]
    r = post(server, "/api/calibration/stop")
    assert r.status_code == 409 and r.json()["error"].startswith("not yet: the cameras are still being connected")
    recording = requests.get(server.url + "api/recording", timeout=10).json()
    assert recording["mode"] == "calibration" and recording["actions"] == []  # the cameras are busy
    assert post(server, "/api/recording/start").status_code == 409
    assert post(server, "/api/calibration/collect").status_code == 409
    r = post(server, "/api/calibration/cancel")
    assert r.status_code == 200 and r.json()["panel"]["step"] == "check"
    r = post(server, "/api/recording/start")
    assert r.status_code == 200 and r.json()["result"]["out_dir"].startswith(str(guide.out_dir / "sessions"))
    assert post(server, "/api/calibration/collect").json()["error"] == "a recording is running: stop it first"
    assert post(server, "/api/recording/stop").status_code == 200


def test_the_page_offers_recorded_trajectories_and_calibrations(app):
    guide, server = app
    for folder, names in (("sessions/20250101-120000", ("robot.tum", "robot.jsonl", "run.json")),
                          ("calibration/20250101-110000", ("extrinsics.toml", "refined.toml", "extrinsics.run.json"))):
        (guide.out_dir / folder).mkdir(parents=True)
        for name in names:
            (guide.out_dir / folder / name).write_text("x\n")
    files = requests.get(server.url + "api/files", timeout=10).json()
    assert [(f["group"], f["name"]) for f in files] == [
        ("session 20250101-120000", "robot.tum"), ("session 20250101-120000", "robot.jsonl"),
        ("calibration 20250101-110000", "extrinsics.toml"), ("calibration 20250101-110000", "refined.toml")]
    assert requests.get(server.url.rstrip("/") + files[0]["url"], timeout=10).content == b"x\n"


def test_the_dashboard_section_of_the_config_reaches_the_guide_and_a_bad_value_is_one_line(app, tmp_path):
    guide, _ = app
    assert guide.params == DashboardParams()
    lab = (tmp_path / "lab.toml").read_text()
    (tmp_path / "lab.toml").write_text(lab + "\n[dashboard]\ndrive_instants = 7\nmax_spread_cm = 2.5\n")
    config, settings = load_config(tmp_path / "lab.toml")
    server = DashboardServer("127.0.0.1", 0, settings.dashboard)
    try:
        guide = DashboardApp(config, settings, server, tmp_path / "out2", tmp_path / "extrinsics.toml")
        assert (guide.params.drive_instants, guide.params.max_spread_cm) == (7, 2.5)
        assert calibration_advice(2.0, 0.05, 0.1, 45.0, 30, 30, guide.params) == []  # 2 cm is fine now
    finally:
        server.close()
    (tmp_path / "lab.toml").write_text(lab + "\n[dashboard]\njpeg_quality = 0\n")
    p = subprocess.run([sys.executable, "-m", "cubetrack.cli.main", "dashboard", "--config", str(tmp_path / "lab.toml"),
                        "--port", "0"], check=False, capture_output=True, text=True, timeout=120)
    assert p.returncode != 0 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "lab.toml: [dashboard]" in p.stderr and "jpeg_quality" in p.stderr


def test_guide_params_refuse_bad_values():
    from cubetrack.core.errors import ParamsError

    with pytest.raises(ParamsError, match="min_inlier_fraction"):
        DashboardParams(min_inlier_fraction=1.5)
    with pytest.raises(ParamsError, match="max_spread_cm must be positive"):
        DashboardParams(max_spread_cm=0)
    assert make_T(np.eye(3), [0, 0, 0]).shape == (4, 4)


def test_the_drive_counts_instants_as_the_bundle_adjustment_groups_them():
    from cubetrack.sink.dashboard.calibration import InstantCounter

    counter = InstantCounter(max_span_s=0.1, min_cameras=2)
    # three cameras see the robot at one moment: one instant, not one per pose
    assert [counter.add("robot", t, [c]) for t, c in ((1.0, "cam1"), (1.01, "cam2"), (1.02, "cam3"))] \
        == [False, True, False]
    assert counter.count == 1
    # one camera alone, or two cameras too far apart in time: nothing
    for t in (2.0, 2.05, 2.1):
        counter.add("robot", t, ["cam1"])
    counter.add("robot", 2.5, ["cam2"])
    assert counter.count == 1
    # another robot's sightings are its own; a pose several cameras took part in is an instant at once
    counter.add("other", 2.52, ["cam3"])
    assert counter.count == 1
    assert counter.add("robot", 3.0, ["cam1", "cam2"]) and counter.count == 2
    # three cameras needed: two are not enough
    strict = InstantCounter(max_span_s=0.1, min_cameras=3)
    strict.add("robot", 1.0, ["cam1"])
    strict.add("robot", 1.05, ["cam2"])
    assert strict.count == 0 and strict.add("robot", 1.08, ["cam3"]) and strict.count == 1
