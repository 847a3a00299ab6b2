"""The simulated arena: where the cameras stand, what they see (floor, world marker, robot, cube)
and how the robot moves. All poses follow cubetrack's conventions (``T_a_b`` maps b into a;
world = world marker frame, z up; camera optical frame x right, y down, z forward).

Cameras stand evenly around the arena centre at ``distance_m`` and ``height_m``, each turned
(yaw) towards the centre and tilted down by ``tilt_deg``, then moved by a small random placement
error. The robot is a box with a mast and the cube on top; its ground point follows a closed
path at constant speed, heading along the path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from cubetrack.core.cameras import CameraIntrinsics, WorldConfig
from cubetrack.core.errors import SimulationError
from cubetrack.core.geometry import invert_T, make_T, transform_points
from cubetrack.core.layout import CubeLayout, paper_cube_layout
from cubetrack.simulate.params import SimulationParams
from cubetrack.simulate.render import WHITE_ALBEDO, Floor, MarkerTexture, Quad, Solid, box_faces, project_points
from cubetrack.simulate.timing import DeviceClock, make_clock

ROBOT_ALBEDO = 0.15
MAST_ALBEDO = 0.3
FLOOR_ALBEDO = 0.42
WALL_ALBEDO = 0.6
MAST_SIDE_M = 0.03
ROBOT_NAME = "robot"  # the name of a lone robot; several are robot1, robot2, ...

# Independent random streams: (seed, purpose, index) -> Generator. Adding a camera or changing
# one stage's use of randomness leaves the other streams unchanged.
(STREAM_SCENE, STREAM_CLOCK, STREAM_TIMING, STREAM_SYNC, STREAM_IMAGE, STREAM_GAIN,
 STREAM_CAL_TIMING, STREAM_CAL_SYNC, STREAM_CAL_IMAGE, STREAM_CAL_GAIN) = range(10)


def rng_for(seed: int, purpose: int, index: int = 0) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), purpose, index]))


@dataclass(frozen=True, slots=True, eq=False)
class CameraSetup:
    """One simulated camera node: name, intrinsics, true pose of its optical frame, clock, the
    phase of its capture grid on its own clock (s), and its lighting (gradient direction)."""

    name: str
    intrinsics: CameraIntrinsics
    T_world_cam: np.ndarray
    clock: DeviceClock
    capture_phase_s: float
    light_direction_rad: float


class RobotPath:
    """A closed path on the floor travelled at constant speed, heading along the path.

    ``figure8``: x = a sin(th), y = b sin(2 th) (crosses the arena centre, so the robot drives
    over the world marker). ``rectangle``: the superellipse |x/a|^4 + |y/b|^4 = 1.
    """

    def __init__(self, kind: str, half_extent_m: tuple[float, float], speed_m_s: float, start_fraction: float):
        self.kind = kind
        self.a, self.b = half_extent_m
        self.speed_m_s = speed_m_s
        th = np.linspace(0.0, 2.0 * math.pi, 20001)
        pts = self._point(th)
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        self._theta = th
        self._arc = np.concatenate([[0.0], np.cumsum(seg)])
        self.length_m = float(self._arc[-1])
        self._s0 = start_fraction * self.length_m

    def _point(self, th: np.ndarray) -> np.ndarray:
        if self.kind == "figure8":
            return np.stack([self.a * np.sin(th), self.b * np.sin(2.0 * th)], axis=-1)
        c, s = np.cos(th), np.sin(th)
        return np.stack([self.a * np.sign(c) * np.sqrt(np.abs(c)), self.b * np.sign(s) * np.sqrt(np.abs(s))], axis=-1)

    def pose(self, t_s: float) -> tuple[np.ndarray, float]:
        """Ground position (x, y) in metres and heading (rad) ``t_s`` seconds after the start."""
        s = (self._s0 + self.speed_m_s * t_s) % self.length_m
        th = float(np.interp(s, self._arc, self._theta))
        eps = 1e-5
        p = self._point(np.array([th - eps, th, th + eps]))
        d = p[2] - p[0]
        return p[1], math.atan2(d[1], d[0])


@dataclass(frozen=True, slots=True, eq=False)
class SimRobot:
    """One simulated robot: its name, its cube's layout and the path it drives."""

    name: str
    layout: CubeLayout
    path: RobotPath


