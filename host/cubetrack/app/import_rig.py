"""``cubetrack import``: a calibrated camera rig's footage converted into cubetrack's formats.

A user whose cameras were calibrated by another tool has videos, a frame-time table and that
tool's calibration; the tracker reads a recording folder, ``camera_info`` YAML, an extrinsics
TOML, a body layout and a config (contracts §3, §4). :func:`import_caliscope` converts the
project layout of caliscope (https://github.com/mprib/caliscope): its calibration, board and frame
times (read by :mod:`cubetrack.io.caliscope`, which lists the files) and its videos
``video/cam_N.mp4``.

Written into the output folder: ``recording/`` (one camera ``camN`` per video, JPEG frames, the
frame times as both device and host times, and a ``clock.csv`` saying the cameras' clock is the
host's, so frames are stamped at capture, not at arrival; ``camera_info/camN.yaml``),
``extrinsics.toml``, ``board.toml`` (the ChArUco board as a body: its markers where OpenCV's
``CharucoBoard`` puts them, body frame = the board's centre, x along its rows, y towards its first
row, z out of the printed face; ``motion = "free"``: a calibration board is moved by hand, docs/tracking.md "A
motion switch per body") and ``config.toml`` (the board as the one robot; a world marker of
the board's dictionary that is not on the board, since the world frame is the calibration's; a board printed
inverted: ``[detector]`` white-on-black markers only; ``[estimator] use_upright_prior = false``,
since the calibration's world frame need not have z up and a hand-held board tilts freely).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2

from cubetrack.calib.reference import board_markers
from cubetrack.core.cameras import CameraIntrinsics, ClockSample, WorldBoard
from cubetrack.core.errors import ConfigError
from cubetrack.core.layout import CubeLayout, LayoutMarker, layout_to_table
from cubetrack.core.progress import Progress
from cubetrack.detect.detector import aruco_dictionary
from cubetrack.io.caliscope import read_caliscope_frame_times, read_caliscope_rig
from cubetrack.io.camera_info import write_camera_info
from cubetrack.io.config import write_extrinsics, write_toml
from cubetrack.io.recording import CameraEntry, RecordingWriter

log = logging.getLogger(__name__)

@dataclass(frozen=True, slots=True)
class ImportResult:
    """The files :func:`import_caliscope` wrote and how many frames per camera."""

    config: Path
    recording: Path
    extrinsics: Path
    layout: Path
    frames: Mapping[str, int]


def board_layout(board: WorldBoard) -> CubeLayout:
    """The ChArUco ``board`` as a body: one marker per face ``mID`` where OpenCV's board puts it,
    in the board frame (:class:`~cubetrack.core.cameras.WorldBoard`: centre, x along the rows, y
    towards the first row, z out of the printed face), moved freely (by hand)."""
    markers = tuple(LayoutMarker(f"m{m.marker_id}", m.marker_id, m.size_m, m.T_world_marker)
                    for m in board_markers(board))
    return CubeLayout(board.dictionary, markers, "free")


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
    aruco_dictionary(rig.board.dictionary)  # DetectionError naming the valid ones
    times = read_caliscope_frame_times(project / "video" / "timestamps.csv")
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
        "detector": {"detect_inverted_marker": rig.inverted, "detect_normal_marker": not rig.inverted},
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
