"""Pictures of the dashboard: camera frames annotated on the server with OpenCV, and the
geometry of the top view.

:func:`view_overlay` computes, in the frame's full-resolution pixels, what a camera tile draws:
each detected marker (outline, id and, where the predicted cube identifies it, its face), each
recently tracked robot's cube markers where its pose projects them (the view's own predicted
corners when it carries them), and the world axes and world marker of a calibrated camera.
:func:`annotated_jpeg` draws that onto the frame scaled down to the tile's width. Colours (BGR):
detections green, predicted cube orange, world x/y/z red/green/blue, world marker cyan.

:func:`floor_footprint` is a camera's field of view on the floor (z = 0), for the top view.
"""

from __future__ import annotations

import numpy as np

from cubetrack.core.cameras import CameraIntrinsics, WorldConfig
from cubetrack.core.geometry import transform_points
from cubetrack.core.layout import CubeLayout, marker_corners_m
from cubetrack.core.records import CameraView
from cubetrack.sink.base import CameraSetup
from cubetrack.sink.foxglove import project

GREEN = (60, 220, 60)
ORANGE = (0, 140, 255)
CYAN = (230, 200, 0)
AXIS_COLOURS = ((40, 40, 230), (40, 200, 40), (230, 90, 30))  # x red, y green, z blue
LABEL_SCALE = 0.35


def _face_of(detection, cubes_px: list[tuple[str, CubeLayout, np.ndarray]]) -> tuple[str, str] | None:
    """(robot, face) whose projected marker lies on ``detection``: same id and dictionary, centre
    within half a marker side; None when no projected cube explains it."""
    centre = detection.corners_px.mean(axis=0)
    side_px = float(np.sqrt(max(detection.area_px2, 1.0)))
    best = None
    for robot, layout, squares in cubes_px:
        if detection.dictionary and detection.dictionary != layout.dictionary:
            continue
        for i in layout.indices_of(detection.marker_id):
            d = float(np.linalg.norm(squares[i].mean(axis=0) - centre))
            if d <= 0.5 * side_px and (best is None or d < best[0]):
                best = (d, robot, layout.markers[i].face)
    return None if best is None else (best[1], best[2])


def view_overlay(view: CameraView, camera: CameraSetup | None,
                 cubes: list[tuple[str, CubeLayout, np.ndarray]], world: WorldConfig | None) -> dict:
    """What a tile draws over ``view`` (JSON-ready, full-resolution pixels): ``detections`` (id,
    corners, face and robot when known), ``cubes`` (robot -> its markers' projected corners),
    ``axes`` (origin, x, y, z tips) and ``world_marker`` (4 corners), the last two None when the
    camera is not calibrated or they lie behind it. ``cubes``: (robot, layout, T_world_cube)."""
    cubes_px = []
    for robot, layout, T_world_cube in cubes:
        corners = view.predicted_corners_px.get(robot)
        if corners is None and camera is not None:
            corners = project(camera, transform_points(T_world_cube, layout.corners_m.reshape(-1, 3)))
        if corners is not None:
            cubes_px.append((robot, layout, np.asarray(corners, float).reshape(-1, 4, 2)))
    detections = []
    for d in view.detections:
        face = _face_of(d, cubes_px)
        detections.append({"id": int(d.marker_id), "corners_px": np.round(d.corners_px, 2).tolist(),
                           "robot": face[0] if face else None, "face": face[1] if face else None})
    axes = marker = None
    if world is not None and camera is not None:
        length_m = world.marker_size_m
        tips = project(camera, np.array([[0, 0, 0], [length_m, 0, 0], [0, length_m, 0], [0, 0, length_m]], float))
        axes = None if tips is None else np.round(tips, 2).tolist()
        square = marker_corners_m(world.marker_size_m)
        found = project(camera, square)
        marker = None if found is None else np.round(found, 2).tolist()
    return {"camera": view.camera, "seq": view.seq, "time_s": view.time_s, "detections": detections,
            "cubes": {robot: np.round(squares, 2).tolist() for robot, _, squares in cubes_px},
            "axes": axes, "world_marker": marker}


