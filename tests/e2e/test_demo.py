"""`cubetrack demo` end to end (README's first command): simulate, calibrate, serve the session
with the emulator, track it live over HTTP, evaluate; and the offline comparison."""

import pytest

from cubetrack.cli.main import main

pytestmark = pytest.mark.slow


def test_the_demo_tracks_live_over_http_and_prints_both_tables(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--duration", "8"]) == 0
    text = capsys.readouterr().out
    assert "live tracking over HTTP" in text and "live filter" in text
    for method in ("mean", "weighted", "gaussian", "filter"):
        assert f"offline {method}" in text
    live_row = next(line for line in text.splitlines() if line.startswith("live filter"))
    rmse_cm = float(live_row.split()[2].removesuffix("cm"))
    assert rmse_cm < 1.5
    assert (out / "live" / "track" / "robot.tum").exists() and (out / "live" / "ground_truth_live.tum").exists()
    assert (out / "live" / "config.toml").exists()
    from cubetrack.io.run import read_run_record

    demo = read_run_record(out)
    assert demo["command"] == "demo" and demo["parameters"]["simulation"]["duration_s"] == 8
    assert demo["parameters"]["fusion"]["method"] == "filter"
    assert read_run_record(out / "extrinsics.run.json")["command"] == "calibrate"
    for folder in (out / "live" / "track", out / "track" / "mean"):
        assert read_run_record(folder)["command"] == "track", folder


def test_the_offline_demo_keeps_the_old_behaviour(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "d"), "--duration", "5", "--offline"]) == 0
    text = capsys.readouterr().out
    assert "offline mean" in text and "live tracking over HTTP" not in text
