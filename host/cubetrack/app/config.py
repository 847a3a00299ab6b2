"""The workflow layer's one reading of a tracker config: parameter sections and camera intrinsics.

A tracker config (contracts §4, :func:`cubetrack.io.config.read_tracker_config`) keeps one raw
table per parameter section. :func:`config_params` turns every section into its stage's params
dataclass exactly once, refusing an unknown section or a bad value with one line naming the file
and section; :func:`recording_intrinsics` reads each camera's intrinsics file. The library
functions below ``app/`` take what these return (params dataclasses, intrinsics, frames), never
a config or a path, so they run without any file on disk.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cubetrack.app.parallel import LiveParams
from cubetrack.app.tracker import StageParams
from cubetrack.calib.bundle import BundleAdjustmentParams
from cubetrack.calib.extrinsics import CalibrationParams
from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import ConfigError
from cubetrack.core.params import params_from_table, params_to_table
from cubetrack.io.camera_info import read_camera_info
from cubetrack.io.config import TrackerConfig, camera_intrinsics_path, read_tracker_config
from cubetrack.io.recording import Recording
from cubetrack.sink.dashboard.state import DashboardParams
from cubetrack.source.streams import SourceParams


@dataclass(frozen=True, slots=True)
class ConfigParams(StageParams):
    """Every parameter section of a tracker config, resolved (defaults where the file is silent).

    The fields are the sections, in the order ``cubetrack defaults`` prints them: the tracker's
    (``[detector]`` ... ``[track]``, from :class:`~cubetrack.app.tracker.StageParams`, so these
    parameters run a :class:`~cubetrack.app.tracker.Tracker` as they are), then calibration,
    bundle adjustment, the live source, live processing and the dashboard. This class is the one
    list of sections.
    """

    calibration: CalibrationParams = field(default_factory=CalibrationParams)
    bundle_adjustment: BundleAdjustmentParams = field(default_factory=BundleAdjustmentParams)
    source: SourceParams = field(default_factory=SourceParams)
    live: LiveParams = field(default_factory=LiveParams)
    dashboard: DashboardParams = field(default_factory=DashboardParams)

    @property
    def stages(self) -> StageParams:
        """Only the tracker's sections (what a track run records)."""
        return StageParams(**{f.name: getattr(self, f.name) for f in dataclasses.fields(StageParams)})


SECTIONS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(ConfigParams))


def config_params(config: TrackerConfig) -> ConfigParams:
    """Every parameter section of ``config`` as its params dataclass; ConfigError (one line naming
    the file and section) for an unknown section, key or value."""
    unknown = sorted(set(config.sections) - set(SECTIONS))
    if unknown:
        known = ("world", "cameras", "robots", *SECTIONS)
        raise ConfigError(f"{config.path}: unknown section(s) {', '.join(unknown)}; known: {', '.join(known)}")
    hints = typing.get_type_hints(ConfigParams)
    return ConfigParams(**{name: params_from_table(hints[name], config.section(name), f"{config.path}: [{name}]")
                           for name in SECTIONS})


def load_config(path: str | Path) -> tuple[TrackerConfig, ConfigParams]:
    """Read a tracker config and resolve its parameter sections (both checked)."""
    config = read_tracker_config(path)
    return config, config_params(config)


def parameter_tables(params: Any) -> dict[str, dict[str, Any]]:
    """Section name -> TOML-ready table of a :class:`ConfigParams` or
    :class:`~cubetrack.app.tracker.StageParams` (for run records)."""
    return {f.name: params_to_table(getattr(params, f.name)) for f in dataclasses.fields(params)}


def recording_intrinsics(config: TrackerConfig, recording: Recording,
                         cameras: Iterable[str] | None = None) -> dict[str, CameraIntrinsics]:
    """Intrinsics of the recording's cameras (or of ``cameras``): the config's ``camera_info``,
    else the recording's ``camera_info/<camera>.yaml``."""
    names = recording.camera_names if cameras is None else tuple(cameras)
    return {name: read_camera_info(camera_intrinsics_path(config, name, recording.path)) for name in names}
