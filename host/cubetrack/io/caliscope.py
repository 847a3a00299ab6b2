"""The calibration and frame times of a caliscope project (https://github.com/mprib/caliscope), read
into cubetrack's values; :mod:`cubetrack.app.import_rig` converts a project with them. The
files, as caliscope writes them:

- ``calibration/camera_array.toml`` (or ``config.toml``): per camera ``[cameras.N]`` (or
  ``[cam_N]``) ``size`` [w, h], ``matrix`` K (px), ``distortions`` (OpenCV k1 k2 p1 p2 k3) and the
  extrinsics ``rotation`` R, ``translation`` t (metres) with x_cam = R x_world + t;
- ``calibration/charuco.toml`` (or the ``[charuco]`` table of ``config.toml``): ``columns``,
  ``rows``, ``dictionary``, ``aruco_scale`` (marker side / square side), the square side
  (``square_size_override_cm``, else the board's size in ``units`` over its squares) and
  ``inverted`` (white markers on black squares);
- ``video/timestamps.csv`` (``sync_index,cam_id,frame_index,frame_time``: frame i of ``cam_N.mp4``
  is camera N's i-th row in ``sync_index`` order; ``frame_time`` in seconds, one clock for every
  camera).
"""

from __future__ import annotations

import csv
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, WorldBoard
from cubetrack.core.errors import ConfigError
from cubetrack.core.geometry import make_T

_INCH_M = 0.0254
_UNITS_M = {"inch": _INCH_M, "cm": 0.01, "mm": 0.001, "m": 1.0}



@dataclass(frozen=True, slots=True)
class CaliscopeRig:
    """What a caliscope project says: per camera id its intrinsics and extrinsics, the board, and
    whether the board is printed inverted."""

    intrinsics: Mapping[int, CameraIntrinsics]
    extrinsics: Mapping[int, CameraExtrinsics]
    board: WorldBoard
    inverted: bool


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{path}: not found (a caliscope project has calibration/camera_array.toml, "
                          f"calibration/charuco.toml and video/)") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def _matrix(table: Mapping[str, Any], key: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    try:
        value = np.asarray(table[key], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise ConfigError(f"{where}: needs {key} as numbers of shape {shape}") from None
    if value.size != int(np.prod(shape)) or not np.isfinite(value).all():
        raise ConfigError(f"{where}: {key} must be {shape} finite numbers, got {value.size}")
    return value.reshape(shape)


def _camera_tables(doc: Mapping[str, Any]) -> dict[int, Mapping[str, Any]]:
    """Camera id -> table, from ``[cameras.N]`` (camera_array.toml) or ``[cam_N]`` (config.toml)."""
    cams = doc.get("cameras")
    items: Iterable[tuple[str, Any]]
    if isinstance(cams, dict):
        items = cams.items()
    else:
        items = ((k[4:], v) for k, v in doc.items() if k.startswith("cam_") and isinstance(v, dict))
    out = {}
    for key, table in items:
        try:
            out[int(key)] = table
        except ValueError:
            raise ConfigError(f"camera table {key!r}: the camera id must be an integer") from None
    return out


def read_caliscope_rig(project: Path) -> CaliscopeRig:
    """The cameras and board of the caliscope project folder ``project`` (module docstring);
    ConfigError naming the file and key when something is missing."""
    calib = project / "calibration"
    array_path = calib / "camera_array.toml"
    doc = _read_toml(array_path if array_path.exists() else calib / "config.toml")
    tables = _camera_tables(doc)
    if not tables:
        raise ConfigError(f"{array_path}: no [cameras.N] tables")
    intrinsics, extrinsics = {}, {}
    for cam_id, t in sorted(tables.items()):
        where = f"{array_path}: camera {cam_id}"
        width, height = (int(v) for v in _matrix(t, "size", (2,), where))
        K = _matrix(t, "matrix", (3, 3), where)
        dist = _matrix(t, "distortions", (5,), where)
        R = _matrix(t, "rotation", (3, 3), where)
        tvec = _matrix(t, "translation", (3,), where)
        if abs(np.linalg.det(R) - 1.0) > 1e-3:
            raise ConfigError(f"{where}: rotation is not a rotation matrix (det {np.linalg.det(R):.4f})")
        intrinsics[cam_id] = CameraIntrinsics(width, height, K, dist, camera_name=f"cam{cam_id}")
        # x_cam = R x_world + t  ->  T_world_cam = [R^T, -R^T t]
        extrinsics[cam_id] = CameraExtrinsics(make_T(R.T, -R.T @ tvec), method="caliscope")
    board_path = calib / "charuco.toml"
    charuco = _read_toml(board_path) if board_path.exists() else _read_toml(calib / "config.toml").get("charuco")
    if not isinstance(charuco, dict):
        raise ConfigError(f"{board_path}: not found, and calibration/config.toml has no [charuco] table")
    return CaliscopeRig(intrinsics, extrinsics, _board(charuco, str(board_path)), bool(charuco.get("inverted", False)))


def _board(t: Mapping[str, Any], where: str) -> WorldBoard:
    try:
        columns, rows, dictionary = int(t["columns"]), int(t["rows"]), str(t["dictionary"])
        scale = float(t.get("aruco_scale", 0.75))
        if "square_size_override_cm" in t:
            square_m = float(t["square_size_override_cm"]) * 0.01
        else:
            square_m = min(float(t["board_width"]) / columns, float(t["board_height"]) / rows) * _UNITS_M[t["units"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: needs columns, rows, dictionary and a square size "
                          f"(square_size_override_cm, or board_width/board_height in units): {exc}") from None
    if not (columns >= 2 and rows >= 2 and 0.0 < scale < 1.0 and square_m > 0.0):
        raise ConfigError(f"{where}: need columns, rows >= 2, 0 < aruco_scale < 1 and a positive square size")
    return WorldBoard(columns, rows, square_m, square_m * scale, dictionary)


def read_caliscope_frame_times(path: Path) -> dict[int, list[float]]:
    """Camera id -> its frames' times (s) in video order, from caliscope's timestamps.csv."""
    rows: dict[int, list[tuple[int, float]]] = {}
    try:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            for i, row in enumerate(reader):
                try:
                    rows.setdefault(int(row["cam_id"]), []).append((int(row["sync_index"]),
                                                                    float(row["frame_time"])))
                except (KeyError, TypeError, ValueError):
                    raise ConfigError(f"{path}: row {i + 2} needs sync_index, cam_id and frame_time numbers") from None
    except FileNotFoundError:
        raise ConfigError(f"{path}: not found (caliscope's frame times)") from None
    return {cam: [t for _, t in sorted(r)] for cam, r in rows.items()}
