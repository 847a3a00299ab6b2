"""Issue 23: every command resolves its config once. Resolving a config logs its warnings (here: a
``[filter] corner_noise_px`` that trusts the edge fit's corners too much), so a command that
resolved it twice, as ``track --live`` once did (the CLI, then the live loop), prints each warning
twice. Each command runs as a user runs it (a subprocess, its stderr read) on a short simulated
session, the live ones against camera URLs where nothing listens."""

from __future__ import annotations

import socket
import subprocess
import sys
import tomllib

import pytest
import tomli_w

from cubetrack.simulate import SimulationParams, simulate

WARNING = "corner_noise_px = 0.1 trusts the corners"


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("config_once")
    rec = root / "rec"
    simulate(SimulationParams(duration_s=1.5, calibration_frames=8, seed=7), rec)
    doc = tomllib.loads((rec / "config.toml").read_text())
    port = closed_port()
    for camera in doc["cameras"]:  # live commands read these URLs: nothing answers there
        camera["url"] = f"http://127.0.0.1:{port}/{camera['name']}/stream"
    doc["filter"] = {"corner_noise_px": 0.1}
    (rec / "config.toml").write_text(tomli_w.dumps(doc))
    return rec


def commands(rec, out) -> dict[str, list[str]]:
    config, extrinsics = str(rec / "config.toml"), str(rec / "true_extrinsics.toml")
    bus = ["--bus-listen", f"tcp/127.0.0.1:{closed_port()}", "--bus-mode", "peer"]
    return {
        "track --recording": ["track", "--config", config, "--recording", str(rec), "--extrinsics", extrinsics,
                              "--out", str(out / "replay")],
        "track --live": ["track", "--config", config, "--live", "--uncalibrated", "--duration", "1",
                         "--out", str(out / "live")],
        "calibrate": ["calibrate", "--config", config, "--recording", str(rec / "calibration"),
                      "--out", str(out / "extrinsics.toml")],
        "record": ["record", "--config", config, "--out", str(out / "recorded"), "--duration", "1"],
        "dashboard": ["dashboard", "--config", config, "--out", str(out / "dashboard"), "--port", "0",
                      "--duration", "1"],
        "worker": ["worker", "--config", config, "--uncalibrated", "--duration", "1", *bus],
        "fuse": ["fuse", "--config", config, "--uncalibrated", "--duration", "1", "--out", str(out / "fused"), *bus],
    }


def test_every_command_prints_a_config_warning_once(scene, tmp_path):
    running = {name: subprocess.Popen([sys.executable, "-m", "cubetrack.cli.main", *argv], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
               for name, argv in commands(scene, tmp_path).items()}
    counts, errors = {}, {}
    for name, process in running.items():
        _, err = process.communicate(timeout=600)
        counts[name] = err.count(WARNING)
        errors[name] = err[-600:]
    assert counts == dict.fromkeys(running, 1), errors
