"""A calibration checked against the frames it came from: how well a camera's calibrated pose
explains where its own frames show the world marker (the dashboard's calibration panel,
:mod:`cubetrack.app.dashboard`)."""

from __future__ import annotations

import math
from collections.abc import Iterable

import cv2
import numpy as np

from cubetrack.calib.extrinsics import world_detector
from cubetrack.core.cameras import CameraIntrinsics, WorldConfig
from cubetrack.core.errors import ImageError
from cubetrack.core.geometry import invert_T, transform_points
from cubetrack.core.layout import marker_corners_m
from cubetrack.core.records import Frame
from cubetrack.detect.detector import DetectorParams, decode_gray
from cubetrack.estimate.match import detections_of


def world_marker_reprojection(frames: Iterable[Frame], T_world_cam: np.ndarray, intrinsics: CameraIntrinsics,
                              world: WorldConfig, detector_params: DetectorParams | None = None,
                              max_frames: int = 30) -> tuple[float, float, int]:
    """How well a calibrated camera pose explains the camera's own frames: (RMS distance in
    pixels between the world marker's detected corners and their projection through
    ``T_world_cam``, the marker's mean apparent side in pixels, frames used). The first
    ``max_frames`` frames that show the marker once are used; (NaN, NaN, 0) when none does."""
    corners_world = marker_corners_m(world.marker_size_m)  # the world frame is the marker's
    T_cam_world = invert_T(T_world_cam)
    projected, _ = cv2.projectPoints(transform_points(T_cam_world, corners_world), np.zeros(3), np.zeros(3),
                                     intrinsics.K, intrinsics.dist)
    projected = projected.reshape(4, 2)
    detector = world_detector(world, detector_params)
    errors: list[np.ndarray] = []
    sides: list[float] = []
    for frame in frames:
        if len(sides) >= max_frames:
            break
        try:
            gray = decode_gray(frame.jpeg, f"{frame.camera} frame {frame.seq}")
        except ImageError:
            continue
        found = detections_of(detector.detect(gray), world.dictionary, (world.marker_id,))
        if len(found) != 1:
            continue
        errors.append(np.sum((found[0].corners_px - projected) ** 2, axis=1))
        sides.append(math.sqrt(found[0].area_px2))
    if not sides:
        return math.nan, math.nan, 0
    return float(np.sqrt(np.mean(errors))), float(np.mean(sides)), len(sides)
