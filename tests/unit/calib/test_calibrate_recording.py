"""Calibration of a rendered 3-camera recording (true camera poses known by construction),
through the library and the CLI: accuracy, bad frames, missing cameras, file round trip."""

import shutil

import numpy as np
import pytest
from calib_scene import CAMERAS, look_at, write_scene

from cubetrack.app.calibrate import calibrate_recording
from cubetrack.app.config import config_params
from cubetrack.calib.extrinsics import CalibrationMethod, CalibrationParams, extrinsics_errors
from cubetrack.cli import main as cli_main
from cubetrack.core.errors import CalibrationError, ConfigError
from cubetrack.io.config import read_extrinsics, read_tracker_config
from cubetrack.io.recording import Recording


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    cameras = dict(CAMERAS)
    cameras["away"] = look_at((0.5, 0.5, 1.0), (3.0, 3.0, 0.5))  # never sees the world marker
    config, rec, truth = write_scene(root, frames=30, cameras=cameras, corrupt={"cam1": 4})
    return config, rec, truth


@pytest.fixture
def cli(monkeypatch):
    # only these commands: the boundary (error handling, exit codes) is main's own
    monkeypatch.setattr(cli_main, "COMMANDS", {"calibrate": "calibrate",
                                               "calibrate-intrinsics": "calibrate_intrinsics"})
    return cli_main.main


def _errors_mm(config, rec, truth, method):
    report = calibrate_recording(config, Recording.open(rec), CalibrationParams(method=method), allow_missing=True)
    assert set(report.cameras) == set(CAMERAS) and set(report.missing) == {"away"}
    assert report.cameras["cam1"].skipped == {"corrupt JPEG": 4}
    assert report.cameras["cam1"].frames_read == 26
    return report, extrinsics_errors(report.extrinsics, truth)


def test_robust_is_within_millimetres_whatever_the_detector_corners(scene, tmp_path):
    """The robust method measures the corners itself (edge fit with the lens model), so it is
    within millimetres both with the default [detector] corners and with OpenCV's unrefined ones,
    which the paper's CMA takes as they are: with those (~0.5 px inside the marker) CMA is
    centimetres off. Measured: robust 0.9-1.1 mm; CMA 2.0 mm with edge corners, 44 mm with none."""
    config_path, rec, truth_path = scene
    truth = read_extrinsics(truth_path)
    opencv_corners = tmp_path / "opencv_corners.toml"
    (tmp_path / "cube.toml").write_text((config_path.parent / "cube.toml").read_text())
    opencv_corners.write_text(config_path.read_text() + '\n[detector]\ncorner_refinement = "none"\n')
    robust, cma = {}, {}
    for label, path in (("edge", config_path), ("none", opencv_corners)):
        config = read_tracker_config(path)
        robust[label] = _errors_mm(config, rec, truth, CalibrationMethod.ROBUST)
        cma[label] = _errors_mm(config, rec, truth, CalibrationMethod.CMA)[1]
        for name, (pos_m, rot_deg) in robust[label][1].items():
            assert pos_m < 0.005 and rot_deg < 0.15, (label, name, pos_m, rot_deg)  # target: 1.5 cm, 0.3 deg
    for name, (pos_m, rot_deg) in cma["edge"].items():
        assert pos_m < 0.015 and rot_deg < 0.3, (name, pos_m, rot_deg)
    # the robust result does not depend on the [detector] corner refinement at all
    for name, cam in robust["edge"][0].cameras.items():
        np.testing.assert_allclose(cam.extrinsics.T_world_cam, robust["none"][0].cameras[name].extrinsics.T_world_cam)
    mean_mm = {label: 1000 * np.mean([e[0] for e in errors.values()]) for label, errors in
               (("robust", robust["none"][1]), ("cma edge", cma["edge"]), ("cma none", cma["none"]))}
    assert mean_mm["cma none"] > 10 * mean_mm["robust"], mean_mm
    assert mean_mm["robust"] < mean_mm["cma edge"] + 1.0, mean_mm  # not worse than the paper's, within 1 mm


