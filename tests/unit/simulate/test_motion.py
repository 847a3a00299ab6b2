"""The sharp path drives like a wheeled robot: the yaw rate ramps (no step), its yaw acceleration
stays within what the wheels give (2 accel / wheel track), and the robot heads along its path."""

from __future__ import annotations

import math

import numpy as np
import pytest

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
