"""The items of an output process's pipe (:class:`cubetrack.sink.process.OutputProcess`): each
record the outputs are handed (a pose, a camera's health, a camera view) as a compact tuple of
plain values, its arrays as bytes; pickling the frozen dataclasses and their small numpy arrays
as objects cost ten times more. Both ends run the same code, so nothing here is versioned.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from cubetrack.core.records import CameraHealth, CameraView, Detection, TrackedPose


def _array(values: np.ndarray | None) -> bytes | None:
    return None if values is None else np.ascontiguousarray(values, dtype=float).tobytes()


def _unarray(data: bytes | None, *shape: int) -> np.ndarray | None:
    return None if data is None else np.frombuffer(data).reshape(shape)


def _array_of(data: bytes, *shape: int) -> np.ndarray:
    return np.frombuffer(data).reshape(shape)


def pack_output(kind: str, value: object) -> tuple:
    """``(kind, fields)`` with the records' arrays as bytes: what crosses the pipe."""
    if isinstance(value, TrackedPose):
        p = value
        return kind, (p.robot, p.time_s, _array(p.position_m), _array(p.quaternion_xyzw), p.cameras, p.markers,
                      p.latency_s, _array(p.velocity_m_s), _array(p.angular_velocity_rad_s),
                      _array(p.covariance), p.arrival_latency_s, p.predicted, p.smoothed, p.smooth_lag_s)
    if isinstance(value, CameraView):
        v = value
        return kind, (v.camera, v.seq, v.time_s, v.jpeg,
                      tuple((d.marker_id, _array(d.corners_px), d.area_px2, d.dictionary) for d in v.detections),
                      {robot: np.asarray(c, float) for robot, c in v.predicted_corners_px.items()})
    if isinstance(value, CameraHealth):
        return kind, tuple(getattr(value, name) for name in CameraHealth.__slots__)
    return kind, value


def unpack_output(kind: str, fields: Any) -> tuple[str, object]:
    """The call :func:`pack_output` packed."""
    if kind == "pose":
        (robot, time_s, position, quaternion, cameras, markers, latency_s, velocity, angular, covariance,
         arrival_latency_s, predicted, smoothed, smooth_lag_s) = fields
        return kind, TrackedPose(robot, time_s, _array_of(position, 3), _array_of(quaternion, 4), cameras, markers,
                                 latency_s, _unarray(velocity, 3), _unarray(angular, 3),
                                 _unarray(covariance, 6, 6), arrival_latency_s, predicted, smoothed, smooth_lag_s)
    if kind == "camera_view":
        camera, seq, time_s, jpeg, detections, predicted = fields
        return kind, CameraView(camera, seq, time_s, jpeg, tuple(
            Detection(marker_id, _array_of(corners, 4, 2), area, dictionary)
            for marker_id, corners, area, dictionary in detections), predicted)
    if kind == "camera_health":
        return kind, CameraHealth(*fields)
    return kind, fields
