"""Calibration workflows: a tracker config and recording folders in, extrinsics (or a body
layout) out.

They turn the config and the folders into the typed arguments of the calibration library once
(:mod:`cubetrack.app.config`) and call it: :func:`cubetrack.calib.extrinsics.calibrate_cameras`
(the world marker), :func:`cubetrack.calib.bundle.adjust_extrinsics` (bundle adjustment over
the cube sightings of a tracking recording) and :func:`cubetrack.calib.body.calibrate_body` (the
markers' placement on a body), which themselves read no file.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from cubetrack.app.config import ConfigParams, config_params, parameter_tables, recording_intrinsics
from cubetrack.calib.body import BodyCalibrationReport, calibrate_body
from cubetrack.calib.bundle import BundleAdjustmentReport, adjust_extrinsics
from cubetrack.calib.extrinsics import CalibrationParams, CalibrationReport, calibrate_cameras
from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.core.errors import CalibrationError, ConfigError
from cubetrack.core.layout import layout_to_table, read_layout
from cubetrack.core.progress import Progress
from cubetrack.io.config import RobotConfig, TrackerConfig, write_extrinsics, write_toml
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
    (None without a tracking recording), the bodies calibrated from that recording (robot ->
    report; robot -> the layout file written beside the extrinsics, :func:`body_path`), the robots
    whose body could not be calibrated (robot -> why: they keep their layout), the extrinsics file
    written and its run record."""

    report: CalibrationReport
    adjusted: BundleAdjustmentReport | None
    extrinsics_path: Path
    run_record_path: Path
    bodies: dict[str, BodyCalibrationReport] = dataclasses.field(default_factory=dict)
    body_paths: dict[str, Path] = dataclasses.field(default_factory=dict)
    body_failures: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def extrinsics(self) -> dict[str, CameraExtrinsics]:
        """What was written: the adjusted extrinsics, else the world-marker calibration."""
        return self.report.extrinsics if self.adjusted is None else self.adjusted.extrinsics


def body_path(extrinsics_path: str | Path, robot: str) -> Path:
    """Where ``cubetrack calibrate --refine-with`` writes ``robot``'s calibrated body and where the
    tracker looks for it (:func:`with_calibrated_bodies`): beside the extrinsics,
    ``<extrinsics stem>.<robot>.body.toml`` (``extrinsics.toml`` -> ``extrinsics.robot.body.toml``)."""
    path = Path(extrinsics_path)
    return path.with_name(f"{path.stem}.{robot}.body.toml")


def with_calibrated_bodies(config: TrackerConfig, extrinsics_path: str | Path) -> tuple[TrackerConfig, list[Path]]:
    """``config`` with each robot's layout replaced by the body calibrated together with the
    extrinsics at ``extrinsics_path`` (:func:`body_path`), where that file exists; and the files used."""
    found = {r.name: body_path(extrinsics_path, r.name) for r in config.robots}
    found = {name: path for name, path in found.items() if path.is_file()}
    robots = tuple(dataclasses.replace(r, layout=read_layout(found[r.name]), layout_path=found[r.name])
                   if r.name in found else r for r in config.robots)
    return dataclasses.replace(config, robots=robots), list(found.values())


def calibrate_bodies(config: TrackerConfig, recording: Recording, extrinsics: dict[str, CameraExtrinsics],
                     params: ConfigParams, progress: Progress | None = None
                     ) -> tuple[dict[str, BodyCalibrationReport], dict[str, str]]:
    """Every robot's body calibrated from ``recording`` (:func:`calibrate_recording_body`): (robot
    -> report, robot -> why it could not be, e.g. it was not in the recording)."""
    bodies: dict[str, BodyCalibrationReport] = {}
    failures: dict[str, str] = {}
    for robot in config.robots:  # one robot's failure leaves the others' bodies
        try:
            bodies[robot.name] = calibrate_recording_body(config, recording, extrinsics, robot.name, params, progress)
        except CalibrationError as exc:
            failures[robot.name] = str(exc)
    return bodies, failures