@dataclass(frozen=True, slots=True, eq=False)
class Scene:
    """Everything the renderer and the timing model need, built once from the parameters."""

    params: SimulationParams
    cameras: tuple[CameraSetup, ...]
    robots: tuple[SimRobot, ...]
    world: WorldConfig
    floor: Floor
    world_marker: Solid

    def T_world_robot(self, t_s: float, robot: int = 0) -> np.ndarray:
        """A robot's ground frame (x forward, z up) ``t_s`` seconds after the start."""
        (x, y), yaw = self.robots[robot].path.pose(t_s)
        return make_T(Rotation.from_euler("z", yaw).as_matrix(), [x, y, 0.0])

    def T_robot_cube(self) -> np.ndarray:
        """The cube frame in the robot's ground frame: straight above it, same axes."""
        return make_T(np.eye(3), [0.0, 0.0, self.params.cube_centre_height_m])

    def T_world_cube(self, t_s: float, robot: int = 0) -> np.ndarray:
        """A robot's cube frame in the world ``t_s`` seconds after the start of the recording."""
        return self.T_world_robot(t_s, robot) @ self.T_robot_cube()

    def moving_solids(self, t_s: float, camera_position_m: np.ndarray) -> tuple[Solid, ...]:
        """Every robot's body, mast and cube at ``t_s``, in painter's order (far robots first)
        for a camera at ``camera_position_m`` above the cubes."""
        poses = [self.T_world_robot(t_s, k) for k in range(len(self.robots))]
        order = sorted(range(len(poses)), key=lambda k: -float(np.linalg.norm(poses[k][:3, 3] - camera_position_m)))
        return tuple(solid for k in order for solid in self.robot_solids_at(poses[k], self.robots[k].layout))

    def robot_solids_at(self, T_robot: np.ndarray, layout: CubeLayout) -> tuple[Solid, ...]:
        """Robot body, mast and cube with the robot's ground frame at ``T_robot`` (world)."""
        p = self.params
        length, width, height = p.robot_size_m
        body = Solid(box_faces(T_robot @ make_T(np.eye(3), [0, 0, height / 2]), (length, width, height),
                               ROBOT_ALBEDO))
        solids = [body]
        if p.mast_height_m > 0:
            mast_T = T_robot @ make_T(np.eye(3), [0, 0, height + p.mast_height_m / 2])
            side = min(MAST_SIDE_M, p.cube_size_m)
            solids.append(Solid(box_faces(mast_T, (side, side, p.mast_height_m), MAST_ALBEDO)))
        T_cube = T_robot @ self.T_robot_cube()
        faces, decals = [], []
        for m in layout.markers:
            T = T_cube @ m.T_cube_marker
            faces.append(Quad(T, (p.cube_size_m, p.cube_size_m), WHITE_ALBEDO))
            decals.append(Quad(T, (m.size_m, m.size_m), texture=MarkerTexture(layout.dictionary, m.marker_id)))
        # the face without a marker (the bottom) is never seen from above; the cube is closed anyway
        solids.append(Solid(tuple(faces), tuple(decals)))
        return tuple(solids)


