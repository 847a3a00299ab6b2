"""Markers found at their predicted corners (no candidate search), and every way that falls back."""

from __future__ import annotations

import numpy as np
import pytest
from numba.types import Array
from scenes import T_WORLD_CAM_UP, marker_corners_px, render_in_front
from test_detect_markers import INTR, _two_markers_image, facing

from cubetrack.core.layout import paper_cube_layout
from cubetrack.core.records import Detection
from cubetrack.detect import predicted as predicted_module
from cubetrack.detect.detector import CornerRefinement, Detector, DetectorParams
from cubetrack.detect.predicted import cell_errors, marker_cells, marker_reads, predicted_markers, predicted_view

SIZE_M = 0.08
POSES = [facing(0.7, 30, 10, 15, 0.05, -0.03), facing(1.2, -40, 25, 100, -0.2, 0.1), facing(0.9, 5, 50, 200, 0.0, 0.1)]


@pytest.fixture(scope="module")
def scenes() -> list[tuple[np.ndarray, np.ndarray]]:
    out = []
    for i, T in enumerate(POSES):
        img = render_in_front(INTR, [(T, "DICT_4X4_50", 7, SIZE_M, 0.04)], blur_px=0.7, noise_std=2.0,
                              jpeg_quality=85, rng=np.random.default_rng(i))
        out.append((img, marker_corners_px(INTR, T_WORLD_CAM_UP, T_WORLD_CAM_UP @ T, SIZE_M)))
    return out


def _prediction(corners_px: np.ndarray, marker_id: int = 7) -> Detection:
    return Detection(marker_id, np.asarray(corners_px, dtype=float), 0.0, "DICT_4X4_50")


def _box(corners_px: np.ndarray, grow_px: float = 20.0) -> tuple[int, int, int, int]:
    (x0, y0), (x1, y1) = corners_px.min(axis=0) - grow_px, corners_px.max(axis=0) + grow_px
    return max(int(x0), 0), max(int(y0), 0), min(int(x1), INTR.width), min(int(y1), INTR.height)


@pytest.mark.parametrize("refinement", [CornerRefinement.EDGE, CornerRefinement.TEMPLATE])
def test_a_prediction_pixels_off_gives_the_searched_corners_without_a_search(scenes, refinement):
    """At a turn the prediction is pixels off: the fit from it must keep none of that (the filter would
    get its own prediction back as a measurement; 2 edge fits from 3 px off left up to 0.11 px here)."""
    det = Detector(DetectorParams(corner_refinement=refinement))
    for seed in range(5):
        rng = np.random.default_rng(seed)
        for gray, truth in scenes:
            box = _box(truth)
            searched = det.find(gray, [box], INTR)
            fast = det.find(gray, [box], INTR, predicted=[_prediction(truth + 3.0 * rng.choice([-1.0, 1.0], (4, 2)))])
            assert fast.predicted and not searched.predicted
            assert [d.marker_id for d in fast.detections] == [7]
            # the same edge fit, started elsewhere: the same corners to well under the fit's own error
            np.testing.assert_allclose(fast.detections[0].corners_px, searched.detections[0].corners_px, atol=0.01)
            assert np.abs(fast.detections[0].corners_px - truth).max() < 0.5


def test_a_wrong_id_or_a_marker_far_from_its_prediction_falls_back_to_the_search(scenes):
    det = Detector()
    gray, truth = scenes[0]
    box = _box(truth, 100.0)
    searched = det.find(gray, [box], INTR).detections
    for prediction in (_prediction(truth, marker_id=8),             # another id where the marker is
                       _prediction(truth + (80.0, 0.0))):            # the marker is far from its prediction
        found = det.find(gray, [box], INTR, predicted=[prediction])
        assert not found.predicted
        assert [d.marker_id for d in found.detections] == [7]
        np.testing.assert_array_equal(found.detections[0].corners_px, searched[0].corners_px)
    # one prediction reads, another is not there (nor in a box around it): not seen, as a search would not see it
    both = det.find(gray, [box], INTR, predicted=[_prediction(truth), _prediction(truth + (80.0, 0.0), 9)])
    assert both.predicted and [d.marker_id for d in both.detections] == [7]


