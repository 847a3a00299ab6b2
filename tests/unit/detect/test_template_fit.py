"""Tracking's template corner refinement ([detector] corner_refinement = "template",
cubetrack.detect.template_fit) on markers rendered with exact corners: a marker with a white
margin on a darker background seen obliquely through a wide-angle lens, averaged over each
pixel's area (5 x 5 samples), blurred, noisy, 8-bit. The truth is where the renderer put the
corners; the edge fit (the default) is the reference it must beat."""

import functools

import cv2
import numpy as np
import pytest

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import undistort_points
from cubetrack.detect.detector import CornerRefinement, Detector, DetectorParams, aruco_dictionary
from cubetrack.detect.template_fit import (
    READ_SETTINGS,
    LensMap,
    TemplateFitSettings,
    distort_px,
    fast_template_corners,
    square_homography,
    square_homography_derivatives,
)

DICT, MARKER_ID = "DICT_4X4_50", 3
WIDTH, HEIGHT = 320, 240
SAMPLES = 5  # render samples per pixel along each axis
WIDE_LENS = (-0.3, 0.1, 0.0, 0.0, 0.0)


def camera(dist=WIDE_LENS) -> CameraIntrinsics:
    K = np.array([[260.0, 0.0, 158.7], [0.0, 260.0, 121.4], [0.0, 0.0, 1.0]])
    return CameraIntrinsics(WIDTH, HEIGHT, K, np.array(dist, float))


@functools.lru_cache(maxsize=2)
def ideal_samples(dist: tuple[float, ...]) -> np.ndarray:
    """(H SAMPLES, W SAMPLES, 3): where each render sample lies in the ideal pinhole image, homogeneous."""
    lens = camera(dist)
    offsets = (np.arange(SAMPLES) + 0.5) / SAMPLES - 0.5
    xs, ys = np.meshgrid(np.add.outer(np.arange(WIDTH), offsets).ravel(),
                         np.add.outer(np.arange(HEIGHT), offsets).ravel())
    ideal = undistort_points(np.stack([xs, ys], axis=-1), lens.K, lens.dist, lens.K)
    return np.concatenate([ideal, np.ones(ideal.shape[:2] + (1,))], axis=-1)


