"""The simulated recording: contract files, ground truth, calibration frames, determinism, CLI."""

from __future__ import annotations

import filecmp

import cv2
import numpy as np
import pytest

from cubetrack.cli.main import main
from cubetrack.core.errors import ParamsError, SimulationError
from cubetrack.core.geometry import T_from_position_quat, rotation_angle
from cubetrack.core.layout import read_layout
from cubetrack.io.camera_info import read_camera_info
from cubetrack.io.config import read_extrinsics, read_tracker_config
from cubetrack.io.recording import Recording
from cubetrack.io.trajectory import read_tum
from cubetrack.simulate import SimulationParams, simulate
from cubetrack.simulate.render import Renderer, View, project_points
from cubetrack.simulate.scenario import build_scene


def _detector(refine=cv2.aruco.CORNER_REFINE_SUBPIX):
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = refine
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)


def _decode(jpeg: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)


def test_recording_follows_the_contract(session):
    rec = Recording.open(session.path)
    assert rec.camera_names == ("cam1", "cam2", "cam3")
    for cam in session.cameras:
        frames = list(rec.frames(cam.name))
        assert len(frames) == cam.frames_written > 0.6 * session.params.duration_s * session.params.fps
        image = _decode(frames[0].jpeg)
        assert image.shape == (480, 640)
        info = read_camera_info(rec.camera_info_path(cam.name))
        assert np.array_equal(info.K, cam.intrinsics.K)
        assert (info.K[0, 2], info.K[1, 2]) == (319.5, 239.5)
    assert not rec.skipped


def test_config_layout_and_true_extrinsics(session):
    config = read_tracker_config(session.path / "config.toml")
    assert [c.name for c in config.cameras] == ["cam1", "cam2", "cam3"]
    assert all(c.camera_info is not None and c.camera_info.exists() for c in config.cameras)
    assert (config.world.marker_id, config.world.marker_size_m) == (0, 0.25)
    layout = config.robots[0].layout
    assert len(layout.markers) == 5 and layout.has_repeated_ids  # the paper's one-id cube
    assert read_layout(session.path / "cube.toml").ids == {1}
    extrinsics = read_extrinsics(session.path / "true_extrinsics.toml")
    for cam in session.cameras:
        T = extrinsics[cam.name].T_world_cam
        assert np.allclose(T[:3, 3], cam.T_world_cam[:3, 3], atol=1e-9)
        assert rotation_angle(T[:3, :3], cam.T_world_cam[:3, :3], "deg") < 1e-6
        assert cam.T_world_cam[2, 3] == pytest.approx(session.params.height_m, abs=0.15)
    assert set(session.T_world_cam) == set(session.intrinsics) == {"cam1", "cam2", "cam3"}


def test_ground_truth_is_the_cube_at_100_hz(session):
    gt = read_tum(session.path / "ground_truth.tum")
    assert np.allclose(np.diff(gt.times_s), 0.01, atol=2e-6)
    assert gt.times_s[0] == pytest.approx(session.params.start_unix_s)
    assert gt.times_s[-1] == pytest.approx(session.params.start_unix_s + session.params.duration_s)
    assert np.allclose(gt.positions_m[:, 2], session.params.cube_centre_height_m, atol=1e-6)
    speed = np.linalg.norm(np.diff(gt.positions_m, axis=0), axis=1) / 0.01
    assert np.allclose(speed, session.params.speed_m_s, rtol=0.02)
    for k in (0, 123, len(gt) - 1):
        T = T_from_position_quat(gt.positions_m[k], gt.quats_xyzw[k])
        assert np.allclose(T, session.T_world_cube(gt.times_s[k]), atol=2e-6)
        # the cube's x axis (forward) follows the direction of travel
    heading = np.diff(gt.positions_m[:2, :2], axis=0)[0]
    forward = T_from_position_quat(gt.positions_m[0], gt.quats_xyzw[0])[:2, 0]
    assert np.dot(heading / np.linalg.norm(heading), forward) > 0.99


