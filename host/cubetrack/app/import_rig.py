"""``cubetrack import``: a calibrated camera rig's footage converted into cubetrack's formats.

A user whose cameras were calibrated by another tool has videos, a frame-time table and that
tool's calibration; the tracker reads a recording folder, ``camera_info`` YAML, an extrinsics
TOML, a body layout and a config (contracts §3, §4). :func:`import_caliscope` converts the
project layout of caliscope (https://github.com/mprib/caliscope), the format these facts are
taken from:

- ``calibration/camera_array.toml`` (or ``config.toml``): per camera ``[cameras.N]`` (or
  ``[cam_N]``) ``size`` [w, h], ``matrix`` K (px), ``distortions`` (OpenCV k1 k2 p1 p2 k3) and the
  extrinsics ``rotation`` R, ``translation`` t (metres) with x_cam = R x_world + t;
- ``calibration/charuco.toml`` (or the ``[charuco]`` table of ``config.toml``): ``columns``,
  ``rows``, ``dictionary``, ``aruco_scale`` (marker side / square side), the square side
  (``square_size_override_cm``, else the board's size in ``units`` over its squares) and
  ``inverted`` (white markers on black squares);
- ``video/cam_N.mp4`` and ``video/timestamps.csv`` (``sync_index,cam_id,frame_index,frame_time``:
  frame i of ``cam_N.mp4`` is camera N's i-th row in ``sync_index`` order; ``frame_time`` in
  seconds, one clock for every camera).

Written into the output folder: ``recording/`` (one camera ``camN`` per video, JPEG frames, the
frame times as both device and host times, and a ``clock.csv`` saying the cameras' clock is the
host's, so frames are stamped at capture, not at arrival; ``camera_info/camN.yaml``),
``extrinsics.toml``, ``board.toml`` (the ChArUco board as a body: its markers where OpenCV's
``CharucoBoard`` puts them, body frame = the board's centre, x along its rows, y towards its first
row, z out of the printed face) and ``config.toml`` (the board as the one robot; a world marker of
the board's dictionary that is not on the board, since the world frame is the calibration's;
``[detector] detect_inverted_marker`` from the board; ``[estimator] use_upright_prior = false``,
since the calibration's world frame need not have z up and a hand-held board tilts freely).
"""

from __future__ import annotations

import csv
import logging
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cubetrack.calib.reference import board_markers
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, ClockSample, WorldBoard
from cubetrack.core.errors import ConfigError
from cubetrack.core.geometry import make_T
from cubetrack.core.layout import CubeLayout, LayoutMarker, layout_to_table
from cubetrack.core.progress import Progress
from cubetrack.detect.detector import aruco_dictionary
from cubetrack.io.camera_info import write_camera_info
from cubetrack.io.config import write_extrinsics, write_toml
from cubetrack.io.recording import CameraEntry, RecordingWriter

log = logging.getLogger(__name__)

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


@dataclass(frozen=True, slots=True)
class ImportResult:
    """The files :func:`import_caliscope` wrote and how many frames per camera."""

    config: Path
    recording: Path
    extrinsics: Path
    layout: Path
    frames: Mapping[str, int]


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
    aruco_dictionary(dictionary)  # DetectionError naming the valid ones
    if not (columns >= 2 and rows >= 2 and 0.0 < scale < 1.0 and square_m > 0.0):
        raise ConfigError(f"{where}: need columns, rows >= 2, 0 < aruco_scale < 1 and a positive square size")
    return WorldBoard(columns, rows, square_m, square_m * scale, dictionary)


def board_layout(board: WorldBoard) -> CubeLayout:
    """The ChArUco ``board`` as a body: one marker per face ``mID`` where OpenCV's board puts it,
    in the board frame (:class:`~cubetrack.core.cameras.WorldBoard`: centre, x along the rows, y
    towards the first row, z out of the printed face)."""
    markers = tuple(LayoutMarker(f"m{m.marker_id}", m.marker_id, m.size_m, m.T_world_marker)
                    for m in board_markers(board))
    return CubeLayout(board.dictionary, markers)


def _frame_times(path: Path) -> dict[int, list[float]]:
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


