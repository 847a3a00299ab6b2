"""Value types of the cameras and the world that every stage shares: intrinsics, a calibrated
camera pose, the world reference (the world marker, more floor markers, a ChArUco board), and one
clock round trip.

They are plain frozen values; reading and writing them is :mod:`cubetrack.io` (``camera_info``
YAML, the config and extrinsics TOML, ``clock.csv``).

Pixel convention: OpenCV's, (0, 0) is the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cubetrack.core.errors import CameraInfoError
from cubetrack.core.geometry import make_T, transform_points
from cubetrack.core.layout import DEFAULT_DICTIONARY, marker_corners_m


@dataclass(frozen=True, slots=True, eq=False)
class CameraIntrinsics:
    """Pinhole intrinsics of one camera: image size (px), ``K`` (3x3 camera matrix, px) and the
    plumb_bob distortion coefficients ``dist`` (k1, k2, p1, p2, k3); ``readout_s``: the sensor's
    rolling-shutter readout, top row to bottom row (s; 0: a global shutter): row ``v`` is exposed
    ``(v - (height - 1) / 2) readout_s / height`` after the frame's stamp."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    camera_name: str = ""
    readout_s: float = 0.0

    def __post_init__(self) -> None:
        if self.K.shape != (3, 3) or not np.all(np.isfinite(self.K)):
            raise CameraInfoError(f"camera matrix must be a finite 3x3 matrix, got {self.K!r}")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise CameraInfoError(f"focal lengths must be positive, got {self.K[0, 0]}, {self.K[1, 1]}")
        if self.width <= 0 or self.height <= 0:
            raise CameraInfoError(f"image size must be positive, got {self.width}x{self.height}")
        if not 0.0 <= self.readout_s < 1.0:
            raise CameraInfoError(f"rolling-shutter readout must be in [0, 1) s, got {self.readout_s}")


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


@dataclass(frozen=True, slots=True, eq=False)
class WorldMarker:
    """A marker of the world reference at a known pose: its id, black-square side (metres),
    dictionary and ``T_world_marker`` (marker frame: centre, x right, y up, z out of the face)."""

    marker_id: int
    size_m: float
    T_world_marker: np.ndarray
    dictionary: str = DEFAULT_DICTIONARY

    def corners_world_m(self) -> np.ndarray:
        """(4, 3) corners in the world frame, TL TR BR BL (the detector's order)."""
        return transform_points(self.T_world_marker, marker_corners_m(self.size_m))


@dataclass(frozen=True, slots=True, eq=False)
class WorldBoard:
    """A ChArUco board of the world reference (OpenCV's ``CharucoBoard``): ``squares_x`` columns
    x ``squares_y`` rows of ``square_size_m`` squares, markers of ``marker_size_m`` from
    ``dictionary`` with ids ``first_marker_id`` on (``legacy_pattern``: boards of OpenCV < 4.6).

    Board frame: origin at the board's centre, x along its rows (left to right as OpenCV draws
    it), y towards its first row, z out of the printed face. ``T_world_board`` places it in the
    world (identity: the board is the world frame)."""

    squares_x: int
    squares_y: int
    square_size_m: float
    marker_size_m: float
    dictionary: str = DEFAULT_DICTIONARY
    first_marker_id: int = 0
    legacy_pattern: bool = False
    T_world_board: np.ndarray = field(default_factory=lambda: np.eye(4))

    @property
    def marker_count(self) -> int:
        return self.squares_x * self.squares_y // 2

    @property
    def marker_ids(self) -> range:
        return range(self.first_marker_id, self.first_marker_id + self.marker_count)

    @property
    def T_board_opencv(self) -> np.ndarray:
        """OpenCV's board frame (origin at the first row's outer corner, y down the rows, z into
        the board) in this board frame."""
        w, h = self.squares_x * self.square_size_m, self.squares_y * self.square_size_m
        return make_T(np.diag([1.0, -1.0, -1.0]), [-w / 2.0, h / 2.0, 0.0])


@dataclass(frozen=True, slots=True)
class WorldConfig:
    """The world reference. The world marker: the world frame's origin (centre), z up;
    ``marker_size_m`` = black square side. Optionally more ``markers`` at known world poses and a
    ChArUco ``board``, for larger rooms and better calibration; ``origin_marker`` False: the world
    marker is not part of the reference (then the markers or the board define the world frame)."""

    dictionary: str = DEFAULT_DICTIONARY
    marker_id: int = 0
    marker_size_m: float = 0.25
    markers: tuple[WorldMarker, ...] = ()
    board: WorldBoard | None = None
    origin_marker: bool = True

    @property
    def single_marker(self) -> bool:
        """Only the world marker: the reference of the paper (and of every version before)."""
        return self.origin_marker and not self.markers and self.board is None

    def reference_markers(self) -> tuple[WorldMarker, ...]:
        """The single markers of the reference: the world marker (when used) at the origin, then ``markers``."""
        origin = ((WorldMarker(self.marker_id, self.marker_size_m, np.eye(4), self.dictionary),)
                  if self.origin_marker else ())
        return origin + self.markers

    @property
    def dictionaries(self) -> tuple[str, ...]:
        """Every dictionary of the reference, the world marker's first."""
        names = [m.dictionary for m in self.reference_markers()] + ([self.board.dictionary] if self.board else [])
        return tuple(dict.fromkeys([self.dictionary, *names]))


@dataclass(frozen=True, slots=True)
class ClockSample:
    """One ``/time`` round trip of a camera: host send time, node clock, host receive time (seconds;
    host times Unix time, the node's clock since boot)."""

    host_send_s: float
    device_time_s: float
    host_recv_s: float