def test_cube_markers_are_detected_where_the_truth_projects_them(session):
    """Each frame shows the cube where the ground truth puts it at the frame's capture instant.
    (Cube markers are small here, 15-25 px, often foreshortened: detector errors of 1-3 px are
    the detector's; a timing error of one latency would add about 3 px along the motion.)"""
    rec = Recording.open(session.path)
    detector = _detector()
    errors = []
    for cam in session.cameras:
        seen = 0
        frames = list(rec.frames(cam.name))
        for frame, capture in zip(frames, [c for c in cam.captures if c.delivered], strict=True):
            corners, ids, _ = detector.detectMarkers(_decode(frame.jpeg))
            cube = [] if ids is None else [c.reshape(4, 2) for c, i in zip(corners, ids.ravel(), strict=True) if i == 1]
            seen += bool(cube)
            T_world_cube = session.T_world_cube(capture.capture_host_s)
            truths = [project_points(cam.intrinsics, cam.T_world_cam,
                                     (T_world_cube @ np.c_[m.corners_cube_m(), np.ones(4)].T).T[:, :3])
                      for m in session.layout.markers]
            errors += [min(np.abs(c - t).max() for t in truths) for c in cube]  # nearest face
        assert seen >= 0.8 * len(frames)
    assert np.median(errors) < 1.2 and max(errors) < 4.0


def test_world_marker_is_detected_in_every_calibration_frame(session):
    rec = Recording.open(session.calibration_path)
    detector = _detector()
    h = session.params.world_marker_size_m / 2
    corners_world = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
    for cam in session.cameras:
        truth = project_points(cam.intrinsics, cam.T_world_cam, corners_world)
        frames = list(rec.frames(cam.name))
        assert len(frames) == session.params.calibration_frames
        for frame in frames:
            corners, ids, _ = detector.detectMarkers(_decode(frame.jpeg))
            assert ids is not None and ids.ravel().tolist() == [0]
            assert np.abs(corners[0].reshape(4, 2) - truth).max() < 1.0
        assert read_camera_info(rec.camera_info_path(cam.name)).width == 640
        assert rec.clock_samples(cam.name)
    # calibration happens before the tracking recording, on the same node clocks
    last_cal = max(r.host_time_s for c in rec.camera_names for r in rec.index(c))
    assert last_cal < session.params.start_unix_s


def test_robot_occludes_the_world_marker_sometimes():
    p = SimulationParams(duration_s=30.0)
    scene = build_scene(p)
    # rendered: with the robot standing on the marker, some camera no longer finds it
    detector = _detector(cv2.aruco.CORNER_REFINE_NONE)
    found = []
    for cam in scene.cameras:
        renderer = Renderer(View(cam.intrinsics, cam.T_world_cam, 2), scene.floor, (scene.world_marker,))
        image = renderer.render([scene.robot_solids_at(np.eye(4), scene.robots[0].layout)])
        _, ids, _ = detector.detectMarkers(np.clip(image * 255, 0, 255).astype(np.uint8))
        found.append(ids is not None and 0 in ids.ravel())
    assert not all(found)
    # along the figure-eight: the robot's image overlaps the marker's in some frames, not all
    h = p.world_marker_size_m / 2
    marker = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
    for cam in scene.cameras:
        m = project_points(cam.intrinsics, cam.T_world_cam, marker)
        overlaps = []
        for t in np.arange(0.0, p.duration_s, 0.25):
            body = scene.robot_solids_at(scene.T_world_robot(t), scene.robots[0].layout)[0].corners_world()
            b = project_points(cam.intrinsics, cam.T_world_cam, body)
            overlaps.append(b[:, 0].min() < m[:, 0].max() and b[:, 0].max() > m[:, 0].min()
                            and b[:, 1].min() < m[:, 1].max() and b[:, 1].max() > m[:, 1].min())
        assert 0.0 < np.mean(overlaps) < 0.7


def test_same_seed_same_bytes_other_seed_other_frames(tmp_path):
    p = SimulationParams(cameras=2, duration_s=1.5, calibration_frames=3, seed=4)
    a = simulate(p, tmp_path / "a", workers=1)
    b = simulate(p, tmp_path / "b", workers=2)
    files = sorted(f.relative_to(a.path) for f in a.path.rglob("*") if f.is_file())
    assert len(files) > 20
    for f in files:
        if f.name == "recording.json":  # holds the creation time
            continue
        assert filecmp.cmp(a.path / f, b.path / f, shallow=False), f
    c = simulate(SimulationParams(cameras=2, duration_s=1.5, calibration_frames=3, seed=5), tmp_path / "c")
    jpgs = sorted((a.path / "cam1").glob("*.jpg"))
    other = sorted((c.path / "cam1").glob("*.jpg"))
    assert jpgs and other
    assert all(x.read_bytes() != y.read_bytes() for x, y in zip(jpgs, other, strict=True))
    assert (a.path / "ground_truth.tum").read_bytes() != (c.path / "ground_truth.tum").read_bytes()


