"""The simulated arena: where the cameras stand, what they see (floor, world marker, robot, cube,
people) and how it moves. All poses follow cubetrack's conventions (``T_a_b`` maps b into a;
world = world marker frame, z up; camera optical frame x right, y down, z forward).

Cameras stand evenly around the arena centre at ``distance_m`` and ``height_m``, each turned
(yaw) towards the centre and tilted down by ``tilt_deg``, then moved by a small random placement
error. The robot is a box with a mast and the cube on top; its ground point follows a closed
path (:mod:`cubetrack.simulate.motion`), on an uneven floor when asked. The cube is drawn as
built (:func:`cubetrack.simulate.imperfections.built_layout`); the tracker is given the nominal
layout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from cubetrack.core.cameras import CameraIntrinsics, WorldConfig
from cubetrack.core.errors import SimulationError
from cubetrack.core.geometry import invert_T, make_T, transform_points
from cubetrack.core.layout import CubeLayout, paper_cube_layout
from cubetrack.simulate.camera_motion import CameraMotion, plan_camera_motions
from cubetrack.simulate.imperfections import built_layout, calibrated_intrinsics, true_intrinsics
from cubetrack.simulate.motion import (
    PERSON_BODY_M,
    PERSON_HEAD_M,
    HandPath,
    Person,
    RobotPath,
    SharpPath,
    Terrain,
    make_path,
    plan_people,
)
from cubetrack.simulate.params import SimulationParams
from cubetrack.simulate.render import (
    BLACK_ALBEDO,
    WHITE_ALBEDO,
    Floor,
    MarkerTexture,
    Quad,
    Solid,
    box_faces,
    project_points,
)
from cubetrack.simulate.timing import DeviceClock, make_clock

ROBOT_ALBEDO = 0.15
MAST_ALBEDO = 0.3
FLOOR_ALBEDO = 0.42
WALL_ALBEDO = 0.6
HEAD_ALBEDO = 0.35
MAST_SIDE_M = 0.03
LIGHT_ELEVATION_DEG = 50.0  # the directional light of face_shading comes from this high up

# Independent random streams: (seed, purpose, index) -> Generator. Adding a camera or changing
# one stage's use of randomness leaves the other streams unchanged.
(STREAM_SCENE, STREAM_CLOCK, STREAM_TIMING, STREAM_SYNC, STREAM_IMAGE, STREAM_GAIN,
 STREAM_CAL_TIMING, STREAM_CAL_SYNC, STREAM_CAL_IMAGE, STREAM_CAL_GAIN,
 STREAM_LENS, STREAM_INFO, STREAM_BUILD, STREAM_FLOOR, STREAM_VIBRATION, STREAM_PATH, STREAM_PEOPLE,
 STREAM_EXPOSURE, STREAM_CAL_EXPOSURE, STREAM_LIGHT, STREAM_CAMERA_MOTION) = range(21)


def rng_for(seed: int, purpose: int, index: int = 0) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), purpose, index]))


@dataclass(frozen=True, slots=True, eq=False)
class CameraSetup:
    """One simulated camera node: name, true intrinsics, true pose of its optical frame, clock,
    the phase of its capture grid on its own clock (s), its lighting (gradient direction), the
    intrinsics the tracker is told (``camera_info``; the truth unless calibration errors are on)
    and its rolling-shutter readout (s; 0 = global shutter)."""

    name: str
    intrinsics: CameraIntrinsics
    T_world_cam: np.ndarray
    clock: DeviceClock
    capture_phase_s: float
    light_direction_rad: float
    camera_info: CameraIntrinsics
    readout_s: float = 0.0
    motion: CameraMotion = CameraMotion()

    def T_world_cam_at(self, t_s: float) -> np.ndarray:
        """The camera's true pose ``t_s`` seconds after the recording's start (bumps and drift included)."""
        return self.motion.T_world_cam(self.T_world_cam, t_s) if not self.motion.still else self.T_world_cam.copy()

    @property
    def row_s(self) -> float:
        """Time between the exposures of two consecutive rows, seconds."""
        return self.readout_s / self.intrinsics.height

    @property
    def reference_row(self) -> float:
        """The row whose mid-exposure instant is the frame's stamp (the image's middle row)."""
        return (self.intrinsics.height - 1) / 2.0


@dataclass(frozen=True, slots=True, eq=False)
class SimRobot:
    """One simulated robot: its name, its cube's layout (nominal, as the tracker is told), the
    path it drives, the cube as built (``true_layout``) and the uneven floor and vibration that
    tilt it (None: a flat floor, no vibration)."""

    name: str
    layout: CubeLayout
    path: RobotPath | SharpPath | HandPath
    true_layout: CubeLayout
    terrain: Terrain | None = None


@dataclass(frozen=True, slots=True, eq=False)
class Scene:
    """Everything the renderer and the timing model need, built once from the parameters."""

    params: SimulationParams
    cameras: tuple[CameraSetup, ...]
    robots: tuple[SimRobot, ...]
    world: WorldConfig
    floor: Floor
    world_marker: Solid
    people: tuple[Person, ...] = ()
    light_world: np.ndarray | None = None  # unit vector towards the light of face_shading

    def T_world_robot(self, t_s: float, robot: int = 0) -> np.ndarray:
        """A robot's ground frame (x forward, z up) ``t_s`` seconds after the start; on an uneven
        floor it stands on its four wheels and vibrates."""
        r = self.robots[robot]
        if isinstance(r.path, HandPath):  # carried: no floor under it
            return r.path.T_world_robot(t_s)
        xy, yaw = r.path.pose(t_s)
        if r.terrain is not None:
            return r.terrain.T_world_robot(np.asarray(xy, float), yaw, t_s)
        x, y = xy
        return make_T(Rotation.from_euler("z", yaw).as_matrix(), [x, y, 0.0])

    def T_robot_cube(self) -> np.ndarray:
        """The cube frame in the robot's ground frame: straight above it, same axes."""
        return make_T(np.eye(3), [0.0, 0.0, self.params.cube_centre_height_m])

    def T_world_cube(self, t_s: float, robot: int = 0) -> np.ndarray:
        """A robot's cube frame in the world ``t_s`` seconds after the start of the recording."""
        return self.T_world_robot(t_s, robot) @ self.T_robot_cube()

    def moving_solids(self, t_s: float, camera_position_m: np.ndarray) -> tuple[Solid, ...]:
        """Every robot's body, mast and cube and every person in the room at ``t_s``, in
        painter's order (far ones first) for a camera at ``camera_position_m``."""
        groups = []
        for k, robot in enumerate(self.robots):
            T = self.T_world_robot(t_s, k)
            groups.append((T[:3, 3], lambda T=T, robot=robot: self.robot_solids_at(T, robot.layout, robot.true_layout)))
        for person in self.people:
            T_person = person.T_world_person(t_s)
            if T_person is not None:
                centre = T_person[:3, 3] + [0.0, 0.0, PERSON_BODY_M[2] / 2]
                groups.append((centre, lambda T=T_person, person=person: self.person_solids_at(T, person.albedo)))
        order = sorted(range(len(groups)), key=lambda k: -float(np.linalg.norm(groups[k][0] - camera_position_m)))
        return tuple(solid for k in order for solid in groups[k][1]())

    def robot_solids_at(self, T_robot: np.ndarray, layout: CubeLayout,
                        built: CubeLayout | None = None) -> tuple[Solid, ...]:
        """Robot body, mast and cube with the robot's ground frame at ``T_robot`` (world): the
        cube's faces where ``layout`` puts them, its markers where ``built`` (default: the same
        layout) has them."""
        p = self.params
        length, width, height = p.robot_size_m
        body = Solid(self._shaded(box_faces(T_robot @ make_T(np.eye(3), [0, 0, height / 2]),
                                            (length, width, height), ROBOT_ALBEDO)))
        solids = [body]
        if p.mast_height_m > 0:
            mast_T = T_robot @ make_T(np.eye(3), [0, 0, height + p.mast_height_m / 2])
            side = min(MAST_SIDE_M, p.cube_size_m)
            solids.append(Solid(self._shaded(box_faces(mast_T, (side, side, p.mast_height_m), MAST_ALBEDO))))
        T_cube = T_robot @ self.T_robot_cube()
        faces, decals = [], []
        for m, b in zip(layout.markers, (built or layout).markers, strict=True):
            T = T_cube @ m.T_cube_marker
            shade = self.shade(T[:3, 2])
            faces.append(Quad(T, (p.cube_size_m, p.cube_size_m), BLACK_ALBEDO if p.inverted_markers else WHITE_ALBEDO,
                              shade=shade))
            decals.append(Quad(T_cube @ b.T_cube_marker, (b.size_m, b.size_m),
                               texture=MarkerTexture(layout.dictionary, b.marker_id, p.inverted_markers), shade=shade))
        # the face without a marker (the bottom) is never seen from above; the cube is closed anyway
        solids.append(Solid(tuple(faces), tuple(decals)))
        return tuple(solids)

    def person_solids_at(self, T_person: np.ndarray, albedo: float) -> tuple[Solid, ...]:
        """A person standing at ``T_person`` (floor frame, x along the walk): body and head boxes."""
        depth, width, height = PERSON_BODY_M
        body = box_faces(T_person @ make_T(np.eye(3), [0, 0, height / 2]), (depth, width, height), albedo)
        head = box_faces(T_person @ make_T(np.eye(3), [0, 0, height + PERSON_HEAD_M[2] / 2]), PERSON_HEAD_M,
                         HEAD_ALBEDO)
        return Solid(self._shaded(body)), Solid(self._shaded(head))

    def shade(self, normal_world: np.ndarray) -> float:
        """Brightness factor of a face with this outward normal under the directional light."""
        if self.light_world is None:
            return 1.0
        return 1.0 - self.params.face_shading * (1.0 - max(0.0, float(np.dot(normal_world, self.light_world))))

    def _shaded(self, quads: tuple[Quad, ...]) -> tuple[Quad, ...]:
        if self.light_world is None:
            return quads
        return tuple(Quad(q.T_world_quad, q.size_m, q.albedo, q.texture, self.shade(q.T_world_quad[:3, 2]))
                     for q in quads)


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