def test_a_marker_that_does_not_read_at_its_prediction_is_searched_for_near_it():
    gray = _two_markers_image()              # ids 3 and 5, 60 px squares at x, y 300, 200 and 80, 300
    det = Detector()
    box = (40, 150, 420, 400)
    searched = det.find(gray, [box]).detections
    assert [d.marker_id for d in searched] == [3, 5]
    square = np.array([[-0.5, -0.5], [59.5, -0.5], [59.5, 59.5], [-0.5, 59.5]])
    at_3 = _prediction(square + (300.0, 200.0), 3)
    for at_5 in (_prediction(square + (80.0 + 12.0, 300.0), 5),           # off by more than the edge fit reaches
                 _prediction(np.roll(square + (80.0, 300.0), 1, axis=0), 5)):   # turned a quarter
        found = det.find(gray, [box], predicted=[at_3, at_5])
        assert found.predicted and [d.marker_id for d in found.detections] == [3, 5]
        np.testing.assert_allclose(found.detections[1].corners_px, searched[1].corners_px, atol=1e-6)
        np.testing.assert_allclose(found.detections[0].corners_px, searched[0].corners_px, atol=0.02)


def test_predictions_are_ignored_without_regions_or_for_inverted_markers_or_other_refinements(scenes):
    gray, truth = scenes[0]
    box = _box(truth)
    for params in (DetectorParams(detect_inverted_marker=True),
                   DetectorParams(corner_refinement=CornerRefinement.NONE)):
        assert not Detector(params).find(gray, [box], INTR, predicted=[_prediction(truth)]).predicted
    assert not Detector().find(gray, None, INTR, predicted=[_prediction(truth)]).predicted


def test_cells_read_the_dictionary_bits_and_an_empty_patch_is_unreadable(scenes):
    gray, truth = scenes[0]
    errors = cell_errors(gray, np.array([truth, truth]), [_prediction(truth), _prediction(truth, 8)])
    assert errors[0].tolist() == [0, 0] and errors[1, 0] == 0 and errors[1, 1] > 0   # 8's bits are not 7's
    assert cell_errors(np.full_like(gray, 128), truth[None], [_prediction(truth)]).tolist() == [[-1, -1]]
    shifted = cell_errors(gray, (truth + (truth[1] - truth[0]) / 6.0)[None], [_prediction(truth)])  # a cell right
    assert shifted[0, 0] > 0
    assert marker_cells("DICT_4X4_50", 7).shape == (6, 6)


def test_predicted_markers_keep_the_faces_that_face_the_camera_inside_the_image():
    layout = paper_cube_layout()
    M = len(layout.marker_ids)
    square = np.array([[100.0, 100.0], [140.0, 100.0], [140.0, 140.0], [100.0, 140.0]])
    quads = np.repeat(square[None], M, axis=0)
    quads[1] = square[::-1]                                  # counter-clockwise: seen from behind
    quads[2] = square * 0.1                                  # 16 px around
    quads[3] = square + (500.0, 0.0)                         # reaches x = 640
    kept = predicted_markers(quads, layout, INTR.width, INTR.height, min_perimeter_px=19.0, border_px=3.0)
    assert [d.marker_id for d in kept] == [int(i) for k, i in enumerate(layout.marker_ids) if k not in (1, 2, 3)]
    assert all(d.dictionary == layout.marker_dictionaries[0] and d.area_px2 == pytest.approx(1600.0) for d in kept)


def test_the_predicted_path_runs_kernels_compiled_when_the_detector_was_built(scenes):
    """Planning (predicted_markers) and a frame found at its predictions run no kernel compile: each
    call's argument types are those the detector compiled at start-up (a read-only array, or another
    integer type, would be a new signature compiled on a frame)."""
    from cubetrack.detect import predicted as module

    det = Detector()
    kernels = (module._facing_quads, module._cell_errors, module._grown_box)
    built = [set(k.signatures) for k in kernels]
    assert all(built)
    gray, truth = scenes[1]
    layout = paper_cube_layout()
    predicted_markers(np.repeat(truth[None], len(layout.marker_ids), axis=0), layout, INTR.width, INTR.height,
                      19.0, 3)
    T_cam_cube = np.eye(4)
    T_cam_cube[:3, 3] = (0.05, 0.02, 0.9)
    assert predicted_view(T_cam_cube, layout, INTR, 0.05, det.params).box is not None
    assert det.find(gray, [_box(truth)], INTR, predicted=[_prediction(truth)]).predicted
    # this process's signatures (other tests' calls included) are the start-up ones: no read-only arrays
    assert [set(k.signatures) for k in kernels] == built
    read_only = [t for k in kernels for sig in k.signatures for t in sig if isinstance(t, Array) and not t.mutable]
    assert not read_only, read_only


