"""The sharp path drives like a wheeled robot: the yaw rate ramps (no step), its yaw acceleration
stays within what the wheels give (2 accel / wheel track), and the robot heads along its path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cubetrack.simulate import SimulationParams
from cubetrack.simulate.motion import WHEEL_TRACK_M, SharpPath

STEP_S = 0.001
DIFF_S = 0.01  # finite differences over 10 ms: the path is tabulated every millimetre


def drive(seed: int, duration_s: float) -> tuple[SharpPath, np.ndarray, np.ndarray]:
    path = SharpPath((1.0, 0.6), 0.5, 1.0, math.radians(200.0), 0.08, 0.3, np.random.default_rng(seed))
    poses = [path.pose(t) for t in np.arange(0.0, duration_s, STEP_S)]
    return path, np.array([p[0] for p in poses]), np.unwrap([p[1] for p in poses])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_yaw_rate_ramps_within_the_wheels_yaw_acceleration(seed):
    path, _, yaw = drive(seed, 15.0)
    assert path.yaw_accel_limit_rad_s2 == pytest.approx(2.0 * 1.0 / WHEEL_TRACK_M)
    h = round(DIFF_S / STEP_S)
    yaw_rate = (yaw[2 * h:] - yaw[:-2 * h]) / (2 * DIFF_S)
    yaw_accel = (yaw[2 * h:] - 2 * yaw[h:-h] + yaw[:-2 * h]) / DIFF_S**2
    assert np.abs(yaw_accel).max() <= 1.05 * path.yaw_accel_limit_rad_s2
    # the turns are still as sharp: the yaw rate reaches the turn rate limit, and never exceeds it
    assert 0.9 * math.radians(200.0) < np.abs(yaw_rate).max() <= 1.02 * math.radians(200.0)


def test_the_robot_heads_along_its_path_and_the_loop_closes():
    path, xy, yaw = drive(3, 30.0)
    velocity = np.diff(xy, axis=0) / STEP_S
    moving = np.linalg.norm(velocity, axis=1) > 0.05
    direction = np.arctan2(velocity[:, 1], velocity[:, 0])
    off = (direction - 0.5 * (yaw[1:] + yaw[:-1]) + math.pi) % (2 * math.pi) - math.pi
    assert np.abs(off[moving]).max() < math.radians(1.0)  # no sideways skid
    assert path.lap_s < 30.0  # the drive crossed the loop's end: no jump there
    assert np.linalg.norm(np.diff(xy, axis=0), axis=1).max() <= 0.5 * STEP_S * 1.05


def test_a_hand_held_body_moves_freely_and_smoothly_within_its_volume():
    """The ``handheld`` motion (issue 25): free 6-DoF at the asked RMS speed, within the path's
    extent and the hand's lift, tilting tens of degrees, smooth (bounded acceleration); each seed
    its own motion."""
    from cubetrack.simulate.motion import HAND_LIFT_M, HAND_TILT_DEG, HandPath

    hand = HandPath((0.8, 0.5), 0.25, np.random.default_rng(1))
    t = np.arange(0.0, 120.0, 0.01)
    T = np.array([hand.T_world_robot(x) for x in t])
    v = np.diff(T[:, :3, 3], axis=0) / 0.01
    assert np.sqrt(np.mean(np.sum(v[:, :2] ** 2, axis=1))) == pytest.approx(0.25, rel=0.15)
    assert np.abs(T[:, 0, 3]).max() <= 0.8 and np.abs(T[:, 1, 3]).max() <= 0.5
    assert HAND_LIFT_M[0] <= T[:, 2, 3].min() and T[:, 2, 3].max() <= HAND_LIFT_M[1]
    tilt_deg = np.degrees(np.arccos(np.clip(T[:, 2, 2], -1.0, 1.0)))
    assert 0.5 * HAND_TILT_DEG < tilt_deg.max() < 1.6 * HAND_TILT_DEG and np.median(tilt_deg) > 5.0
    assert np.abs(np.diff(v, axis=0) / 0.01).max() < 2.0  # m/s^2: a hand, not a jump
    other = HandPath((0.8, 0.5), 0.25, np.random.default_rng(2))
    assert not np.allclose(other.T_world_robot(3.0), hand.T_world_robot(3.0))


def test_the_hand_held_path_carries_one_body_and_leaves_the_floor():
    from cubetrack.core.errors import ParamsError
    from cubetrack.simulate.scenario import build_scene

    with pytest.raises(ParamsError, match="handheld carries one body"):
        SimulationParams(path="handheld", robots=2)
    scene = build_scene(SimulationParams(path="handheld", calibration_frames=0, duration_s=2.0))
    heights = [scene.T_world_cube(t)[2, 3] for t in np.arange(0.0, 2.0, 0.1)]
    assert min(heights) > scene.params.cube_centre_height_m  # lifted off the floor
    assert np.ptp(heights) > 0.005  # and moving up and down
    assert [r.layout.motion for r in scene.robots] == ["free"]  # the tracker is told it is hand-held
    assert build_scene(SimulationParams(calibration_frames=0, duration_s=2.0)).robots[0].layout.motion == "floor"
