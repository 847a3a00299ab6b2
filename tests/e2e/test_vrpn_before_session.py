"""A VRPN client started before `cubetrack demo --vrpn` and before `cubetrack track --live --vrpn`
(issue 29): a client that starts as the C++ library's does (its ping cycle at once, call-back
requests until the server calls back) and counts the lines the C++ client would print for
unanswered pings (tests/unit/sink/vrpn_client.py PingWatcher, from vrpn-facts.md §3.2 and §10).
It must print nothing once connected, find every robot by name at connection, and receive every
pose from the first one. Both commands run as their own processes, over real sockets."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests" / "unit" / "sink"))  # the consumers written for the unit tests

from sink_helpers import free_port  # noqa: E402
from vrpn_client import PingWatcher  # noqa: E402

from cubecam.emulator import Emulator  # noqa: E402
from cubetrack.app.demo import write_live_config  # noqa: E402

pytestmark = pytest.mark.slow


def cubetrack_watched(args: list[str], port: int) -> tuple[subprocess.CompletedProcess, PingWatcher]:
    """Start the watcher, then run ``cubetrack *args`` to its end; the watcher stops after it."""
    watcher = PingWatcher(port, "robot")
    try:
        done = subprocess.run([sys.executable, "-m", "cubetrack.cli.main", *args], capture_output=True, text=True,
                              timeout=600, check=False)
    finally:
        watcher.close()
    return done, watcher


def tum_rows(path: Path) -> list[list[float]]:
    return [[float(v) for v in line.split()] for line in path.read_text().splitlines()]


def assert_quiet_and_found(watcher: PingWatcher) -> None:
    """Connected, answered at the first ping after connecting, the robot described at once, and
    no error line at all. Warning lines come only while the command starts (no server yet: the
    C++ client warns from 3 s after its own start) up to that first ping after the connection."""
    assert watcher.connected_at is not None
    print(f"connected {watcher.connected_at - watcher.started:.1f} s after the client started; "
          f"{len(watcher.warnings)} warning and {len(watcher.errors)} error lines")
    assert not watcher.errors
    assert watcher.pong_at is not None and watcher.pong_at - watcher.connected_at < 1.5
    assert set(watcher.described_at) == {"robot"}
    assert watcher.described_at["robot"] - watcher.connected_at < 0.5


def assert_same_poses(received: list[tuple[str, float, bytes]], rows: list[list[float]]) -> None:
    import struct

    assert len(received) == len(rows) > 5
    for (sender, time_s, body), row in zip(received, rows, strict=True):
        sensor, _, *values = struct.unpack(">ii7d", body)
        assert sender == "robot" and sensor == 0
        assert time_s == pytest.approx(row[0], abs=2e-6)  # the TUM file's capture time, to its digits
        assert values == pytest.approx(row[1:], abs=2e-6)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("vrpn-demo") / "demo"
    port = free_port()
    done, watcher = cubetrack_watched(["demo", "--out", str(out), "--duration", "3", "--vrpn",
                                       f"127.0.0.1:{port}"], port)
    assert done.returncode == 0, done.stderr[-3000:]
    return out, watcher


def test_a_client_started_before_the_demo_is_answered_at_once_and_gets_every_live_pose(demo):
    out, watcher = demo
    assert_quiet_and_found(watcher)
    assert_same_poses(watcher.poses, tum_rows(out / "live" / "track" / "robot.tum"))


def test_a_client_started_before_track_live_is_answered_at_once_and_gets_every_pose_after(demo, tmp_path):
    out, _ = demo
    rec = out / "rec"
    port = free_port()
    with Emulator(rec, host="127.0.0.1", port=0, loop=True) as emu:  # the demo's 3 s, over and over
        config = write_live_config(rec / "config.toml", emu.urls, tmp_path / "live.toml")
        done, watcher = cubetrack_watched(["track", "--config", str(config), "--extrinsics",
                                           str(out / "extrinsics.toml"), "--live", "--out", str(tmp_path / "out"),
                                           "--duration", "8", "--vrpn", f"127.0.0.1:{port}"], port)
    assert done.returncode == 0, done.stderr[-3000:]
    assert_quiet_and_found(watcher)
    rows = tum_rows(tmp_path / "out" / "robot.tum")
    # every pose from the one after the client connected (a client calls back every 2 s until the
    # server is up, so it may connect after the first poses: those it cannot have)
    assert_same_poses(watcher.poses, rows[len(rows) - len(watcher.poses):])
