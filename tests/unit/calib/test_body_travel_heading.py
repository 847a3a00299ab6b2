"""The body frame's yaw from the direction of travel (``[body_calibration] heading_from_travel``).

The calibrated body frame is the nominal layout's best fit to the markers, so its yaw carries the
mean of their build errors, which no image shows. A robot that only drives forward moves along
its heading, so its poses over a drive say where its x axis is. :func:`travel_heading` must find
that direction (whatever the robot's tilt, and with the body's origin ahead of the point it
turns about) and must refuse a body that moves sideways; calibrate_body with the option must
turn the frame to it and with it off must leave the markers' frame."""

import math

import numpy as np
import pytest
import test_body_tilting_robot as tilting_robot
from scipy.spatial.transform import Rotation

from cubetrack.calib import bundle
from cubetrack.calib.body import (
    TRAVEL_MAX_SIDEWAYS,
    best_fit_transform,
    calibrate_body,
    placement_errors,
    travel_heading,
)
from cubetrack.calib.bundle import BodyCalibrationParams
from cubetrack.core.geometry import make_T
from cubetrack.simulate.motion import HandPath


def _drive(yaw_deg: float, lever_m: float, *, sideways: bool = False, tilt_deg: float = 0.0, seconds: float = 30.0,
           dt: float = 0.05):
    """Poses of a body on a weaving drive at 0.25 m/s: the robot's ground frame (on the floor, z = 0)
    heads along its path (or, with ``sideways``, moves in directions of its own, as a holonomic
    base does), rolling and pitching by ``tilt_deg`` about it; the body sits 0.2 m up, ``lever_m``
    ahead of the robot's turning point, its x turned by ``-yaw_deg`` from the robot's, so the
    travel reads ``yaw_deg`` in the body frame."""
    t = np.arange(0.0, seconds, dt)
    heading = 0.8 * np.sin(0.3 * t) + 0.4 * t
    course = np.stack([np.cos(0.7 * t), np.sin(0.5 * t + 1.0)], 1) if sideways else \
        np.stack([np.cos(heading), np.sin(heading)], 1)
    xy = np.cumsum(0.25 * course * dt, axis=0)
    T_robot_body = make_T(Rotation.from_euler("z", -yaw_deg, degrees=True).as_matrix(), [lever_m, 0.0, 0.2])
    tilt = math.radians(tilt_deg)
    poses = [make_T(Rotation.from_euler("zyx", [h, tilt * math.sin(1.1 * s), tilt * math.sin(0.7 * s + 1)]).as_matrix(),
                    [x, y, 0.0]) @ T_robot_body for s, h, (x, y) in zip(t, heading, xy, strict=True)]
    return t, np.array(poses)


@pytest.mark.parametrize(("yaw_deg", "lever_m", "tilt_deg"), [(1.5, 0.0, 0.0), (-0.8, 0.06, 0.0), (2.0, -0.04, 4.0)])
def test_travel_heading_finds_the_direction_of_travel(yaw_deg, lever_m, tilt_deg):
    fit = travel_heading(*_drive(yaw_deg, lever_m, tilt_deg=tilt_deg))
    assert fit.usable
    # tilting while the travel stays level leaves a few hundredths of a degree (0.05 at 4 deg)
    assert abs(fit.yaw_deg - yaw_deg) < 0.05 if tilt_deg == 0 else 0.1
    assert abs(fit.lever_m - lever_m) < 0.01


def test_travel_heading_refuses_a_body_that_moves_sideways():
    fit = travel_heading(*_drive(0.0, 0.0, sideways=True))
    assert fit.sideways > TRAVEL_MAX_SIDEWAYS and not fit.usable


def test_travel_heading_refuses_a_body_carried_by_hand():
    """The simulator's hand-carried body (turning and tilting as a wrist does, whatever its travel)."""
    path = HandPath((0.6, 0.4), 0.25, np.random.default_rng(3))
    t = np.arange(0.0, 30.0, 0.05)
    assert not travel_heading(t, np.array([path.T_world_robot(s) for s in t])).usable


