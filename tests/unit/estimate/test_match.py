"""The one matcher (estimate.match): detections -> faces of a body, with and without a predicted
pose, on exact projections of cubes at known poses."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scenes import look_at
from scipy.spatial.transform import Rotation
from test_estimate_poses import DISTORTED, PINHOLE, T_world_cube_at, cube_detections

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import EstimationError
from cubetrack.core.geometry import invert_T, make_T
from cubetrack.core.layout import CubeLayout, paper_cube_layout
from cubetrack.core.records import Detection
from cubetrack.estimate.marker import marker_pose
from cubetrack.estimate.match import body_detections, identify_faces, match_faces
from cubetrack.estimate.reprojection import associate, corner_set, reprojection_residuals_px

CUBE_M = 0.11
SAME_ID = paper_cube_layout(cube_size_m=CUBE_M)
DISTINCT = paper_cube_layout(cube_size_m=CUBE_M, distinct_ids=True)


def view(layout, intr=PINHOLE, yaw_deg=-10.0, eye=(1.0, 0.7, 0.9)):
    """(T_world_cam, T_world_cube, [(true face, detection)]) of a camera seeing three faces."""
    T_world_cube = T_world_cube_at(0.05, -0.05, yaw_deg)
    T_world_cam = look_at(eye, T_world_cube[:3, 3])
    return T_world_cam, T_world_cube, cube_detections(layout, intr, invert_T(T_world_cam) @ T_world_cube)


def test_body_detections_keep_the_bodys_ids_in_its_dictionary():
    c = np.zeros((4, 2))
    mine = Detection(3, c, 1.0, "DICT_4X4_50")
    unnamed = Detection(5, c, 1.0, "")
    other_dict = Detection(3, c, 1.0, "DICT_6X6_250")
    other_id = Detection(9, c, 1.0, "DICT_4X4_50")
    assert body_detections([other_id, mine, other_dict, unnamed], DISTINCT) == (mine, unnamed)


@pytest.mark.parametrize("layout", [SAME_ID, DISTINCT], ids=["one id", "distinct ids"])
@pytest.mark.parametrize("intr", [PINHOLE, DISTORTED], ids=["pinhole", "distorted"])
def test_both_ways_find_the_true_faces_and_pair_the_corners(layout, intr):
    T_world_cam, T_world_cube, truth = view(layout, intr)
    assert len(truth) == 3
    detections = [d for _f, d in truth]
    true_face = {id(d): f for f, d in truth}
    by_prediction = match_faces(detections, layout, intr, T_world_cam, T_world_cube)
    without = match_faces(detections, layout, intr, T_world_cam)
    assert [m.detection for m in by_prediction] == detections          # detection order
    assert [m.detection.area_px2 for m in without] == sorted((d.area_px2 for d in detections), reverse=True)
    for matches in (by_prediction, without):
        assert all(m.face == true_face[id(m.detection)] == layout.markers[m.marker].face for m in matches)
        for m in matches:
            np.testing.assert_array_equal(m.points_body_m, layout.corners_m[m.marker])
        # the pairs are right: the corners reproject onto the detections at the true pose
        s = corner_set(matches, intr, T_world_cam, "cam", 1.0)
        assert s.faces == tuple(m.face for m in matches)
        assert np.abs(reprojection_residuals_px(T_world_cube, [s])).max() < 1e-6
    assert all(m.observation is None for m in by_prediction)
    for m in without:
        assert m.observation.face == m.face and m.observation.marker_pose.detection is m.detection
        np.testing.assert_allclose(m.observation.T_world_cube, T_world_cube, atol=1e-6)


def test_without_a_prediction_it_is_identify_faces_over_the_marker_poses():
    T_world_cam, _T, truth = view(SAME_ID, DISTORTED, yaw_deg=5.0)
    detections = [d for _f, d in truth]
    poses = [marker_pose(d, 0.08, DISTORTED, polish=False) for d in detections]
    faces = identify_faces(poses, SAME_ID, T_world_cam)
    matches = match_faces(detections, SAME_ID, DISTORTED, T_world_cam)
    assert len(faces) == 3 and [m.face for m in matches] == [f.face for f in faces]
    for m, f in zip(matches, faces, strict=True):
        np.testing.assert_array_equal(m.observation.T_world_cube, f.T_world_cube)
        np.testing.assert_array_equal(m.observation.marker_pose.T_cam_marker, f.marker_pose.T_cam_marker)


def test_a_prediction_settles_faces_that_share_an_id():
    """One id on every face: which face a detection is, is where the prediction puts it. A
    prediction a little off still names every face right; one turned by a quarter turn about z
    puts each side face where its neighbour is seen, turned in the image, so nothing matches;
    one far off matches nothing."""
    T_world_cam, T_world_cube, truth = view(SAME_ID)
    detections = [d for _f, d in truth]
    true_faces = {id(d): f for f, d in truth}
    off = make_T(Rotation.from_euler("z", 4, degrees=True).as_matrix() @ T_world_cube[:3, :3],
                 T_world_cube[:3, 3] + [0.01, -0.01, 0.0])
    assert {id(m.detection): m.face for m in match_faces(detections, SAME_ID, PINHOLE, T_world_cam, off)} == true_faces
    quarter = T_world_cube @ make_T(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [0, 0, 0])
    assert match_faces(detections, SAME_ID, PINHOLE, T_world_cam, quarter) == ()
    far = make_T(T_world_cube[:3, :3], T_world_cube[:3, 3] + [0.3, 0.0, 0.0])
    assert match_faces(detections, SAME_ID, PINHOLE, T_world_cam, far) == ()
    assert corner_set((), PINHOLE, T_world_cam, "cam", 0.0) is None


def test_a_face_is_matched_once():
    T_world_cam, T_world_cube, truth = view(DISTINCT)
    (_f, d), *_ = truth
    twice = [d, Detection(d.marker_id, d.corners_px + 0.5, d.area_px2, d.dictionary)]
    assert len(match_faces(twice, DISTINCT, PINHOLE, T_world_cam, T_world_cube)) == 1
    assert len(match_faces(twice, DISTINCT, PINHOLE, T_world_cam)) == 1


@pytest.mark.parametrize("dist", [DISTORTED.dist, np.r_[DISTORTED.dist, np.zeros(7), 0.001, -0.002]],
                         ids=["compiled lens", "tilted sensor (OpenCV projects)"])
def test_a_prediction_matches_a_named_dictionarys_detection_to_its_faces_only(dist):
    """Two dictionaries, the same ids on both: a detection naming its dictionary takes a face of
    that dictionary only (where the prediction puts the other one's face with its id, nothing);
    one naming none takes the face with its id wherever it is; a face is still taken once."""
    intr = CameraIntrinsics(640, 480, DISTORTED.K, dist)
    other = "DICT_5X5_50"
    mixed = CubeLayout(DISTINCT.dictionary, tuple(dataclasses.replace(m, dictionary=other if m.face == "left" else "")
                                                   for m in DISTINCT.markers))
    T_world_cam, T_world_cube, truth = view(DISTINCT, intr)
    by_face = {f: d for f, d in truth}
    left = by_face["left"]
    named = {name: Detection(left.marker_id, left.corners_px, left.area_px2, name)
             for name in ("", DISTINCT.dictionary, other)}
    for name, expected in (("", "left"), (other, "left"), (DISTINCT.dictionary, None)):
        found = match_faces([named[name]], mixed, intr, T_world_cam, T_world_cube)
        assert [m.face for m in found] == ([expected] if expected else [])
    found = match_faces([named[other], named[""], by_face["front"]], mixed, intr, T_world_cam, T_world_cube)
    assert [(m.detection, m.face) for m in found] == [(named[other], "left"), (by_face["front"], "front")]


def test_a_camera_pose_that_is_not_rigid_is_an_error_either_way():
    T_world_cam, T_world_cube, truth = view(DISTINCT)
    bad = T_world_cam.copy()
    bad[:3, :3] *= 1.01
    for prediction in (None, T_world_cube):
        with pytest.raises(EstimationError, match="T_world_cam"):
            match_faces([d for _f, d in truth], DISTINCT, PINHOLE, bad, prediction)


def test_the_layout_carries_the_matchers_tables():
    for layout in (SAME_ID, DISTINCT):
        for k, m in enumerate(layout.markers):
            np.testing.assert_allclose(layout.T_marker_cube[k] @ m.T_cube_marker, np.eye(4), atol=1e-12)
            assert layout.sizes_m[k] == m.size_m and layout.marker_ids[k] == m.marker_id
            assert k in layout.indices_of(m.marker_id)
        for table in (layout.corners_m, layout.normals, layout.T_marker_cube, layout.sizes_m, layout.indices_of(1)):
            assert not table.flags.writeable
    assert SAME_ID.indices_of(1).tolist() == [0, 1, 2, 3, 4] and SAME_ID.has_repeated_ids
    assert DISTINCT.indices_of(3).tolist() == [2] and not DISTINCT.has_repeated_ids
    assert DISTINCT.indices_of(42).tolist() == [] and DISTINCT.ids == frozenset({1, 2, 3, 4, 5})


def test_associate_is_a_deprecated_name_for_the_matcher_and_corner_set():
    T_world_cam, T_world_cube, truth = view(SAME_ID)
    detections = [d for _f, d in truth]
    with pytest.warns(DeprecationWarning, match="corner_set"):
        old = associate(detections, SAME_ID, T_world_cube, T_world_cam, PINHOLE, "cam", 2.0, 12.0)
    new = corner_set(match_faces(detections, SAME_ID, PINHOLE, T_world_cam, T_world_cube), PINHOLE, T_world_cam,
                     "cam", 2.0)
    assert old.faces == new.faces
    np.testing.assert_array_equal(old.normalized, new.normalized)
    np.testing.assert_array_equal(old.points_cube_m, new.points_cube_m)
