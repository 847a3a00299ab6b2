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
import logging
import typing
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cubetrack.app.tracker import StageParams
from cubetrack.calib.bundle import MOVED_BODY_KEYS, BodyCalibrationParams, BundleAdjustmentParams
from cubetrack.calib.extrinsics import CalibrationParams
from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import ConfigError
from cubetrack.core.frame_pool import LiveParams
from cubetrack.core.layout import CubeLayout, face_T_cube_marker
from cubetrack.core.params import params_from_table, params_to_table
from cubetrack.detect.detector import CornerRefinement
from cubetrack.io.camera_info import read_camera_info
from cubetrack.io.config import RobotConfig, TrackerConfig, camera_intrinsics_path, read_tracker_config
from cubetrack.io.recording import Recording
from cubetrack.sink.dashboard.state import DashboardParams
from cubetrack.source.streams import SourceParams

log = logging.getLogger(__name__)

# [filter] corner_noise_px below this trusts the corners more than the edge fit measures them
# (0.08-0.35 px by view angle; its best setting is 0.2): docs/history/accuracy.md "What better corners would buy"
TRUSTING_CORNER_NOISE_PX = 0.2


@dataclass(frozen=True, slots=True)
class ConfigParams(StageParams):
    """Every parameter section of a tracker config, resolved (defaults where the file is silent).

    The fields are the sections, in the order ``cubetrack defaults`` prints them: the tracker's
    (``[detector]`` ... ``[track]``, from :class:`~cubetrack.app.tracker.StageParams`, so these
    parameters run a :class:`~cubetrack.app.tracker.Tracker` as they are), then calibration,
    bundle adjustment, body calibration, the live source, live processing and the dashboard. This class is the one
    list of sections.
    """

    calibration: CalibrationParams = field(default_factory=CalibrationParams)
    bundle_adjustment: BundleAdjustmentParams = field(default_factory=BundleAdjustmentParams)
    body_calibration: BodyCalibrationParams = field(default_factory=BodyCalibrationParams)
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
    moved = [key for key in config.section("bundle_adjustment") or {} if key in MOVED_BODY_KEYS]
    if moved:
        raise ConfigError(f"{config.path}: [bundle_adjustment] " + ", ".join(moved) + " moved to [body_calibration] as "
                          + ", ".join(MOVED_BODY_KEYS[key] for key in moved) + " (the same meaning and values)")
    hints = typing.get_type_hints(ConfigParams)
    params = ConfigParams(**{name: params_from_table(hints[name], config.section(name), f"{config.path}: [{name}]")
                             for name in SECTIONS})
    if params.detector.corner_refinement is not CornerRefinement.EDGE and "corner_noise_by_width" not in (
            config.section("filter") or {}):  # the width law is the edge fit's (FilterParams.corner_noise_by_width)
        params = dataclasses.replace(params, filter=dataclasses.replace(params.filter, corner_noise_by_width=False))
    for warning in corner_trust_warnings(params, config.robots):
        log.warning("%s: %s", config.path, warning)
    return params


def corner_trust_warnings(params: StageParams, robots: Iterable[RobotConfig]) -> list[str]:
    """One line per way the ``[filter]`` trusts the corners more than they deserve: a
    ``corner_noise_px`` below :data:`TRUSTING_CORNER_NOISE_PX` with the edge fit's corners, or with
    template corners on a cube whose layout is as designed (not calibrated: a marker placed 1 mm off
    then reads as a turned cube; realistic rotation 2.3° against 1.6°, docs/tracking.md)."""
    noise = params.filter.corner_noise_px
    if noise >= TRUSTING_CORNER_NOISE_PX:
        return []
    refinement = params.detector.corner_refinement
    if refinement is not CornerRefinement.TEMPLATE:
        return [(f"[filter] corner_noise_px = {noise:g} trusts the corners more than [detector] corner_refinement = "
                 f"{refinement.value} measures them; use corner_refinement = \"template\" (with a calibrated body) "
                 f"or corner_noise_px >= {TRUSTING_CORNER_NOISE_PX:g}")]
    return [(f"[filter] corner_noise_px = {noise:g} trusts the corners, but robot {r.name}'s cube layout is as "
             f"designed, not calibrated: markers a millimetre off read as a turned cube; run cubetrack calibrate-body "
             f"or use corner_noise_px >= {TRUSTING_CORNER_NOISE_PX:g}") for r in robots if is_as_designed(r.layout)]


def is_as_designed(layout: CubeLayout) -> bool:
    """Whether every marker of ``layout`` sits exactly (1 µm, 1e-6 rad) on the centre of its named
    face of a cube (the layouts people write and ``cubetrack simulate`` writes; ``calibrate-body``'s
    are measured, never exact); False for a layout with a face not named after a cube face."""
    for marker in layout.markers:
        T = marker.T_cube_marker
        try:
            designed = face_T_cube_marker(marker.face, 2.0 * float(np.linalg.norm(T[:3, 3])))
        except ConfigError:
            return False
        if not np.allclose(T[:3, :3], designed[:3, :3], atol=1e-6) or not np.allclose(T[:3, 3], designed[:3, 3],
                                                                                        atol=1e-6):
            return False
    return True


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
