"""The camera watching in an offline replay (issue 27), end to end through `cubetrack track
--recording` as its own process: a simulated session whose cam2 the simulator bumps (2 cm / 1 deg
at 6 s; its true pose over time in the recording's true_camera_poses/) is replayed with
`[camera_watch] enabled` (the live e2e test's quick settings). The replay keeps what was learnt as
a live session does: camera_watch.jsonl, run.json's session.camera_watch, the status lines, and
extrinsics.watch-1.toml with cam2 near its new true pose, the user's --extrinsics file untouched.
A second replay into the same folder, with a frame worker process where the first had none, is the
same (the fits run inline), numbers its extrinsics file after the first one's instead of writing
over it, and with --update-extrinsics also updates the user's file. An output folder that cannot
be made is one error line, and nothing is written over."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cubetrack.cli.main import main
from cubetrack.core.geometry import T_from_position_quat, rotation_angle
from cubetrack.io.config import read_extrinsics
from cubetrack.io.run import read_run_record
from cubetrack.io.trajectory import read_tum
from tests.e2e.test_camera_watch_live import WATCH

pytestmark = pytest.mark.slow

BUMP_AT_S, BUMP_STEP_M, BUMP_TURN_DEG = 6.0, 0.02, 1.0


@pytest.fixture(scope="module")
def bumped(tmp_path_factory) -> tuple[Path, Path, Path]:
    """(work, rec, config): the bumped recording, its tracker config with the watching on, and
    work/extrinsics.toml (the cameras' true poses before the bump: the user's file)."""
    work = tmp_path_factory.mktemp("watch-replay")
    rec = work / "rec"
    assert main(["simulate", "--out", str(rec), "--cameras", "4", "--duration", "25", "--seed", "5",
                 "--calibration-frames", "1", "--workers", "2", "--bump-camera", "2", "--bump-at", str(BUMP_AT_S),
                 "--bump-step", str(BUMP_STEP_M), "--bump-turn", str(BUMP_TURN_DEG)]) == 0
    config = rec / "watched.toml"  # beside the config: its relative paths (cube layout, camera_info) hold
    config.write_text((rec / "config.toml").read_text(encoding="utf-8") + WATCH, encoding="utf-8")
    shutil.copy(rec / "true_extrinsics.toml", work / "extrinsics.toml")
    return work, rec, config


def _track(config: Path, rec: Path, extrinsics: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cubetrack.cli.main", "track", "--config", str(config),
                           "--extrinsics", str(extrinsics), "--recording", str(rec), "--out", str(out), *extra],
                          capture_output=True, text=True, timeout=600)


def _true_pose(rec: Path, camera: str, row: int) -> np.ndarray:
    truth = read_tum(rec / "true_camera_poses" / f"{camera}.tum")
    return T_from_position_quat(truth.positions_m[row], truth.quats_xyzw[row])


def _events(out: Path) -> list[dict]:
    return [json.loads(x) for x in (out / "camera_watch.jsonl").read_text(encoding="utf-8").splitlines()]


def test_an_offline_replay_keeps_what_the_watching_learnt(bumped):
    work, rec, config = bumped
    user_file = work / "extrinsics.toml"
    user_bytes = user_file.read_bytes()
    out = work / "out"
    first = _track(config, rec, user_file, out, "--replay-workers", "0")
    assert first.returncode == 0, first.stderr[-3000:]

    events = _events(out)
    assert [(e["event"], e["camera"]) for e in events] == [("moved", "cam2"), ("rejoined", "cam2")], events
    assert events[1]["extrinsics"] == "extrinsics.watch-1.toml" and events[1]["sightings"] > 0
    assert read_run_record(out)["session"]["camera_watch"] == events
    assert "cam2 moved" in first.stderr and "set aside, re-calibrating" in first.stderr
    assert f"re-calibrated from {events[1]['sightings']} sightings" in first.stderr
    assert "camera watch: 2 events" in first.stdout and "extrinsics.watch-1.toml" in first.stdout
    # the new pose: near cam2's true pose after the bump (the pose it had is 2 cm / 1 deg from it)
    new = read_extrinsics(out / "extrinsics.watch-1.toml")
    before, after = _true_pose(rec, "cam2", 0), _true_pose(rec, "cam2", -1)
    T = new["cam2"].T_world_cam
    error_m, error_deg = np.linalg.norm(T[:3, 3] - after[:3, 3]), rotation_angle(T[:3, :3], after[:3, :3], unit="deg")
    bump_m, bump_deg = np.linalg.norm(after[:3, 3] - before[:3, 3]), rotation_angle(after[:3, :3], before[:3, :3],
                                                                                     unit="deg")
    print(f"cam2's new pose vs its true new pose: {1000 * error_m:.1f} mm / {error_deg:.3f} deg "
          f"(bump {1000 * bump_m:.1f} mm / {bump_deg:.3f} deg), {events[1]['sightings']} sightings")
    assert bump_m == pytest.approx(BUMP_STEP_M, abs=1e-4) and bump_deg == pytest.approx(BUMP_TURN_DEG, abs=1e-3)
    # within twice the spread the rejoin asks of the fit (rejoin_spread 5 mm / 0.15 deg; 5.8 mm / 0.063 deg
    # from 54 sightings in session 26), a fifth of the bump's turn and half its step
    assert error_m < 0.01 and error_deg < 0.2, (error_m, error_deg)
    assert events[0]["time"] - _moved_truth_time(rec) < 3.0  # declared within 3 s of the bump
    user = read_extrinsics(user_file)
    for camera in ("cam1", "cam3", "cam4"):
        assert np.allclose(new[camera].T_world_cam, user[camera].T_world_cam, atol=1e-9), camera
    assert user_file.read_bytes() == user_bytes  # never over the user's file without --update-extrinsics

    # again into the same folder, with a frame worker process and --update-extrinsics: the same events
    # and pose (the fits run inline), the first replay's extrinsics file kept, the user's file updated
    kept = (out / "extrinsics.watch-1.toml").read_bytes()
    second = _track(config, rec, user_file, out, "--replay-workers", "1", "--update-extrinsics")
    assert second.returncode == 0, second.stderr[-3000:]
    again = _events(out)
    assert [{**e, "extrinsics": None} for e in again[2:]] == [{**e, "extrinsics": None} for e in events]
    assert again[3]["extrinsics"] == "extrinsics.watch-2.toml" and again[:2] == events
    assert (out / "extrinsics.watch-1.toml").read_bytes() == kept
    assert (out / "extrinsics.watch-2.toml").read_bytes() == kept
    assert read_run_record(out)["session"]["camera_watch"] == again[2:]
    assert np.allclose(read_extrinsics(user_file)["cam2"].T_world_cam, T, atol=1e-9)
    assert f"{user_file}: updated with cam2's new pose" in second.stderr


def test_an_output_folder_that_cannot_be_made_is_one_error_line(bumped, tmp_path):
    work, rec, config = bumped
    blocker = tmp_path / "results"
    blocker.write_text("an earlier result\n", encoding="utf-8")
    for out in (blocker, blocker / "out"):
        done = _track(config, rec, work / "extrinsics.toml", out)
        assert done.returncode == 1, done.stderr[-3000:]
        assert len(done.stderr.strip().splitlines()) == 1 and "cannot write" in done.stderr, done.stderr
        assert blocker.read_text(encoding="utf-8") == "an earlier result\n"


def _moved_truth_time(rec: Path) -> float:
    """The host time of cam2's first frame rendered at its bumped pose."""
    truth = read_tum(rec / "true_camera_poses" / "cam2.tum")
    moved = np.linalg.norm(truth.positions_m - truth.positions_m[0], axis=1) > BUMP_STEP_M / 2
    return float(truth.times_s[np.argmax(moved)])
