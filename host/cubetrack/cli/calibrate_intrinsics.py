"""Calibrate a camera's intrinsics (K, distortion) from photos of a ChArUco board.

Each image is searched for the board (OpenCV 5 CharucoDetector); views with enough corners are
fitted together with cv2.calibrateCamera. Prints the RMS reprojection error, fx and fy with
their standard deviations, and how each image was used; writes ROS camera_info YAML.
Use 10-20 photos with the board filling much of the frame at varied angles. Boards printed by
OpenCV < 4.6 with an even number of rows need --legacy. Options left out keep the board
parameters' defaults (cubetrack.calib.intrinsics.IntrinsicsParams: the board of the example
below, 3 usable views at least). See docs/calibration.md.

Or live from any camera (--camera usb:0, v4l2:/dev/video2, http://.../stream, file:video.avi):
views are kept as the board is moved in front of it, each one that shows a part of the image or
a tilt the others do not (cubetrack.calib.live_views), with a line of guidance per frame on
stderr (where the board has not been yet), until --views are kept or --duration passes.

Examples:
  cubetrack calibrate-intrinsics img_*.jpg --board 5x7 --square 0.04 --marker 0.02 \\
      --dictionary DICT_6X6_250 --out cam1.yaml
  cubetrack calibrate-intrinsics --camera usb:0 --board 5x7 --square 0.04 --marker 0.02 \\
      --dictionary DICT_6X6_250 --out cam1.yaml
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import Any

HELP = "intrinsics from ChArUco photos -> ROS camera_info YAML"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("images", nargs="*", type=Path, metavar="IMAGE", help="photos of the ChArUco board")
    p.add_argument("--camera", metavar="URL", help="capture the views live from this camera instead (usb:0, "
                   "v4l2:/dev/video2, http://host/stream, file:video.avi)")
    p.add_argument("--views", type=int, default=15, metavar="N", help="with --camera: views to keep (default 15)")
    p.add_argument("--duration", type=float, default=180.0, metavar="S",
                   help="with --camera: stop looking after S seconds, with the views kept so far (default 180)")
    p.add_argument("--board", metavar="COLSxROWS", help="squares across x and y, e.g. 5x7")
    p.add_argument("--square", type=float, metavar="M", help="square side, metres")
    p.add_argument("--marker", type=float, metavar="M", help="marker side, metres")
    p.add_argument("--dictionary", help="marker dictionary, e.g. DICT_6X6_250")
    p.add_argument("--legacy", action="store_true",
                   help="board made by OpenCV < 4.6 (matters for an even number of rows)")
    p.add_argument("--min-views", type=int, metavar="N", help="usable views needed")
    p.add_argument("--camera-name", default=None, help="camera_name in the YAML (default: the output's stem)")
    p.add_argument("--out", required=True, type=Path, metavar="YAML", help="camera_info YAML to write")


def parse_board(text: str) -> tuple[int, int]:
    from cubetrack.core.errors import ConfigError

    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise ConfigError(f"--board {text!r}: expected squares as COLSxROWS, e.g. 5x7")
    return int(m.group(1)), int(m.group(2))


def run(args: argparse.Namespace) -> int:
    from cubetrack.calib.intrinsics import IntrinsicsParams, calibrate_intrinsics, calibrate_intrinsics_files
    from cubetrack.core.params import params_with
    from cubetrack.core.progress import StderrProgress
    from cubetrack.io.camera_info import write_camera_info

    given = {"square_m": args.square, "marker_m": args.marker, "dictionary": args.dictionary,
             "legacy_pattern": args.legacy or None, "min_views": args.min_views}
    if args.board is not None:
        given["squares_x"], given["squares_y"] = parse_board(args.board)
    params = params_with(IntrinsicsParams(), "board", **{k: v for k, v in given.items() if v is not None})
    name = args.camera_name or args.out.stem
    if bool(args.images) == bool(args.camera):
        from cubetrack.core.errors import ConfigError

        raise ConfigError("give either photos of the board or --camera URL (to capture the views live)")
    if args.camera:
        result = calibrate_intrinsics(_live_views(args, params), params, name)
    else:
        result = calibrate_intrinsics_files(args.images, params, name, StderrProgress())
    write_camera_info(result.intrinsics, args.out)
    K = result.intrinsics.K
    used = sum(v.used for v in result.views)
    print(f"{'image':<40} {'corners':>7}  use")
    for v in result.views:
        status = f"rms {v.rms_px:.3f} px" if v.used else f"not used: {v.reason}"
        print(f"{v.name:<40} {v.corners:>7}  {status}")
    print(f"{used} of {len(result.views)} views, RMS reprojection error {result.rms_px:.3f} px")
    print(f"fx {K[0, 0]:.2f} ± {result.std_fx_px:.2f}  fy {K[1, 1]:.2f} ± {result.std_fy_px:.2f}  "
          f"cx {K[0, 2]:.2f}  cy {K[1, 2]:.2f} px; dist {', '.join(f'{d:.4g}' for d in result.intrinsics.dist)}")
    print(f"wrote {args.out}")
    return 0


def _live_views(args: argparse.Namespace, params: Any) -> list:
    """Views of the board picked from ``--camera`` as it streams, a guidance line per frame on stderr."""
    import sys

    from cubetrack.calib.live_views import ViewPicker, pick_views_live
    from cubetrack.core.errors import ConfigError

    if args.views < 1 or not args.duration > 0:
        raise ConfigError("--views must be at least 1 and --duration positive")
    picker = ViewPicker(params, target_views=args.views)

    def report(view: Any, guidance: str) -> None:
        what = f"kept ({view.corners} corners)" if view.kept else view.reason
        print(f"{view.name}: {what} | {guidance}", file=sys.stderr, flush=True)

    try:
        pick_views_live(args.camera, picker, args.duration, report)
    except KeyboardInterrupt:  # enough views: Ctrl-C calibrates with those kept so far
        print(f"stopped by Ctrl-C with {len(picker.views)} views", file=sys.stderr)
    print(f"{len(picker.views)} views captured from {args.camera}: {picker.guidance()}", file=sys.stderr)
    return picker.views
