"""A small exact renderer for detection tests: textured planar patches seen by a pinhole camera.

Each output pixel is the mean of ``ss x ss`` point samples placed symmetrically inside the
pixel (OpenCV's pixel-centre convention: pixel (u, v) covers [u-0.5, u+0.5] x [v-0.5, v+0.5]).
Each sample is a ray cast through ``K`` (no distortion) and intersected with every patch; the
nearest front-facing patch wins. Texture lookup is exact (nearest bit cell, no interpolation),
so edges land where the geometry puts them, to within the 1/ss sampling — no bias.

Ground truth corners are then simply ``project(K, T_cam_marker, marker_corners_m(size))``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cubetrack.layout import CubeLayout, marker_corners_m


@dataclass(frozen=True)
class Patch:
    """A square patch of side ``side_m`` centred on its frame's origin (x right, y up, z out),
    with an optional marker of side ``marker_m`` in the middle. ``bits`` is the marker image
    with one pixel per module (border included), 0 black, 255 white."""

    T_cam_patch: np.ndarray
    side_m: float
    bits: np.ndarray | None = None
    marker_m: float = 0.0
    grey: int = 255


def marker_bits(dictionary: str, marker_id: int) -> np.ndarray:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    n = d.markerSize + 2
    return cv2.aruco.generateImageMarker(d, marker_id, n, borderBits=1)


def project(K: np.ndarray, T_cam_x: np.ndarray, points_x: np.ndarray) -> np.ndarray:
    """Pinhole projection (no distortion) of (N, 3) points in frame x; (N, 2) pixels."""
    p = np.asarray(points_x, float) @ T_cam_x[:3, :3].T + T_cam_x[:3, 3]
    uv = p @ K.T
    return uv[:, :2] / uv[:, 2:3]


def render(K: np.ndarray, size_px: tuple[int, int], patches: list[Patch], *, ss: int = 4,
           background: int = 90, blur_sigma_px: float = 0.0, noise_sigma: float = 0.0,
           jpeg_quality: int | None = None, seed: int = 0) -> np.ndarray:
    """Render patches into a uint8 grayscale image of ``size_px = (width, height)``."""
    width, height = size_px
    # Only cast rays inside the bounding box of the projected patches (plus a margin).
    boxes = []
    for p in patches:
        h = p.side_m / 2
        corners = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
        z = corners @ p.T_cam_patch[:3, :3].T + p.T_cam_patch[:3, 3]
        if np.any(z[:, 2] <= 1e-6):
            boxes.append((0, 0, width, height))
            continue
        uv = project(K, p.T_cam_patch, corners)
        boxes.append((uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()))
    boxes = np.array(boxes)
    x0 = int(max(0, np.floor(boxes[:, 0].min()) - 2))
    y0 = int(max(0, np.floor(boxes[:, 1].min()) - 2))
    x1 = int(min(width, np.ceil(boxes[:, 2].max()) + 3))
    y1 = int(min(height, np.ceil(boxes[:, 3].max()) + 3))
    image = np.full((height, width), float(background))
    if x1 > x0 and y1 > y0:
        offs = (np.arange(ss) + 0.5) / ss - 0.5
        xs = (np.arange(x0, x1)[:, None] + offs[None, :]).reshape(-1)
        ys = (np.arange(y0, y1)[:, None] + offs[None, :]).reshape(-1)
        X, Y = np.meshgrid(xs, ys)
        rays = np.stack([X.ravel(), Y.ravel(), np.ones(X.size)], axis=1) @ np.linalg.inv(K).T
        depth = np.full(X.size, np.inf)
        value = np.full(X.size, float(background))
        for p in patches:
            R, t = p.T_cam_patch[:3, :3], p.T_cam_patch[:3, 3]
            if float(R[:, 2] @ t) >= 0.0:  # back-facing: the camera is behind the patch
                continue
            o = -R.T @ t  # camera centre in patch frame
            d = rays @ R  # ray directions in patch frame (R^T d)
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = -o[2] / d[:, 2]
            px = o[0] + lam * d[:, 0]
            py = o[1] + lam * d[:, 1]
            h = p.side_m / 2
            hit = (lam > 0) & (np.abs(px) <= h) & (np.abs(py) <= h) & (lam < depth)
            val = np.full(X.size, float(p.grey))
            if p.bits is not None:
                n = p.bits.shape[0]
                m = p.marker_m / 2
                inside = (np.abs(px) < m) & (np.abs(py) < m)
                col = np.clip(np.floor((px + m) / p.marker_m * n).astype(int), 0, n - 1)
                row = np.clip(np.floor((m - py) / p.marker_m * n).astype(int), 0, n - 1)
                val = np.where(inside, p.bits[row, col].astype(float), val)
            depth = np.where(hit, lam, depth)
            value = np.where(hit, val, value)
        block = value.reshape(y1 - y0, ss, x1 - x0, ss).mean(axis=(1, 3))
        image[y0:y1, x0:x1] = block
    if blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur_sigma_px)
    if noise_sigma > 0:
        image = image + np.random.default_rng(seed).normal(0.0, noise_sigma, image.shape)
    out = np.clip(np.round(image), 0, 255).astype(np.uint8)
    if jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        out = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return out


def marker_patch(dictionary: str, marker_id: int, size_m: float, T_cam_marker: np.ndarray,
                 quiet_zone: float = 0.5) -> Patch:
    """A marker with a white quiet zone of ``quiet_zone`` x its side on every edge."""
    return Patch(T_cam_marker, size_m * (1 + 2 * quiet_zone), marker_bits(dictionary, marker_id), size_m)


def cube_patches(layout: CubeLayout, cube_size_m: float, T_cam_cube: np.ndarray) -> list[Patch]:
    """One white face of side ``cube_size_m`` per layout marker, with the marker on it."""
    out = []
    for m in layout.markers:
        bits = marker_bits(layout.dictionary, m.marker_id)
        out.append(Patch(T_cam_cube @ m.T_cube_marker, cube_size_m, bits, m.size_m))
    return out


def true_corners(K: np.ndarray, T_cam_marker: np.ndarray, size_m: float) -> np.ndarray:
    return project(K, T_cam_marker, marker_corners_m(size_m))
