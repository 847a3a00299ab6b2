"""The README's quick start "two webcams and a printed cube", end to end, with two emulated webcams:
a simulated session's frames as video files read through OpenCV's VideoCapture, the path of
``usb:0`` / ``usb:1`` (``file:...?at=``, docs/live.md). ``make-body`` prints the cube, ``record``
records the empty arena through the webcams, ``calibrate`` places them, and ``track --live`` tracks
the robot, scored against the ground truth. (Intrinsics come from the simulation: the live
ChArUco capture is tests/e2e/test_calibrate_intrinsics_live.py.)"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from cubecam.replay import load_recording
from cubetrack.app.demo import shift_trajectory, write_live_config
from cubetrack.cli.main import main
from cubetrack.evaluate.metrics import evaluate
from cubetrack.io.trajectory import read_tum
from tests.helpers.webcams import paced_video

pytestmark = pytest.mark.slow

# the videos start this long after the command is set up: it starts its worker processes and opens the cameras first,
# which took over 2 s in clean-clone CI beside the other pytest worker (its status lines: the videos ended ~2 s
# early, detection ratio 0.61); the session lasts this much longer, so no frame of the drive is past when it opens
LEAD_S = 6.0


def webcams(recording: Path, work: Path, label: str) -> tuple[dict[str, str], float, float]:
    """``file:`` URLs playing each camera of ``recording`` from ``LEAD_S`` from now, each frame at
    its capture time (the recording's device clock mapped through its clock.csv, as the emulator
    does); the shift from the recording's clock to the live one, and how long the videos play."""
    tracks, _ = load_recording(recording)
    captured = {t.name: [t.clock.host(f.device_time_s) for f in t.frames] for t in tracks}
    first_s = min(times[0] for times in captured.values())
    last_s = max(times[-1] for times in captured.values())
    videos = {track.name: paced_video(captured[track.name], [f.path for f in track.frames],
                                      1.0 / track.frame_interval_s, work / f"{label}-{track.name}.avi")
              for track in tracks}
    # the clock starts once the videos are written: writing them takes seconds on a loaded machine,
    # which would otherwise eat the lead and start the session part-way through the drive
    shift_s = time.time() + LEAD_S - first_s
    urls = {name: f"file:{video}?at={captured[name][0] + shift_s:.6f}" for name, video in videos.items()}
    return urls, shift_s, last_s - first_s


def test_two_webcams_and_a_printed_cube(tmp_path, capsys):
    rec = tmp_path / "rec"
    assert main(["simulate", "--out", str(rec), "--cameras", "2", "--duration", "6", "--seed", "3",
                 "--calibration-frames", "20", "--workers", "1"]) == 0
    assert main(["make-body", "--out", str(tmp_path / "cube")]) == 0  # the sheet to print and fold
    assert (tmp_path / "cube.svg").read_text().startswith("<?xml")
    urls, _, span_s = webcams(rec / "calibration", tmp_path, "empty")
    lab = write_live_config(rec / "config.toml", urls, tmp_path / "lab-empty.toml")
    assert main(["record", "--config", str(lab), "--out", str(tmp_path / "empty"),
                 "--duration", str(span_s + LEAD_S + 1.0)]) == 0
    assert main(["calibrate", "--config", str(lab), "--recording", str(tmp_path / "empty"),
                 "--out", str(tmp_path / "extrinsics.toml")]) == 0
    # the same drive offline first: the reference, and it leaves every kernel the live session runs in
    # numba's cache (on a fresh checkout a first compile takes tens of seconds on a loaded machine: the
    # webcams, playing in real time meanwhile, would be past most of the drive when the session starts)
    assert main(["track", "--config", str(rec / "config.toml"), "--extrinsics", str(tmp_path / "extrinsics.toml"),
                 "--recording", str(rec), "--out", str(tmp_path / "offline")]) == 0
    offline = evaluate(read_tum(tmp_path / "offline" / "robot.tum"), read_tum(rec / "ground_truth.tum"))
    urls, shift_s, span_s = webcams(rec, tmp_path, "drive")
    lab = write_live_config(rec / "config.toml", urls, tmp_path / "lab.toml")
    capsys.readouterr()
    assert main(["track", "--config", str(lab), "--extrinsics", str(tmp_path / "extrinsics.toml"), "--live",
                 "--out", str(tmp_path / "out"), "--duration", str(span_s + LEAD_S + 1.0)]) == 0
    err = capsys.readouterr().err
    truth = shift_trajectory(read_tum(rec / "ground_truth.tum"), shift_s)
    live = evaluate(read_tum(tmp_path / "out" / "robot.tum"), truth)
    print(f"two emulated webcams, live: {live.position_rmse_m * 100:.2f} cm / {live.rotation_rmse_deg:.2f} deg, "
          f"detection ratio {live.detection_ratio:.2f}; the same recording offline: "
          f"{offline.position_rmse_m * 100:.2f} cm / {offline.rotation_rmse_deg:.2f} deg")
    if live.detection_ratio < 0.8:  # say what the live session saw (its status lines), so a failure in CI shows why
        print(err[-4000:])
    assert live.detection_ratio >= 0.8
    assert live.position_rmse_m < offline.position_rmse_m + 0.005
    assert live.rotation_rmse_deg < offline.rotation_rmse_deg + 1.0
    assert "no clock" not in err  # video files (as USB cameras with driver stamps) are timed
