"""The parameters of a simulated session (one frozen dataclass; no heavy imports here, so the
command line can build its options from the fields without loading OpenCV).

Every field's ``doc`` gives its unit and meaning; ``cubetrack simulate --help`` shows them.
Values are checked on construction and refused with :class:`cubetrack.core.errors.ParamsError`, as
every params class's are (:mod:`cubetrack.core.params`).

Two presets: the defaults are the *clean* preset (pinhole lens with exactly known intrinsics, a
global shutter, a perfectly built cube on a robot that never tilts, nobody in the room);
:data:`REALISTIC` (``SimulationParams.realistic()``, ``cubetrack simulate --realistic``) switches
on every effect of real cameras and robots. Each effect is its own field (0 or off = absent), so
any preset can switch single effects on or off.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from cubetrack.core.params import check, check_between, check_finite, check_non_negative, check_positive, param

PATHS = ("figure8", "rectangle", "sharp", "handheld")


LIMITS = {"focal_spread": 0.1, "info_focal_error": 0.05, "info_k1_error": 0.1, "marker_undersize": 0.2,
          "principal_offset_px": 50.0, "info_principal_error_px": 50.0, "marker_shift_mm": 5.0, "marker_turn_deg": 10.0,
          "face_tilt_deg": 10.0, "wobble_deg": 10.0, "bounce_mm": 20.0, "floor_bumps_mm": 20.0,
          "exposure_step": 1.0}  # the most each effect of the realistic preset may be set to


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
    principal_offset_px: float = param(0.0, "true principal point of each camera off the image centre "
                                            "(std per axis), pixels")
    focal_spread: float = param(0.0, "true focal length of each camera off focal_px (relative std)")
    readout_ms: float = param(0.0, "rolling shutter: rows are exposed one after the other, readout_ms / image "
                                   "height apart, milliseconds (0: global shutter)")
    # --- what the tracker is told (camera_info/<cam>.yaml), as a real calibration leaves it
    info_focal_error: float = param(0.0, "camera_info focal length error (relative std; fx and fy share most of it)")
    info_principal_error_px: float = param(0.0, "camera_info principal point error (std per axis), pixels")
    info_k1_error: float = param(0.0, "camera_info k1 error (std); the k2 error is correlated with it as in a "
                                      "calibration (about -3.4 times, so the two cancel at mid-field)")
    # --- markers and robot
    dictionary: str = param("DICT_4X4_50", "ArUco dictionary of the world marker and the cube")
    world_marker_id: int = param(0, "id of the world marker on the floor (origin of the world frame)")
    world_marker_size_m: float = param(0.25, "side of the world marker's black square, metres")
    world_margin_m: float = param(0.03, "white paper margin around the world marker, metres")
    cube_marker_id: int = param(1, "id of the cube's markers (first id with distinct_ids)")
    distinct_ids: bool = param(False, "give each cube face its own id instead of the paper's one id on five faces")
    inverted_markers: bool = param(False, "the cube's markers printed inverted: white cells and border on a black "
                                          "face (the world marker stays dark on white); the config written asks the "
                                          "detector for inverted markers")
    cube_size_m: float = param(0.11, "side of the cube, metres")
    marker_size_m: float = param(0.08, "side of each cube marker's black square, metres")
    robot_size_m: tuple[float, ...] = param((0.30, 0.25, 0.20), "robot body length, width, height, metres")
    mast_height_m: float = param(0.05, "height of the mast between robot body and cube, metres")
    robots: int = param(1, "number of robots on the same path, each with its own cube (ids: cube_marker_id + k, "
                           "or + 5 k with distinct_ids); more than one are named robot1, robot2, ...")
    robot_spacing: float = param(0.3, "with several robots: their distance along the path, as a fraction of its length")
    # --- an imperfectly built cube (cube.toml stays nominal; true_cube.toml has the truth)
    marker_shift_mm: float = param(0.0, "imperfect cube: each marker's position error (std per in-plane axis, "
                                        "half of it along the face normal), millimetres")
    marker_turn_deg: float = param(0.0, "imperfect cube: each marker's in-plane rotation error (std), degrees")
    marker_undersize: float = param(0.0, "imperfect cube: markers are printed this fraction under size "
                                         "(each within about 20 % of it)")
    face_tilt_deg: float = param(0.0, "imperfect cube: faces not quite square, each marker plane tilted "
                                      "(std about each in-plane axis), degrees")
    # --- motion
    path: str = param("figure8", "robot path: figure8 (crosses the world marker), rectangle (rounded), sharp "
                                 "(random waypoints, sharp turns, accelerating and braking) or handheld (the body "
                                 "carried by hand: smooth random 6-DoF motion within path_size_m, lifted 0.05-0.35 m, "
                                 "tilting about 25 deg, at speed_m_s RMS; no floor contact)")
    path_size_m: tuple[float, ...] = param((0.8, 0.5), "half-extent of the path along world x and y, metres")
    speed_m_s: float = param(0.25, "robot speed along the path (sharp: top speed), metres per second")
    accel_m_s2: float = param(1.0, "sharp path: acceleration and braking limit, metres per second squared")
    turn_rate_deg_s: float = param(200.0, "sharp path: highest yaw rate in a turn, degrees per second")
    turn_radius_m: float = param(0.08, "sharp path: radius of its rounded corners, metres")
    floor_bumps_mm: float = param(0.0, "uneven floor: height undulation (std, wavelengths 0.4-1.5 m) that tilts "
                                       "the robot, millimetres")
    bounce_mm: float = param(0.0, "robot vibration: vertical bounce (std, 3-12 Hz), millimetres")
    wobble_deg: float = param(0.0, "robot vibration: roll and pitch wobble (std each, 3-12 Hz), degrees")
    people: int = param(0, "people walking through the arena (occluders), each crossing it again and again")
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
    exposure_steps_per_s: float = param(0.0, "auto-exposure steps per second per camera (0: none)")
    exposure_step: float = param(0.25, "auto-exposure: size of each step (std of the log gain factor)")
    face_shading: float = param(0.0, "directional light: brightness lost by robot, cube and people faces turned "
                                     "away from the light, fraction (0: evenly lit)")
    # --- session
    seed: int = param(0, "random seed: the same seed gives byte-identical frames and files")
    calibration_frames: int = param(200, "frames per camera of the empty-arena calibration recording (0: none)")
    ground_truth_hz: float = param(100.0, "rate of the ground-truth trajectory, samples per second")

    def __post_init__(self) -> None:
        check_finite(self)
        check_positive(self, "height_m", "distance_m", "focal_px", "world_marker_size_m", "cube_size_m",
                       "marker_size_m", "speed_m_s", "duration_s", "fps", "clock_period_s", "accel_m_s2",
                       "turn_rate_deg_s", "turn_radius_m", "ground_truth_hz")
        check_non_negative(self, "position_jitter_m", "angle_jitter_deg", "world_margin_m", "mast_height_m",
                           "capture_jitter_s", "exposure_s", "drift_ppm", "latency_ms", "latency_jitter_ms", "spike_ms",
                           "rtt_ms", "slow_rtt_ms", "noise_std", "blur_px", "gain_jitter", "light_gradient",
                           "vignetting", "start_unix_s", "principal_offset_px", "focal_spread", "readout_ms",
                           "info_focal_error", "info_principal_error_px", "info_k1_error", "marker_shift_mm",
                           "marker_turn_deg", "marker_undersize", "face_tilt_deg", "floor_bumps_mm", "bounce_mm",
                           "wobble_deg", "exposure_steps_per_s", "exposure_step")
        check_between(self, 0, 1, "spike_rate", "slow_rtt_rate", "vignetting", "face_shading")
        check(0 <= self.drop_rate < 1, f"drop_rate must be at least 0 and below 1, got {self.drop_rate}")
        check_between(self, 0, 8, "people")
        for name, most in LIMITS.items():
            check(getattr(self, name) <= most, f"{name} must be at most {most:g}, got {getattr(self, name)}")
        period = f"the frame period {1.0 / self.fps:.4f} s"
        check(self.readout_ms * 1e-3 + self.exposure_s < 1.0 / self.fps,
              f"readout_ms ({self.readout_ms}) plus exposure must be shorter than {period}")
        check(self.exposure_s < 1.0 / self.fps, f"exposure_s ({self.exposure_s}) must be shorter than {period}")
        check_between(self, 1, 8, "robots", "supersample")
        check_between(self, 1, 16, "cameras")
        check_between(self, 1, 100, "jpeg_quality")
        check_between(self, 0, 100_000, "calibration_frames")
        check(0 < self.robot_spacing < 1,
              f"robot_spacing must be between 0 and 1 (exclusive), got {self.robot_spacing}")
        check(0 < self.tilt_deg < 90, f"tilt_deg must be between 0 and 90 degrees (exclusive), got {self.tilt_deg}")
        check(16 <= self.image_width_px <= 4096 and 16 <= self.image_height_px <= 4096,
              f"image size must be 16..4096 pixels per side, got {self.image_width_px} x {self.image_height_px}")
        self._check_geometry()

    def _check_geometry(self) -> None:
        """What the scene's parts need of each other: lens, cube, robot, path, ids, clocks, cameras."""
        check(len(self.distortion) in (4, 5, 8),
              "distortion needs 4, 5 or 8 plumb_bob/rational coefficients (k1 k2 p1 p2 [k3 ...])")
        check(self.marker_size_m <= self.cube_size_m,
              f"marker_size_m ({self.marker_size_m}) must fit on the cube side ({self.cube_size_m} m)")
        check(len(self.robot_size_m) == 3 and min(self.robot_size_m) > 0,
              "robot_size_m needs three positive numbers: length width height")
        check(len(self.path_size_m) == 2 and min(self.path_size_m) > 0,
              "path_size_m needs two positive numbers: half-extent along x and y")
        check(self.path in PATHS, f"path must be one of {', '.join(PATHS)}, got {self.path!r}")
        check(self.path != "handheld" or self.robots == 1, "path handheld carries one body: set robots = 1")
        check(self.world_marker_id >= 0 and self.cube_marker_id >= 0, "marker ids must not be negative")
        cube_ids = range(self.cube_marker_id, self.cube_marker_id + (5 if self.distinct_ids else 1) * self.robots)
        check(self.world_marker_id not in cube_ids,
              f"world_marker_id must differ from the cube's ids ({cube_ids.start}..{cube_ids.stop - 1})")
        check(self.uptime_max_s >= 60.0, f"uptime_max_s must be at least 60 seconds, got {self.uptime_max_s}")
        check(0 <= self.seed < 2**63, f"seed must be a non-negative integer, got {self.seed}")
        reach = max(self.path_size_m) + 0.5
        check(self.distance_m > reach, f"distance_m ({self.distance_m}) must exceed the path's half-extent + 0.5 m "
              f"({reach:.2f} m): the robot would drive into a camera")
        top = self.cube_top_m
        check(self.height_m > top + 0.1, f"height_m ({self.height_m}): cameras must be at least 0.1 m above the "
              f"cube's top ({top:.3f} m)")

    @classmethod
    def realistic(cls, **changes: Any) -> SimulationParams:
        """The realistic preset (:data:`REALISTIC`: every effect of real cameras and robots on),
        with ``changes`` applied on top (e.g. ``cameras=5, seed=3`` or ``readout_ms=0``)."""
        return cls(**{**REALISTIC, **changes})

    @classmethod
    def rig(cls, **changes) -> SimulationParams:
        """The real-rig preset (:data:`RIG`: the realistic preset plus what the rigs of real
        footage have: 1280 x 720 webcams at 6 fps, inverted markers with distinct ids), with
        ``changes`` applied on top."""
        return cls(**{**REALISTIC, **RIG, **changes})

    @property
    def cube_centre_height_m(self) -> float:
        """Height of the cube frame's origin above the floor, metres."""
        return self.robot_size_m[2] + self.mast_height_m + self.cube_size_m / 2.0

    @property
    def robot_names(self) -> tuple[str, ...]:
        """The simulated robots' names: ``robot`` alone, else ``robot1``, ``robot2``, ..."""
        return ("robot",) if self.robots == 1 else tuple(f"robot{k + 1}" for k in range(self.robots))

    @property
    def cube_top_m(self) -> float:
        """Height of the cube's top face above the floor, metres."""
        return self.robot_size_m[2] + self.mast_height_m + self.cube_size_m


