"""Rendered test scenes with ground truth by construction, through the simulator's exact renderer
(:mod:`cubetrack.simulate.render`: anti-aliased, OpenCV's pixel-centre convention, optional lens
distortion; its own accuracy is tested in ``tests/unit/simulate/test_render.py``).

The detection, estimation and calibration tests share this one renderer: markers on white paper,
the paper's cube, a floor marker, each at a known pose; the true corners are the projections of
the markers' corners (:func:`cubetrack.simulate.render.project_points`).

Grey levels as the old test renderers had them: white paper 255, black ink 15 (the simulator's
albedos scaled so that paper is 255), a uniform grey background.
"""

from __future__ import annotations

import cv2
import numpy as np

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import make_T
from cubetrack.core.layout import CubeLayout, marker_corners_m
from cubetrack.simulate.render import (
    WHITE_ALBEDO,
    Floor,
    MarkerTexture,
    Quad,
    Renderer,
    Solid,
    View,
    encode_jpeg,
    form_image,
    project_points,
)

# A camera 10 m above the floor looking straight up sees only the "wall" (uniform background):
# scenes given in the camera frame are placed in front of it.
T_WORLD_CAM_UP = make_T(np.eye(3), [0.0, 0.0, 10.0])


def look_at(eye_m, target_m) -> np.ndarray:
    """T_world_cam of a camera at ``eye_m`` looking at ``target_m`` (world z up, image x level)."""
    eye, target = np.asarray(eye_m, float), np.asarray(target_m, float)
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return make_T(np.column_stack([x, np.cross(z, x), z]), eye)


def marker_on_paper(T_world_marker: np.ndarray, dictionary: str, marker_id: int, size_m: float,
                    margin_m: float) -> Solid:
    """A marker (black square of side ``size_m``) printed on white paper ``margin_m`` wider on
    every side; frame as a marker's (x right, y up, z out of the face)."""
    paper = size_m + 2.0 * margin_m
    return Solid((Quad(T_world_marker, (paper, paper), WHITE_ALBEDO),),
                 (Quad(T_world_marker, (size_m, size_m), texture=MarkerTexture(dictionary, marker_id)),))


def cube_solid(layout: CubeLayout, cube_size_m: float, T_world_cube: np.ndarray) -> Solid:
    """A white cube of side ``cube_size_m`` with the layout's markers on its faces (one face per
    layout marker; the paper's cube has no bottom marker and is drawn without a bottom)."""
    faces, decals = [], []
    for m in layout.markers:
        T = T_world_cube @ m.T_cube_marker
        faces.append(Quad(T, (cube_size_m, cube_size_m), WHITE_ALBEDO))
        decals.append(Quad(T, (m.size_m, m.size_m), texture=MarkerTexture(layout.dictionary, m.marker_id)))
    return Solid(tuple(faces), tuple(decals))


def marker_corners_px(intrinsics: CameraIntrinsics, T_world_cam: np.ndarray, T_world_marker: np.ndarray,
                      size_m: float) -> np.ndarray:
    """The true (4, 2) corners (TL, TR, BR, BL, lens distortion applied) of a marker."""
    corners = marker_corners_m(size_m) @ T_world_marker[:3, :3].T + T_world_marker[:3, 3]
    return project_points(intrinsics, T_world_cam, corners)


class Camera:
    """One camera over a static scene: the exact albedo image is rendered once; each call of
    :meth:`image` adds blur, noise (its own ``rng`` draw) and optionally JPEG compression."""

    def __init__(self, intrinsics: CameraIntrinsics, T_world_cam: np.ndarray, solids: list[Solid] | tuple,
                 background: float = 90.0, supersample: int = 4):
        albedo = background / 255.0 * WHITE_ALBEDO
        floor = Floor(np.full((2, 2), albedo, np.float32), 1.0, wall_albedo=albedo)
        self.intrinsics = intrinsics
        self.T_world_cam = np.asarray(T_world_cam, float)
        self.albedo = Renderer(View(intrinsics, self.T_world_cam, supersample), floor, tuple(solids)).background
        self._gain = np.full(self.albedo.shape, 1.0 / WHITE_ALBEDO, np.float32)

    def image(self, blur_px: float = 0.0, noise_std: float = 0.0, jpeg_quality: int | None = None,
              rng: np.random.Generator | None = None) -> np.ndarray:
        """The 8-bit grayscale image (after a JPEG round trip when ``jpeg_quality`` is given)."""
        img = form_image(self.albedo, self._gain, blur_px, noise_std, rng or np.random.default_rng(0))
        if jpeg_quality is not None:
            img = cv2.imdecode(np.frombuffer(encode_jpeg(img, jpeg_quality), np.uint8), cv2.IMREAD_GRAYSCALE)
        return img

    def jpeg(self, quality: int, blur_px: float = 0.0, noise_std: float = 0.0,
             rng: np.random.Generator | None = None) -> bytes:
        """The image as JPEG bytes (a recorded frame)."""
        return encode_jpeg(self.image(blur_px, noise_std, None, rng), quality)


def render_in_front(intrinsics: CameraIntrinsics, solids_cam: list[tuple], **image_args) -> np.ndarray:
    """Markers held in front of a camera on a uniform background: ``solids_cam`` are
    ``(T_cam_marker, dictionary, marker_id, size_m, margin_m)``; keyword arguments go to
    :meth:`Camera.image`."""
    solids = [marker_on_paper(T_WORLD_CAM_UP @ T, d, i, s, m) for T, d, i, s, m in solids_cam]
    return Camera(intrinsics, T_WORLD_CAM_UP, solids).image(**image_args)
