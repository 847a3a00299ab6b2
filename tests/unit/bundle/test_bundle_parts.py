"""The bundle adjustment's parts on synthetic data built from known poses (no images)."""

import numpy as np
from scipy.spatial.transform import Rotation

from cubetrack.calib.bundle import (
    BundleAdjustmentParams,
    CubeFrame,
    Instant,
    _build_problem,
    _solve,
    group_instants,
    robust_average_corners,
    velocities,
)
from cubetrack.core.geometry import R_from_rotvec, invert_T, make_T, rotation_angle
from cubetrack.core.layout import marker_corners_m, paper_cube_layout
from cubetrack.estimate.reprojection import CornerSet


def look_at(position, target=(0.0, 0.0, 0.15)):
    z = np.asarray(target, float) - position
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return make_T(np.column_stack([x, np.cross(z, x), z]), position)


def test_group_instants_pairs_frames_of_different_cameras_once():
    f = lambda cam, t: CubeFrame(cam, "r", 0, t, ())  # noqa: E731
    frames = [f("a", 0.00), f("b", 0.03), f("a", 0.10), f("b", 0.30), f("c", 0.32), f("a", 0.34)]
    groups = group_instants(frames, 0.05, 2)
    assert [[x.camera for x in g] for g in groups] == [["a", "b"], ["b", "c", "a"]]


def test_velocities_of_a_constant_twist():
    t = np.linspace(0.0, 1.0, 21)
    Ts = np.array([make_T(Rotation.from_rotvec([0, 0, 0.5 * ti]).as_matrix(), [0.2 * ti, -0.1 * ti, 0.15]) for ti in t])
    v, w = velocities(t, Ts, 0.3)
    assert np.allclose(v, [0.2, -0.1, 0.0], atol=1e-9) and np.allclose(w, [0, 0, 0.5], atol=1e-9)


def test_robust_average_ignores_a_bumped_frame():
    rng = np.random.default_rng(0)
    corners = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float) + rng.normal(0, 0.05, (30, 4, 2))
    corners[7] += 5.0
    mean, inliers = robust_average_corners(corners, 1.0)
    assert inliers == 29 and np.abs(mean - [[0, 0], [10, 0], [10, 10], [0, 10]]).max() < 0.05


def test_bundle_adjustment_recovers_cameras_from_exact_corners():
    """Three cameras 2.2 m out see a moving cube at 40 instants; world-marker corners fix the
    gauge. Starting 1 cm / 0.5 deg off, the solve returns the true poses."""
    rng = np.random.default_rng(1)
    layout = paper_cube_layout()
    cams = {f"cam{i}": look_at(np.array([2.2 * np.cos(a), 2.2 * np.sin(a), 1.0]))
            for i, a in enumerate(np.radians([0, 120, 240]))}
    f = 520.0
    world_points = marker_corners_m(0.25)
    instants = []
    for k in range(40):
        t = 0.2 * k
        T_cube = make_T(Rotation.from_euler("z", 0.3 * t).as_matrix(), [0.6 * np.sin(0.4 * t), 0.4 * np.sin(0.8 * t), 0.35])
        sets = []
        for name, T_wc in cams.items():
            T_cw = invert_T(T_wc)
            pts, faces = [], []
            for m in layout.markers:
                normal_cam = (T_cw @ T_cube)[:3, :3] @ m.T_cube_marker[:3, 2]
                centre_cam = (T_cw @ T_cube @ m.T_cube_marker)[:3, 3]
                if normal_cam @ centre_cam < -0.3 * np.linalg.norm(centre_cam):
                    pts.append(m.corners_cube_m())
                    faces.append(m.face)
            pts = np.vstack(pts)
            pc = (pts @ T_cube[:3, :3].T + T_cube[:3, 3]) @ T_cw[:3, :3].T + T_cw[:3, 3]
            sets.append(CornerSet(name, t, T_cw, f, pts, pc[:, :2] / pc[:, 2:], tuple(faces)))
        instants.append(Instant("r", t, (), tuple(sets), T_cube))
    world = {}
    for name, T_wc in cams.items():
        T_cw = invert_T(T_wc)
        pc = world_points @ T_cw[:3, :3].T + T_cw[:3, 3]
        world[name] = (pc[:, :2] / pc[:, 2:], f)
    index = {c: i for i, c in enumerate(cams)}
    prob = _build_problem(instants, index, np.zeros((40, 3)), np.zeros((40, 3)), world, world_points)
    true_cams = np.array(list(cams.values()))
    start = np.array([make_T(R_from_rotvec(rng.normal(0, 0.005, 3)) @ T[:3, :3], T[:3, 3] + rng.normal(0, 0.01, 3))
                      for T in true_cams])
    cubes0 = np.array([make_T(R_from_rotvec(rng.normal(0, 0.01, 3)) @ i.T_world_cube[:3, :3],
                              i.T_world_cube[:3, 3] + rng.normal(0, 0.005, 3)) for i in instants])
    T_cams, _ = _solve(prob, start, cubes0, BundleAdjustmentParams(max_nfev=100))
    for T, T_true in zip(T_cams, true_cams):
        assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 1e-5
        assert rotation_angle(T[:3, :3], T_true[:3, :3], "deg") < 1e-4
