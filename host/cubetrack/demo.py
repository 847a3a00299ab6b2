"""The end-to-end offline demo as a library flow: simulate -> calibrate -> track -> evaluate.

:func:`run_demo` is what ``cubetrack demo`` runs; ``examples/offline_demo.py`` drives the same
steps one by one through the library.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from cubetrack.calibrate import calibrate_recording, extrinsics_errors
from cubetrack.evaluate import EvaluationResult, evaluate
from cubetrack.fuse import FusionMethod, FusionParams
from cubetrack.io.config import read_extrinsics, read_tracker_config, write_extrinsics
from cubetrack.io.recording import Recording
from cubetrack.io.trajectory import read_tum
from cubetrack.pipeline import StageParams, track_recording
from cubetrack.progress import Progress
from cubetrack.simulate import SimulationParams, simulate


@dataclass(frozen=True, slots=True)
class DemoResult:
    """Calibration errors per camera (position m, rotation deg) and scores per tracking method."""

    out_dir: Path
    calibration_errors: dict[str, tuple[float, float]]
    scores: dict[str, EvaluationResult]


def run_demo(out_dir: Path, sim: SimulationParams, methods: tuple[FusionMethod, ...] = tuple(FusionMethod),
             progress: Progress | None = None) -> DemoResult:
    """Simulate a session into ``out_dir/rec``, calibrate, track with each method, evaluate."""
    rec_dir = out_dir / "rec"
    simulate(sim, rec_dir, progress=progress)
    config = read_tracker_config(rec_dir / "config.toml")
    report = calibrate_recording(config, Recording.open(rec_dir / "calibration"), progress=progress)
    write_extrinsics(report.extrinsics, out_dir / "extrinsics.toml")
    errors = extrinsics_errors(report.extrinsics, read_extrinsics(rec_dir / "true_extrinsics.toml"))
    truth = read_tum(rec_dir / "ground_truth.tum")
    base = StageParams.from_config(config)
    scores = {}
    for method in methods:
        params = dataclasses.replace(base, fusion=dataclasses.replace(base.fusion, method=method))
        result = track_recording(config, Recording.open(rec_dir), report.extrinsics, out_dir / "track" / method.value,
                                 params, progress)
        robot = config.robots[0].name
        scores[method.value] = evaluate(read_tum(result.outputs[robot][0]), truth)
    return DemoResult(out_dir, errors, scores)
