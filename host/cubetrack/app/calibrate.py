"""Calibration workflows: a tracker config and recording folders in, extrinsics out.

They turn the config and the folders into the typed arguments of the calibration library once
(:mod:`cubetrack.app.config`) and call it: :func:`cubetrack.calib.extrinsics.calibrate_cameras`
(the world marker) and :func:`cubetrack.calib.bundle.adjust_extrinsics` (bundle adjustment over
the cube sightings of a tracking recording), which themselves read no file.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from cubetrack.app.config import ConfigParams, config_params, parameter_tables, recording_intrinsics
from cubetrack.calib.bundle import BundleAdjustmentReport, adjust_extrinsics
from cubetrack.calib.extrinsics import CalibrationParams, CalibrationReport, calibrate_cameras
from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.core.errors import CalibrationError
from cubetrack.core.progress import Progress
from cubetrack.io.config import TrackerConfig, write_extrinsics
from cubetrack.io.recording import Recording
from cubetrack.io.run import run_record_beside, write_run_record


def calibrate_recording(config: TrackerConfig, recording: Recording, params: CalibrationParams | None = None,
                        progress: Progress | None = None, allow_missing: bool = False,
                        settings: ConfigParams | None = None) -> CalibrationReport:
    """Calibrate every camera of ``recording`` against the config's world marker.

    Intrinsics come from the config's ``camera_info`` or the recording's ``camera_info/``;
    ``settings`` are the config's resolved sections (None: read from ``config``) and ``params``
    replaces their ``[calibration]``. Errors name the recording (see
    :func:`cubetrack.calib.extrinsics.calibrate_cameras` for ``allow_missing``).
    """
    settings = settings or config_params(config)
    intrinsics = recording_intrinsics(config, recording)
    try:
        return calibrate_cameras(
            {name: recording.frames(name) for name in recording.camera_names}, intrinsics, config.world,
            params or settings.calibration, settings.detector, progress, allow_missing,
            frame_counts={name: len(recording.index(name)) for name in recording.camera_names})
    except CalibrationError as exc:
        raise CalibrationError(f"{recording.path}: {exc}") from None


def adjust_recording_extrinsics(config: TrackerConfig, recording: Recording,
                                extrinsics: dict[str, CameraExtrinsics], calibration: Recording | None = None,
                                params: ConfigParams | None = None,
                                progress: Progress | None = None) -> BundleAdjustmentReport:
    """Refine ``extrinsics`` by bundle adjustment over the cube sightings of the tracking
    ``recording`` (stamped with its ``clock.csv``) and the world marker in the ``calibration``
    recording (None: cube sightings only); ``params``: the config's resolved sections (None: read
    from ``config``), of which ``[bundle_adjustment]``, ``[calibration]`` and ``[detector]`` apply."""
    params = params or config_params(config)
    cameras = [c for c in recording.camera_names if c in extrinsics]
    world_frames = world_counts = None
    if calibration is not None:
        world_frames = {c: calibration.frames(c) for c in calibration.camera_names}
        world_counts = {c: len(calibration.index(c)) for c in calibration.camera_names}
    try:
        return adjust_extrinsics(
            {c: recording.frames(c) for c in recording.camera_names}, extrinsics,
            recording_intrinsics(config, recording, cameras), {r.name: r.layout for r in config.robots},
            config.world, clock_samples={c: recording.clock_samples(c) for c in cameras},
            world_frames=world_frames, params=params.bundle_adjustment, calibration_params=params.calibration,
            detector_params=params.detector, progress=progress,
            frame_count=sum(len(recording.index(c)) for c in cameras), world_frame_counts=world_counts)
    except CalibrationError as exc:
        raise CalibrationError(f"{recording.path}: {exc}") from None


@dataclasses.dataclass(frozen=True, slots=True, eq=False)
class CalibrationRun:
    """What :func:`run_calibration` produced: the world-marker calibration, the bundle adjustment
    (None without a tracking recording), the extrinsics file written and its run record."""

    report: CalibrationReport
    adjusted: BundleAdjustmentReport | None
    extrinsics_path: Path
    run_record_path: Path

    @property
    def extrinsics(self) -> dict[str, CameraExtrinsics]:
        """What was written: the adjusted extrinsics, else the world-marker calibration."""
        return self.report.extrinsics if self.adjusted is None else self.adjusted.extrinsics


def run_calibration(config: TrackerConfig, recording: Recording, out: str | Path,
                    params: ConfigParams | None = None, *, adjust_with: Recording | None = None,
                    allow_missing: bool = False, progress: Progress | None = None) -> CalibrationRun:
    """``cubetrack calibrate``: calibrate ``recording``, optionally refine with the tracking
    recording ``adjust_with``, write the extrinsics TOML to ``out`` and its run record beside it
    (``<out stem>.run.json``). Nothing is written when a step fails."""
    params = params or config_params(config)
    report = calibrate_recording(config, recording, params.calibration, progress, allow_missing, params)
    adjusted = None
    if adjust_with is not None:
        adjusted = adjust_recording_extrinsics(config, adjust_with, report.extrinsics, recording, params, progress)
    out = Path(out)
    result = CalibrationRun(report, adjusted, out, run_record_beside(out))
    write_extrinsics(result.extrinsics, out)
    sections = parameter_tables(params)
    used = {k: sections[k] for k in ("detector", "calibration", *(("bundle_adjustment",) if adjusted else ()))}
    write_run_record(result.run_record_path, "calibrate", used,
                     {"config": config.path, "recording": recording.path,
                      "tracking_recording": adjust_with.path if adjust_with is not None else None},
                     {"outputs": {"extrinsics": str(out.resolve())}})
    return result