def test_travel_heading_refuses_a_cube_mounted_turned():
    assert not travel_heading(*_drive(30.0, 0.0)).usable


def test_travel_heading_keeps_pieces_apart():
    """Two drives in one recording: no velocity across the jump between them."""
    t, poses = _drive(1.0, 0.0)
    half = len(t) // 2
    poses[half:, :3, 3] += [5.0, -3.0, 0.0]  # the second drive elsewhere, straight after the first
    first = np.zeros(len(t), bool)
    first[[0, half]] = True
    fit = travel_heading(t, poses, first)
    assert fit.usable and abs(fit.yaw_deg - 1.0) < 0.05
    assert not travel_heading(t, poses).usable  # taken as one piece, the jump reads as sideways motion


def _frame_yaw_deg(layout, truth) -> float:
    """The calibrated body frame's yaw from the true body frame (degrees, about the truth's z)."""
    G = best_fit_transform(truth.corners_m.reshape(-1, 3), layout.corners_m.reshape(-1, 3))
    return float(Rotation.from_matrix(G[:3, :3]).as_rotvec(degrees=True)[2])


def test_travel_heading_refuses_a_circle_at_one_speed():
    """test_body_tilting_robot's robot: a heading off and a body ahead of the turning point both move
    it sideways at a constant rate, so the drive cannot tell them apart."""
    t = np.arange(0.0, 8.0, 0.05)
    fit = travel_heading(t, np.array([tilting_robot._pose(s) for s in t]))
    assert fit.independence < 0.01 and not fit.usable


def _weaving_pose(t: float) -> np.ndarray:
    """A robot driving a figure eight (turning both ways, at changing speed), heading along it,
    rolling by 4 deg about its ground point; its cube 0.3 m up."""
    heading = math.atan2(0.25 * math.cos(t), 0.2 * math.cos(0.5 * t))
    R = Rotation.from_euler("zyx", [heading, 0.0, math.radians(4.0) * math.sin(1.1 * t)]).as_matrix()
    return make_T(R, [0.4 * math.sin(0.5 * t), 0.25 * math.sin(t), 0.0]) @ make_T(np.eye(3), [0.0, 0.0, 0.3])


def _frame_yaw_deg(layout, truth) -> float:
    """The calibrated body frame's yaw from the true body frame (degrees, about the truth's z)."""
    G = best_fit_transform(truth.corners_m.reshape(-1, 3), layout.corners_m.reshape(-1, 3))
    return float(Rotation.from_matrix(G[:3, :3]).as_rotvec(degrees=True)[2])


def test_calibrate_body_turns_the_frame_to_the_travel(monkeypatch):
    """The weaving robot's hand-built cube: the markers' frame is off the truth's in yaw; with the
    option the calibrated frame follows the travel, the markers' placement on it unchanged."""
    monkeypatch.setattr(tilting_robot, "_pose", _weaving_pose)
    frames, extrinsics, intrinsics, layout, truth = tilting_robot._scene()
    monkeypatch.setattr(bundle, "cube_frames", lambda *_a, **_k: list(frames))
    report = calibrate_body({name: [] for name in extrinsics}, extrinsics, intrinsics, layout,
                            body=BodyCalibrationParams(heading_from_travel=True))
    t = np.arange(0.0, 8.0, 0.05)
    assert travel_heading(t, np.array([_weaving_pose(s) for s in t])).usable
    markers_frame = _frame_yaw_deg(layout, truth)  # the nominal layout's best fit to the cube as built
    assert report.travel is not None and report.travel.usable
    assert abs(markers_frame) > 0.2
    # the knots' velocities (10 frames a second per camera) leave about 0.1 deg
    assert abs(_frame_yaw_deg(report.layout, truth)) < min(0.15, abs(markers_frame) / 2)
    errors = placement_errors(report.layout, truth)  # placement (frame aside) as without the option
    assert max(e[0] for e in errors.values()) < 0.1e-3 and max(e[1] for e in errors.values()) < 0.05
