"""The renderer is exact to the sub-pixel: rendered shapes sit where the camera model projects
them (OpenCV's pixel-centre convention), with and without lens distortion."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import make_T
from cubetrack.simulate.render import (
    WHITE_ALBEDO,
    Floor,
    MarkerTexture,
    Quad,
    Renderer,
    Solid,
    View,
    draw_solid,
    encode_jpeg,
    form_image,
    project_points,
)

K = np.array([[520.0, 0.0, 319.5], [0.0, 520.0, 239.5], [0.0, 0.0, 1.0]])
DISTORTIONS = [np.zeros(5), np.array([-0.2, 0.05, 0.001, -0.001, 0.0])]


def _intrinsics(dist: np.ndarray) -> CameraIntrinsics:
    return CameraIntrinsics(640, 480, K, dist)


def _square_facing_camera(rng: np.random.Generator, side_m: float) -> Quad:
    """A white square in front of a camera at the world origin, tilted up to 50 degrees."""
    R = Rotation.from_euler("xyz", rng.uniform(-50, 50, 3), degrees=True).as_matrix() @ np.diag([1, -1, -1])
    t = [rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), rng.uniform(0.8, 1.5)]
    return Quad(make_T(R, t), (side_m, side_m), 1.0)


def _render_alone(view: View, quad: Quad) -> np.ndarray:
    """The quad on black, no blur, no noise: final-resolution coverage in [0, 1]."""
    w, h = view.canvas_size
    canvas = np.zeros((h, w), np.float32)
    draw_solid(canvas, view.canvas_origin, view, Solid((quad,)))
    if view.distorted:
        canvas = cv2.remap(canvas, view.map_x, view.map_y, cv2.INTER_LINEAR)
    return cv2.resize(canvas, (view.width, view.height), interpolation=cv2.INTER_AREA)


def _polygon_area_centroid(p: np.ndarray) -> tuple[float, np.ndarray]:
    x, y = p[:, 0], p[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    c = x * y1 - x1 * y
    area = c.sum() / 2.0
    return abs(area), np.array([((x + x1) * c).sum(), ((y + y1) * c).sum()]) / (6.0 * area)


@pytest.mark.parametrize("dist", DISTORTIONS, ids=["pinhole", "distorted"])
def test_rendered_square_has_the_projected_centroid_and_area(dist):
    rng = np.random.default_rng(5)
    view = View(_intrinsics(dist), np.eye(4), 4)
    for _ in range(6):
        quad = _square_facing_camera(rng, 0.08)
        img = _render_alone(view, quad)
        corners = quad.corners_world()
        # the projected outline, densely (distortion bends the edges)
        edge = np.linspace(0.0, 1.0, 200, endpoint=False)[:, None]
        outline = np.concatenate([corners[i] + edge * (corners[(i + 1) % 4] - corners[i]) for i in range(4)])
        outline_px = project_points(view.intrinsics, view.T_world_cam, outline)
        area, centroid = _polygon_area_centroid(outline_px)
        ys, xs = np.mgrid[0:img.shape[0], 0:img.shape[1]]
        mass = float(img.sum())
        measured = np.array([(img * xs).sum(), (img * ys).sum()]) / mass
        perimeter = np.linalg.norm(np.diff(np.vstack([outline_px, outline_px[:1]]), axis=0), axis=1).sum()
        assert np.abs(measured - centroid).max() <= 0.01, (measured, centroid)
        # an edge shifted outwards by e pixels grows the area by about e * perimeter
        assert abs(mass - area) / perimeter <= 0.002, (mass, area, perimeter)


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return make_T(np.column_stack([x, np.cross(z, x), z]), eye)


@pytest.mark.parametrize("distance_m, max_mean_px", [(0.8, 0.3), (1.5, 0.7)])
def test_subpix_detector_finds_rendered_corners_at_the_projected_truth(distance_m, max_mean_px):
    """8 cm marker, VGA f=520, blur, noise and JPEG as in a recording. SUBPIX has a small inward
    bias of its own (docs/simulation.md); a pixel-convention error would show as a mean shift."""
    rng = np.random.default_rng(2)
    intr = _intrinsics(np.zeros(5))
    floor = Floor(np.full((8, 8), 0.42, np.float32), 4.0)
    marker = Solid((Quad(np.eye(4), (0.11, 0.11), WHITE_ALBEDO),),
                   (Quad(np.eye(4), (0.08, 0.08), texture=MarkerTexture("DICT_4X4_50", 1)),))
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)
    errors, shifts = [], []
    for _ in range(10):
        elev, az = np.radians(rng.uniform(30, 70)), rng.uniform(0, 2 * np.pi)
        eye = distance_m * np.array([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
        roll = make_T(Rotation.from_euler("z", rng.uniform(-180, 180), degrees=True).as_matrix(), [0, 0, 0])
        T_world_cam = _look_at(eye, np.array([rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02), 0.0])) @ roll
        renderer = Renderer(View(intr, T_world_cam, 4), floor, (marker,))
        image = form_image(renderer.background, np.ones((480, 640), np.float32), 0.6, 2.0, rng)
        image = cv2.imdecode(np.frombuffer(encode_jpeg(image, 80), np.uint8), cv2.IMREAD_GRAYSCALE)
        corners, ids, _ = detector.detectMarkers(image)
        assert ids is not None and ids.ravel().tolist() == [1]
        truth = project_points(intr, T_world_cam, marker.decals[0].corners_world())
        d = corners[0].reshape(4, 2) - truth
        errors.append(np.linalg.norm(d, axis=1))
        shifts.append(d.mean(axis=0))
    assert np.mean(errors) <= max_mean_px
    assert np.abs(np.mean(shifts, axis=0)).max() <= 0.1


def test_marker_texture_matches_opencv_marker():
    tex = MarkerTexture("DICT_4X4_50", 7).image(3, 2)
    ref = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), 7, 6)
    assert tex.shape == (12, 18)
    assert np.array_equal(tex[::2, ::3] > 0.5, ref > 127)


def test_back_faces_are_not_drawn():
    view = View(_intrinsics(np.zeros(5)), np.eye(4), 2)
    facing_away = Quad(make_T(np.eye(3), [0.0, 0.0, 1.0]), (0.2, 0.2), 1.0)  # its +z points away
    assert _render_alone(view, facing_away).max() == 0.0
