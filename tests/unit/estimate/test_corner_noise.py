"""Each corner's noise from its marker's quad (issue 26): the border module's width across the
corner's sides, read off the detected corners, sets the corner's weight in the filter."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import invert_T, make_T, shoelace_area
from cubetrack.core.layout import paper_cube_layout
from cubetrack.core.records import Detection
from cubetrack.estimate.corner_noise import (
    EXPONENT,
    WIDE_MODULE_PX,
    border_module_px,
    corner_noise_factors,
    corner_noise_scale,
)
from cubetrack.estimate.match import match_faces
from cubetrack.estimate.reprojection import corner_set
from cubetrack.fuse.corner_filter import FilterParams, PoseFilter, _without_face, inverse_variances
from cubetrack.fuse.fusion import sighting_corner_sets

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
LAYOUT = paper_cube_layout()
T_WORLD_CAM = make_T(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), [-1.8, 0.0, 0.05])  # looks +x


def rectangle(width_px: float, height_px: float) -> np.ndarray:
    return np.array([[0.0, 0.0], [width_px, 0.0], [width_px, height_px], [0.0, height_px]]) + 100.0


def test_wide_border_modules_keep_the_nominal_noise_and_narrow_ones_follow_the_measured_law() -> None:
    assert np.allclose(border_module_px(rectangle(60, 60), 6), 10.0)
    assert np.allclose(corner_noise_scale(rectangle(60, 60), 6), 1.0)
    # a marker seen obliquely about its vertical axis: its top and bottom sides keep 10 px modules across
    # them, its left and right sides 2 px (12 px / 6): every corner meets one of each, the narrow one counts
    squashed = rectangle(12, 60)
    assert np.allclose(border_module_px(squashed, 6), 2.0)
    assert np.allclose(corner_noise_scale(squashed, 6), (WIDE_MODULE_PX / 2.0) ** EXPONENT)
    small = rectangle(9, 9)   # far away, head-on: 1.5 px modules
    assert np.allclose(corner_noise_scale(small, 6), (WIDE_MODULE_PX / 1.5) ** EXPONENT)
    assert corner_noise_scale(rectangle(1, 1), 6).max() <= 8.0   # bounded for a quad that is barely a marker
    # a quad narrower at one end (perspective), 12 px across: symmetric about its axis, every factor above 1,
    # and the path the tracker takes (a sighting's quads stacked, one compiled call) gives the same factors
    trapezoid = np.array([[100.0, 100.0], [112.0, 104.0], [112.0, 126.0], [100.0, 130.0]])
    scale = corner_noise_scale(trapezoid, 6)
    assert scale[1] == scale[2] and scale[0] == scale[3] and scale.min() > 1.0
    stacked = corner_noise_factors(np.concatenate([squashed, trapezoid]), [6, 6])
    assert stacked[4:].tolist() == scale.tolist() and np.allclose(stacked[:4], corner_noise_scale(squashed, 6))


def detections(T_world_cube: np.ndarray) -> tuple[Detection, ...]:
    """Exact corners of every face the camera sees (from the front, more than ~10° off edge-on)."""
    T_cam_cube = invert_T(T_WORLD_CAM) @ T_world_cube
    out = []
    for m in LAYOUT.markers:
        T = T_cam_cube @ m.T_cube_marker
        if -T[:3, 2] @ T[:3, 3] / np.linalg.norm(T[:3, 3]) < 0.2:
            continue
        px, _ = cv2.projectPoints(m.corners_cube_m(), cv2.Rodrigues(T_cam_cube[:3, :3])[0], T_cam_cube[:3, 3], K, None)
        px = px.reshape(4, 2)
        out.append(Detection(m.marker_id, px, shoelace_area(px), "DICT_4X4_50"))
    return tuple(out)


@pytest.mark.parametrize("readout_s", [0.0, 0.03])
def test_corner_sets_carry_each_corners_noise_from_its_own_quad(readout_s: float) -> None:
    """Two faces, one near head-on and one oblique: the sets (one per frame, or one per face under a
    rolling shutter) carry each corner's factor, in the order of their points, and keep it aligned
    when a face is dropped."""
    T_world_cube = make_T(cv2.Rodrigues(np.array([0.0, 0.0, np.radians(25.0)]))[0], [0.0, 0.0, 0.0])
    intrinsics = CameraIntrinsics(640, 480, K, np.zeros(5), "cam", readout_s=readout_s)
    matches = match_faces(detections(T_world_cube), LAYOUT, intrinsics, T_WORLD_CAM, T_world_cube, gate_px=5.0)
    assert len(matches) == 2
    expected = np.concatenate([corner_noise_scale(m.detection.corners_px, 6) for m in matches])
    assert sorted(np.unique(expected.round(6)))[0] == 1.0 and expected.max() > 2.0   # the oblique face's: noisier
    sets = sighting_corner_sets(matches, intrinsics, T_WORLD_CAM, "cam", 1.0)
    assert len(sets) == (2 if readout_s else 1)
    assert np.array_equal(np.concatenate([s.noise_scale for s in sets]), expected)
    if not readout_s:
        assert np.array_equal(corner_set(matches, intrinsics, T_WORLD_CAM, "cam", 1.0).noise_scale, expected)
    noise_px = FilterParams().corner_noise_px
    assert np.allclose(inverse_variances(sets, noise_px), 1.0 / (noise_px * expected) ** 2)
    assert np.allclose(inverse_variances(sets, noise_px, by_width=False), 1.0 / noise_px**2)
    kept = _without_face(sets, 0)
    assert np.array_equal(np.concatenate([s.noise_scale for s in kept]), expected[4:])
    assert not np.array_equal(expected[:4], expected[4:])
    plain = [dataclasses.replace(s, noise_scale=None) for s in sets]
    assert np.allclose(inverse_variances(plain, noise_px), 1.0 / noise_px**2)


def test_under_a_rolling_shutter_each_corner_is_taken_at_its_own_rows_instant() -> None:
    """A face's set is at its mean row's instant and each corner at its own row's, on a host clock
    (float64 even when the detector's corners are float32: a float32 offset would turn the clock's
    seconds to float32, 128 s steps at 1.75e9); dropping a face keeps them aligned."""
    T_world_cube = make_T(cv2.Rodrigues(np.array([0.0, 0.0, np.radians(25.0)]))[0], [0.0, 0.0, 0.0])
    readout_s, stamp_s = 0.03, 1_750_000_000.25
    intrinsics = CameraIntrinsics(640, 480, K, np.zeros(5), "cam", readout_s=readout_s)
    matches = match_faces(detections(T_world_cube), LAYOUT, intrinsics, T_WORLD_CAM, T_world_cube, gate_px=5.0)
    matches = [dataclasses.replace(m, detection=dataclasses.replace(
        m.detection, corners_px=m.detection.corners_px.astype(np.float32))) for m in matches]
    sets = sighting_corner_sets(matches, intrinsics, T_WORLD_CAM, "cam", stamp_s)
    rows = np.concatenate([m.detection.corners_px[:, 1] for m in matches]).astype(np.float64)
    expected = stamp_s + (rows - 239.5) * readout_s / 480
    times = np.concatenate([s.corner_times_s() for s in sets])
    assert times.dtype == np.float64 and np.abs(times - expected).max() < 1e-6
    assert np.ptp(times[:4]) > 1e-4   # the face's rows span a tenth of a millisecond and more
    assert [s.time_s for s in sets] == pytest.approx([t.mean() for t in np.split(expected, len(sets))], abs=1e-6)
    assert np.array_equal(np.concatenate([s.corner_times_s() for s in _without_face(sets, 0)]), times[4:])


def test_the_filter_leans_on_the_corners_its_noise_says_are_good() -> None:
    """The same 0.5 px error on the oblique face's corners (1.5 px border modules) moves the filter's
    pose less than on the head-on face's (3.4 px): each corner's weight is its own."""
    T_world_cube = make_T(cv2.Rodrigues(np.array([0.0, 0.0, np.radians(25.0)]))[0], [0.0, 0.0, 0.0])
    intrinsics = CameraIntrinsics(640, 480, K, np.zeros(5), "cam")
    dets = detections(T_world_cube)
    scales = [corner_noise_scale(d.corners_px, 6).mean() for d in dets]
    assert len(dets) == 2 and min(scales) == 1.0 and max(scales) > 2.0
    moves = {}
    for shifted in range(2):
        bad = tuple(dataclasses.replace(d, corners_px=d.corners_px + 0.5 * (k == shifted)) for k, d in enumerate(dets))
        matches = match_faces(bad, LAYOUT, intrinsics, T_WORLD_CAM, T_world_cube, gate_px=5.0)
        f = PoseFilter(FilterParams(), 0.0, T_world_cube, np.diag(np.repeat([1e-4, 1e-3, 0.01, 0.1], 3)),
                       np.zeros(3), np.zeros(3))
        assert f.update([corner_set(matches, intrinsics, T_WORLD_CAM, "cam", 0.0)]).accepted
        which = "oblique" if scales[shifted] > 1.0 else "head-on"
        moves[which] = float(np.linalg.norm(f.position_m - T_world_cube[:3, 3]))
    assert moves["oblique"] < 0.8 * moves["head-on"], moves   # measured 1.3 / 1.9 mm (one noise: 3.0 / 2.9)
