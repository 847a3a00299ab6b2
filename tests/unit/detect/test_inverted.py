"""Inverted markers through every corner refinement, and the detector's drop counts.

Ground truth by construction: a marker rendered through a wide-angle lens (the template fit
tests' renderer) and its negative. With ``detect_inverted_marker`` the negative's markers are
found in the negated negative, i.e. in the original image: every refinement must give the
negative exactly the corners it gives the original, and those must be where the marker is."""

from __future__ import annotations

import numpy as np
import pytest
from test_template_fit import DICT, MARKER_ID, SCENES, camera, oblique_square, render

from cubetrack.detect.detector import DROP_QUAD, CornerRefinement, Detector, DetectorParams
from cubetrack.detect.template_fit import distort_px


@pytest.mark.parametrize("refinement", list(CornerRefinement))
def test_an_inverted_marker_gets_the_corners_of_its_negative(refinement):
    lens = camera()
    centre, half, squash, turn = SCENES[1]
    truth_ideal = oblique_square(centre, half, squash, turn)
    image = render(truth_ideal, lens)
    inverted = 255 - image
    normal = Detector(DetectorParams(corner_refinement=refinement), [DICT]).find(image, lens=lens)
    assert Detector(DetectorParams(corner_refinement=refinement), [DICT]).detect(inverted, lens=lens) == ()
    both = Detector(DetectorParams(corner_refinement=refinement, detect_inverted_marker=True), [DICT])
    found = both.find(inverted, lens=lens)
    assert [d.marker_id for d in found.detections] == [MARKER_ID] == [d.marker_id for d in normal.detections]
    np.testing.assert_array_equal(found.detections[0].corners_px, normal.detections[0].corners_px)
    # the normal marker is still found by the same detector (both polarities, one image each)
    assert [d.marker_id for d in both.detect(image, lens=lens)] == [MARKER_ID]
    error_px = np.abs(found.detections[0].corners_px - distort_px(truth_ideal, lens.K, lens.dist)).max()
    assert error_px < (1.5 if refinement in (CornerRefinement.NONE, CornerRefinement.CONTOUR) else 0.6), error_px


def test_markers_dropped_after_detection_are_counted_by_reason():
    lens = camera()
    image = render(oblique_square(*SCENES[0]), lens)
    assert Detector(DetectorParams(), [DICT]).find(image).dropped == {}
    too_small = Detector(DetectorParams(min_area_px2=1e6), [DICT]).find(image)
    assert too_small.detections == () and too_small.dropped == {DROP_QUAD: 1}
    both = Detector(DetectorParams(min_area_px2=1e6, detect_inverted_marker=True), [DICT])
    assert both.find(np.concatenate([image, 255 - image], axis=1)).dropped == {DROP_QUAD: 2}


def test_the_run_summary_sums_the_drops_and_is_loud_when_no_pose_came_of_them():
    from cubetrack.app.tracker import TrackStats
    from cubetrack.cli.track import dropped_line

    stats = TrackStats()
    assert dropped_line(stats) == "markers dropped after detection: none"
    stats.dropped_detections.update({DROP_QUAD: 2})
    stats.dropped_detections.update({DROP_QUAD: 1, "edge fit failed": 4})
    line = dropped_line(stats)
    assert "edge fit failed: 4" in line and f"{DROP_QUAD}: 3" in line and "WARNING" in line
    stats.poses["robot"] += 1
    assert "WARNING" not in dropped_line(stats)