def _world_table(board: WorldBoard) -> dict[str, Any]:
    """A world marker that cannot be confused with the board's: the world frame is the
    calibration's, so the marker is only named, never needed."""
    size = aruco_dictionary(board.dictionary).bytesList.shape[0]
    unused = max(i for i in range(size) if i not in board.marker_ids)
    return {"dictionary": board.dictionary, "marker_id": unused, "marker_size": board.marker_size_m}


def import_caliscope(project: str | Path, out: str | Path, jpeg_quality: int = 95, overwrite: bool = False,
                     progress: Progress | None = None) -> ImportResult:
    """Convert the caliscope project folder ``project`` into ``out`` (module docstring); returns
    what was written. ConfigError for a project that lacks a file or key, or a video whose frame
    count differs from its rows in timestamps.csv; RecordingError when ``out`` already holds a
    recording (unless ``overwrite``)."""
    project, out = Path(project), Path(out)
    if not 1 <= jpeg_quality <= 100:
        raise ConfigError(f"JPEG quality must be in 1..100, got {jpeg_quality}")
    rig = read_caliscope_rig(project)
    times = _frame_times(project / "video" / "timestamps.csv")
    missing = sorted(set(rig.intrinsics) - set(times))
    if missing:
        raise ConfigError(f"{project}: cameras {missing} have no rows in video/timestamps.csv")
    names = {cam: f"cam{cam}" for cam in rig.intrinsics}
    recording = out / "recording"
    total = sum(len(times[c]) for c in names)
    counts: dict[str, int] = {}
    with RecordingWriter(recording, [CameraEntry(n, f"caliscope:{project.name}/cam_{c}.mp4")
                                     for c, n in names.items()], overwrite=overwrite) as writer:
        for cam, name in names.items():
            write_camera_info(rig.intrinsics[cam], writer.camera_info_path(name))
            counts[name] = _write_video(writer, project / "video" / f"cam_{cam}.mp4", name, times[cam],
                                        rig.intrinsics[cam], jpeg_quality, progress, sum(counts.values()), total)
    extrinsics_path, layout_path, config_path = out / "extrinsics.toml", out / "board.toml", out / "config.toml"
    write_extrinsics({names[c]: e for c, e in rig.extrinsics.items()}, extrinsics_path)
    write_toml(layout_to_table(board_layout(rig.board)), layout_path)
    write_toml({
        "world": _world_table(rig.board),
        "cameras": [{"name": n} for n in names.values()],
        "robots": [{"name": "board", "layout": layout_path.name}],
        "detector": {"detect_inverted_marker": rig.inverted},
        "estimator": {"use_upright_prior": False},
    }, config_path)
    return ImportResult(config_path, recording, extrinsics_path, layout_path, counts)


def _write_video(writer: RecordingWriter, video: Path, name: str, times_s: list[float],
                 intrinsics: CameraIntrinsics, jpeg_quality: int, progress: Progress | None,
                 done: int, total: int) -> int:
    """Every frame of ``video`` as JPEG into camera ``name`` of ``writer``, stamped ``times_s``
    (device and host clock alike: one clock), with round trips saying so; the frame count."""
    if not video.exists():
        raise ConfigError(f"{video}: not found")
    capture = cv2.VideoCapture(str(video))
    count = 0
    try:
        while True:
            ok, image = capture.read()
            if not ok:
                break
            if count >= len(times_s):
                raise ConfigError(f"{video}: more frames than its {len(times_s)} rows in timestamps.csv")
            if (image.shape[1], image.shape[0]) != (intrinsics.width, intrinsics.height):
                raise ConfigError(f"{video}: frames are {image.shape[1]}x{image.shape[0]}, the calibration's "
                                  f"{intrinsics.width}x{intrinsics.height}")
            ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
            t = times_s[count]
            writer.add_clock_sample(name, ClockSample(t, t, t))
            writer.add_frame(name, count, t, t, jpeg.tobytes())
            count += 1
            if progress is not None:
                progress("import", done + count, total)
    finally:
        capture.release()
    if count != len(times_s):
        raise ConfigError(f"{video}: {count} frames, but timestamps.csv has {len(times_s)} rows for it")
    return count
