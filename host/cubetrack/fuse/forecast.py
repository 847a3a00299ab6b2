"""What a process without the fusion plans frames with: the fusion's predictions as a small
picklable value (a camera worker process, :mod:`cubetrack.app.camera_workers`, is sent one after
every batch of fused results; ``cubetrack worker`` plans with :data:`NO_FORECAST`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from cubetrack.estimate.reprojection import moved_pose
from cubetrack.fuse.base import Fusion

FORECAST_SPAN_S = 0.1  # the motion in a forecast: from the fusion's predictions this far apart


@dataclass(frozen=True, slots=True)
class Forecast:
    """What a worker process plans frames with: per tracked robot its predicted pose at
    ``time_s`` with constant world-frame linear and angular velocity (the filter's motion
    model), and the robots whose fusion asks for per-camera estimates. Duck-types the two
    :class:`~cubetrack.fuse.base.Fusion` methods that planning uses
    (:class:`cubetrack.app.tracker.Forecaster`)."""

    motions: Mapping[str, tuple[float, np.ndarray, np.ndarray, np.ndarray]]  # time_s, T_world_cube, v, w
    estimate_robots: frozenset[str]
    #: camera -> the pose it was re-calibrated to while tracking (issue 27), which its frames are planned
    #: through (:meth:`cubetrack.app.tracker.Tracker.plan_cameras_at`); the calibrated pose for the others
    camera_poses: Mapping[str, np.ndarray] = field(default_factory=dict)

    def predicted_pose(self, robot: str, time_s: float) -> np.ndarray | None:
        motion = self.motions.get(robot)
        if motion is None:
            return None
        t0, T, v, w = motion
        return moved_pose(T, v, w, time_s - t0)

    def needs_estimate(self, robot: str) -> bool:
        return robot in self.estimate_robots

    def plain(self) -> tuple:
        """This forecast as plain values, which pickle several times faster (to the camera worker
        processes; :meth:`from_plain` turns them back): the arrays as their float64 bytes."""
        motions = tuple((robot, t0, *(np.asarray(a, np.float64).tobytes() for a in (T, v, w)))
                        for robot, (t0, T, v, w) in self.motions.items())
        cameras = tuple((camera, np.asarray(T, np.float64).tobytes()) for camera, T in self.camera_poses.items())
        return motions, tuple(self.estimate_robots), cameras

    @classmethod
    def from_plain(cls, values: tuple) -> Forecast:
        """The forecast :meth:`plain` gave ``values`` of (writable arrays)."""
        motions, estimate_robots, cameras = values
        return cls({robot: (t0, np.frombuffer(bytearray(T)).reshape(4, 4), np.frombuffer(bytearray(v)),
                            np.frombuffer(bytearray(w))) for robot, t0, T, v, w in motions},
                   frozenset(estimate_robots),
                   {camera: np.frombuffer(bytearray(T)).reshape(4, 4) for camera, T in cameras})


def forecast_of(fusion: Fusion, robots: Sequence[str], now_s: float,
                camera_poses: Mapping[str, np.ndarray] | None = None) -> Forecast:
    """The fusion's predictions at ``now_s`` and ``FORECAST_SPAN_S`` later, as a :class:`Forecast`
    (with ``camera_poses``: the cameras re-calibrated while tracking)."""
    motions = {}
    for robot in robots:
        T0 = fusion.predicted_pose(robot, now_s)
        if T0 is None:
            continue
        T1 = fusion.predicted_pose(robot, now_s + FORECAST_SPAN_S)
        if T1 is None:
            v = w = np.zeros(3)
        else:
            v = (T1[:3, 3] - T0[:3, 3]) / FORECAST_SPAN_S
            w = cv2.Rodrigues(T1[:3, :3] @ T0[:3, :3].T)[0].reshape(3) / FORECAST_SPAN_S
        motions[robot] = (now_s, T0, v, w)
    return Forecast(motions, frozenset(r for r in robots if fusion.needs_estimate(r)), dict(camera_poses or {}))


NO_FORECAST = Forecast({}, frozenset())  # no prediction (every frame searched whole), no estimates asked for
