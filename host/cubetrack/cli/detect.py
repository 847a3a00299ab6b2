"""Detect square markers in one image and print them as JSON.

For every marker: its dictionary, id, corners in pixels (TL, TR, BR, BL; (0, 0) is the centre of
the top-left pixel), shoelace pixel area, and — with --camera-info and --marker-size — its pose
in the camera optical frame (x right, y down, z forward): position in metres and
quaternion_xyzw of the marker frame (x right, y up, z out of the marker), plus the other planar
(IPPE) solution. Intrinsics: ROS camera_info YAML or OpenCV FileStorage YAML.

Example:
  cubetrack detect board.jpg --camera-info cam.yml --dictionary DICT_6X6_250 --marker-size 0.02
  cubetrack detect inverted-board.jpg --dictionary DICT_4X4_1000 --inverted   # white-on-black markers
"""

from __future__ import annotations

import argparse

HELP = "detect markers in one image; print ids, corners, areas and poses as JSON"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("image", help="image file (JPEG, PNG, ...)")
    parser.add_argument("--camera-info", metavar="YAML",
                        help="intrinsics (ROS camera_info or OpenCV FileStorage YAML); "
                             "without it no poses are printed")
    parser.add_argument("--dictionary", action="append", metavar="NAME",
                        help="OpenCV dictionary, e.g. DICT_6X6_250 (repeat for several; "
                             "default: the [detector] dictionary)")
    parser.add_argument("--marker-size", type=float, metavar="METRES",
                        help="side of the black square in metres (needed for poses)")
    parser.add_argument("--refinement", metavar="METHOD",
                        help="corner refinement; overrides [detector] corner_refinement "
                             "(`cubetrack defaults --section detector` lists the methods)")
    parser.add_argument("--inverted", action="store_true",
                        help="also find white-on-black (inverted) markers; sets [detector] detect_inverted_marker")
    parser.add_argument("--indent", type=int, default=2, help="JSON indentation (0: one line)")


def _pose_json(T, err_px: float) -> dict:
    from cubetrack.core.geometry import position_quat_from_T

    position_m, q_xyzw = position_quat_from_T(T)
    return {"position": [round(float(v), 6) for v in position_m],
            "quaternion_xyzw": [round(float(v), 8) for v in q_xyzw],
            "reprojection_error_px": round(float(err_px), 4)}


def run(args: argparse.Namespace) -> int:
    import json
    import logging
    from pathlib import Path

    from cubetrack.core.errors import DetectionError
    from cubetrack.core.params import params_with
    from cubetrack.detect.detector import Detector, DetectorParams, read_gray
    from cubetrack.estimate.marker import marker_pose
    from cubetrack.io.camera_info import read_camera_info

    names = args.dictionary or [DetectorParams().dictionary]
    params = params_with(DetectorParams(), "--dictionary", dictionary=names[0])
    if args.refinement:
        params = params_with(params, "--refinement", corner_refinement=args.refinement)
    if args.inverted:
        params = params_with(params, "--inverted", detect_inverted_marker=True)
    detector = Detector(params, dictionaries=names)
    intrinsics = read_camera_info(args.camera_info) if args.camera_info else None
    if intrinsics is not None and not (args.marker_size and args.marker_size > 0):
        raise DetectionError("poses need --marker-size (the black square's side in metres, e.g. 0.02)")
    path = Path(args.image)
    gray = read_gray(path)
    if intrinsics is not None and (gray.shape[1], gray.shape[0]) != (intrinsics.width, intrinsics.height):
        logging.getLogger(__name__).warning(
            "%s: intrinsics are for %dx%d images, %s is %dx%d: poses will be wrong",
            args.camera_info, intrinsics.width, intrinsics.height, path, gray.shape[1], gray.shape[0])
    markers = []
    found = detector.find(gray, lens=intrinsics)
    for det in found.detections:
        entry = {"dictionary": det.dictionary, "id": det.marker_id,
                 "corners_px": [[round(float(x), 4), round(float(y), 4)] for x, y in det.corners_px],
                 "area_px2": round(det.area_px2, 3)}
        if intrinsics is not None:
            mp = marker_pose(det, args.marker_size, intrinsics)
            entry["pose"] = None if mp is None else _pose_json(mp.T_cam_marker, mp.reprojection_error_px)
            entry["pose_alt"] = (None if mp is None or mp.T_cam_marker_alt is None
                                 else _pose_json(mp.T_cam_marker_alt, mp.reprojection_error_alt_px))
        markers.append(entry)
    out = {
        "image": str(path), "width": int(gray.shape[1]), "height": int(gray.shape[0]),
        "dictionaries": list(detector.dictionaries),
        "corner_refinement": detector.params.corner_refinement.value,
        "marker_size_m": args.marker_size, "pose_frame": "camera optical (x right, y down, z forward)"
        if intrinsics is not None else None,
        "markers": markers,
        "dropped": dict(found.dropped),
    }
    print(json.dumps(out, indent=args.indent or None))
    return 0