def test_distinct_ids_and_distortion(tmp_path):
    p = SimulationParams(cameras=1, duration_s=1.0, calibration_frames=0, distinct_ids=True,
                         distortion=(-0.05, 0.01, 0.0, 0.0, 0.0))
    result = simulate(p, tmp_path / "rec")
    assert sorted(m.marker_id for m in result.layout.markers) == [1, 2, 3, 4, 5]
    assert result.calibration_path is None and not (tmp_path / "rec" / "calibration").exists()
    info = read_camera_info(tmp_path / "rec" / "camera_info" / "cam1.yaml")
    assert np.allclose(info.dist, [-0.05, 0.01, 0, 0, 0])


def test_bad_parameters_are_refused():
    with pytest.raises(ParamsError, match="cameras"):
        SimulationParams(cameras=0)
    with pytest.raises(ParamsError, match="tilt_deg"):
        SimulationParams(tilt_deg=95.0)
    with pytest.raises(SimulationError, match="world marker"):
        build_scene(SimulationParams(tilt_deg=75.0))  # looks at the floor in front of itself
    with pytest.raises(ParamsError, match="drive into a camera"):
        SimulationParams(distance_m=1.0)
    with pytest.raises(ParamsError, match="above the cube"):
        SimulationParams(height_m=0.4)
    with pytest.raises(ParamsError, match="differ from the cube"):
        SimulationParams(world_marker_id=3, distinct_ids=True)
    with pytest.raises(SimulationError, match="dictionary"):
        build_scene(SimulationParams(dictionary="DICT_NOPE"))


def test_params_round_trip_through_a_toml_table(session):
    import tomllib

    from cubetrack.core.params import params_from_table, params_to_table

    p = SimulationParams(cameras=5, height_m=1.2, tilt_deg=40.0, seed=3, distortion=(-0.1, 0.0, 0.0, 0.0))
    assert params_from_table(SimulationParams, params_to_table(p), "sim") == p
    written = tomllib.loads((session.path / "simulation.toml").read_text())
    assert params_from_table(SimulationParams, written["params"], "simulation.toml") == session.params
    assert written["cameras"]["cam2"]["drift_ppm"] == session.camera("cam2").clock.drift_ppm


def test_cli_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for option in ("--out", "--cameras", "--height", "--tilt", "--distance", "--duration", "--fps", "--seed",
                   "--jpeg-quality", "--distinct-ids", "--cube-size", "--marker-size", "--latency-ms",
                   "--drop-rate", "--calibration-frames", "--force"):
        assert option in text
    assert "metres" in text and "(default: 7.5)" in text


@pytest.mark.parametrize("option", [["--cameras", "0"], ["--jpeg-quality", "101"], ["--tilt", "-5"],
                                    ["--marker-size", "0.2"]])
def test_cli_bad_option_is_one_line_and_exit_1(tmp_path, capsys, option):
    assert main(["simulate", "--out", str(tmp_path / "rec"), *option]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("cubetrack simulate: error:")
    assert not (tmp_path / "rec").exists()


def test_cli_writes_and_refuses_to_overwrite_without_force(tmp_path, capsys):
    out = str(tmp_path / "rec")
    args = ["simulate", "--out", out, "--cameras", "1", "--duration", "1", "--calibration-frames", "2"]
    assert main(args) == 0
    assert "wrote" in capsys.readouterr().out
    assert main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "already holds a recording" in err[0]
    assert main([*args, "--force", "--seed", "9"]) == 0
    assert Recording.open(out).index("cam1")


def test_several_robots_get_their_own_ids_layouts_and_ground_truth(tmp_path):
    from cubetrack.io.config import read_tracker_config
    from cubetrack.io.trajectory import read_tum
    from cubetrack.simulate import SimulationParams, simulate

    result = simulate(SimulationParams(robots=3, duration_s=1.0, calibration_frames=0, seed=2), tmp_path / "rec")
    config = read_tracker_config(tmp_path / "rec" / "config.toml")
    assert [r.name for r in config.robots] == ["robot1", "robot2", "robot3"]
    assert [sorted(r.layout.ids) for r in config.robots] == [[1], [2], [3]]
    for k, r in enumerate(config.robots):
        gt = read_tum(tmp_path / "rec" / "ground_truth" / f"{r.name}.tum")
        np.testing.assert_allclose(gt.positions_m[0], result.T_world_cube(gt.times_s[0], k)[:3, 3], atol=1e-6)
    starts = [result.T_world_cube(result.params.start_unix_s, k)[:2, 3] for k in range(3)]
    assert min(np.linalg.norm(a - b) for i, a in enumerate(starts) for b in starts[i + 1:]) > 0.3
