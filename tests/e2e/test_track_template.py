"""`cubetrack track --recording R` with [detector] corner_refinement = "template" end to end on a
short simulated 3-camera scene: the run records the switch, every frame still gives a pose, and
the poses are closer to the truth than with the edge fit's corners — in rotation with the default
filter, in rotation and position with one that trusts the corners (the perfect cube of the clean
preset: its layout is as built)."""

import json

import pytest

from cubetrack.cli.main import main
from cubetrack.io.run import read_run_record
from tests.helpers.scene import simulated_recording

pytestmark = pytest.mark.slow

TEMPLATE = '\n[detector]\ncorner_refinement = "template"\n'
TRUSTING = "\n[filter]\ncorner_noise_px = 0.05\nangular_accel_noise = 5.0\n"


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    return simulated_recording(tmp_path_factory.mktemp("template") / "rec", duration_s=4)


def track(rec, out, *sections, capsys):
    config = rec / f"config_{out.name}.toml"  # beside the original: its relative paths still hold
    config.write_text((rec / "config.toml").read_text() + "".join(sections))
    assert main(["track", "--config", str(config), "--extrinsics", str(rec / "true_extrinsics.toml"),
                 "--recording", str(rec), "--out", str(out), "--replay-workers", "0"]) == 0
    capsys.readouterr()
    assert main(["evaluate", "--estimate", str(out / "robot.tum"), "--ground-truth", str(rec / "ground_truth.tum"),
                 "--json"]) == 0
    return json.loads(capsys.readouterr().out)["robot"]


def test_template_corners_track_closer_to_the_truth(rec, tmp_path, capsys):
    edge = track(rec, tmp_path / "edge", capsys=capsys)
    template = track(rec, tmp_path / "template", TEMPLATE, capsys=capsys)
    assert read_run_record(tmp_path / "template")["parameters"]["detector"]["corner_refinement"] == "template"
    assert read_run_record(tmp_path / "edge")["parameters"]["detector"]["corner_refinement"] == "edge"
    assert template["detection_ratio"] >= 0.99 and template["poses_total"] >= edge["poses_total"] > 60
    # measured (seed 8): rotation 0.221 against 0.293 deg (0.32 before the edge fit's corners got each their own
    # noise, issue 26, session 15; with that law applied to template corners too, 0.316: it is the edge fit's);
    # position 0.12 against 0.09 cm — with the default filter the edge fit's corners track position as closely
    # (the position claim holds with a filter that trusts the corners, below)
    assert template["rotation_rmse_deg"] < 0.85 * edge["rotation_rmse_deg"]


def test_a_filter_that_trusts_template_corners_does_better_than_one_that_trusts_edge_corners(rec, tmp_path, capsys):
    edge = track(rec, tmp_path / "edge_trusted", TRUSTING, capsys=capsys)
    template = track(rec, tmp_path / "template_trusted", TEMPLATE, TRUSTING, capsys=capsys)
    # measured (seed 8): 0.18 against 0.86 deg; 0.09 against 0.32 cm
    assert template["rotation_rmse_deg"] < 0.5 * edge["rotation_rmse_deg"]
    assert template["position_rmse_m"] < 0.6 * edge["position_rmse_m"]
