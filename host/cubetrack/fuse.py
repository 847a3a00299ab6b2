"""Fusion: per-camera cube estimates, which arrive unsynchronised and late, -> one pose per robot.

The paper's three methods (§II.D) combine the cube poses implied by every face that each camera
saw in its latest frame, over the cameras whose latest estimate is at most ``window_s`` older
than the newest one:

- ``mean``      eq. 2:  p = (1/n) Σ p_i
- ``weighted``  eqs. 3–4: p = Σ a_i p_i / Σ a_i, with a_i the marker's pixel area (shoelace)
- ``gaussian``  eqs. 5–6: σ_i² = 1/a_i², p = σ² Σ p_i/σ_i², σ² = (Σ 1/σ_i²)⁻¹ (i.e. weights a_i²)

Orientation uses the same weights in a chordal L2 rotation mean (sign-safe), not a
component-wise quaternion average. A fused pose is stamped with the newest contributing
capture time (what a live node publishing on every new estimate would do).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from cubetrack.geometry import mean_rotation, quat_xyzw_from_R
from cubetrack.params import param
from cubetrack.records import CameraEstimate, TrackedPose


@enum.unique
class FusionMethod(enum.Enum):
    MEAN = "mean"
    WEIGHTED = "weighted"
    GAUSSIAN = "gaussian"


@dataclass(frozen=True, slots=True)
class FusionParams:
    """The ``[fusion]`` section of the tracker config."""

    method: FusionMethod = param(FusionMethod.MEAN, "mean | weighted | gaussian (paper eqs. 2, 4, 6)")
    window_s: float = param(0.2, "seconds; a camera's latest estimate joins the fusion only if it is at most this much older than the newest")

    def __post_init__(self) -> None:
        if not self.window_s > 0:
            raise ValueError(f"window_s must be positive, got {self.window_s}")


def paper_weights(method: FusionMethod, areas_px2: np.ndarray) -> np.ndarray:
    """Fusion weights of the paper's methods from marker pixel areas (px²)."""
    areas = np.asarray(areas_px2, dtype=float)
    if method is FusionMethod.MEAN:
        return np.ones_like(areas)
    if method is FusionMethod.WEIGHTED:
        return areas
    return areas**2  # 1 / σ_i² with σ_i² = 1 / a_i²


def fuse_poses(positions_m: np.ndarray, Rs: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean of (N, 3) positions and chordal mean of (N, 3, 3) rotations."""
    w = np.asarray(weights, dtype=float)
    position = (w[:, None] * np.asarray(positions_m)).sum(axis=0) / w.sum()
    return position, mean_rotation(Rs, w / w.sum())


class LatestEstimateFusion:
    """Keeps each camera's latest estimate per robot and fuses them on every new estimate.

    State: ``latest[(robot, camera)]`` — visible and small. Feed estimates in arrival order.
    """

    def __init__(self, params: FusionParams = FusionParams()):
        self.params = params
        self.latest: dict[tuple[str, str], CameraEstimate] = {}

    def add(self, estimate: CameraEstimate, now_s: float) -> TrackedPose:
        """Take one camera estimate (``now_s`` = host time it became available) and fuse."""
        self.latest[(estimate.robot, estimate.camera)] = estimate
        newest = estimate.capture_time_s
        current = [
            e for (robot, _), e in self.latest.items()
            if robot == estimate.robot and newest - self.params.window_s <= e.capture_time_s <= newest
        ]
        faces = [(e, f) for e in current for f in e.faces]
        positions = np.array([f.T_world_cube[:3, 3] for _, f in faces])
        Rs = np.array([f.T_world_cube[:3, :3] for _, f in faces])
        weights = paper_weights(self.params.method, np.array([f.area_px2 for _, f in faces]))
        position, R = fuse_poses(positions, Rs, weights)
        return TrackedPose(
            robot=estimate.robot,
            time_s=newest,
            position_m=position,
            quaternion_xyzw=quat_xyzw_from_R(R),
            cameras=tuple(sorted({e.camera for e in current})),
            markers=tuple(f"{e.camera}:{f.face}" for e, f in faces),
            latency_s=now_s - newest,
        )
