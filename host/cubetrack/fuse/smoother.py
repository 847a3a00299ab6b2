"""Smoothing of the filter fusion's tracks: each pose from the sightings before and after it, not
only the earlier ones (a whole recording offline, or a fixed lag live).

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
went on from a camera's own pose), a track lost. The fusion keeps what a whole recording needs
only when asked (:meth:`~cubetrack.fuse.fusion.FilterFusion.keep_trail`), so live tracking pays
nothing for it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cubetrack.core.geometry import quat_xyzw_from_R
from cubetrack.core.records import TrackedPose
from cubetrack.fuse.corner_filter import PoseFilter, transition

CONTINUING = frozenset({"accepted sighting", "rejected sighting"})  # outcomes that go on from the state before


@dataclass(frozen=True, slots=True)
class TrailStep:
    """One sighting of a robot as capture-order processing finally applied it: its outcome (a
    fusion ``stats`` key), the filter after it (None: no track), the pose it gave (None: none),
    when the sighting arrived and when it was captured (host clock, seconds)."""

    outcome: str
    filter: PoseFilter | None
    pose: TrackedPose | None
    arrival_time_s: float
    capture_time_s: float


def gain(f: PoseFilter, after: PoseFilter) -> tuple[np.ndarray, PoseFilter]:
    """The smoother's gain ``G`` from state ``f`` to the next one, ``after``, and ``f`` predicted
    to ``after``'s time (``x_k+1|k``, ``P_k+1|k``)."""
    predicted = f.copy()
    predicted.predict(after.time_s)
    return np.linalg.solve(predicted.P, transition(after.time_s - f.time_s) @ f.P).T, predicted  # P_pred symmetric


class Gains:
    """The gain and prediction of each pair of consecutive filter states, kept from one backward
    pass to the next: a fixed lag runs one pass per pose over nearly the same states. They depend
    on the pair alone (states are snapshots nothing changes); each pass keeps only the pairs it used."""

    def __init__(self) -> None:
        self._kept: dict[tuple[int, int], tuple] = {}  # (id, id) -> (the pair, G, prediction): held, so ids stay unique
        self._used: dict[tuple[int, int], tuple] = {}

    def of(self, f: PoseFilter, after: PoseFilter) -> tuple[np.ndarray, PoseFilter]:
        key = (id(f), id(after))
        entry = self._kept.get(key)
        if entry is None or entry[0] is not f or entry[1] is not after:
            entry = (f, after, *gain(f, after))
        self._used[key] = entry
        return entry[2], entry[3]

    def pass_done(self) -> None:
        self._kept, self._used = self._used, {}


def rts(filters: Sequence[PoseFilter], gains: Gains | None = None) -> list[PoseFilter]:
    """The smoothed states of one track segment: ``filters[k + 1]`` is ``filters[k]`` predicted to
    its time and then updated (or not: a rejected sighting). ``gains``: those of an earlier pass."""
    smoothed = [filters[-1]]
    for f, following in zip(reversed(filters[:-1]), reversed(filters[1:]), strict=True):
        after = smoothed[-1]
        G, predicted = gain(f, following) if gains is None else gains.of(f, following)
        smoothed.append(f.moved(G @ after.error_from(predicted), f.P + G @ (after.P - predicted.P) @ G.T))
    return smoothed[::-1]


def segments(trail: Sequence[TrailStep]) -> list[list[int]]:
    """The indices of the trail's steps, split where the filter did not go on from the state
    before (track start, re-acquisition, lost track); steps without a filter are left out."""
    out: list[list[int]] = []
    for i, step in enumerate(trail):
        if step.filter is not None:
            if i > 0 and trail[i - 1].filter is not None and step.outcome in CONTINUING:
                out[-1].append(i)
            else:
                out.append([i])
    return out


def smoothed_poses(trail: Sequence[TrailStep], now_s: float, count: int | None = None,
                   lag_s: float | None = None, gains: Gains | None = None) -> list[TrackedPose]:
    """The poses of the trail's first ``count`` steps (None: all) that gave one, in order, from
    their states smoothed over the whole trail; ``now_s``: the host time they are output (their
    latencies count to it). Each is flagged ``"smoothed": true`` in ``extra``; with a fixed lag
    ``lag_s``, also ``"smooth_lag_s"``: the capture time the trail covers after the pose, at most
    ``lag_s`` (less for a pose that left before a sighting that much newer came). ``gains``: kept
    from the last call over (mostly) the same trail, and for the next."""
    count = len(trail) if count is None else count
    newest_s = trail[-1].capture_time_s if trail else 0.0
    poses = []
    for segment in segments(trail):
        if segment[0] >= count:
            break
        filters = [f for i in segment if (f := trail[i].filter) is not None]  # (all are: segments())
        for i, f in zip(segment, rts(filters, gains), strict=True):
            pose = trail[i].pose
            if i < count and pose is not None:
                poses.append(dataclasses.replace(
                    pose, position_m=f.position_m.copy(), quaternion_xyzw=quat_xyzw_from_R(f.R_world_cube),
                    velocity_m_s=f.velocity_m_s.copy(), angular_velocity_rad_s=f.angular_velocity_rad_s.copy(),
                    covariance=f.pose_covariance, latency_s=max(0.0, now_s - f.time_s),
                    arrival_latency_s=max(0.0, now_s - trail[i].arrival_time_s), smoothed=True,
                    smooth_lag_s=None if lag_s is None else round(min(lag_s, newest_s - pose.time_s), 4)))
    if gains is not None:
        gains.pass_done()
    return poses