def build_scene(p: SimulationParams) -> Scene:
    """The arena for a parameter set; raises SimulationError when a camera cannot see the whole
    world marker (calibration would be impossible)."""
    scene_rng = rng_for(p.seed, STREAM_SCENE)
    floor = make_floor(scene_rng)
    world = WorldConfig(p.dictionary, p.world_marker_id, p.world_marker_size_m)
    start = float(scene_rng.uniform(0.0, 1.0))
    uneven = p.floor_bumps_mm > 0 or p.bounce_mm > 0 or p.wobble_deg > 0
    robots = []
    for k in range(p.robots):
        first_id = p.cube_marker_id + k * (5 if p.distinct_ids else 1)
        layout = paper_cube_layout(p.cube_size_m, p.marker_size_m, first_id, p.dictionary, p.distinct_ids)
        # robots share one path and one floor (same streams), each its own cube and vibration
        path = make_path(p.path, (p.path_size_m[0], p.path_size_m[1]), p.speed_m_s, (start + k * p.robot_spacing) % 1.0,
                         p.accel_m_s2, math.radians(p.turn_rate_deg_s), p.turn_radius_m, rng_for(p.seed, STREAM_PATH))
        if isinstance(path, HandPath):  # a body carried by hand says so, as a user's layout would
            layout = replace(layout, motion="free")
        terrain = None
        if uneven:
            terrain = Terrain(1e-3 * p.floor_bumps_mm, 1e-3 * p.bounce_mm, math.radians(p.wobble_deg),
                              (p.robot_size_m[0], p.robot_size_m[1]), rng_for(p.seed, STREAM_FLOOR),
                              rng_for(p.seed, STREAM_VIBRATION, k))
        robots.append(SimRobot(p.robot_names[k], layout, path,
                               built_layout(layout, p, rng_for(p.seed, STREAM_BUILD, k)), terrain))
    cameras = []
    motions = plan_camera_motions(p.cameras, p.bump_camera, p.bump_at_s, p.bump_step_m, p.bump_turn_deg,
                                  p.drift_camera, p.drift_mm_per_min, p.drift_deg_per_min,
                                  [rng_for(p.seed, STREAM_CAMERA_MOTION, k) for k in range(len(p.bump_camera) + 1)])
    for i in range(p.cameras):
        name = f"cam{i + 1}"
        azimuth = math.radians(-75.0) + 2.0 * math.pi * i / p.cameras
        T_world_cam = camera_pose(azimuth, p, scene_rng)
        clock_rng = rng_for(p.seed, STREAM_CLOCK, i)
        clock = make_clock(p, clock_rng)
        phase = float(clock_rng.uniform(0.0, 1.0 / p.fps))
        light = float(scene_rng.uniform(0.0, 2.0 * math.pi))
        intrinsics = true_intrinsics(p, name, rng_for(p.seed, STREAM_LENS, i))
        # the tracker is told the readout too (the sensor mode's datasheet value: exact)
        info = replace(calibrated_intrinsics(intrinsics, p, rng_for(p.seed, STREAM_INFO, i)),
                       readout_s=1e-3 * p.readout_ms)
        cameras.append(CameraSetup(name, intrinsics, T_world_cam, clock, phase, light, info, 1e-3 * p.readout_ms,
                                   motions[i]))
    for marker_id in sorted({p.world_marker_id, *(i for r in robots for i in r.layout.ids)}):
        MarkerTexture(p.dictionary, marker_id).cells  # noqa: B018 (unknown dictionary or id: SimulationError)
    light_world = None
    if p.face_shading > 0:
        azimuth = float(rng_for(p.seed, STREAM_LIGHT).uniform(0.0, 2.0 * math.pi))
        elevation = math.radians(LIGHT_ELEVATION_DEG)
        light_world = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                                math.sin(elevation)])
    scene = Scene(p, tuple(cameras), tuple(robots), world, floor, make_world_marker(p), (), light_world)
    if p.people:
        cameras_xy = np.array([c.T_world_cam[:2, 3] for c in cameras])

        def robot_xy_at(t: float) -> np.ndarray:
            return np.array([scene.T_world_robot(t, k)[:2, 3] for k in range(len(robots))])

        people = plan_people(p.people, p.duration_s, cameras_xy, robot_xy_at, rng_for(p.seed, STREAM_PEOPLE))
        scene = Scene(p, scene.cameras, scene.robots, world, floor, scene.world_marker, people, light_world)
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
