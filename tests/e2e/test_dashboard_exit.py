"""`cubetrack dashboard` ends cleanly however it is stopped: Ctrl-C (SIGINT), `kill` or a service
manager (SIGTERM), a closed terminal (SIGHUP) or --duration. Each run is its own process with its
own temporary folder (TMPDIR): the watch session's scratch folder (robot.tum, robot.jsonl) is gone
afterwards and the exit code is 0, as for a live session ended by Ctrl-C. Before SIGTERM stopped a
command as Ctrl-C does, every `kill` left a `cubetrack-dashboard-*` folder in /tmp."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from cubetrack.app.demo import write_live_config
from cubetrack.cli.main import main

pytestmark = pytest.mark.slow

REFUSED_URL = "http://127.0.0.1:9/stream"  # the discard port: nobody listens


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A short simulated recording: its config, intrinsics and cube."""
    rec = tmp_path_factory.mktemp("dashboard-exit") / "rec"
    assert main(["simulate", "--out", str(rec), "--duration", "0.3", "--calibration-frames", "1", "--force"]) == 0
    return rec


@pytest.fixture
def lab(recorded, tmp_path):
    """The recording's cameras at an address nobody serves: the watch session runs, retrying them."""
    write_live_config(recorded / "config.toml", {c: REFUSED_URL for c in ("cam1", "cam2", "cam3")},
                      tmp_path / "lab.toml")
    (tmp_path / "tmp").mkdir()
    return tmp_path


def start(lab, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cubetrack.cli.main", "dashboard", "--config",
                             str(lab / "lab.toml"), "--port", "0", "--out", str(lab / "out"), *args],
                            cwd=lab, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "TMPDIR": str(lab / "tmp"), "PYTHONUNBUFFERED": "1"})


def scratch_of(proc: subprocess.Popen, lab, timeout_s: float = 60.0):
    """The dashboard's scratch folder, once its watch session has opened its outputs there."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        folders = list((lab / "tmp").glob("cubetrack-dashboard-*"))
        if folders and (folders[0] / "robot.tum").exists():
            return folders[0]
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    proc.kill()
    raise AssertionError(f"no watch session started: {proc.communicate()}")


@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP], ids=lambda n: n.name)
def test_a_signal_stops_the_dashboard_and_removes_its_scratch_folder(lab, number):
    proc = start(lab)
    try:
        scratch = scratch_of(proc, lab)
        proc.send_signal(number)
        _out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert not scratch.exists() and list((lab / "tmp").iterdir()) == [], list((lab / "tmp").iterdir())
    assert "Traceback" not in err, err


def test_the_end_of_duration_removes_the_scratch_folder(lab):
    proc = start(lab, "--duration", "3")
    scratch = scratch_of(proc, lab)
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert not scratch.exists() and list((lab / "tmp").iterdir()) == []
