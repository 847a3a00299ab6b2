"""Convert a calibrated camera rig's footage into cubetrack's formats, ready for ``track``.

Today's format: a caliscope project folder (https://github.com/mprib/caliscope): its
calibration/camera_array.toml (intrinsics and extrinsics, x_cam = R x_world + t),
calibration/charuco.toml (the board) and video/cam_N.mp4 with video/timestamps.csv. Written
into OUT: recording/ (JPEG frames stamped with the rig's frame times, camera_info/), extrinsics.toml,
board.toml (the ChArUco board as a body) and config.toml (docs/tracking.md "Real footage").

Example:
  cubetrack import caliscope ../shared/data/real/caliscope-4cam --out rig
  cubetrack track --config rig/config.toml --extrinsics rig/extrinsics.toml --recording rig/recording --out rig/poses
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "convert a calibrated rig's footage (a caliscope project) into a recording, extrinsics, body and config"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("format", choices=("caliscope",), help="the rig's format")
    parser.add_argument("project", type=Path, help="the project folder (calibration/ and video/)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--jpeg-quality", type=int, default=95, metavar="Q", help="JPEG quality of the frames (1-100)")
    parser.add_argument("--force", action="store_true", help="overwrite a recording already in OUT/recording")


def run(args: argparse.Namespace) -> int:
    from cubetrack.app.import_rig import import_caliscope
    from cubetrack.core.progress import StderrProgress

    result = import_caliscope(args.project, args.out, args.jpeg_quality, args.force, StderrProgress())
    print(f"recording: {result.recording} ({', '.join(f'{c}: {n} frames' for c, n in result.frames.items())})")
    print(f"extrinsics: {result.extrinsics}\nbody: {result.layout}\nconfig: {result.config}")
    print(f"track it: cubetrack track --config {result.config} --extrinsics {result.extrinsics} "
          f"--recording {result.recording} --out {args.out / 'poses'}")
    return 0
