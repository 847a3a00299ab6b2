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


def test_sigterm_in_the_live_part_ends_the_demo_there_and_says_what_was_saved(tmp_path):
    """SIGTERM takes the stop path Ctrl-C takes (the session runtime): the live session finishes with
    what had arrived, its poses and run.json are kept, and the demo does not go on to the offline
    replays (before, a stopped live part went on to replay the recording with every method)."""
    import json
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "demo"
    proc = subprocess.Popen([sys.executable, "-m", "cubetrack.cli.main", "demo", "--out", str(out), "--duration", "30"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    poses = out / "live" / "track" / "robot.jsonl"
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:  # until the live part has made poses
            if poses.exists() and len(poses.read_text().splitlines()) >= 5:
                break
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, stderr
    assert "SIGTERM" in stderr and "offline replay was not run" in stderr and "Traceback" not in stderr, stderr
    assert "offline" not in stdout and not (out / "track").exists()
    assert len(poses.read_text().splitlines()) >= 5
    record = json.loads((out / "live" / "track" / "run.json").read_text())
    assert record["session"]["ended"] == "SIGTERM" and record["session"]["poses"]["robot"] >= 5
