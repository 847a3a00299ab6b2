"""benchmarks/body_calibration.py --extrinsics calibrated: calibrate-body starts from the
extrinsics a user has (``cubetrack calibrate`` on the world marker's recording, rendered for the
same seed beside the driving recording) rather than the simulation's truth. A short realistic
scene through the real CLI; the one-minute figures are the benchmark's (docs/calibration.md)."""

import importlib
import tomllib
from pathlib import Path

import numpy as np
import pytest

from cubetrack.calib.extrinsics import extrinsics_errors
from cubetrack.io.config import read_extrinsics

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture(scope="module")
def bench():
    with pytest.MonkeyPatch.context() as mp:
        mp.syspath_prepend(str(BENCHMARKS))
        yield importlib.import_module("body_calibration")


def test_calibrated_extrinsics_come_from_the_world_marker_recording(bench, tmp_path, capsys):
    rec = tmp_path / "seed3"
    rec.mkdir()
    scene = ["--path", "sharp", "--height", "0.8"]
    bench.simulate(rec, 3, 0.5, scene)
    assert bench.extrinsics_for(rec, 3, scene, "true") == rec / "true_extrinsics.toml"

    path = bench.extrinsics_for(rec, 3, scene, "calibrated")
    assert path.parent == rec and path.is_file()
    world = tmp_path / "seed3_world"
    for folder in (rec, world):  # the scene's options reach both renders
        assert tomllib.loads((folder / "simulation.toml").read_text())["params"]["height_m"] == 0.8
    assert len((world / "calibration" / "cam1" / "index.csv").read_text().splitlines()) == bench.CALIBRATION_FRAMES + 1
    truth = read_extrinsics(rec / "true_extrinsics.toml")
    calibrated = read_extrinsics(path)
    assert calibrated.keys() == truth.keys()
    errors = np.array(list(extrinsics_errors(calibrated, truth).values()))
    # a calibration, not the truth: off by what the world marker and camera_info's error leave
    assert np.all(errors[:, 0] < 0.05) and np.all(errors[:, 1] < 1.5), errors
    assert np.all(errors[:, 0] > 1e-4), errors
    assert "calibrated extrinsics against the truth" in capsys.readouterr().out

    # the world recording is reused, and refused when it is not the driving recording's scene
    truth_text = (rec / "true_extrinsics.toml").read_text()
    (rec / "true_extrinsics.toml").write_text(truth_text.replace("0.", "0.0", 1))
    with pytest.raises(SystemExit, match="not the same scene"):
        bench.extrinsics_for(rec, 3, scene, "calibrated")
    assert "reusing" in capsys.readouterr().out
