"""Run records (contracts §5): what a run used, written atomically, read back."""

import hashlib
import json

import pytest

from cubetrack.calib.extrinsics import CalibrationMethod, CalibrationParams
from cubetrack.core.errors import ConfigError
from cubetrack.io.run import RUN_FILE, read_run_record, run_record_beside, write_run_record


def test_a_record_holds_versions_resolved_parameters_and_inputs(tmp_path):
    config = tmp_path / "lab.toml"
    config.write_text("[world]\n")
    path = write_run_record(tmp_path / "out" / RUN_FILE, "calibrate",
                            {"calibration": CalibrationParams(method=CalibrationMethod.CMA), "extra": {"k": 1}},
                            {"config": config, "recording": tmp_path, "unused": None}, {"note": "x"})
    doc = read_run_record(tmp_path / "out")
    assert path == tmp_path / "out" / RUN_FILE and doc["command"] == "calibrate" and doc["note"] == "x"
    assert doc["versions"]["cubetrack"] and doc["versions"]["python"]
    assert doc["parameters"]["calibration"]["method"] == "cma"  # enums by value, every field
    assert doc["parameters"]["calibration"]["samples"] == CalibrationParams().samples
    assert doc["parameters"]["extra"] == {"k": 1}
    assert doc["inputs"]["config"] == {"path": str(config.resolve()),
                                       "sha256": hashlib.sha256(config.read_bytes()).hexdigest()}
    assert doc["inputs"]["recording"] == {"path": str(tmp_path.resolve())} and "unused" not in doc["inputs"]
    assert not list((tmp_path / "out").glob("*.part"))


def test_a_new_record_replaces_the_old_one_whole(tmp_path):
    write_run_record(tmp_path / RUN_FILE, "track", {}, {}, {"n": 1})
    write_run_record(tmp_path / RUN_FILE, "track", {}, {}, {"n": 2})
    assert json.loads((tmp_path / RUN_FILE).read_text())["n"] == 2


def test_the_record_of_an_output_file_sits_beside_it(tmp_path):
    assert run_record_beside(tmp_path / "extrinsics.toml") == tmp_path / "extrinsics.run.json"


@pytest.mark.parametrize("content,match", [(None, "not found"), ("{", "not a run record"),
                                           ('{"format": "x"}', "format")])
def test_reading_a_bad_record_is_one_line(tmp_path, content, match):
    if content is not None:
        (tmp_path / RUN_FILE).write_text(content)
    with pytest.raises(ConfigError, match=match):
        read_run_record(tmp_path)
