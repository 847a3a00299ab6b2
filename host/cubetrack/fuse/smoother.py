"""Offline smoothing of the filter fusion's tracks: each pose from every sighting of the recording,
before and after it, not only the earlier ones.

A Rauch-Tung-Striebel smoother over the states of :class:`~cubetrack.fuse.fusion.FilterFusion`'s
filter (:class:`~cubetrack.fuse.corner_filter.PoseFilter`), run backwards over each track segment
on the filter's error state ``[δp, δθ, δv, δω]``: with the filtered state ``x_k`` (covariance
``P_k``), its prediction to the next sighting's time ``x_k+1|k`` (``P_k+1|k``, the filter's own
:meth:`~cubetrack.fuse.corner_filter.PoseFilter.predict`: the same transition ``F`` and process
noise, the turning level included) and the next smoothed state ``x_k+1|s``,

    G = P_k F^T P_k+1|k^-1,    x_k|s = x_k ⊞ G (x_k+1|s ⊟ x_k+1|k),
    P_k|s = P_k + G (P_k+1|s - P_k+1|k) G^T.

A rejected sighting is a step without an update (its state is the prediction). A segment ends
where the filter did not go on from the state before: a track start, a re-acquisition (the track
went on from a camera's own pose), a track lost. The fusion keeps what this needs only when asked
(:meth:`~cubetrack.fuse.fusion.FilterFusion.keep_trail`), so live tracking pays nothing for it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from cubetrack.core.geometry import quat_xyzw_from_R
from cubetrack.core.records import TrackedPose
from cubetrack.fuse.corner_filter import PoseFilter, transition
from cubetrack.fuse.fusion import FilterFusion, TrailStep

CONTINUING = frozenset({"accepted sighting", "rejected sighting"})  # outcomes that go on from the state before


def rts(filters: Sequence[PoseFilter]) -> list[PoseFilter]:
    """The smoothed states of one track segment: ``filters[k + 1]`` is ``filters[k]`` predicted to
    its time and then updated (or not: a rejected sighting)."""
    smoothed = [filters[-1]]
    for f in reversed(filters[:-1]):
        after = smoothed[-1]
        predicted = f.copy()
        predicted.predict(after.time_s)
        G = np.linalg.solve(predicted.P, transition(after.time_s - f.time_s) @ f.P).T  # P_pred symmetric
        smoothed.append(f.moved(G @ after.error_from(predicted), f.P + G @ (after.P - predicted.P) @ G.T))
    return smoothed[::-1]


def segments(trail: Sequence[TrailStep]) -> list[list[TrailStep]]:
    """The trail split where the filter did not go on from the state before (track start,
    re-acquisition, lost track); steps without a filter state are left out."""
    out: list[list[TrailStep]] = []
    previous: TrailStep | None = None
    for step in trail:
        if step.state.filter is not None:
            if previous is not None and previous.state.filter is not None and step.outcome in CONTINUING:
                out[-1].append(step)
            else:
                out.append([step])
        previous = step
    return out


def smoothed_poses(fusion: FilterFusion, robot: str, now_s: float) -> list[TrackedPose]:
    """The robot's poses (one per sighting that gave one, in capture order) from the smoothed
    states of every sighting since ``fusion.keep_trail()``; ``now_s``: the host time they are
    output (their ``latency_s`` counts to it). Each is flagged ``"smoothed": true`` in ``extra``."""
    trail = fusion.trail(robot, now_s)
    poses = []
    for segment in segments(trail):
        for step, f in zip(segment, rts([step.state.filter for step in segment])):
            if step.pose is not None:
                poses.append(dataclasses.replace(
                    step.pose, position_m=f.position_m.copy(), quaternion_xyzw=quat_xyzw_from_R(f.R_world_cube),
                    velocity_m_s=f.velocity_m_s.copy(), angular_velocity_rad_s=f.angular_velocity_rad_s.copy(),
                    covariance=f.pose_covariance, latency_s=max(0.0, now_s - f.time_s), arrival_latency_s=None,
                    extra={**step.pose.extra, "smoothed": True}))
    return poses
