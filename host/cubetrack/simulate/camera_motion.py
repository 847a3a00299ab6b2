"""Cameras that move during a session: a bumped tripod (a step of the pose at a given time) and
a slipping clamp (a slow drift at a given rate), for issue 27's camera watching.

A camera's pose is constant over each of its frames (taken at the frame's stamp); a bump is an
instant step (the shaking while a tripod settles is not modelled). A drift advances in steps of
:data:`DRIFT_STEP_S` (at 2 mm/min a step is 0.033 mm), so the renderer draws one background per
step and the pose written as truth is exactly the one each frame was rendered with.

Each bump's translation direction and rotation axis are drawn uniformly on the sphere from the
seed (its own random stream per bump), its sizes are the parameters'; the rotation turns the
camera about its own optical centre. A drift moves along one random direction and turns about one
random axis, from the start of the tracking recording. The calibration recording, which ends
before the start, sees every camera at its original pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cubetrack.core.geometry import R_from_rotvec, make_T

DRIFT_STEP_S = 1.0  # a drifting camera's pose advances this often, seconds


@dataclass(frozen=True, slots=True, eq=False)
class PoseStep:
    """One change of a camera's pose: from ``time_s`` (seconds after the recording's start) the
    camera stands ``translation_m`` (world, 3) further and turned by ``rotvec_rad`` (world-frame
    rotation vector about its optical centre)."""

    time_s: float
    translation_m: np.ndarray
    rotvec_rad: np.ndarray


@dataclass(frozen=True, slots=True, eq=False)
class CameraMotion:
    """How one camera's pose changes over the session: its bumps (sorted by time) and a drift
    (``drift_m_per_s`` along ``drift_direction``, ``drift_rad_per_s`` about ``drift_axis``)."""

    bumps: tuple[PoseStep, ...] = ()
    drift_m_per_s: float = 0.0
    drift_rad_per_s: float = 0.0
    drift_direction: np.ndarray | None = None
    drift_axis: np.ndarray | None = None

    @property
    def still(self) -> bool:
        """True when the camera never moves."""
        return not self.bumps and self.drift_m_per_s == 0.0 and self.drift_rad_per_s == 0.0

    def segment(self, t_s: float) -> tuple[int, int]:
        """Which constant piece of the pose ``t_s`` (seconds after the start) falls in: (bumps
        passed, drift steps passed). Equal segments mean equal poses."""
        bumps = sum(b.time_s <= t_s for b in self.bumps)
        drifting = self.drift_m_per_s > 0.0 or self.drift_rad_per_s > 0.0
        steps = max(0, math.floor(t_s / DRIFT_STEP_S)) if drifting else 0
        return bumps, steps

    def T_world_cam(self, T_world_cam0: np.ndarray, t_s: float) -> np.ndarray:
        """The camera's pose ``t_s`` seconds after the start, from its original pose ``T_world_cam0``."""
        bumps, steps = self.segment(t_s)
        R = T_world_cam0[:3, :3].copy()
        p = T_world_cam0[:3, 3].copy()
        for bump in self.bumps[:bumps]:
            R = R_from_rotvec(bump.rotvec_rad) @ R
            p = p + bump.translation_m
        if steps:
            elapsed = steps * DRIFT_STEP_S
            if self.drift_axis is not None:
                R = R_from_rotvec(self.drift_axis * self.drift_rad_per_s * elapsed) @ R
            if self.drift_direction is not None:
                p = p + self.drift_direction * self.drift_m_per_s * elapsed
        return make_T(R, p)


def unit_vector(rng: np.random.Generator) -> np.ndarray:
    """A direction drawn uniformly on the unit sphere."""
    v = rng.normal(0.0, 1.0, 3)
    return v / np.linalg.norm(v)


def plan_camera_motions(cameras: int, bump_camera: tuple[int, ...], bump_at_s: tuple[float, ...],
                        step_m: float, turn_deg: float, drift_camera: int, drift_mm_per_min: float,
                        drift_deg_per_min: float, rngs: list[np.random.Generator]) -> tuple[CameraMotion, ...]:
    """Each of ``cameras`` cameras' motion: bump ``k`` moves camera ``bump_camera[k]`` (1-based)
    at ``bump_at_s[k]`` by ``step_m`` in a random direction and turns it by ``turn_deg`` about a
    random axis (``rngs[k]`` draws both); camera ``drift_camera`` (0: none) drifts at the given
    rates, its direction and axis drawn by ``rngs[len(bump_camera)]``."""
    bumps: list[list[PoseStep]] = [[] for _ in range(cameras)]
    for k, (camera, at) in enumerate(zip(bump_camera, bump_at_s, strict=True)):
        direction, axis = unit_vector(rngs[k]), unit_vector(rngs[k])
        bumps[camera - 1].append(PoseStep(at, direction * step_m, axis * math.radians(turn_deg)))
    motions = []
    for i in range(cameras):
        steps = tuple(sorted(bumps[i], key=lambda b: b.time_s))
        if i + 1 == drift_camera:
            rng = rngs[len(bump_camera)]
            direction, axis = unit_vector(rng), unit_vector(rng)
            motions.append(CameraMotion(steps, drift_mm_per_min * 1e-3 / 60.0, math.radians(drift_deg_per_min) / 60.0,
                                        direction, axis))
        else:
            motions.append(CameraMotion(steps))
    return tuple(motions)