def test_a_marker_predicted_with_cells_narrower_than_a_pixel_is_not_searched_for():
    gray = _two_markers_image()              # ids 3 and 5, 60 px squares at x, y 300, 200 and 80, 300
    det = Detector()
    at_3 = _prediction(np.array([[-0.5, -0.5], [59.5, -0.5], [59.5, 59.5], [-0.5, 59.5]]) + (300.0, 200.0), 3)
    # id 5 predicted edge-on where it is: 70 x 5 px, under a pixel per cell (6 cells across) on its short
    # sides; the box around it holds the whole marker, which OpenCV would find there
    thin = np.array([[75.0, 327.0], [145.0, 327.0], [145.0, 332.0], [75.0, 332.0]])
    found = det.find(gray, [(40, 150, 420, 400)], predicted=[at_3, _prediction(thin, 5)])
    assert found.predicted and [d.marker_id for d in found.detections] == [3]
    # 6 px on its short sides (a pixel per cell): searched for, and found
    wider = det.find(gray, [(40, 150, 420, 400)], predicted=[at_3, _prediction(thin + [[0, -0.5], [0, -0.5],
                                                                                      [0, 0.5], [0, 0.5]], 5)])
    assert [d.marker_id for d in wider.detections] == [3, 5]


def test_only_a_marker_that_may_be_there_is_searched_for_in_its_box(monkeypatch):
    """A box search costs an OpenCV detection: it is spent on a marker whose fit failed (moved off its
    prediction) or whose border is black but its cells another id's or rotation's, not on a valid quad
    without a dark border (nothing OpenCV could identify lies there)."""
    gray = _two_markers_image()              # ids 3 and 5, 60 px squares at x, y 300, 200 and 80, 300
    plain = gray.copy()
    plain[303:357, 83:137] = plain[305, 85]  # id 5's cells painted over with its border's black: a square, no bits
    square = np.array([[-0.5, -0.5], [59.5, -0.5], [59.5, 59.5], [-0.5, 59.5]])
    at_3, at_5 = _prediction(square + (300.0, 200.0), 3), _prediction(square + (80.0, 300.0), 5)
    det = Detector()
    boxes: list[tuple[int, int, int, int]] = []
    search = det._detect_box
    monkeypatch.setattr(det, "_detect_box",
                        lambda image, box, dropped: boxes.append(box) or search(image, box, dropped))
    found = det.find(plain, [(40, 150, 420, 400)], predicted=[at_3, at_5])
    assert found.predicted and [d.marker_id for d in found.detections] == [3] and boxes == []
    # the same square predicted as the marker turned a quarter (a dark border, other cells): searched, found
    turned = _prediction(np.roll(square + (80.0, 300.0), 1, axis=0), 5)
    found = det.find(gray, [(40, 150, 420, 400)], predicted=[at_3, turned])
    assert [d.marker_id for d in found.detections] == [3, 5] and len(boxes) == 1
    # predicted where there is no marker (it left): searched for, not seen
    gone = det.find(plain, [(40, 150, 420, 400)], predicted=[at_3, _prediction(square + (200.0, 320.0), 5)])
    assert [d.marker_id for d in gone.detections] == [3] and len(boxes) == 2


def test_a_dark_border_allows_the_readers_rate_of_the_border_cells_white(monkeypatch, scenes):
    """Reading takes OpenCV's limit (0.35 x 16 = 5 white border cells for DICT_4X4_50); the box search's dark
    border the same rate of the border's own 20 cells (7): a marker with 6 white border cells does not read but
    may be OpenCV's (searched for), one with 8 is not a marker there, nor is a patch without contrast."""
    gray, truth = scenes[0]
    errors = np.array([[0, 0], [5, 0], [6, 0], [7, 3], [8, 0], [-1, -1]])
    monkeypatch.setattr(predicted_module, "cell_errors", lambda *_: errors)
    read, bordered = marker_reads(gray, np.repeat(truth[None], len(errors), axis=0),
                                  tuple(_prediction(truth) for _ in errors), 0.6)
    assert read.tolist() == [True, True, False, False, False, False]
    assert bordered.tolist() == [True, True, True, True, False, False]
