"""The tracker config TOML (contracts §4) and the extrinsics TOML written by calibration.

Relative paths inside a config resolve against the config file's folder. Every other table
(``[detector]``, ``[estimator]``, ``[fusion]``, ``[calibration]``, ...) is kept raw in
``TrackerConfig.sections``; the workflow layer (:func:`cubetrack.app.config.config_params`) turns
each into its stage's params dataclass, once, and refuses unknown sections.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from cubetrack.core.cameras import CameraExtrinsics, WorldConfig
from cubetrack.core.errors import ConfigError, RecordingError
from cubetrack.core.geometry import T_from_position_quat, position_quat_from_T
from cubetrack.core.layout import DEFAULT_DICTIONARY, CubeLayout, read_layout
from cubetrack.core.params import read_toml
from cubetrack.io.files import atomic_write
from cubetrack.io.recording import check_camera_name


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """A camera node: name, stream URL, and its intrinsics file (None: take the recording's)."""

    name: str
    url: str = ""
    camera_info: Path | None = None


@dataclass(frozen=True, slots=True, eq=False)
class RobotConfig:
    """A tracked robot and the layout of its cube (``layout_path``: the file it was read from)."""

    name: str
    layout: CubeLayout
    layout_path: Path | None = None


@dataclass(frozen=True, slots=True, eq=False)
class TrackerConfig:
    """A whole tracker config file, parsed and checked."""

    path: Path
    world: WorldConfig
    cameras: tuple[CameraConfig, ...]
    robots: tuple[RobotConfig, ...]
    sections: dict[str, dict[str, Any]] = field(default_factory=dict)  # name -> raw parameter table
    outputs: tuple[dict[str, Any], ...] = ()  # raw [[outputs]] tables (cubetrack.app.outputs reads them)

    def section(self, name: str) -> dict[str, Any]:
        """The raw table of a parameter section (empty when the file has none)."""
        return dict(self.sections.get(name, {}))


def _world(table: Any, where: str) -> WorldConfig:
    if table is None:
        return WorldConfig()
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: [world] must be a table")
    unknown = set(table) - {"dictionary", "marker_id", "marker_size"}
    if unknown:
        raise ConfigError(f"{where}: [world] has unknown key(s) {', '.join(sorted(unknown))}")
    world = WorldConfig(
        dictionary=table.get("dictionary", DEFAULT_DICTIONARY),
        marker_id=table.get("marker_id", 0),
        marker_size_m=table.get("marker_size", 0.25),
    )
    if not isinstance(world.dictionary, str):
        raise ConfigError(f"{where}: [world] dictionary must be a name like {DEFAULT_DICTIONARY!r}")
    if not isinstance(world.marker_id, int) or isinstance(world.marker_id, bool) or world.marker_id < 0:
        raise ConfigError(f"{where}: [world] marker_id must be a non-negative integer")
    size = world.marker_size_m
    if not isinstance(size, (int, float)) or isinstance(size, bool) or not 0 < size < math.inf:
        raise ConfigError(f"{where}: [world] marker_size must be a positive number of metres")
    return WorldConfig(world.dictionary, world.marker_id, float(size))


def read_tracker_config(path: str | Path) -> TrackerConfig:
    """Read and check a tracker config TOML file (contracts §4)."""
    path = Path(path)
    doc = read_toml(path, "tracker config")
    where = str(path)
    base = path.parent
    cameras = []
    for key in ("cameras", "robots", "outputs"):
        if not isinstance(doc.get(key, []), list) or not all(isinstance(t, dict) for t in doc.get(key, [])):
            raise ConfigError(f"{where}: {key} must be [[{key}]] tables")
    for i, row in enumerate(doc.get("cameras", [])):
        if not isinstance(row, dict) or "name" not in row:
            raise ConfigError(f"{where}: cameras[{i}] needs a name")
        try:
            name = check_camera_name(row["name"])
        except RecordingError as exc:
            raise ConfigError(f"{where}: cameras[{i}]: {exc}") from None
        info = row.get("camera_info")
        if info is not None and not isinstance(info, str):
            raise ConfigError(f"{where}: cameras[{i}].camera_info must be a file name")
        cameras.append(CameraConfig(name, str(row.get("url", "")), base / info if info else None))
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise ConfigError(f"{where}: camera names must be unique, got {names}")
    robots = []
    for i, row in enumerate(doc.get("robots", [])):
        if not isinstance(row, dict) or "name" not in row or "layout" not in row:
            raise ConfigError(f"{where}: robots[{i}] needs a name and a layout file")
        layout_path = base / str(row["layout"])
        robots.append(RobotConfig(str(row["name"]), read_layout(layout_path), layout_path))
    if not robots:
        raise ConfigError(f"{where}: needs at least one [[robots]] table with a cube layout")
    if len({r.name for r in robots}) != len(robots):
        raise ConfigError(f"{where}: robot names must be unique")
    world = _world(doc.get("world"), where)
    owner: dict[tuple[str, int], str] = {(world.dictionary, world.marker_id): "the world marker"}
    for r in robots:
        for marker_id in sorted(r.layout.ids):
            key = (r.layout.dictionary, marker_id)
            if key in owner:
                raise ConfigError(f"{where}: robot {r.name!r} uses {key[0]} id {marker_id}, already used by "
                                  f"{owner[key]}; every robot needs ids of its own")
            owner[key] = f"robot {r.name!r}"
    sections = {}
    for name, table in doc.items():
        if name in ("world", "cameras", "robots", "outputs"):
            continue
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: {name} must be a [{name}] table of parameters")
        sections[name] = table
    return TrackerConfig(path, world, tuple(cameras), tuple(robots), sections, tuple(doc.get("outputs", [])))


def tracker_config_to_table(
    world: WorldConfig,
    cameras: list[CameraConfig],
    robots: list[tuple[str, str]],
    sections: dict[str, dict[str, Any]] | None = None,
    relative_to: Path | None = None,
) -> dict[str, Any]:
    """A tracker config document; ``robots`` are (name, layout path as written) pairs."""

    def rel(p: Path) -> str:
        if relative_to is not None:
            try:
                return str(Path(p).relative_to(relative_to))
            except ValueError:
                pass
        return str(p)

    doc: dict[str, Any] = {
        "world": {"dictionary": world.dictionary, "marker_id": world.marker_id,
                  "marker_size": world.marker_size_m},
        "cameras": [
            {"name": c.name, "url": c.url, **({"camera_info": rel(c.camera_info)} if c.camera_info else {})}
            for c in cameras
        ],
        "robots": [{"name": n, "layout": layout} for n, layout in robots],
    }
    doc.update(sections or {})
    return doc


def write_toml(doc: dict[str, Any], path: str | Path) -> None:
    """Write a TOML document (atomically: an earlier file is replaced only by the whole new one)."""
    atomic_write(path, tomli_w.dumps(doc))


def write_extrinsics(extrinsics: dict[str, CameraExtrinsics], path: str | Path) -> None:
    """Write the extrinsics TOML: one table per camera (contracts §4)."""
    doc = {}
    for name, e in extrinsics.items():
        position, q = position_quat_from_T(e.T_world_cam)
        doc[name] = {
            "position": [float(v) for v in position],
            "quaternion_xyzw": [float(v) for v in q],
            "samples": int(e.samples),
            "spread_position_m": float(e.spread_position_m),
            "spread_rotation_deg": float(e.spread_rotation_deg),
            "method": e.method,
        }
    write_toml(doc, path)


def read_extrinsics(path: str | Path) -> dict[str, CameraExtrinsics]:
    """Read the extrinsics TOML written by ``cubetrack calibrate``."""
    path = Path(path)
    doc = read_toml(path, "extrinsics")
    if not doc:
        raise ConfigError(f"{path}: no camera tables; expected [cam1] position = [...] quaternion_xyzw = [...]")
    out = {}
    for name, table in doc.items():
        where = f"{path}: [{name}]"
        if not isinstance(table, dict):
            raise ConfigError(f"{where} must be a table")
        try:
            position = np.array(table["position"], dtype=float).reshape(3)
            q = np.array(table["quaternion_xyzw"], dtype=float).reshape(4)
        except (KeyError, TypeError, ValueError):
            raise ConfigError(f"{where} needs position = [x, y, z] and quaternion_xyzw = [x, y, z, w]") from None
        if not (np.all(np.isfinite(position)) and np.all(np.isfinite(q)) and np.linalg.norm(q) > 1e-9):
            raise ConfigError(f"{where} has a non-finite position or a zero quaternion")
        try:
            out[name] = CameraExtrinsics(
                T_from_position_quat(position, q),
                int(table.get("samples", 0)),
                float(table.get("spread_position_m", 0.0)),
                float(table.get("spread_rotation_deg", 0.0)),
                str(table.get("method", "")),
            )
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f"{where}: samples must be an integer and the spreads numbers") from None
    return out


def camera_intrinsics_path(config: TrackerConfig, camera: str, recording_path: Path | None) -> Path:
    """Where a camera's intrinsics come from: the config's ``camera_info``, else the recording's
    ``camera_info/<camera>.yaml`` (contracts §4)."""
    for c in config.cameras:
        if c.name == camera and c.camera_info is not None:
            return c.camera_info
    if recording_path is not None:
        candidate = Path(recording_path) / "camera_info" / f"{camera}.yaml"
        if candidate.exists():
            return candidate
    raise ConfigError(
        f"{config.path}: no intrinsics for camera {camera!r}: set camera_info in its [[cameras]] table"
        + (f" or add {Path(recording_path) / 'camera_info' / (camera + '.yaml')}" if recording_path else "")
    )
