"""A tiny exact renderer of a floor world marker seen by static cameras, for calibration tests.

Ground truth by construction: the marker texture is mapped into the image through the exact
plane homography at 4x supersampling (pixel-centre convention kept at both resolutions), box
downsampled, blurred, noised and JPEG-encoded. Independent of ``cubetrack.simulate``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from cubetrack.geometry import invert_T, make_T
from cubetrack.io.camera_info import CameraIntrinsics, write_camera_info
from cubetrack.io.config import CameraExtrinsics, tracker_config_to_table, write_extrinsics, write_toml, WorldConfig, CameraConfig
from cubetrack.io.recording import CameraEntry, RecordingWriter
from cubetrack.layout import paper_cube_layout, write_layout

W, H = 640, 480
MARGIN = 60
K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])


def look_at(position_m, target_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """T_world_cam of an optical frame (x right, y down, z forward) at ``position_m`` aimed at
    ``target_m``, level (image x horizontal)."""
    p = np.asarray(position_m, float)
    z = np.asarray(target_m, float) - p
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.column_stack([x, y, z]), p)


def marker_texture(dictionary: str, marker_id: int, px: int = 480, margin: int = 60) -> np.ndarray:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    m = cv2.aruco.generateImageMarker(d, marker_id, px, borderBits=1)
    return cv2.copyMakeBorder(m, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)


def _distortion_maps(K, dist, ss):
    """For each high-res pixel of the distorted image, where it lies in the ideal (undistorted)
    high-res image: maps for cv2.remap."""
    ys, xs = np.mgrid[0:H * ss, 0:W * ss].astype(np.float64)
    low = np.stack([(xs + 0.5) / ss - 0.5, (ys + 0.5) / ss - 0.5], axis=-1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(low, K, np.asarray(dist, float), P=K).reshape(H * ss, W * ss, 2)
    hi = ss * (ideal + 0.5) - 0.5
    return hi[..., 0].astype(np.float32), hi[..., 1].astype(np.float32)


def render(T_world_cam, size_m=0.25, dictionary="DICT_4X4_50", marker_id=0, rng=None,
           noise=2.0, blur=0.7, quality=85, ss=4, K=K, floor=90, dist=None) -> bytes:
    px, margin = 480, MARGIN
    tex = marker_texture(dictionary, marker_id, px, margin)
    # texture pixel coords (centre convention) -> world plane (x, y), marker = world frame
    s = size_m / px
    A = np.array([[s, 0, -size_m / 2 - (margin - 0.5) * s],
                  [0, -s, size_m / 2 + (margin - 0.5) * s],
                  [0, 0, 1]])
    T_cam_world = invert_T(T_world_cam)
    Hw = K @ np.column_stack([T_cam_world[:3, 0], T_cam_world[:3, 1], T_cam_world[:3, 3]])
    S = np.array([[ss, 0, (ss - 1) / 2], [0, ss, (ss - 1) / 2], [0, 0, 1]])  # low -> high res
    Hh = S @ Hw @ A
    hi = cv2.warpPerspective(tex, Hh, (W * ss, H * ss), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=floor)
    if dist is not None:
        mx, my = _distortion_maps(K, dist, ss)
        hi = cv2.remap(hi, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=floor)
    img = cv2.resize(hi.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA)
    if blur:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    rng = rng or np.random.default_rng(0)
    img = img + rng.normal(0, noise, img.shape)
    img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return buf.tobytes()


# three cameras like the paper's 1.0 m setup: 1.0 m high, about 30 deg down, around the arena
CAMERAS = {
    "cam1": look_at((1.7, -0.3, 1.0), (0.0, 0.0, 0.0)),
    "cam2": look_at((-1.0, 1.45, 1.0), (0.0, 0.1, 0.0)),
    "cam3": look_at((-0.9, -1.5, 1.0), (0.1, -0.1, 0.0)),
}


def write_scene(root: Path, frames: int = 30, cameras=None, seed: int = 1,
                corrupt: dict[str, int] | None = None) -> tuple[Path, Path, Path]:
    """Write a calibration recording, a tracker config and the true extrinsics under ``root``.

    ``corrupt`` = {camera: how many of its frames get garbage bytes}. Returns (config, rec, truth).
    """
    cameras = cameras or CAMERAS
    rng = np.random.default_rng(seed)
    rec = root / "rec"
    with RecordingWriter(rec, [CameraEntry(n) for n in cameras]) as w:
        for name, T in cameras.items():
            write_camera_info(CameraIntrinsics(W, H, K, np.zeros(5), name), w.camera_info_path(name))
            bad = (corrupt or {}).get(name, 0)
            for i in range(frames):
                jpeg = b"not a jpeg" if i < bad else render(T, rng=rng)
                w.add_frame(name, i, 0.1 * i, 1000.0 + 0.1 * i, jpeg)
    write_layout(paper_cube_layout(), root / "cube.toml")
    doc = tracker_config_to_table(WorldConfig(), [CameraConfig(n) for n in cameras], [("robot", "cube.toml")])
    write_toml(doc, root / "config.toml")
    write_extrinsics({n: CameraExtrinsics(T) for n, T in cameras.items()}, root / "truth.toml")
    return root / "config.toml", rec, root / "truth.toml"