def test_samples_limit_and_progress(scene):
    config_path, rec, _ = scene
    calls = []
    params = CalibrationParams(samples=10)
    report = calibrate_recording(read_tracker_config(config_path), Recording.open(rec), params,
                                 progress=lambda *a: calls.append(a), allow_missing=True)
    assert all(c.sightings == 10 for c in report.cameras.values())
    assert ("calibrate cam2", 30, 30) in calls  # finished early, reported complete


def test_a_camera_without_the_world_marker_is_named(scene):
    config_path, rec, _ = scene
    params = CalibrationParams(method=CalibrationMethod.CMA, samples=5)
    with pytest.raises(CalibrationError, match="'away'.*0 of 30 frames.*--allow-missing"):
        calibrate_recording(read_tracker_config(config_path), Recording.open(rec), params)


def test_calibration_section_is_read_and_checked(tmp_path, scene):
    config_path, _, _ = scene
    text = config_path.read_text() + '\n[calibration]\nmethod = "cma"\nsamples = 50\n'
    (tmp_path / "cube.toml").write_text((config_path.parent / "cube.toml").read_text())
    (tmp_path / "c.toml").write_text(text)
    params = config_params(read_tracker_config(tmp_path / "c.toml")).calibration
    assert params.method is CalibrationMethod.CMA and params.samples == 50
    (tmp_path / "c.toml").write_text(text.replace("samples = 50", "samples = 50\nsmaples = 3"))
    with pytest.raises(ConfigError, match="smaples"):
        config_params(read_tracker_config(tmp_path / "c.toml"))
    (tmp_path / "c.toml").write_text(text.replace('"cma"', '"median"'))
    with pytest.raises(ConfigError, match="method"):
        config_params(read_tracker_config(tmp_path / "c.toml"))


def test_cli_writes_extrinsics_that_read_back(scene, tmp_path, cli, capsys):
    config_path, rec, truth_path = scene
    out = tmp_path / "ext.toml"
    rc = cli(["calibrate", "--config", str(config_path), "--recording", str(rec), "--out", str(out),
              "--allow-missing", "--samples", "20", "--truth", str(truth_path)])
    assert rc == 0
    ext = read_extrinsics(out)
    assert set(ext) == set(CAMERAS)
    assert all(e.method == "robust" and 0 < e.samples <= 20 for e in ext.values())
    assert all(0 < e.spread_position_m < 0.01 and 0 < e.spread_rotation_deg < 0.5 for e in ext.values())
    truth = read_extrinsics(truth_path)
    for pos_m, rot_deg in extrinsics_errors(ext, truth).values():
        assert pos_m < 0.01 and rot_deg < 0.2
    printed = capsys.readouterr().out
    assert "cam1" in printed and "4 corrupt JPEG" in printed and "away" in printed and "NOT CALIBRATED" in printed


def test_cli_fails_on_a_missing_camera_without_allow_missing(scene, tmp_path, cli, capsys):
    config_path, rec, _ = scene
    rc = cli(["calibrate", "--config", str(config_path), "--recording", str(rec),
              "--out", str(tmp_path / "e.toml"), "--method", "cma", "--samples", "5"])
    assert rc == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("cubetrack calibrate: error:") and "'away'" in err
    assert not (tmp_path / "e.toml").exists()


def test_cli_bad_inputs_give_one_line_errors(scene, tmp_path, cli, capsys):
    config_path, rec, _ = scene
    cases = [
        ["--config", str(tmp_path / "nope.toml"), "--recording", str(rec)],
        ["--config", str(config_path), "--recording", str(tmp_path / "norec")],
        ["--config", str(config_path), "--recording", str(rec), "--samples", "0"],
    ]
    for args in cases:
        rc = cli(["calibrate", *args, "--out", str(tmp_path / "e.toml")])
        lines = capsys.readouterr().err.strip().splitlines()
        assert rc == 1 and lines[-1].startswith("cubetrack calibrate: error:"), lines


def test_missing_intrinsics_are_an_error_naming_the_camera(scene, tmp_path):
    config_path, rec, _ = scene
    copy = tmp_path / "rec"
    shutil.copytree(rec, copy)
    (copy / "camera_info" / "cam2.yaml").unlink()
    with pytest.raises(ConfigError, match="cam2"):
        calibrate_recording(read_tracker_config(config_path), Recording.open(copy), allow_missing=True)