def run_calibration(config: TrackerConfig, recording: Recording, out: str | Path,
                    params: ConfigParams | None = None, *, adjust_with: Recording | None = None,
                    allow_missing: bool = False, progress: Progress | None = None,
                    with_bodies: bool = False) -> CalibrationRun:
    """``cubetrack calibrate``: calibrate ``recording``, optionally refine with the tracking
    recording ``adjust_with``, write the extrinsics TOML to ``out`` and its run record beside it
    (``<out stem>.run.json``). With ``with_bodies`` (and ``adjust_with``) every robot's body is
    first calibrated from that recording on the world-marker extrinsics, the refinement takes
    the calibrated bodies, and each is written beside ``out`` (:func:`body_path`); a body file
    there from an earlier run that made none is removed (it belongs to the extrinsics replaced).
    Nothing is written when a step fails."""
    params = params or config_params(config)
    report = calibrate_recording(config, recording, params.calibration, progress, allow_missing, params)
    adjusted = None
    bodies: dict[str, BodyCalibrationReport] = {}
    failures: dict[str, str] = {}
    if adjust_with is not None:
        if with_bodies:
            bodies, failures = calibrate_bodies(config, adjust_with, report.extrinsics, params, progress)
        calibrated = dataclasses.replace(config, robots=tuple(
            dataclasses.replace(r, layout=bodies[r.name].layout) if r.name in bodies else r for r in config.robots))
        adjusted = adjust_recording_extrinsics(calibrated, adjust_with, report.extrinsics, recording, params,
                                               progress)
    out = Path(out)
    paths = {name: body_path(out, name) for name in bodies}
    result = CalibrationRun(report, adjusted, out, run_record_beside(out), bodies, paths, failures)
    write_extrinsics(result.extrinsics, out)
    for robot in config.robots:
        if robot.name in bodies:
            write_toml(layout_to_table(bodies[robot.name].layout), paths[robot.name])
        elif robot.layout_path is None or body_path(out, robot.name).resolve() != robot.layout_path.resolve():
            body_path(out, robot.name).unlink(missing_ok=True)  # never the layout the config names
    sections = parameter_tables(params)
    used = {k: sections[k] for k in ("detector", "calibration", *(("bundle_adjustment",) if adjusted else ()),
                                     *(("body_calibration",) if bodies else ()))}
    write_run_record(result.run_record_path, "calibrate", used,
                     {"config": config.path, "recording": recording.path,
                      "tracking_recording": adjust_with.path if adjust_with is not None else None},
                     {"outputs": {"extrinsics": str(out.resolve()),
                                  **{f"body {name}": str(path.resolve()) for name, path in paths.items()}},
                      **({"bodies_not_calibrated": failures} if failures else {})})
    return result


def config_robot(config: TrackerConfig, robot: str | None) -> RobotConfig:
    """The config's robot named ``robot`` (None: its only robot); ConfigError naming the robots
    otherwise."""
    names = [r.name for r in config.robots]
    if robot is None and len(names) == 1:
        return config.robots[0]
    if robot is None:
        raise ConfigError(f"{config.path}: robots {', '.join(names)}: say which body to calibrate (--robot)")
    for r in config.robots:
        if r.name == robot:
            return r
    raise ConfigError(f"{config.path}: no robot {robot!r}; robots: {', '.join(names)}")


def calibrate_recording_body(config: TrackerConfig, recording: Recording, extrinsics: dict[str, CameraExtrinsics],
                             robot: str | None = None, params: ConfigParams | None = None,
                             progress: Progress | None = None) -> BodyCalibrationReport:
    """Calibrate the placement of the markers on ``robot``'s body (None: the config's only robot)
    from its sightings in the tracking ``recording`` (stamped with its ``clock.csv``) by the
    cameras of ``extrinsics``; ``params``: the config's resolved sections (None: read from
    ``config``), of which ``[bundle_adjustment]``, ``[body_calibration]`` and ``[detector]`` apply."""
    params = params or config_params(config)
    body = config_robot(config, robot)
    cameras = [c for c in recording.camera_names if c in extrinsics]
    try:
        return calibrate_body(
            {c: recording.frames(c) for c in recording.camera_names}, extrinsics,
            recording_intrinsics(config, recording, cameras), body.layout, body.name,
            clock_samples={c: recording.clock_samples(c) for c in cameras}, params=params.bundle_adjustment,
            body=params.body_calibration, detector_params=params.detector, progress=progress,
            frame_count=sum(len(recording.index(c)) for c in cameras),
            edge_corners=params.body_calibration.edge_corners)
    except CalibrationError as exc:
        raise CalibrationError(f"{recording.path}: {exc}") from None


@dataclasses.dataclass(frozen=True, slots=True, eq=False)
class BodyCalibrationRun:
    """What :func:`run_body_calibration` produced: the report, the layout file written and its run record."""

    report: BodyCalibrationReport
    layout_path: Path
    run_record_path: Path


def run_body_calibration(config: TrackerConfig, recording: Recording, extrinsics: dict[str, CameraExtrinsics],
                         out: str | Path, params: ConfigParams | None = None, *, robot: str | None = None,
                         extrinsics_path: str | Path | None = None,
                         progress: Progress | None = None) -> BodyCalibrationRun:
    """``cubetrack calibrate-body``: calibrate the body, write its layout TOML to ``out`` (never
    over the layout file the config names: that is the nominal layout) and the run record beside
    it. Nothing is written when a step fails."""
    params = params or config_params(config)
    body = config_robot(config, robot)
    out = Path(out)
    if body.layout_path is not None and out.resolve() == body.layout_path.resolve():
        raise ConfigError(f"{out} is the nominal layout of robot {body.name!r} the calibration starts from; "
                          "write the calibrated layout to another file and point [[robots]] layout at it")
    report = calibrate_recording_body(config, recording, extrinsics, body.name, params, progress)
    result = BodyCalibrationRun(report, out, run_record_beside(out))
    write_toml(layout_to_table(report.layout), out)
    write_run_record(result.run_record_path, "calibrate-body",
                     {k: v for k, v in parameter_tables(params).items()
                      if k in ("detector", "bundle_adjustment", "body_calibration")},
                     {"config": config.path, "recording": recording.path, "extrinsics": extrinsics_path,
                      "nominal_layout": body.layout_path},
                     {"robot": body.name, "outputs": {"layout": str(out.resolve())}})
    return result
