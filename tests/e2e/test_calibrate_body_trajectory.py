"""`cubetrack calibrate-body` on a continuous-time trajectory of the body (the default,
``[body_calibration] knot_s``), end to end: a short realistic simulation (sharp turns,
rolling shutter, wobble, a wide-angle lens, a hand-built cube), rendered JPEGs, the CLI, the
layout file it writes.

Short for CI: 6 s of driving and the detector's corners (``[body_calibration] edge_corners = false``; the
template fit costs about a minute more here). The bound is loose (every marker's rotation error
at most half the nominal layout's); the one-minute figures are benchmarks/body_calibration.py's
(docs/calibration.md)."""

import numpy as np
import pytest

from cubetrack.calib.body import placement_errors
from cubetrack.cli import main as cli_main
from cubetrack.core.layout import read_layout
from cubetrack.simulate import SimulationParams, simulate


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    rec = tmp_path_factory.mktemp("body_trajectory") / "rec"
    simulate(SimulationParams.realistic(duration_s=6, calibration_frames=0, seed=7, people=0), rec)
    return rec


def test_calibrate_body_follows_the_trajectory(scene, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cli_main, "COMMANDS", {"calibrate-body": "calibrate_body"})
    config = scene / "config_detector_corners.toml"  # beside the recording's: it names cube.toml relative to itself
    config.write_text((scene / "config.toml").read_text()
                      + "\n[body_calibration]\nedge_corners = false\n")
    out = tmp_path / "body.toml"
    assert cli_main.main(["calibrate-body", "--config", str(config),
                          "--extrinsics", str(scene / "true_extrinsics.toml"),
                          "--recording", str(scene), "--out", str(out), "--truth", str(scene / "true_cube.toml")]) == 0
    printed = capsys.readouterr().out
    assert "frames on its continuous-time trajectory" in printed, printed
    truth = read_layout(scene / "true_cube.toml")
    before, after = placement_errors(read_layout(scene / "cube.toml"), truth), placement_errors(read_layout(out), truth)
    for face, (_pos_m, rot_deg, _size_m) in after.items():
        assert rot_deg < 0.5 * before[face][1], (face, after[face], before[face])
    assert np.mean([e[0] for e in after.values()]) < 0.5 * np.mean([e[0] for e in before.values()])


def test_bad_trajectory_setting_is_one_line(scene, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cli_main, "COMMANDS", {"calibrate-body": "calibrate_body"})
    config = scene / "config_bad_knots.toml"
    config.write_text((scene / "config.toml").read_text() + "\n[body_calibration]\nknot_s = -0.02\n")
    out = tmp_path / "body.toml"
    assert cli_main.main(["calibrate-body", "--config", str(config),
                          "--extrinsics", str(scene / "true_extrinsics.toml"),
                          "--recording", str(scene), "--out", str(out)]) != 0
    err = capsys.readouterr().err
    assert "[body_calibration]: knot_s must not be negative" in err and err.count("\n") == 1, err
    assert not out.exists()
