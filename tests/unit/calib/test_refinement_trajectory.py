"""The extrinsics refinement on a continuous-time trajectory (``[bundle_adjustment] knot_s`` > 0),
on synthetic detections from known poses (no images).

Two robots (distinct marker ids) turn ever faster (40 rad/s^2: a sharp turn's start) while they
drive, seen by three unsynchronised cameras at 30 frames/s (each 11 ms after the previous one), the
corners exact at each frame's own time; the cameras start 1 cm / 0.3 deg off and the world marker's
exact corners hold the gauge. An instant's frames span 22 ms, in which a constant velocity is
wrong; each robot's trajectory compares every frame at its own time."""

import numpy as np
from scenes import look_at
from scipy.spatial.transform import Rotation

from cubetrack.calib.bundle import (
    BundleAdjustmentParams,
    CubeFrame,
    Refinement,
    Trajectory,
    TrajectorySpec,
    make_instants,
)
from cubetrack.calib.solver import project
from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import make_T, rotation_angle, shoelace_area
from cubetrack.core.layout import marker_corners_m, paper_cube_layout
from cubetrack.core.records import Detection

CAMERAS = ("cam1", "cam2", "cam3")
LENS = CameraIntrinsics(640, 480, np.array([[520.0, 0, 319.5], [0, 520.0, 239.5], [0, 0, 1]]), np.zeros(5))
T_TRUE = {c: look_at([2.2 * np.cos(a), 2.2 * np.sin(a), 1.0], [0.0, 0.0, 0.1])
          for c, a in zip(CAMERAS, np.radians([10, 130, 250]), strict=True)}
LAYOUTS = {"a": paper_cube_layout(marker_id=1, distinct_ids=True),
           "b": paper_cube_layout(marker_id=10, distinct_ids=True)}
WORLD_M = marker_corners_m(0.25)


def _pose(robot: str, t: float) -> np.ndarray:
    """The robot's true body pose at time t (s): a turn that sharpens while it drives."""
    sign, start = (1.0, np.array([-0.3, 0.0])) if robot == "a" else (-1.0, np.array([0.3, 0.1]))
    yaw = sign * (20.0 * t ** 2 + 0.3 * t)
    xy = start + np.array([0.2 * t, sign * 0.35 * t ** 2])
    return make_T(Rotation.from_euler("z", yaw).as_matrix(), [*xy, 0.055])


def _pixels(c: str, X: np.ndarray) -> np.ndarray:
    T = T_TRUE[c]
    return project((X - T[:3, 3]) @ T[:3, :3], LENS.K, LENS.dist)[0]


def _frames(duration_s: float = 0.4) -> list[CubeFrame]:
    frames = []
    for i, c in enumerate(CAMERAS):
        for seq, t in enumerate(np.arange(0.011 * i, duration_s, 1 / 30)):
            for robot, layout in LAYOUTS.items():
                T = _pose(robot, t)
                dets = []
                for m in layout.markers:
                    centre = T[:3, :3] @ m.T_cube_marker[:3, 3] + T[:3, 3]
                    to_camera = T_TRUE[c][:3, 3] - centre
                    if (T[:3, :3] @ m.T_cube_marker[:3, 2]) @ to_camera < 0.3 * np.linalg.norm(to_camera):
                        continue
                    X = (T @ m.T_cube_marker @ np.c_[marker_corners_m(m.size_m), np.ones(4)].T).T[:, :3]
                    px = _pixels(c, X)
                    dets.append(Detection(m.marker_id, px, shoelace_area(px), layout.dictionary))
                if dets:
                    frames.append(CubeFrame(c, robot, seq, float(t), tuple(dets)))
    return sorted(frames, key=lambda f: (f.time_s, f.camera))


def _camera_errors(ref: Refinement) -> tuple[float, float]:
    """Worst position (mm) and rotation (deg) error of the refined cameras."""
    errors = [(1000 * np.linalg.norm(T[:3, 3] - T_TRUE[c][:3, 3]), rotation_angle(T[:3, :3], T_TRUE[c][:3, :3], "deg"))
              for c, T in ref.T_world_cam().items()]
    return max(e[0] for e in errors), max(e[1] for e in errors)


def _refinement(params: BundleAdjustmentParams) -> Refinement:
    """The instants of the drive, started from cameras 1 cm / 0.3 deg off, body poses solved with
    them held (as :func:`cubetrack.calib.bundle.start_refinement` starts)."""
    rng = np.random.default_rng(3)
    start = {c: make_T(Rotation.from_rotvec(np.radians(0.3) * rng.normal(size=3) / np.sqrt(3)).as_matrix() @ T[:3, :3],
                       T[:3, 3] + 0.01 * rng.normal(size=3) / np.sqrt(3)) for c, T in T_TRUE.items()}
    lenses = dict.fromkeys(CAMERAS, LENS)
    instants = make_instants(_frames(), LAYOUTS, lenses, start, params)
    assert {i.robot for i in instants} == set(LAYOUTS)
    ref = Refinement.start(instants, list(CAMERAS), start, lenses, LAYOUTS, params)
    for _ in range(2):
        ref.solve(ref.freedom(cameras=False))
        ref.update_velocities()
    return ref


def test_two_robots_trajectories_give_the_cameras_where_a_constant_velocity_does_not():
    params = BundleAdjustmentParams(knot_s=1 / 60, planar_motion=False, upright_sigma_deg=0.0, corner_noise_px=0.1,
                                    max_nfev=20)
    world = {c: (WORLD_M, _pixels(c, WORLD_M)) for c in CAMERAS}

    ref = _refinement(params)
    trajectory = Trajectory.start(ref, TrajectorySpec(params.knot_s, params.max_span_s, 10.0, 100.0))
    assert set(trajectory.robot.tolist()) == {0, 1} and len(trajectory.frames) > 2 * len(ref.instants)
    for _ in range(2):
        trajectory.solve(ref.freedom(), world)
        trajectory.rematch()
    on_trajectory = _camera_errors(ref)
    # each robot's pose anywhere on its trajectory is the true one
    for robot in LAYOUTS:
        T = trajectory.pose_at(robot, 0.3)
        assert np.linalg.norm(T[:3, 3] - _pose(robot, 0.3)[:3, 3]) < 5e-4

    instants = _refinement(params)
    for _ in range(2):
        instants.solve(instants.freedom(), world)
        instants.update_velocities()
        instants.rematch()
    constant_velocity = _camera_errors(instants)
    assert on_trajectory[0] < 0.5 and on_trajectory[1] < 0.01, on_trajectory
    assert constant_velocity[1] > 3 * on_trajectory[1], (constant_velocity, on_trajectory)