# The realistic preset: what real camera nodes and robots add to the clean defaults (docs/simulation.md).
REALISTIC: dict[str, object] = {
    # a wide-angle lens, exactly rendered; each camera's own principal point and focal length
    "distortion": (-0.3, 0.1, 0.0, 0.0, 0.0),
    "principal_offset_px": 5.0,
    "focal_spread": 0.01,
    # camera_info as a ChArUco calibration leaves it
    "info_focal_error": 0.003,
    "info_principal_error_px": 2.0,
    "info_k1_error": 0.005,
    # rolling shutter and a short exposure
    "readout_ms": 30.0,
    "exposure_s": 0.005,
    # faster driving with sharp turns on an uneven floor, a vibrating robot
    "path": "sharp",
    "speed_m_s": 0.5,
    "floor_bumps_mm": 3.0,
    "bounce_mm": 1.0,
    "wobble_deg": 0.5,
    # a hand-built cube
    "marker_shift_mm": 1.0,
    "marker_turn_deg": 1.0,
    "marker_undersize": 0.01,
    "face_tilt_deg": 0.5,
    # light: auto-exposure steps, stronger gradients and vignetting, shaded faces
    "exposure_steps_per_s": 0.1,
    "light_gradient": 0.4,
    "vignetting": 0.35,
    "face_shading": 0.3,
    # people walking through
    "people": 2,
    # fast motion: a denser ground truth (nearest-sample scoring)
    "ground_truth_hz": 1000.0,
}


# The real-rig preset on top of the realistic one (docs/simulation.md): what the rig of
# ../shared/data/real/caliscope-4cam has that the realistic preset lacks (its README): 1280 x 720
# webcams (focal length as its calibrated cameras', 640-900 px) at about 6 fps, free-running
# (unsynchronised: each camera's own clock and capture phase, as every preset), markers printed
# inverted, each with its own id. Its board's free hand-held motion is ``path = "handheld"`` on top
# (benchmarks/accuracy.py --presets hand).
RIG: dict[str, object] = {
    "image_width_px": 1280,
    "image_height_px": 720,
    "focal_px": 760.0,
    "fps": 6.0,
    "inverted_markers": True,
    "distinct_ids": True,
}
