"""A simulated session made ready for live tests: simulated, calibrated, and tracked offline (the
reference a live or distributed run is compared with)."""

from __future__ import annotations

from pathlib import Path


def simulated_recording(rec: Path, duration_s: float, seed: int = 8, cameras: int = 3, workers: int = 1) -> Path:
    """A short simulated recording in ``rec`` (one calibration frame, ``workers`` render workers:
    for tests that replay it with ``cubetrack track``; the frames do not depend on ``workers``)."""
    from cubetrack.cli.main import main

    assert main(["simulate", "--out", str(rec), "--cameras", str(cameras), "--duration", str(duration_s),
                 "--seed", str(seed), "--calibration-frames", "1", "--workers", str(workers)]) == 0
    return rec


def simulated_scene(work: Path, duration_s: float, seed: int, calibration_frames: int) -> tuple[Path, Path]:
    """``(work, rec)``: the recording in ``work/rec``, extrinsics in ``work/extrinsics.toml``, the
    offline replay's poses in ``work/offline``."""
    from cubetrack.cli.main import main

    rec = work / "rec"
    assert main(["simulate", "--out", str(rec), "--duration", str(duration_s), "--seed", str(seed),
                 "--calibration-frames", str(calibration_frames)]) == 0
    assert main(["calibrate", "--config", str(rec / "config.toml"), "--recording", str(rec / "calibration"),
                 "--out", str(work / "extrinsics.toml")]) == 0
    assert main(["track", "--config", str(rec / "config.toml"), "--extrinsics", str(work / "extrinsics.toml"),
                 "--recording", str(rec), "--out", str(work / "offline")]) == 0
    return work, rec
