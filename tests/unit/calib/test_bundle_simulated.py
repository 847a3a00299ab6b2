"""Issue 5 item 4 on a simulated 3-camera 1.0 m / 30° scene (16 s of driving, 60 calibration
frames): the bundle adjustment brings every camera's rotation well below the world-marker
calibration's error, a camera moved after calibration is named and recovered, bad input gives
one-line errors. The truth is REC/true_extrinsics.toml."""

import dataclasses
import re

import numpy as np
import pytest

from cubetrack.app.calibrate import adjust_recording_extrinsics, calibrate_recording
from cubetrack.calib.bundle import METHOD, layout_with
from cubetrack.calib.extrinsics import CalibrationParams, extrinsics_errors
from cubetrack.cli import main as cli_main
from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.core.errors import CalibrationError
from cubetrack.core.geometry import R_from_rotvec, make_T
from cubetrack.io.config import read_extrinsics, read_tracker_config
from cubetrack.io.recording import Recording
from cubetrack.simulate import SimulationParams, simulate


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    rec = tmp_path_factory.mktemp("bundle") / "rec"
    simulate(SimulationParams(duration_s=16, calibration_frames=60, seed=3), rec)
    config = read_tracker_config(rec / "config.toml")
    truth = read_extrinsics(rec / "true_extrinsics.toml")
    prior = calibrate_recording(config, Recording.open(rec / "calibration"), CalibrationParams()).extrinsics
    return rec, config, truth, prior


def test_cli_refine_with_beats_the_world_marker_calibration(scene, tmp_path, monkeypatch, capsys):
    rec, _config, truth, prior = scene
    monkeypatch.setattr(cli_main, "COMMANDS", {"calibrate": "calibrate"})
    out = tmp_path / "refined.toml"
    assert cli_main.main(["calibrate", "--config", str(rec / "config.toml"), "--recording", str(rec / "calibration"),
                          "--out", str(out), "--refine-with", str(rec), "--no-body",
                          "--truth", str(rec / "true_extrinsics.toml")]) == 0
    printed = capsys.readouterr().out
    assert "multi-camera instants" in printed and "MOVED" not in printed
    refined = read_extrinsics(out)
    assert set(refined) == set(truth) and all(e.method == METHOD for e in refined.values())
    before, after = extrinsics_errors(prior, truth), extrinsics_errors(refined, truth)
    rot_before = np.mean([e[1] for e in before.values()])
    rot_after = np.mean([e[1] for e in after.values()])
    assert rot_after < 0.6 * rot_before, (before, after)
    for name, (pos_m, rot_deg) in after.items():
        # rotation: clearly below the marker's 0.03-0.1 deg; position: the cube markers' scale
        # (a 0.01 px corner bias = 0.1 %) leaves ~2 mm radially, about the marker's own error
        assert rot_deg < 0.05 and pos_m < 0.005, (name, pos_m, rot_deg)


def _moved(T: np.ndarray, shift_m: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    return make_T(R_from_rotvec(rotvec) @ T[:3, :3], T[:3, 3] + shift_m)


def test_camera_moved_after_calibration_is_named_and_recovered(scene):
    rec, config, truth, _prior = scene
    # cam2's calibration says where it stood before someone bumped it by 3 cm and 1 degree
    stale = dict(truth)
    stale["cam2"] = CameraExtrinsics(_moved(truth["cam2"].T_world_cam, np.array([0.02, -0.02, 0.01]),
                                            np.radians([0.6, 0.0, 0.8])))
    report = adjust_recording_extrinsics(config, Recording.open(rec), stale, Recording.open(rec / "calibration"))
    assert report.moved == ("cam2",)
    assert report.cameras["cam2"].moved and not report.cameras["cam1"].moved
    warning = next(w for w in report.warnings if "cam2" in w)
    assert re.search(r"camera cam2 has moved after calibration.* (2\.[89]|3\.[01]) cm", warning), warning
    errors = extrinsics_errors(report.extrinsics, truth)
    pos_m, rot_deg = errors["cam2"]
    assert pos_m < 0.006 and rot_deg < 0.1, errors
    assert report.cameras["cam2"].shift_m == pytest.approx(0.03, abs=0.005)


def test_recording_without_the_calibrated_cameras_is_one_line_error(scene):
    rec, config, truth, _prior = scene
    renamed = {f"other{i}": e for i, e in enumerate(truth.values())}
    with pytest.raises(CalibrationError, match="share 0 camera") as exc:
        adjust_recording_extrinsics(config, Recording.open(rec), renamed)
    assert "\n" not in str(exc.value)


def test_no_multi_camera_cube_sightings_is_one_line_error(scene):
    rec, config, truth, _prior = scene
    # the calibration recording shows the empty arena: no cube anywhere
    with pytest.raises(CalibrationError, match="no instant where") as exc:
        adjust_recording_extrinsics(config, Recording.open(rec / "calibration"), truth)
    assert "\n" not in str(exc.value)



@pytest.mark.slow
def test_a_refinement_that_contradicts_the_world_marker_is_refused(tmp_path):
    """Issue 26: cube.toml says the markers are 5 % larger than printed (a size measured wrong):
    the cube sightings would pull every camera out and the refined poses would miss the world
    marker by more than its corners' noise, so the refinement is refused with one warning that
    names the cameras and the world-marker calibration is kept as it was. (A 3 s scene of its own:
    the module's 16 s one costs a minute per refinement.)"""
    rec = tmp_path / "rec"
    simulate(SimulationParams(duration_s=3, calibration_frames=12, seed=3), rec)
    config = read_tracker_config(rec / "config.toml")
    prior = calibrate_recording(config, Recording.open(rec / "calibration"), CalibrationParams()).extrinsics
    robot = config.robots[0]
    wrong = layout_with(robot.layout, np.array([m.T_cube_marker for m in robot.layout.markers]),
                        np.array([1.05 * m.size_m for m in robot.layout.markers]))
    config = dataclasses.replace(config, robots=(dataclasses.replace(robot, layout=wrong),))
    report = adjust_recording_extrinsics(config, Recording.open(rec), prior, Recording.open(rec / "calibration"))
    (refusal,) = [w for w in report.warnings if "refinement refused" in w]
    assert all(f"{c}'s world marker reprojects" in refusal for c in prior) and "\n" not in refusal, refusal
    assert all(np.array_equal(report.extrinsics[c].T_world_cam, prior[c].T_world_cam) for c in prior)
    assert report.refused  # what `cubetrack calibrate` prints: "refinement refused", never "refined"
