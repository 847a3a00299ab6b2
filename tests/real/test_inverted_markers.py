"""Inverted (white-on-black) markers on a real photograph: a frame of ../shared/data/real/caliscope-4cam
(its README), a hand-held ChArUco board printed inverted, seen by a calibrated 1280x720 webcam.

Reference: the board's pose from its own chessboard corners (OpenCV's CharucoDetector on the
negated image, PnP through the camera's calibration: 0.09 px RMS); each marker's corners are where
that pose puts them. Every corner refinement finds the board's markers with
``detect_inverted_marker = true`` and none without it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cubetrack.core.errors import ParamsError
from cubetrack.detect.detector import CornerRefinement, Detector, DetectorParams
from cubetrack.io.caliscope import read_caliscope_rig

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real" / "caliscope-4cam"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=f"{DATA} not present (the real footage is in ../shared)")
CAMERA, FRAME = 3, 79
# median / largest corner error against the board's pose (px); measured 0.17-0.22 / 0.40-0.55 for the
# fitted refinements, 0.43-0.74 / 1.3-1.4 for OpenCV's subpix, contour and none
TOLERANCE_PX = {CornerRefinement.EDGE: (0.35, 0.8), CornerRefinement.TEMPLATE: (0.35, 0.8),
                CornerRefinement.APRILTAG: (0.35, 0.8), CornerRefinement.SUBPIX: (0.7, 2.0),
                CornerRefinement.CONTOUR: (1.0, 2.0), CornerRefinement.NONE: (1.0, 2.0)}


@pytest.fixture(scope="module")
def scene():
    rig = read_caliscope_rig(DATA)
    capture = cv2.VideoCapture(str(DATA / "video" / f"cam_{CAMERA}.mp4"))
    for _ in range(FRAME + 1):
        ok, image = capture.read()
        assert ok
    capture.release()
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    b = rig.board
    cv_board = cv2.aruco.CharucoBoard((b.squares_x, b.squares_y), b.square_size_m, b.marker_size_m,
                                      cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, b.dictionary)))
    corners, ids, _, _ = cv2.aruco.CharucoDetector(cv_board).detectBoard(255 - gray)
    intr = rig.intrinsics[CAMERA]
    obj = np.asarray(cv_board.getChessboardCorners())[ids.ravel()]
    ok, rvec, tvec = cv2.solvePnP(obj, corners, intr.K, intr.dist)
    assert ok and len(ids) >= 8
    truth = {int(i): cv2.projectPoints(np.asarray(c), rvec, tvec, intr.K, intr.dist)[0].reshape(4, 2)
             for i, c in zip(cv_board.getIds().ravel(), cv_board.getObjPoints(), strict=True)}
    return gray, intr, b.dictionary, truth


@pytest.mark.parametrize("refinement", list(CornerRefinement))
def test_every_refinement_finds_inverted_markers_where_the_board_is(scene, refinement):
    gray, intr, dictionary, truth = scene
    params = DetectorParams(dictionary=dictionary, corner_refinement=refinement)
    assert Detector(params).detect(gray, lens=intr) == ()          # dark-on-white only: nothing
    found = Detector(DetectorParams(dictionary=dictionary, corner_refinement=refinement,
                                    detect_inverted_marker=True)).find(gray, lens=intr)
    ids = [d.marker_id for d in found.detections]
    assert len(ids) >= 9 and set(ids) <= set(truth), ids
    assert not found.dropped
    # white-on-black only (the negative searched alone, as `cubetrack import` sets for this board): the same
    only = Detector(DetectorParams(dictionary=dictionary, corner_refinement=refinement, detect_inverted_marker=True,
                                   detect_normal_marker=False))
    alone = only.find(gray, lens=intr)
    assert [d.marker_id for d in alone.detections] == ids and alone.dropped == found.dropped
    np.testing.assert_array_equal([d.corners_px for d in alone.detections], [d.corners_px for d in found.detections])
    assert only.detect(255 - gray, lens=intr) == ()                 # the board's markers made dark-on-white
    errors = np.concatenate([np.linalg.norm(d.corners_px - truth[d.marker_id], axis=1) for d in found.detections])
    median_px, max_px = TOLERANCE_PX[refinement]
    assert np.median(errors) < median_px and errors.max() < max_px, (np.median(errors), errors.max())


def test_searching_for_neither_polarity_is_refused():
    with pytest.raises(ParamsError, match="detect_normal_marker = false needs detect_inverted_marker = true"):
        DetectorParams(detect_normal_marker=False)
