"""Issue 26 item 5, the wiring of the body calibrated in the normal workflow: ``run_calibration``
with a drive and ``with_bodies`` calibrates each robot's body from that drive on the world-marker
extrinsics, hands the calibrated layouts to the refinement, writes them beside the extrinsics
where the tracker's ``with_calibrated_bodies`` finds them, and a later run without bodies removes
the stale file but never the config's own layout. The two solves are replaced by stand-ins that
record what they were given (their accuracy is tested in test_body_calibration.py and
test_bundle_simulated.py); the world-marker calibration is real (a 1 s simulated scene)."""

import dataclasses

import numpy as np
import pytest

from cubetrack.app import calibrate as app_calibrate
from cubetrack.calib.body import BodyCalibrationReport
from cubetrack.calib.bundle import BundleAdjustmentReport, layout_with
from cubetrack.core.errors import CalibrationError
from cubetrack.core.layout import read_layout
from cubetrack.io.config import read_tracker_config
from cubetrack.io.recording import Recording
from cubetrack.simulate import SimulationParams, simulate

SHIFT_M = 0.0015  # the stand-in body calibration moves every marker this far along x


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    rec = tmp_path_factory.mktemp("workflow") / "rec"
    simulate(SimulationParams(duration_s=1.0, calibration_frames=8, seed=5), rec)
    return rec


def _shifted(layout):
    Ts = np.array([m.T_cube_marker for m in layout.markers])
    Ts[:, 0, 3] += SHIFT_M
    return layout_with(layout, Ts, layout.sizes_m)


@pytest.fixture
def solves(monkeypatch):
    """Stand-ins for the body calibration and the refinement; what each was given."""
    seen: dict = {"body": [], "refine": []}

    def body(config, recording, extrinsics, robot, params, progress):
        seen["body"].append((robot, dict(extrinsics)))
        if robot in seen.get("fail", ()):
            raise CalibrationError(f"robot {robot} was not seen by two cameras at once")
        layout = next(r.layout for r in config.robots if r.name == robot)
        return BodyCalibrationReport(robot, _shifted(layout), layout, (), 7, dict(extrinsics), {})

    def refine(config, recording, extrinsics, calibration, params, progress):
        seen["refine"].append({r.name: r.layout for r in config.robots})
        return BundleAdjustmentReport(dict(extrinsics), dict(extrinsics), {}, (), 7)

    monkeypatch.setattr(app_calibrate, "calibrate_recording_body", body)
    monkeypatch.setattr(app_calibrate, "adjust_recording_extrinsics", refine)
    return seen


def test_the_drive_calibrates_the_body_the_refinement_uses_it_and_the_tracker_finds_it(scene, tmp_path, solves):
    config = read_tracker_config(scene / "config.toml")
    nominal = config.robots[0].layout
    out = tmp_path / "extrinsics.toml"
    run = app_calibrate.run_calibration(config, Recording.open(scene / "calibration"), out,
                                        adjust_with=Recording.open(scene), with_bodies=True)

    # the body was calibrated on the world-marker extrinsics, and the refinement got that body
    ((robot, start),) = solves["body"]
    assert robot == "robot" and {c: e.T_world_cam.tolist() for c, e in start.items()} == {
        c: e.T_world_cam.tolist() for c, e in run.report.extrinsics.items()}
    (given,) = solves["refine"]
    assert np.allclose(given["robot"].corners_m, _shifted(nominal).corners_m)

    path = app_calibrate.body_path(out, "robot")
    assert path == tmp_path / "extrinsics.robot.body.toml" and run.body_paths == {"robot": path}
    assert np.allclose(read_layout(path).corners_m, _shifted(nominal).corners_m, atol=1e-9)
    tracked, used = app_calibrate.with_calibrated_bodies(config, out)
    assert used == [path] and tracked.robots[0].layout_path == path
    assert np.allclose(tracked.robots[0].layout.corners_m, _shifted(nominal).corners_m, atol=1e-9)

    # extrinsics written again without bodies: the stale body goes with the extrinsics it belonged to
    app_calibrate.run_calibration(config, Recording.open(scene / "calibration"), out)
    assert not path.exists()
    tracked, used = app_calibrate.with_calibrated_bodies(config, out)
    assert used == [] and tracked.robots[0].layout is config.robots[0].layout


def test_a_robot_whose_body_cannot_be_calibrated_keeps_its_layout_and_is_named(scene, tmp_path, solves):
    config = read_tracker_config(scene / "config.toml")
    solves["fail"] = ("robot",)
    out = tmp_path / "extrinsics.toml"
    run = app_calibrate.run_calibration(config, Recording.open(scene / "calibration"), out,
                                        adjust_with=Recording.open(scene), with_bodies=True)
    assert set(run.body_failures) == {"robot"} and "not seen by two cameras" in run.body_failures["robot"]
    assert run.body_paths == {} and not app_calibrate.body_path(out, "robot").exists()
    (given,) = solves["refine"]
    assert given["robot"] is config.robots[0].layout


def test_the_config_own_layout_is_never_removed(scene, tmp_path, solves):
    config = read_tracker_config(scene / "config.toml")
    out = tmp_path / "extrinsics.toml"
    mine = app_calibrate.body_path(out, "robot")  # the user pointed [[robots]] layout at the calibrated body
    mine.write_text((scene / "cube.toml").read_text(encoding="utf-8"), encoding="utf-8")
    robots = (dataclasses.replace(config.robots[0], layout_path=mine),)
    app_calibrate.run_calibration(dataclasses.replace(config, robots=robots), Recording.open(scene / "calibration"),
                                  out)
    assert mine.exists()
