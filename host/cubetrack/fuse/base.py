"""The interface every fusion implements (the paper's per-camera fusions and the corner filter).

A fusion is one ordered consumer: the tracker hands it each camera frame's
:class:`~cubetrack.core.records.CubeSighting` of a robot as soon as that frame is processed, and
it returns the poses that sighting produced. ``now_s`` is the host time at which the sighting
became available (its frame's arrival time in a replay; the wall clock live).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from cubetrack.core.records import CubeSighting, TrackedPose


class Fusion(Protocol):
    def needs_estimate(self, robot: str) -> bool:
        """Whether sightings of ``robot`` must carry a per-camera estimate (some fusions fuse
        those; others need only the matched corners)."""

    def add(self, sighting: CubeSighting, now_s: float) -> list[TrackedPose]:
        """Take one sighting; returns the poses it produced (possibly none)."""

    def predicted_pose(self, robot: str, time_s: float) -> np.ndarray | None:
        """``T_world_cube`` of ``robot`` expected at ``time_s`` (host clock), or None when this
        fusion cannot predict (no track, or a fusion without a motion model). Used only by the
        workflow layer, to tell detection where to look."""

    def flush(self, now_s: float) -> list[TrackedPose]:
        """Poses still held back (the end of a session)."""

    def release(self, now_s: float) -> list[TrackedPose]:
        """Poses held back whose time is up at host time ``now_s`` though what they wait for has
        not come (called after each frame, and live also while none comes)."""
