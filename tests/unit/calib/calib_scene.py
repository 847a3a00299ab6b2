"""A floor world marker seen by static cameras, for calibration tests: the scene (the simulator's
exact renderer, through ``tests/unit/scenes.py``) and a recording of it with the true camera poses.
A world reference of several markers or a ChArUco board (:class:`WorldConfig` with ``markers`` or
``board``) is drawn the same way (:func:`reference_solids`).

Ground truth by construction: the world marker's frame is the world frame; each camera's
``T_world_cam`` is known; frames add blur, noise and JPEG to the exactly rendered image.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scenes import Camera, look_at, marker_corners_px, marker_on_paper
from scipy.spatial.transform import Rotation

from cubetrack.calib.bundle import layout_with
from cubetrack.core.cameras import CameraExtrinsics, CameraIntrinsics, WorldBoard, WorldConfig
from cubetrack.core.geometry import make_T
from cubetrack.core.layout import paper_cube_layout, write_layout
from cubetrack.io.camera_info import write_camera_info
from cubetrack.io.config import CameraConfig, tracker_config_to_table, write_extrinsics, write_toml
from cubetrack.io.recording import CameraEntry, RecordingWriter
from cubetrack.simulate.render import BLACK_ALBEDO, WHITE_ALBEDO, MarkerTexture, Quad, Solid

W, H = 640, 480
K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
MARKER_M = 0.25
MARGIN_M = 0.25 * 60 / 480  # white paper around the marker, 3.1 cm (2-4 px in these views)
FLOOR_GREY = 90


def intrinsics(dist=None) -> CameraIntrinsics:
    return CameraIntrinsics(W, H, K, np.zeros(5) if dist is None else np.asarray(dist, float))


def camera(T_world_cam, dist=None, dictionary="DICT_4X4_50", marker_id=0, world: WorldConfig | None = None,
           lens: CameraIntrinsics | None = None) -> Camera:
    """The world marker (``MARKER_M`` on ``MARGIN_M`` of white paper, at the world origin) on a
    uniform grey floor, seen from ``T_world_cam``; ``.jpeg(...)`` gives frames. With ``world``: its
    whole reference instead (:func:`reference_solids`); ``lens``: other intrinsics."""
    solids = (reference_solids(world) if world is not None
              else [marker_on_paper(np.eye(4), dictionary, marker_id, MARKER_M, MARGIN_M)])
    return Camera(lens or intrinsics(dist), T_world_cam, solids, background=FLOOR_GREY)


def board_solid(board: WorldBoard, margin_m: float = 0.02) -> Solid:
    """A ChArUco board as OpenCV draws it (black square in the first row's first column,
    markers in the white squares row by row) on white paper ``margin_m`` wider."""
    w, h, sq = board.squares_x * board.square_size_m, board.squares_y * board.square_size_m, board.square_size_m
    decals, ids = [], iter(board.marker_ids)
    for row in range(board.squares_y):
        for col in range(board.squares_x):
            T = board.T_world_board @ make_T(np.eye(3), [-w / 2 + (col + 0.5) * sq, h / 2 - (row + 0.5) * sq, 0.0])
            if (row + col) % 2 == 0:
                decals.append(Quad(T, (sq, sq), BLACK_ALBEDO))
            else:
                decals.append(Quad(T, (board.marker_size_m,) * 2, texture=MarkerTexture(board.dictionary, next(ids))))
    return Solid((Quad(board.T_world_board, (w + 2 * margin_m, h + 2 * margin_m), WHITE_ALBEDO),), tuple(decals))


def reference_solids(world: WorldConfig) -> list[Solid]:
    """The world reference as drawn on the floor: each marker on paper (margin in proportion to
    ``MARGIN_M`` of the world marker), the board."""
    solids = [marker_on_paper(m.T_world_marker, m.dictionary, m.marker_id, m.size_m, MARGIN_M * m.size_m / MARKER_M)
              for m in world.reference_markers()]
    return solids + ([board_solid(world.board)] if world.board is not None else [])


def true_corners(T_world_cam, dist=None) -> np.ndarray:
    """The world marker's true (4, 2) corners TL, TR, BR, BL in the (distorted) image."""
    return marker_corners_px(intrinsics(dist), T_world_cam, np.eye(4), MARKER_M)


def frame(cam: Camera, rng, noise=2.0, blur=0.7, quality=85) -> bytes:
    """One recorded frame of ``cam``: blur, noise and JPEG as a camera node's."""
    return cam.jpeg(quality, blur, noise, rng)


# three cameras like the paper's 1.0 m setup: 1.0 m high, about 30 deg down, around the arena
CAMERAS = {
    "cam1": look_at((1.7, -0.3, 1.0), (0.0, 0.0, 0.0)),
    "cam2": look_at((-1.0, 1.45, 1.0), (0.0, 0.1, 0.0)),
    "cam3": look_at((-0.9, -1.5, 1.0), (0.1, -0.1, 0.0)),
}


def write_scene(root: Path, frames: int = 30, cameras=None, seed: int = 1,
                corrupt: dict[str, int] | None = None, world: WorldConfig | None = None,
                lenses: dict[str, CameraIntrinsics] | None = None) -> tuple[Path, Path, Path]:
    """Write a calibration recording, a tracker config and the true extrinsics under ``root``.

    ``corrupt`` = {camera: how many of its frames get garbage bytes}; ``world``: another world
    reference (drawn and written to the config); ``lenses``: each camera's intrinsics (default
    :func:`intrinsics`). Returns (config, rec, truth).
    """
    cameras = cameras or CAMERAS
    rng = np.random.default_rng(seed)
    rec = root / "rec"
    with RecordingWriter(rec, [CameraEntry(n) for n in cameras]) as w:
        for name, T in cameras.items():
            lens = (lenses or {}).get(name) or CameraIntrinsics(W, H, K, np.zeros(5), name)
            write_camera_info(lens, w.camera_info_path(name))
            bad = (corrupt or {}).get(name, 0)
            cam = camera(T, world=world, lens=lens)
            for i in range(frames):
                jpeg = b"not a jpeg" if i < bad else frame(cam, rng)
                w.add_frame(name, i, 0.1 * i, 1000.0 + 0.1 * i, jpeg)
    write_layout(paper_cube_layout(), root / "cube.toml")
    doc = tracker_config_to_table(world or WorldConfig(), [CameraConfig(n) for n in cameras], [("robot", "cube.toml")])
    write_toml(doc, root / "config.toml")
    write_extrinsics({n: CameraExtrinsics(T) for n, T in cameras.items()}, root / "truth.toml")
    return root / "config.toml", rec, root / "truth.toml"


def hand_built_cube(seed: int):
    """The paper's cube as a hand-built one: every marker turned by about a degree and shifted by
    about a millimetre, printed 1 % small. (nominal layout, true marker poses (5, 4, 4), true layout)."""
    layout = paper_cube_layout()
    rng = np.random.default_rng(seed)
    true_markers = np.array([make_T(Rotation.from_rotvec(np.radians(rng.normal(0, 1, 3))).as_matrix(), [0, 0, 0])
                             @ m.T_cube_marker for m in layout.markers])
    true_markers[:, :3, 3] += rng.normal(0, 1e-3, (5, 3))
    return layout, true_markers, layout_with(layout, true_markers, np.array([m.size_m for m in layout.markers]) * 0.99)
