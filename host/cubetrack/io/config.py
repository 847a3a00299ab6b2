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

from cubetrack.core.cameras import CameraExtrinsics, WorldBoard, WorldConfig, WorldMarker
from cubetrack.core.errors import ConfigError, RecordingError
from cubetrack.core.geometry import T_from_position_quat, position_quat_from_T
from cubetrack.core.layout import DEFAULT_DICTIONARY, CubeLayout, pattern_collisions, read_layout
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


def _number(value: Any, where: str, key: str, positive: bool = True) -> float:
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value) or (
            positive and not value > 0):
        raise ConfigError(f"{where}: {key} must be a {'positive ' if positive else ''}number, got {value!r}")
    return float(value)


def _count(value: Any, where: str, key: str, minimum: int = 0) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        raise ConfigError(f"{where}: {key} must be an integer of at least {minimum}, got {value!r}")
    return value


def _pose(table: dict, where: str) -> np.ndarray:
    """``position`` (m) and ``quaternion_xyzw`` of a table (both optional: the identity)."""
    position, q = table.get("position", [0.0, 0.0, 0.0]), table.get("quaternion_xyzw", [0.0, 0.0, 0.0, 1.0])
    for key, value, n in (("position", position, 3), ("quaternion_xyzw", q, 4)):
        if not isinstance(value, list) or len(value) != n:
            raise ConfigError(f"{where}: {key} must be a list of {n} numbers, got {value!r}")
        for v in value:
            _number(v, where, key, positive=False)
    if np.linalg.norm(q) < 1e-9:
        raise ConfigError(f"{where}: quaternion_xyzw must not be zero")
    return T_from_position_quat(np.array(position, float), np.array(q, float))


def _dictionary(table: dict, where: str, default: str) -> str:
    name = table.get("dictionary", default)
    if not isinstance(name, str):
        raise ConfigError(f"{where}: dictionary must be a name like {DEFAULT_DICTIONARY!r}")
    return name


def _keys(table: Any, where: str, allowed: set[str]) -> dict:
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table")
    unknown = set(table) - allowed
    if unknown:
        raise ConfigError(f"{where} has unknown key(s) {', '.join(sorted(unknown))}; known: "
                          f"{', '.join(sorted(allowed))}")
    return table


def _world(table: Any, where: str) -> WorldConfig:
    if table is None:
        return WorldConfig()
    table = _keys(table, f"{where}: [world]",
                  {"dictionary", "marker_id", "marker_size", "markers", "board", "origin_marker"})
    dictionary = _dictionary(table, f"{where}: [world]", DEFAULT_DICTIONARY)
    marker_id = _count(table.get("marker_id", 0), f"{where}: [world]", "marker_id")
    size = _number(table.get("marker_size", 0.25), f"{where}: [world]", "marker_size (metres)")
    rows = table.get("markers", [])
    if not isinstance(rows, list):
        raise ConfigError(f"{where}: world.markers must be [[world.markers]] tables")
    markers = []
    for i, row in enumerate(rows):
        w = f"{where}: world.markers[{i}]"
        row = _keys(row, w, {"id", "size", "dictionary", "position", "quaternion_xyzw"})
        if "id" not in row or "position" not in row:
            raise ConfigError(f"{w} needs an id and a position (and quaternion_xyzw unless it lies flat like "
                              "the world marker)")
        markers.append(WorldMarker(_count(row["id"], w, "id"), _number(row.get("size", size), w, "size (metres)"),
                                   _pose(row, w), _dictionary(row, w, dictionary)))
    board = None
    if "board" in table:
        w = f"{where}: [world.board]"
        b = _keys(table["board"], w, {"squares", "square_size", "marker_size", "dictionary", "first_marker_id",
                                      "legacy_pattern", "position", "quaternion_xyzw"})
        squares = b.get("squares")
        if not isinstance(squares, list) or len(squares) != 2:
            raise ConfigError(f"{w}: squares must be [columns, rows], e.g. [5, 7]")
        missing = {"square_size", "marker_size"} - set(b)
        if missing:
            raise ConfigError(f"{w} lacks {', '.join(sorted(missing))} (metres)")
        legacy = b.get("legacy_pattern", False)
        if not isinstance(legacy, bool):
            raise ConfigError(f"{w}: legacy_pattern must be true or false")
        board = WorldBoard(_count(squares[0], w, "squares", 2), _count(squares[1], w, "squares", 2),
                           _number(b["square_size"], w, "square_size (metres)"),
                           _number(b["marker_size"], w, "marker_size (metres)"), _dictionary(b, w, dictionary),
                           _count(b.get("first_marker_id", 0), w, "first_marker_id"), legacy, _pose(b, w))
        if not board.marker_size_m < board.square_size_m:
            raise ConfigError(f"{w}: marker_size must be smaller than square_size")
    origin = table.get("origin_marker", True)
    if not isinstance(origin, bool):
        raise ConfigError(f"{where}: [world] origin_marker must be true or false")
    if not origin and not markers and board is None:
        raise ConfigError(f"{where}: [world] origin_marker = false needs [[world.markers]] or a [world.board]")
    return WorldConfig(dictionary, marker_id, size, tuple(markers), board, origin)


def world_marker_keys(world: WorldConfig) -> list[tuple[tuple[str, int], str]]:
    """(dictionary, id) of every marker of the world reference, with what it is (for errors)."""
    keys = [((m.dictionary, m.marker_id), "the world marker" if k == 0 and world.origin_marker else f"world marker {k}")
            for k, m in enumerate(world.reference_markers())]
    if world.board is not None:
        keys += [((world.board.dictionary, i), "the world board") for i in world.board.marker_ids]
    return keys


def world_to_table(world: WorldConfig) -> dict[str, Any]:
    """The ``[world]`` table of a world reference (:func:`_world` reads it back)."""
    def pose(T: np.ndarray) -> dict[str, list[float]]:
        position, q = position_quat_from_T(T)
        return {"position": [float(v) for v in position], "quaternion_xyzw": [float(v) for v in q]}

    table: dict[str, Any] = {"dictionary": world.dictionary, "marker_id": world.marker_id,
                             "marker_size": world.marker_size_m}
    if not world.origin_marker:
        table["origin_marker"] = False
    if world.markers:
        table["markers"] = [{"id": m.marker_id, "size": m.size_m, "dictionary": m.dictionary, **pose(m.T_world_marker)}
                            for m in world.markers]
    if world.board is not None:
        b = world.board
        table["board"] = {"squares": [b.squares_x, b.squares_y], "square_size": b.square_size_m,
                          "marker_size": b.marker_size_m, "dictionary": b.dictionary,
                          "first_marker_id": b.first_marker_id, "legacy_pattern": b.legacy_pattern,
                          **pose(b.T_world_board)}
    return table


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
    owner: dict[tuple[str, int], str] = {}
    for marker_key, what in world_marker_keys(world):
        if marker_key in owner:
            raise ConfigError(f"{where}: {what} uses {marker_key[0]} id {marker_key[1]}, already used by "
                              f"{owner[marker_key]}")
        owner[marker_key] = what
    for r in robots:
        for marker_key in sorted(r.layout.keys):
            if marker_key in owner:
                raise ConfigError(f"{where}: robot {r.name!r} uses {marker_key[0]} id {marker_key[1]}, already used "
                                  f"by {owner[marker_key]}; every robot needs ids of its own")
            owner[marker_key] = f"robot {r.name!r}"
    collisions = pattern_collisions(owner)
    if collisions:
        raise ConfigError(f"{where}: {collisions[0]}")
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
        "world": world_to_table(world),
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
