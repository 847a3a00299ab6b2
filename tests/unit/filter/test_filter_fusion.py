"""FilterFusion on synthetic sightings: track start, reordering, fixed-rate output, and a robot
that leaves the view is reported as not seen, never extrapolated."""

import numpy as np
from scipy.spatial.transform import Rotation
from test_joint_and_filter import CAMS, INTR, LAYOUT, detections

from cubetrack.core.geometry import make_T
from cubetrack.core.records import CubeSighting
from cubetrack.estimate.pose import estimate_cube
from cubetrack.fuse.fusion import FilterFusion, FusionParams

V = np.array([0.25, 0.0, 0.0])


def truth(t):
    return make_T(Rotation.from_euler("z", 20, degrees=True).as_matrix(), [-0.4 + V[0] * t, 0.1, 0.305])


def sightings(t_end, rng, t_start=0.0):
    """Three unsynchronised 7.5 fps cameras; sightings arrive 50 ms after capture."""
    out = []
    for k, cam in enumerate(CAMS):
        for t in np.arange(t_start + k * 0.044, t_end, 1 / 7.5):
            dets = detections(truth(t), CAMS[cam], rng, noise_px=0.2)
            est = estimate_cube(dets, LAYOUT, INTR, CAMS[cam], camera=cam, robot="bot", seq=0,
                                capture_time_s=t, arrival_time_s=t + 0.05)
            out.append(CubeSighting(cam, "bot", 0, t, t + 0.05, dets, est, CAMS[cam], INTR))
    return sorted(out, key=lambda s: s.arrival_time_s)


def run(fusion, items):
    poses = []
    for s in items:
        poses += fusion.add(s, s.arrival_time_s)
    return poses + fusion.flush(items[-1].arrival_time_s)


def test_track_starts_and_follows_motion_in_capture_order():
    rng = np.random.default_rng(0)
    poses = run(FilterFusion({"bot": LAYOUT}), sightings(3.0, rng))
    assert len(poses) > 50 and poses[0].time_s < 0.5
    times = [p.time_s for p in poses]
    assert times == sorted(times)  # reordered by capture time
    errors = [np.linalg.norm(p.position_m - truth(p.time_s)[:3, 3]) for p in poses]
    assert np.median(errors) < 0.002 and max(errors[5:]) < 0.01


def test_robot_out_of_view_is_not_extrapolated():
    rng = np.random.default_rng(1)
    items = sightings(1.5, rng) + sightings(4.0, rng, t_start=3.0)  # unseen from 1.5 s to 3 s
    items.sort(key=lambda s: s.arrival_time_s)
    poses = run(FilterFusion({"bot": LAYOUT}, FusionParams(output_rate_hz=30.0)), items)
    times = np.array([p.time_s for p in poses])
    assert not np.any((times > 1.5) & (times < 3.0))  # nothing invented while unseen
    assert np.any(times > 3.0)  # the track restarts when the robot is back
    fixed = [p for p in poses if not p.cameras]  # fixed-rate poses between sightings
    assert fixed and all(abs(p.time_s * 30.0 - round(p.time_s * 30.0)) < 1e-6 for p in fixed)


def test_sighting_later_than_the_reorder_delay_is_dropped_not_used():
    rng = np.random.default_rng(2)
    items = sightings(2.0, rng)
    late = items.pop(10)
    fusion = FilterFusion({"bot": LAYOUT}, FusionParams(reorder_delay_s=0.1))
    poses = run(fusion, items + [CubeSighting(late.camera, late.robot, late.seq, late.capture_time_s,
                                             late.capture_time_s + 1.5, late.detections, late.estimate,
                                             late.T_world_cam, late.intrinsics)])
    assert fusion.stats["late sighting"] == 1
    assert all(p.time_s != late.capture_time_s for p in poses)
