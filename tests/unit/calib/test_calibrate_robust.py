"""The robust method's parts on exact synthetic corners: outlier rejection, averaging + PnP,
the IPPE flip of per-frame poses; and its corner measurement (the detector's edge fit with the
lens model) on rendered frames."""

import numpy as np
import pytest
from calib_scene import CAMERAS, K, camera, frame, look_at, true_corners

from cubetrack.calib.extrinsics import (
    EDGE_FIT,
    CalibrationMethod,
    CalibrationParams,
    Sighting,
    calibrate_robust,
    collect_sightings,
    inlier_frames,
)
from cubetrack.core.cameras import CameraIntrinsics, WorldConfig
from cubetrack.core.geometry import rotation_angle, shoelace_area
from cubetrack.core.records import Detection, Frame
from cubetrack.detect.detector import CornerRefinement, Detector, DetectorParams, decode_gray
from cubetrack.detect.edge_fit import refine_corners_edges

INTR = CameraIntrinsics(640, 480, K, np.zeros(5))


def sightings_from(corners_list):
    out = []
    for c in corners_list:
        out.append(Sighting(0, Detection(0, c, shoelace_area(c)), np.eye(4), None))
    return out


def test_inlier_frames_drops_strays():
    rng = np.random.default_rng(0)
    base = true_corners(CAMERAS["cam1"])
    corners = np.array([base + rng.normal(0, 0.05, base.shape) for _ in range(30)])
    corners[5] += [3.0, 0.0]  # camera bumped in one frame
    corners[9, 2] += [0.0, -2.0]  # one corner wrong
    mask = inlier_frames(corners, 1.0)
    assert not mask[5] and not mask[9]
    assert mask.sum() == 28


def test_calibrate_robust_recovers_the_pose_despite_outliers():
    rng = np.random.default_rng(1)
    T = CAMERAS["cam2"]
    base = true_corners(T)
    corners = [base + rng.normal(0, 0.2, base.shape) for _ in range(60)]
    corners += [base + rng.normal(0, 0.2, base.shape) + [6.0, -4.0] for _ in range(10)]
    ext, inliers = calibrate_robust(sightings_from(corners), WorldConfig(), INTR, CalibrationParams())
    assert inliers == 60
    assert np.linalg.norm(ext.T_world_cam[:3, 3] - T[:3, 3]) < 0.01
    assert rotation_angle(ext.T_world_cam[:3, :3], T[:3, :3], "deg") < 0.15
    assert ext.method == "robust" and ext.samples == 60


def test_spread_ignores_ippe_flips():
    """Per-frame poses whose better IPPE solution is the flipped one are scored by the solution
    nearer the result, so one flip does not inflate the spread by degrees."""
    T = CAMERAS["cam3"]
    base = true_corners(T)
    flipped = np.eye(4)
    flipped[:3, :3] = T[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # far-off rotation
    sightings = [Sighting(i, Detection(0, base, shoelace_area(base)), T, flipped) for i in range(5)]
    sightings.append(Sighting(5, Detection(0, base, shoelace_area(base)), flipped, T))
    ext, _ = calibrate_robust(sightings, WorldConfig(), INTR, CalibrationParams())
    assert ext.spread_rotation_deg < 0.1


@pytest.mark.parametrize("name", sorted(CAMERAS))
def test_robust_corners_are_unbiased(name):
    """On rendered frames (3 cm paper margin on a grey floor, blur, noise, JPEG) the corners the
    robust method measures are within 0.08 px of the truth, per frame and on average."""
    T = CAMERAS[name]
    truth = true_corners(T)
    cam, rng = camera(T), np.random.default_rng(7)
    frames = [Frame(name, i, 0.1 * i, 0.1 * i, frame(cam, rng)) for i in range(8)]
    sightings, read, skipped = collect_sightings(frames, WorldConfig(), INTR, CalibrationParams())
    assert len(sightings) == 8 and not skipped
    refined = np.array([s.detection.corners_px - truth for s in sightings])
    assert np.linalg.norm(refined.mean(axis=0), axis=1).max() < 0.08
    assert np.linalg.norm(refined, axis=2).mean() < 0.08


def test_the_robust_method_measures_with_the_chosen_refinement():
    """corner_refinement selects among the detector's methods; OpenCV's unrefined corners are
    ~0.5 px inside the marker (docs/detection.md), the edge fit's are not."""
    T = CAMERAS["cam2"]
    cam, truth = camera(T), true_corners(T)
    frames = [Frame("cam2", i, 0.1 * i, 0.1 * i, frame(cam, np.random.default_rng(i))) for i in range(3)]
    errors = {}
    for refinement in (CornerRefinement.EDGE, CornerRefinement.NONE):
        params = CalibrationParams(corner_refinement=refinement)
        sightings, _read, _skipped = collect_sightings(frames, WorldConfig(), INTR, params)
        errors[refinement] = np.mean([np.linalg.norm(s.detection.corners_px - truth, axis=1) for s in sightings])
    assert errors[CornerRefinement.EDGE] < 0.1 < 0.3 < errors[CornerRefinement.NONE]
    cma = CalibrationParams(method=CalibrationMethod.CMA, corner_refinement=CornerRefinement.NONE)
    sightings, _read, _skipped = collect_sightings(frames, WorldConfig(), INTR, cma)  # cma: [detector] corners
    assert np.mean([np.linalg.norm(s.detection.corners_px - truth, axis=1) for s in sightings]) < 0.2


def test_edge_refinement_gives_up_on_a_blank_image():
    gray = np.full((480, 640), 128, np.uint8)
    c = np.array([[300.0, 200.0], [340.0, 200.0], [340.0, 240.0], [300.0, 240.0]])
    dist = np.array([-0.25, 0.08, 0.0, 0.0, 0.0])
    assert np.all(np.isnan(refine_corners_edges(gray, c, 6, K=K, dist=dist)))
    assert np.all(np.isnan(refine_corners_edges(gray, c, 6, K=K, dist=dist, **EDGE_FIT)))


def test_edge_refinement_handles_lens_distortion():
    """With barrel distortion the marker's edges are curved in the image; the edge fit with the
    lens model samples along the straight undistorted edges, so its corners land on the true
    (distorted) projections, and without the model they do not."""
    dist = np.array([-0.25, 0.08, 0.0, 0.0, 0.0])
    T = look_at((1.2, 1.0, 0.9), (0.4, -0.3, 0.0))  # marker ~150 px right of the image centre
    truth = true_corners(T, dist)
    gray = decode_gray(frame(camera(T, dist), np.random.default_rng(0), noise=0.0))
    detector = Detector(DetectorParams(corner_refinement=CornerRefinement.NONE))
    (det,) = [d for d in detector.detect(gray) if d.marker_id == 0]
    with_model = refine_corners_edges(gray, det.corners_px, 6, K=K, dist=dist, **EDGE_FIT)
    without = refine_corners_edges(gray, det.corners_px, 6, **EDGE_FIT)
    err_with = np.linalg.norm(with_model - truth, axis=1)
    err_without = np.linalg.norm(without - truth, axis=1)
    assert err_with.max() < 0.1, err_with
    assert err_without.max() > 2 * err_with.max()
