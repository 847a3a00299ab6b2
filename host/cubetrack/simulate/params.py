"""The parameters of a simulated session (one frozen dataclass; no heavy imports here, so the
command line can build its options from the fields without loading OpenCV).

Every field's ``doc`` gives its unit and meaning; ``cubetrack simulate --help`` shows them.
Values are checked on construction and refused with :class:`cubetrack.core.errors.SimulationError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from cubetrack.core.errors import SimulationError
from cubetrack.core.params import param

PATHS = ("figure8", "rectangle")


@dataclass(frozen=True, slots=True)
class SimulationParams:
    """A simulated arena, robot, set of camera nodes and recording (defaults: the paper's setup)."""

    # --- arena and cameras
    cameras: int = param(3, "number of camera nodes, evenly spaced around the arena centre")
    height_m: float = param(1.0, "camera height above the floor, metres (paper: 0.8 / 1.0 / 1.2)")
    tilt_deg: float = param(30.0, "downward tilt of each camera's optical axis, degrees (paper: 20 / 30 / 40)")
    distance_m: float = param(2.2, "horizontal distance of each camera from the arena centre, metres")
    position_jitter_m: float = param(0.03, "random error of each camera's position (std per axis), metres")
    angle_jitter_deg: float = param(1.0, "random error of each camera's orientation (std per axis), degrees")
    # --- camera model
    image_width_px: int = param(640, "image width, pixels")
    image_height_px: int = param(480, "image height, pixels")
    focal_px: float = param(520.0, "focal length fx = fy, pixels (principal point at the image centre)")
    distortion: tuple[float, ...] = param(
        (0.0, 0.0, 0.0, 0.0, 0.0), "plumb_bob lens distortion k1 k2 p1 p2 k3 (rendered exactly)")
    supersample: int = param(4, "anti-aliasing: samples per pixel along each axis (box filter)")
    # --- markers and robot
    dictionary: str = param("DICT_4X4_50", "ArUco dictionary of the world marker and the cube")
    world_marker_id: int = param(0, "id of the world marker on the floor (origin of the world frame)")
    world_marker_size_m: float = param(0.25, "side of the world marker's black square, metres")
    world_margin_m: float = param(0.03, "white paper margin around the world marker, metres")
    cube_marker_id: int = param(1, "id of the cube's markers (first id with distinct_ids)")
    distinct_ids: bool = param(False, "give each cube face its own id instead of the paper's one id on five faces")
    cube_size_m: float = param(0.11, "side of the cube, metres")
    marker_size_m: float = param(0.08, "side of each cube marker's black square, metres")
    robot_size_m: tuple[float, ...] = param((0.30, 0.25, 0.20), "robot body length, width, height, metres")
    mast_height_m: float = param(0.05, "height of the mast between robot body and cube, metres")
    robots: int = param(1, "number of robots on the same path, each with its own cube (ids: cube_marker_id + k, "
                           "or + 5 k with distinct_ids); more than one are named robot1, robot2, ...")
    robot_spacing: float = param(0.3, "with several robots: their distance along the path, as a fraction of its length")
    # --- motion
    path: str = param("figure8", "robot path: figure8 (crosses the world marker) or rectangle (rounded)")
    path_size_m: tuple[float, ...] = param((0.8, 0.5), "half-extent of the path along world x and y, metres")
    speed_m_s: float = param(0.25, "robot speed along the path, metres per second")
    duration_s: float = param(30.0, "length of the tracking recording, seconds")
    # --- capture and timing
    fps: float = param(7.5, "frame rate of each camera node (on its own clock), frames per second")
    capture_jitter_s: float = param(0.002, "random jitter of each capture time (std), seconds")
    exposure_s: float = param(0.01, "exposure time (motion blur; stamps are mid-exposure), seconds")
    drift_ppm: float = param(30.0, "device clock rate error (std over cameras), parts per million")
    uptime_max_s: float = param(3600.0, "device clocks read 60 s .. this many seconds at the start (boot offset)")
    latency_ms: float = param(45.0, "minimum time from capture to complete arrival of a frame, milliseconds")
    latency_jitter_ms: float = param(10.0, "mean of the exponential jitter added to each frame's latency, milliseconds")
    spike_rate: float = param(0.03, "probability that a transfer is slowed by a spike (0..1)")
    spike_ms: float = param(200.0, "mean extra transfer time of a spike, milliseconds")
    drop_rate: float = param(0.02, "probability that a captured frame is lost (0..1); slow transfers skip more")
    clock_period_s: float = param(1.0, "interval between /time round trips, seconds")
    rtt_ms: float = param(8.0, "mean /time round-trip time (host->node 30 %, node->host 70 %), milliseconds")
    slow_rtt_rate: float = param(0.05, "probability that a /time round trip is slow (0..1)")
    slow_rtt_ms: float = param(100.0, "mean extra one-way delay of a slow round trip, milliseconds")
    start_unix_s: float = param(1_750_000_000.0, "host clock (Unix time) at the start of the recording, seconds")
    # --- image formation
    jpeg_quality: int = param(80, "JPEG quality (1..100)")
    noise_std: float = param(2.0, "sensor noise (std), grey levels of 255")
    blur_px: float = param(0.6, "optical blur (Gaussian std), pixels")
    gain_jitter: float = param(0.03, "frame-to-frame exposure gain variation (std, slowly varying), fraction")
    light_gradient: float = param(0.25, "illumination change across the image (random direction), fraction")
    vignetting: float = param(0.15, "brightness loss at the image corners, fraction")
    # --- session
    seed: int = param(0, "random seed: the same seed gives byte-identical frames and files")
    calibration_frames: int = param(200, "frames per camera of the empty-arena calibration recording (0: none)")

    def __post_init__(self) -> None:
        def bad(name: str, what: str) -> SimulationError:
            return SimulationError(f"simulation parameter {name} = {getattr(self, name)!r}: {what}")

        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise bad(f.name, "must be a finite number")
            if isinstance(v, tuple) and not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
                raise bad(f.name, "must be a list of finite numbers")
        positive = ("height_m", "distance_m", "focal_px", "world_marker_size_m", "cube_size_m",
                    "marker_size_m", "speed_m_s", "duration_s", "fps", "clock_period_s")
        for name in positive:
            if not getattr(self, name) > 0:
                raise bad(name, "must be positive")
        non_negative = ("position_jitter_m", "angle_jitter_deg", "world_margin_m", "mast_height_m",
                        "capture_jitter_s", "exposure_s", "drift_ppm", "latency_ms", "latency_jitter_ms",
                        "spike_ms", "rtt_ms", "slow_rtt_ms", "noise_std", "blur_px", "gain_jitter",
                        "light_gradient", "vignetting", "start_unix_s")
        for name in non_negative:
            if getattr(self, name) < 0:
                raise bad(name, "must not be negative")
        for name in ("spike_rate", "slow_rtt_rate", "vignetting"):
            if not 0 <= getattr(self, name) <= 1:
                raise bad(name, "must be between 0 and 1")
        if not 0 <= self.drop_rate < 1:
            raise bad("drop_rate", "must be at least 0 and below 1")
        if not 1 <= self.robots <= 8:
            raise bad("robots", "must be between 1 and 8")
        if not 0 < self.robot_spacing < 1:
            raise bad("robot_spacing", "must be between 0 and 1 (exclusive)")
        if not 1 <= self.cameras <= 16:
            raise bad("cameras", "must be between 1 and 16")
        if not 0 < self.tilt_deg < 90:
            raise bad("tilt_deg", "must be between 0 and 90 degrees (exclusive)")
        if not (16 <= self.image_width_px <= 4096 and 16 <= self.image_height_px <= 4096):
            raise bad("image_width_px", "image size must be 16..4096 pixels per side")
        if len(self.distortion) not in (4, 5, 8):
            raise bad("distortion", "needs 4, 5 or 8 plumb_bob/rational coefficients (k1 k2 p1 p2 [k3 ...])")
        if not 1 <= self.supersample <= 8:
            raise bad("supersample", "must be between 1 and 8")
        if not self.marker_size_m <= self.cube_size_m:
            raise bad("marker_size_m", f"must fit on the cube side ({self.cube_size_m} m)")
        if len(self.robot_size_m) != 3 or min(self.robot_size_m) <= 0:
            raise bad("robot_size_m", "needs three positive numbers: length width height")
        if len(self.path_size_m) != 2 or min(self.path_size_m) <= 0:
            raise bad("path_size_m", "needs two positive numbers: half-extent along x and y")
        if self.path not in PATHS:
            raise bad("path", f"must be one of {', '.join(PATHS)}")
        if not 1 <= self.jpeg_quality <= 100:
            raise bad("jpeg_quality", "must be between 1 and 100")
        if self.world_marker_id < 0 or self.cube_marker_id < 0:
            raise bad("cube_marker_id", "marker ids must not be negative")
        cube_ids = range(self.cube_marker_id, self.cube_marker_id + (5 if self.distinct_ids else 1) * self.robots)
        if self.world_marker_id in cube_ids:
            raise bad("world_marker_id", f"must differ from the cube's ids ({cube_ids.start}..{cube_ids.stop - 1})")
        if self.exposure_s >= 1.0 / self.fps:
            raise bad("exposure_s", f"must be shorter than the frame period {1.0 / self.fps:.4f} s")
        if self.uptime_max_s < 60.0:
            raise bad("uptime_max_s", "must be at least 60 seconds")
        if not 0 <= self.calibration_frames <= 100_000:
            raise bad("calibration_frames", "must be between 0 and 100000")
        if not 0 <= self.seed < 2**63:
            raise bad("seed", "must be a non-negative integer")
        reach = max(self.path_size_m) + 0.5
        if self.distance_m <= reach:
            raise bad("distance_m", f"must exceed the path's half-extent + 0.5 m ({reach:.2f} m): "
                      "the robot would drive into a camera")
        top = self.cube_top_m
        if self.height_m <= top + 0.1:
            raise bad("height_m", f"cameras must be at least 0.1 m above the cube's top ({top:.3f} m)")

    @property
    def cube_centre_height_m(self) -> float:
        """Height of the cube frame's origin above the floor, metres."""
        return self.robot_size_m[2] + self.mast_height_m + self.cube_size_m / 2.0

    @property
    def cube_top_m(self) -> float:
        """Height of the cube's top face above the floor, metres."""
        return self.robot_size_m[2] + self.mast_height_m + self.cube_size_m
