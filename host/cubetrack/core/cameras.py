"""Value types of the cameras and the world that every stage shares: intrinsics, a calibrated
camera pose, the world marker, and one clock round trip.

They are plain frozen values; reading and writing them is :mod:`cubetrack.io` (``camera_info``
YAML, the config and extrinsics TOML, ``clock.csv``).

Pixel convention: OpenCV's, (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cubetrack.core.errors import CameraInfoError
from cubetrack.core.layout import DEFAULT_DICTIONARY


@dataclass(frozen=True, slots=True, eq=False)
class CameraIntrinsics:
    """Pinhole intrinsics of one camera: image size (px), ``K`` (3x3 camera matrix, px) and the
    plumb_bob distortion coefficients ``dist`` (k1, k2, p1, p2, k3)."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    camera_name: str = ""

    def __post_init__(self) -> None:
        if self.K.shape != (3, 3) or not np.all(np.isfinite(self.K)):
            raise CameraInfoError(f"camera matrix must be a finite 3x3 matrix, got {self.K!r}")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise CameraInfoError(f"focal lengths must be positive, got {self.K[0, 0]}, {self.K[1, 1]}")
        if self.width <= 0 or self.height <= 0:
            raise CameraInfoError(f"image size must be positive, got {self.width}x{self.height}")


@dataclass(frozen=True, slots=True, eq=False)
class CameraExtrinsics:
    """A calibrated camera pose: ``T_world_cam`` of the optical frame (x right, y down, z forward).

    ``samples`` = world-marker sightings used; ``spread_position_m`` / ``spread_rotation_deg``
    = RMS deviation of the per-sample poses from the result; ``method`` = how it was computed.
    """

    T_world_cam: np.ndarray
    samples: int = 0
    spread_position_m: float = 0.0
    spread_rotation_deg: float = 0.0
    method: str = ""


@dataclass(frozen=True, slots=True)
class WorldConfig:
    """The world marker: the world frame's origin (centre), z up. ``marker_size_m`` = black square side."""

    dictionary: str = DEFAULT_DICTIONARY
    marker_id: int = 0
    marker_size_m: float = 0.25


@dataclass(frozen=True, slots=True)
class ClockSample:
    """One ``/time`` round trip of a camera: host send time, node clock, host receive time (seconds;
    host times Unix time, the node's clock since boot)."""

    host_send_s: float
    device_time_s: float
    host_recv_s: float