def render(corners_ideal_px: np.ndarray, lens: CameraIntrinsics, blur_px: float = 0.8, seed: int = 0) -> np.ndarray:
    """The image of marker MARKER_ID whose black square's corners are ``corners_ideal_px`` in the
    ideal pinhole image of ``lens`` (one module of white margin, a grey background), through the lens."""
    d = aruco_dictionary(DICT)
    modules = d.markerSize + 2
    cells = cv2.aruco.generateImageMarker(d, MARKER_ID, modules, borderBits=1) > 127
    m = ideal_samples(tuple(lens.dist)) @ np.linalg.inv(
        square_homography(corners_ideal_px, modules)).T
    u, v = m[..., 0] / m[..., 2], m[..., 1] / m[..., 2]   # marker coordinates, modules
    on_marker = (u >= 0) & (u < modules) & (v >= 0) & (v < modules)
    in_margin = (u > -1) & (u < modules + 1) & (v > -1) & (v < modules + 1)
    cell = cells[np.clip(v.astype(int), 0, modules - 1), np.clip(u.astype(int), 0, modules - 1)]
    reflectance = np.where(on_marker, cell, in_margin).astype(float) * 0.8 + np.where(in_margin, 0.1, 0.35)
    image = reflectance.reshape(HEIGHT, SAMPLES, WIDTH, SAMPLES).mean(axis=(1, 3)) * 230.0
    image = cv2.GaussianBlur(image, (0, 0), blur_px) + np.random.default_rng(seed).normal(0.0, 1.5, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def oblique_square(centre, half_px: float, squash: float, angle_deg: float) -> np.ndarray:
    """Corners (TL TR BR BL) of a square of half-side ``half_px`` squashed along y by ``squash``,
    turned by ``angle_deg``, with some perspective: a marker seen obliquely."""
    a = np.radians(angle_deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    unit = np.array([[-1.0, -1.0], [1.0, -1.0], [1.1, 1.0], [-1.1, 1.0]]) * [half_px, half_px * squash]
    return np.asarray(centre, float) + unit @ R.T


def detected_corners(image: np.ndarray, refinement: CornerRefinement, lens: CameraIntrinsics | None) -> np.ndarray:
    found = Detector(DetectorParams(corner_refinement=refinement), [DICT]).detect(image, lens=lens)
    assert [d.marker_id for d in found] == [MARKER_ID]
    return found[0].corners_px


SCENES = [  # centre (ideal px), half side px, squash, turn deg: head-on to strongly foreshortened, near the edge
    ((150.0, 118.0), 26.0, 1.0, 4.0), ((95.0, 80.0), 24.0, 0.5, 25.0), ((228.0, 160.0), 25.0, 0.35, -30.0),
    ((70.0, 175.0), 20.0, 0.6, 60.0)]


@functools.lru_cache(maxsize=4)
def corner_errors(refinement: CornerRefinement, lens_known: bool) -> np.ndarray:
    lens = camera()
    errors = []
    for seed, (centre, half, squash, turn) in enumerate(SCENES):
        truth_ideal = oblique_square(centre, half, squash, turn)
        image = render(truth_ideal, lens, seed=seed)
        truth = distort_px(truth_ideal, lens.K, lens.dist)
        errors.append(detected_corners(image, refinement, lens if lens_known else None) - truth)
    return np.array(errors)


def test_template_corners_are_several_times_closer_to_the_truth_than_the_edge_fit():
    edge = np.sqrt(np.mean(corner_errors(CornerRefinement.EDGE, True) ** 2))
    template = corner_errors(CornerRefinement.TEMPLATE, True)
    rms = np.sqrt(np.mean(template ** 2))
    assert rms < 0.02, f"template corners {rms:.3f} px RMS from the truth"  # measured 0.006 (edge fit 0.10)
    assert rms < edge / 5.0, f"template {rms:.3f} px against the edge fit's {edge:.3f} px"
    assert np.abs(template).max() < 0.05


def test_the_template_fit_follows_the_lens():
    """The same images with the lens taken as a pinhole: the straight-sided model misses the
    curved marker, so the lens model is what the refinement's accuracy rests on."""
    with_lens = np.sqrt(np.mean(corner_errors(CornerRefinement.TEMPLATE, True) ** 2))
    without = np.sqrt(np.mean(corner_errors(CornerRefinement.TEMPLATE, False) ** 2))
    assert without > 4.0 * with_lens, f"without the lens {without:.3f} px, with {with_lens:.3f} px"


def test_a_marker_the_fit_cannot_frame_keeps_the_edge_fit_corners():
    """At the image border the template's margin leaves the image: the edge fit's corners stay
    (the marker is not dropped, nothing crashes)."""
    lens = camera((0.0,) * 5)
    image = render(oblique_square((25.0, 120.0), 18.0, 0.9, 3.0), lens)
    edge = detected_corners(image, CornerRefinement.EDGE, lens)
    np.testing.assert_array_equal(detected_corners(image, CornerRefinement.TEMPLATE, lens), edge)
    assert fast_template_corners(image, edge, DICT, MARKER_ID, LensMap(lens)) is None


def test_homography_derivatives_match_finite_differences():
    corners = np.array([[10.0, 12.0], [61.0, 9.0], [66.0, 50.0], [7.0, 47.0]])
    H, dH = square_homography_derivatives(corners, 6.0)
    np.testing.assert_allclose(H, square_homography(corners, 6.0), atol=1e-12)
    step = 1e-6
    for k in range(8):
        moved = corners.ravel().copy()
        moved[k] += step
        numeric = (square_homography(moved.reshape(4, 2), 6.0) - H) / step
        np.testing.assert_allclose(dH[k], numeric, atol=1e-5 * np.abs(numeric).max() + 1e-9)


def test_the_fits_image_gradient_is_the_blurred_images_slope():
    """The Jacobian's image gradient (template_fit._blurred_with_gradient): along the right axis
    with the right sign and scale (a ramp's slope, to the kernel's 4-sigma tails), steeper than half the difference of
    the two neighbours across an edge blurred by 0.8 px (which understates it: the Gauss-Newton
    steps overshot), and that difference again as the blur goes to nothing (a plain derivative of
    the Gaussian would vanish there: the fit diverged on the real photographs)."""
    from cubetrack.detect.template_fit import _blurred, _blurred_with_gradient

    ys, xs = np.mgrid[0:24, 0:30].astype(np.float32)
    ramp = np.stack([0.03 * xs - 0.02 * ys, 0.05 * ys], axis=-1)
    every = np.ones((24, 30), np.bool_), np.ones((30, 24), np.bool_)  # every pixel wanted (_needed's masks)
    blurred, gx, gy = _blurred_with_gradient(ramp, 0.8, *every)
    np.testing.assert_array_equal(blurred, _blurred(ramp, 0.8, *every))
    inside = (slice(6, -6), slice(6, -6))
    np.testing.assert_allclose(gx[inside], np.broadcast_to([0.03, 0.0], gx[inside].shape), atol=1e-4)
    np.testing.assert_allclose(gy[inside], np.broadcast_to([-0.02, 0.05], gy[inside].shape), atol=1e-4)

    edge = np.zeros((24, 30, 2), np.float32)
    edge[:, 13:, 0] = 1.0
    blurred, gx, _ = _blurred_with_gradient(edge, 0.8, *every)
    assert gx[10, 13, 0] > 1.05 * 0.5 * (blurred[10, 14, 0] - blurred[10, 12, 0]) > 0.0
    rng = np.random.default_rng(5)
    noise = rng.uniform(0.0, 1.0, (24, 30, 2)).astype(np.float32)
    blurred, gx, gy = _blurred_with_gradient(noise, 0.3, *every)
    np.testing.assert_allclose(gx[:, 1:-1], 0.5 * (blurred[:, 2:] - blurred[:, :-2]), atol=0.02)
    np.testing.assert_allclose(gy[1:-1], 0.5 * (blurred[2:] - blurred[:-2]), atol=0.02)


def test_the_fits_blurs_read_only_what_the_compared_pixels_need():
    """A step reads and filters only the pixels its blurs need for the compared ones
    (template_fit._needed): there, every value is the whole region's to the bit, and pixel
    areas beyond the blur's reach are never read (NaN there changes nothing)."""
    from cubetrack.detect.template_fit import _blurred, _blurred_with_gradient, _kernel_half, _needed

    rng = np.random.default_rng(8)
    image = rng.uniform(0.0, 1.0, (30, 34, 2)).astype(np.float32)
    ys, xs = np.mgrid[0:30, 0:34]
    fitted = (np.abs(xs - 17 + 0.4 * (ys - 15)) < 9) & (np.abs(ys - 15) < 8)  # a slanted patch inside the region
    every = np.ones((30, 34), np.bool_), np.ones((34, 30), np.bool_)
    for sigma in (0.6, 1.3):
        rows, need = _needed(fitted, _kernel_half(sigma))
        assert not need.all()
        far = np.where(need[..., None], image, np.float32(np.nan))
        wanted = rows, np.ascontiguousarray(fitted.T)
        for full, part in zip(_blurred_with_gradient(image, sigma, *every), _blurred_with_gradient(far, sigma, *wanted),
                              strict=True):
            np.testing.assert_array_equal(part[fitted], full[fitted])
        np.testing.assert_array_equal(_blurred(far, sigma, *wanted)[fitted], _blurred(image, sigma, *every)[fitted])


@pytest.mark.parametrize("shape", [(7, 2), (300, 200, 2)])  # 60000 points: more than cv2.remap takes in one row
def test_lens_map_reads_the_undistortion(shape):
    """Exact at whole pixels; between them cv2.remap reads in 1/32 px steps (the fit's samples
    then sit up to 1/64 px off their nominal place in the pixel, where the map is exact). Its
    compiled distortion is cv2.projectPoints' (distort_px) to the bit, tangential terms and k3 too."""
    lens = camera()
    points = np.random.default_rng(1).uniform([0.0, 0.0], [WIDTH - 1.0, HEIGHT - 1.0], shape)
    mapping = LensMap(lens)
    for p, tolerance in ((np.rint(points), 2e-4), (points, 0.03)):
        np.testing.assert_allclose(mapping.undistort(p), undistort_points(p, lens.K, lens.dist, lens.K), atol=tolerance)
    np.testing.assert_array_equal(LensMap(None).undistort(points), points)
    for other in (lens, camera((-0.28, 0.09, 0.002, -0.0015, -0.02)), camera((-0.3, 0.1, 0.001, 0.001))):
        np.testing.assert_array_equal(LensMap(other).distort(points), distort_px(points, other.K, other.dist))
    np.testing.assert_array_equal(LensMap(None).distort(points), points)


def test_the_detector_owns_one_lens_map_per_camera():
    """The template fit's lens maps live in the detector, keyed by the intrinsics' values: equal
    intrinsics (another object, e.g. re-read from file) share one map; another camera gets its own;
    another detector builds its own (no process-wide cache)."""
    lens = camera()
    image = render(oblique_square(*SCENES[0]), lens)
    detector = Detector(DetectorParams(corner_refinement=CornerRefinement.TEMPLATE), [DICT])
    first = detector.detect(image, lens=lens)
    same = CameraIntrinsics(lens.width, lens.height, lens.K.copy(), lens.dist.copy())
    np.testing.assert_array_equal(detector.detect(image, lens=same)[0].corners_px, first[0].corners_px)
    assert len(detector._lens_maps) == 1
    other = CameraIntrinsics(lens.width, lens.height, lens.K.copy(), np.zeros(5))
    detector.detect(image, lens=other)
    assert len(detector._lens_maps) == 2
    assert not Detector(DetectorParams(corner_refinement=CornerRefinement.TEMPLATE))._lens_maps


def test_the_pre_blur_is_one_reads_area_in_template_samples():
    """The fast fit's template pre-blur (template_fit._area_steps) is a read's area pulled back into
    the template: a marker half as large in the image needs twice the blur in template samples, and
    a marker squashed along y by 1/2 needs twice the blur along y only (a read of 1/2 px is 1/24 px^2
    of variance; 6 modules of 16 samples across 60 px: 1.6 samples per px)."""
    from cubetrack.detect.template_fit import TEMPLATE_RES, _area_steps

    modules, side_px, step = 6, 60.0, 0.25
    square = np.array([[100.0, 100.0], [100.0 + side_px, 100.0], [100.0 + side_px, 100.0 + side_px],
                       [100.0, 100.0 + side_px]])
    sigma = np.sqrt(1.0 / 48.0) * TEMPLATE_RES * modules / side_px / step  # in steps of 0.25 template samples
    full = _area_steps(square_homography(square, modules), modules, np.eye(2), 2)
    assert full == (round(sigma), round(sigma))
    half = _area_steps(square_homography(100.0 + (square - 100.0) / 2.0, modules), modules, np.eye(2), 2)
    assert half == (round(2 * sigma), round(2 * sigma))
    squashed = square * [1.0, 0.5]
    assert _area_steps(square_homography(squashed, modules), modules, np.eye(2), 2) == (round(sigma), round(2 * sigma))


def test_a_cameras_kept_samples_give_the_corners_a_fresh_lens_map_gives():
    """A LensMap keeps the undistorted samples of every pixel a fit read (its samples table, filled
    as fits first read a pixel): fits in any order through one map, overlapping regions and all,
    give the corners each gives through a map of its own, to the bit; so does an image of
    another size through the same map (a table of its own)."""
    lens = camera()
    images = [render(oblique_square(centre, half, squash, turn), lens, seed=seed)
              for seed, (centre, half, squash, turn) in enumerate(SCENES)]
    images.append(render(oblique_square((96.0, 82.0), 23.0, 0.55, 22.0), lens, seed=9))  # overlaps the second
    starts = [detected_corners(image, CornerRefinement.EDGE, lens) for image in images]
    areas = TemplateFitSettings(supersample=2)  # the fit that reads pixel areas (the calibration's kind)
    alone = [fast_template_corners(image, start, DICT, MARKER_ID, LensMap(lens), settings=areas)
             for image, start in zip(images, starts, strict=True)]
    assert all(c is not None for c in alone)
    shared = LensMap(lens)
    for k in (4, 1, 0, 3, 2, 1, 4):
        np.testing.assert_array_equal(
            fast_template_corners(images[k], starts[k], DICT, MARKER_ID, shared, settings=areas), alone[k])
    padded = np.pad(images[0], ((0, 16), (0, 16)), mode="edge")
    np.testing.assert_array_equal(fast_template_corners(padded, starts[0], DICT, MARKER_ID, shared, settings=areas),
                                  alone[0])


SMALL_SCENES = [  # tracking's usual markers: 18-22 px across, head-on to strongly foreshortened and turned
    ((150.0, 118.0), 10.0, 1.0, 10.0), ((110.0, 100.0), 11.0, 0.45, 35.0), ((210.0, 80.0), 12.0, 0.4, -50.0),
    ((200.0, 150.0), 11.0, 0.5, 70.0)]


def test_the_fit_converges_on_small_oblique_markers():
    """The fit with the blur in the template (READ_SETTINGS) on tracking's usual markers, seen obliquely
    through the wide lens, from the edge fit's corners: every fit succeeds and lands several times closer
    to the truth."""
    lens = camera()
    edge, template = [], []
    for seed, (centre, half, squash, turn) in enumerate(SMALL_SCENES):
        truth_ideal = oblique_square(centre, half, squash, turn)
        image = render(truth_ideal, lens, blur_px=0.7, seed=20 + seed)  # measured: 0.013 px RMS (edge fit 0.11)
        truth = distort_px(truth_ideal, lens.K, lens.dist)
        start = detected_corners(image, CornerRefinement.EDGE, lens)
        fitted = fast_template_corners(image, start, DICT, MARKER_ID, LensMap(lens), settings=READ_SETTINGS)
        assert fitted is not None
        edge.append(start - truth)
        template.append(fitted - truth)
    rms, edge_rms = np.sqrt(np.mean(np.square(template))), np.sqrt(np.mean(np.square(edge)))
    assert rms < 0.03, f"template corners {rms:.3f} px RMS from the truth"
    assert rms < edge_rms / 3.0, f"template {rms:.3f} px against the edge fit's {edge_rms:.3f} px"


def _blurred_reads(corners: np.ndarray, points: np.ndarray, blur: float) -> tuple[np.ndarray, ...]:
    """template_fit._blurred_reads of marker MARKER_ID whose square is ``corners`` at ``points``, no lens."""
    from cubetrack.detect.template_fit import _blurred_reads as reads
    from cubetrack.detect.template_fit import _module_cells, _normal_table

    cells, edges = _module_cells(DICT, MARKER_ID, 1.0)
    spans = np.ascontiguousarray(np.broadcast_to(np.eye(2), (len(points), 2, 2)))
    return reads(cells, edges, _normal_table(), points, np.linalg.inv(square_homography(corners, 6.0)), spans, blur)


def test_the_blurred_reads_are_the_marker_blurred_in_the_image():
    """The fit with the blur in the template predicts each compared pixel in closed form
    (template_fit._blurred_reads): the marker (cells, border, white margin, 0 beyond it; and the
    indicator of what lies beyond) seen through a sheared homography, averaged over the pixel's area
    and blurred by a Gaussian in the image, as a Monte-Carlo average of the template at 40,000 such
    points per pixel gives it (to its noise, 0.0025)."""
    corners = np.array([[10.0, 12.0], [30.0, 16.0], [24.0, 30.0], [4.0, 26.0]])  # the blur's covariance in
    # the template: correlation 0.2
    rng = np.random.default_rng(3)
    points = rng.uniform(0.0, 36.0, (60, 2))
    got = _blurred_reads(corners, points, 0.8)[0]
    cells = cv2.aruco.generateImageMarker(aruco_dictionary(DICT), MARKER_ID, 6, borderBits=1) / 255.0
    H_inv = np.linalg.inv(square_homography(corners, 6.0))
    n = 40_000
    for point, (value, beyond) in zip(points, got, strict=True):
        x = point + rng.normal(0.0, 0.8, (n, 2)) + rng.uniform(-0.5, 0.5, (n, 2))
        m = np.c_[x, np.ones(n)] @ H_inv.T
        u, v = (m[:, :2] / m[:, 2:]).T + rng.normal(0.0, 0.7 / 16.0, (2, n))  # the template's smoothing
        margin = (u > -1.0) & (u < 7.0) & (v > -1.0) & (v < 7.0)
        on = (u >= 0.0) & (u < 6.0) & (v >= 0.0) & (v < 6.0)
        cell = cells[np.clip(v.astype(int), 0, 5), np.clip(u.astype(int), 0, 5)]
        assert abs(np.where(on, cell, margin).mean() - value) < 0.012
        assert abs((~margin).mean() - beyond) < 0.012


def test_the_blurred_reads_slopes_are_their_derivatives():
    """The reads' gradient (undistorted px) and derivative by the blur are the values' finite
    differences: where the template's blur has no correlation (a square turned in the image) to the
    table's steps,
    within 10 % of the largest where it has (the correlation's terms are left out of the derivatives:
    the Gauss-Newton steps' Jacobian, not the model)."""
    rng = np.random.default_rng(4)
    step = 1e-5
    a = np.radians(20.0)
    turned = 18.0 + 12.0 * np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) @ np.array(
        [[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]])
    for corners, tolerance in ((turned, 2e-3),  # the normal integral read linearly from a table
                               (np.array([[10.0, 12.0], [30.0, 16.0], [24.0, 30.0], [4.0, 26.0]]), 0.1)):
        points = rng.uniform(0.0, 36.0, (400, 2))
        _, gradient, by_blur = _blurred_reads(corners, points, 0.8)
        for axis in range(2):
            moved = [points.copy(), points.copy()]
            moved[0][:, axis] += step
            moved[1][:, axis] -= step
            slope = (_blurred_reads(corners, moved[0], 0.8)[0] - _blurred_reads(corners, moved[1], 0.8)[0]) / (2 * step)
            assert np.abs(slope - gradient[..., axis]).max() < tolerance * np.abs(slope).max()
        slope = (_blurred_reads(corners, points, 0.8 + step)[0] - _blurred_reads(corners, points, 0.8 - step)[0]) / (
            2 * step)
        assert np.abs(slope - by_blur).max() < tolerance * np.abs(slope).max()