def make_floor(rng: np.random.Generator, half_size_m: float = 4.0, texels: int = 1024) -> Floor:
    """Mid-grey floor with a mild blotchy texture and fine grain."""
    import cv2

    coarse = rng.normal(0.0, 1.0, (texels // 32, texels // 32)).astype(np.float32)
    blotches = cv2.resize(coarse, (texels, texels), interpolation=cv2.INTER_CUBIC)
    grain = rng.normal(0.0, 1.0, (texels, texels)).astype(np.float32)
    tex = FLOOR_ALBEDO + 0.03 * blotches + 0.015 * grain
    return Floor(np.clip(tex, 0.05, 0.95).astype(np.float32), half_size_m, WALL_ALBEDO)


def make_world_marker(p: SimulationParams) -> Solid:
    """The world marker: a white sheet with the black square centred on the world origin."""
    paper = p.world_marker_size_m + 2.0 * p.world_margin_m
    T = np.eye(4)
    T[2, 3] = 1e-4  # a sheet on the floor
    return Solid((Quad(T, (paper, paper), WHITE_ALBEDO),),
                 (Quad(T, (p.world_marker_size_m, p.world_marker_size_m),
                       texture=MarkerTexture(p.dictionary, p.world_marker_id)),))


def camera_pose(azimuth_rad: float, p: SimulationParams, rng: np.random.Generator) -> np.ndarray:
    """T_world_cam of a camera at ``azimuth_rad`` around the centre, facing it, tilted down."""
    position = np.array([p.distance_m * math.cos(azimuth_rad), p.distance_m * math.sin(azimuth_rad), p.height_m])
    position += rng.normal(0.0, p.position_jitter_m, 3) if p.position_jitter_m > 0 else 0.0
    towards = -np.array([math.cos(azimuth_rad), math.sin(azimuth_rad), 0.0])
    tilt = math.radians(p.tilt_deg)
    z = math.cos(tilt) * towards + math.sin(tilt) * np.array([0.0, 0.0, -1.0])
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.column_stack([x, y, z])
    if p.angle_jitter_deg > 0:
        R = R @ Rotation.from_rotvec(rng.normal(0.0, math.radians(p.angle_jitter_deg), 3)).as_matrix()
    return make_T(R, position)


def intrinsics_of(p: SimulationParams, name: str) -> CameraIntrinsics:
    """VGA-like pinhole intrinsics; principal point at the image centre, pixel-centre convention."""
    K = np.array([[p.focal_px, 0.0, (p.image_width_px - 1) / 2.0],
                  [0.0, p.focal_px, (p.image_height_px - 1) / 2.0],
                  [0.0, 0.0, 1.0]])
    return CameraIntrinsics(p.image_width_px, p.image_height_px, K, np.array(p.distortion, float), name)


def build_scene(p: SimulationParams) -> Scene:
    """The arena for a parameter set; raises SimulationError when a camera cannot see the whole
    world marker (calibration would be impossible)."""
    scene_rng = rng_for(p.seed, STREAM_SCENE)
    floor = make_floor(scene_rng)
    world = WorldConfig(p.dictionary, p.world_marker_id, p.world_marker_size_m)
    start = float(scene_rng.uniform(0.0, 1.0))
    robots = []
    for k in range(p.robots):
        first_id = p.cube_marker_id + k * (5 if p.distinct_ids else 1)
        layout = paper_cube_layout(p.cube_size_m, p.marker_size_m, first_id, p.dictionary, p.distinct_ids)
        path = RobotPath(p.path, (p.path_size_m[0], p.path_size_m[1]), p.speed_m_s,
                         (start + k * p.robot_spacing) % 1.0)
        robots.append(SimRobot(ROBOT_NAME if p.robots == 1 else f"robot{k + 1}", layout, path))
    cameras = []
    for i in range(p.cameras):
        name = f"cam{i + 1}"
        azimuth = math.radians(-75.0) + 2.0 * math.pi * i / p.cameras
        T_world_cam = camera_pose(azimuth, p, scene_rng)
        clock_rng = rng_for(p.seed, STREAM_CLOCK, i)
        clock = make_clock(p, clock_rng)
        phase = float(clock_rng.uniform(0.0, 1.0 / p.fps))
        light = float(scene_rng.uniform(0.0, 2.0 * math.pi))
        cameras.append(CameraSetup(name, intrinsics_of(p, name), T_world_cam, clock, phase, light))
    for marker_id in sorted({p.world_marker_id, *(i for r in robots for i in r.layout.ids)}):
        MarkerTexture(p.dictionary, marker_id).cells  # unknown dictionary or id: SimulationError
    scene = Scene(p, tuple(cameras), tuple(robots), world, floor, make_world_marker(p))
    _check_visibility(scene)
    return scene


def _check_visibility(scene: Scene) -> None:
    p = scene.params
    h = p.world_marker_size_m / 2.0
    corners = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    for cam in scene.cameras:
        depth = transform_points(invert_T(cam.T_world_cam), corners)[:, 2]
        if np.any(depth <= 0.05):
            raise SimulationError(f"{cam.name} cannot see the world marker (it is behind the camera); "
                                  "lower tilt_deg or increase distance_m")
        uv = project_points(cam.intrinsics, cam.T_world_cam, corners)
        margin = 3.0
        inside = ((uv[:, 0] >= margin) & (uv[:, 0] <= p.image_width_px - 1 - margin)
                  & (uv[:, 1] >= margin) & (uv[:, 1] <= p.image_height_px - 1 - margin))
        if not inside.all():
            raise SimulationError(
                f"{cam.name} does not see the whole world marker (height {p.height_m} m, tilt {p.tilt_deg} deg, "
                f"distance {p.distance_m} m); change tilt_deg or distance_m so the arena centre is in view")
