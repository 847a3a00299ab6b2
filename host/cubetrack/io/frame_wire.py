"""The per-frame work's result between processes of one tracker (frame worker processes,
:mod:`cubetrack.core.frame_pool`; camera worker processes, :mod:`cubetrack.app.camera_workers`).

A :class:`~cubetrack.core.records.FrameResult` without its job, in plain values that pickle fast
through a pipe: the outcome's value, per sighting the robot, the marker ids, the corners' float64
bytes (an array pickles several times slower), the areas, the dictionaries, the estimate and the
camera pose when it is the frame's own (the intrinsics and calibrated camera poses, which both
sides hold, stay out), and the markers found then dropped (reason -> count). The job, where it
crosses too, goes as :meth:`~cubetrack.core.records.FrameJob.plain` values. Both ends run the
same code, so nothing here is versioned.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.records import CubeSighting, Detection, FrameJob, FrameOutcome, FrameResult


def pack_result(result: FrameResult, T_world_cam: Mapping[str, np.ndarray]) -> tuple:
    """``result`` as plain values; a sighting's camera pose left out when it is ``T_world_cam``'s
    (the calibrated pose both ends hold)."""
    sightings = []
    for s in result.sightings:
        d = s.detections
        own_pose = None if s.T_world_cam is T_world_cam.get(s.camera) else s.T_world_cam
        corners = np.array([x.corners_px for x in d], np.float64).tobytes()  # (N, 4, 2)
        sightings.append((s.robot, tuple(x.marker_id for x in d), corners,
                          tuple(x.area_px2 for x in d), tuple(x.dictionary for x in d), s.estimate, own_pose))
    return result.outcome.value, tuple(sightings), result.error, dict(result.dropped)


def unpack_result(job: FrameJob, packed: tuple, intrinsics: Mapping[str, CameraIntrinsics],
                  T_world_cam: Mapping[str, np.ndarray]) -> FrameResult:
    """The :class:`FrameResult` of ``job`` that :func:`pack_result` packed, with the intrinsics
    and calibrated camera poses of this end."""
    outcome, packed_sightings, error, dropped = packed
    frame = job.frame
    sightings = tuple(
        CubeSighting(frame.camera, robot, frame.seq, job.capture_time_s, frame.host_time_s,
                     tuple(map(Detection, ids, np.frombuffer(bytearray(corners)).reshape(-1, 4, 2), areas,
                               dictionaries)), estimate,
                     T_world_cam[frame.camera] if own_pose is None else own_pose, intrinsics[frame.camera])
        for robot, ids, corners, areas, dictionaries, estimate, own_pose in packed_sightings)
    return FrameResult(job, FrameOutcome(outcome), sightings, error, dropped)