def _decode_scaled(jpeg: bytes, width_px: int) -> tuple[np.ndarray, float] | None:
    """The frame decoded at (about) ``width_px`` wide, and its scale against the original;
    JPEG's own reduced decoding (1/2, 1/4, 1/8) does most of the work."""
    import cv2

    buf = np.frombuffer(jpeg, np.uint8)
    full = cv2.imdecode(buf, cv2.IMREAD_REDUCED_GRAYSCALE_8 | cv2.IMREAD_IGNORE_ORIENTATION)  # cheap: the size
    if full is None:
        return None
    width = full.shape[1] * 8
    reduced = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
               8: cv2.IMREAD_REDUCED_COLOR_8}
    factor = max([f for f in reduced if width / f >= width_px] or [1])
    img = cv2.imdecode(buf, reduced[factor])
    if img is None:
        return None
    if factor == 1:
        width = img.shape[1]
    if img.shape[1] > width_px:
        img = cv2.resize(img, (width_px, round(img.shape[0] * width_px / img.shape[1])),
                         interpolation=cv2.INTER_AREA)
    return img, img.shape[1] / width


def annotated_jpeg(view: CameraView, overlay: dict, width_px: int, quality: int) -> bytes | None:
    """``view``'s frame at ``width_px`` wide with ``overlay`` (:func:`view_overlay`) drawn on it,
    as a JPEG; None when the frame does not decode."""
    import cv2

    decoded = _decode_scaled(view.jpeg, width_px)
    if decoded is None:
        return None
    img, scale = decoded

    def pts(corners) -> np.ndarray:
        return np.round(np.asarray(corners, float) * scale).astype(np.int32)

    if overlay["world_marker"] is not None:
        cv2.polylines(img, [pts(overlay["world_marker"])], True, CYAN, 1, cv2.LINE_AA)
    if overlay["axes"] is not None:
        origin, *tips = pts(overlay["axes"])
        for tip, colour in zip(tips, AXIS_COLOURS, strict=True):
            cv2.arrowedLine(img, tuple(int(v) for v in origin), tuple(int(v) for v in tip), colour, 2, cv2.LINE_AA,
                            tipLength=0.15)
    for squares in overlay["cubes"].values():
        cv2.polylines(img, list(pts(squares)), True, ORANGE, 1, cv2.LINE_AA)
    for d in overlay["detections"]:
        corners = pts(d["corners_px"])
        cv2.polylines(img, [corners], True, GREEN, 2, cv2.LINE_AA)
    for d in overlay["detections"]:  # labels last, centred on their markers: id and face
        label = str(d["id"]) + (f" {d['face']}" if d["face"] else "")
        (w, h), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, LABEL_SCALE, 1)
        cx, cy = np.asarray(d["corners_px"], float).mean(axis=0) * scale
        at = (int(cx - w / 2), int(cy + h / 2))
        cv2.putText(img, label, at, cv2.FONT_HERSHEY_SIMPLEX, LABEL_SCALE, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(img, label, at, cv2.FONT_HERSHEY_SIMPLEX, LABEL_SCALE, (255, 255, 255), 1, cv2.LINE_AA)
    ok, out = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return out.tobytes() if ok else None


def _border_pixels(intrinsics: CameraIntrinsics, per_side: int = 8) -> np.ndarray:
    """Points around the image border, clockwise from the top-left corner ((4 per_side, 2) px)."""
    w, h = intrinsics.width - 1.0, intrinsics.height - 1.0
    s = np.linspace(0.0, 1.0, per_side, endpoint=False)
    return np.concatenate([np.c_[s * w, 0 * s], np.c_[w + 0 * s, s * h], np.c_[w - s * w, h + 0 * s],
                           np.c_[0 * s, h - s * h]])


def floor_footprint(T_world_cam: np.ndarray, intrinsics: CameraIntrinsics, range_m: float) -> list[list[float]]:
    """The camera's field of view on the floor (z = 0) as a polygon of (x, y) metres: where the
    rays through the image border meet the floor, each cut at ``range_m`` (horizontal distance
    from the camera); rays that never reach the floor are drawn ``range_m`` out."""
    import cv2

    rays = cv2.undistortPoints(_border_pixels(intrinsics).reshape(-1, 1, 2), intrinsics.K, intrinsics.dist)
    rays_cam = np.c_[rays.reshape(-1, 2), np.ones(len(rays))]
    dirs = rays_cam @ T_world_cam[:3, :3].T
    origin = T_world_cam[:3, 3]
    out = []
    for d in dirs:
        flat = np.hypot(d[0], d[1])
        if flat < 1e-9:
            continue
        reach = range_m
        if d[2] < -1e-9 and origin[2] > 0:
            reach = min(range_m, origin[2] / -d[2] * flat)
        out.append([float(origin[0] + d[0] / flat * reach), float(origin[1] + d[1] / flat * reach)])
    return out
