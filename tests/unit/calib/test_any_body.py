"""Issue 15 item 4: a body is any set of markers with sizes and poses — here a cuboid (not a cube)
with a different marker size on each face, repeated and distinct ids, and markers of two
dictionaries, one of whose ids is also used in the other dictionary. Rendered by the simulator's
exact renderer (tests/unit/scenes.py), detected, matched and estimated by the tracker's stages."""

import numpy as np
import pytest
from scenes import Camera, look_at

from cubetrack.app.make_body import box_layout
from cubetrack.core.cameras import CameraIntrinsics, WorldConfig
from cubetrack.core.errors import ConfigError
from cubetrack.core.geometry import R_from_rotvec, make_T, rotation_angle
from cubetrack.core.layout import CubeLayout, LayoutMarker, read_layout, write_layout
from cubetrack.detect.detector import Detector
from cubetrack.estimate.match import body_detections, match_faces
from cubetrack.estimate.pose import estimate_cube
from cubetrack.io.config import read_tracker_config, tracker_config_to_table, write_toml
from cubetrack.simulate.render import WHITE_ALBEDO, MarkerTexture, Quad, Solid

LENS = CameraIntrinsics(640, 480, np.array([[520.0, 0, 319.5], [0, 520.0, 239.5], [0, 0, 1]]), np.zeros(5))
SIZE = (0.20, 0.14, 0.10)  # x forward, y left, z up


def crate() -> CubeLayout:
    """A 20 x 14 x 10 cm box: top 9 cm DICT_4X4_50 id 3, front and back 7 cm DICT_5X5_100 id 3
    (the same id in another dictionary), left and right 5.5 cm DICT_4X4_50 id 8 (repeated)."""
    nominal = box_layout(SIZE)
    faces = {"top": (3, 0.09, ""), "front": (3, 0.07, "DICT_5X5_100"), "back": (3, 0.07, "DICT_5X5_100"),
             "left": (8, 0.055, ""), "right": (8, 0.055, "")}
    return CubeLayout("DICT_4X4_50", tuple(LayoutMarker(m.face, faces[m.face][0], faces[m.face][1], m.T_cube_marker,
                                                        faces[m.face][2]) for m in nominal.markers))


def body_solid(layout: CubeLayout, T_world_body: np.ndarray) -> Solid:
    faces, decals = [], []
    half = np.array(SIZE) / 2
    for m, name in zip(layout.markers, layout.marker_dictionaries, strict=True):
        T = T_world_body @ m.T_cube_marker
        axis = int(np.argmax(np.abs(m.T_cube_marker[:3, 2])))
        in_plane = np.abs(m.T_cube_marker[:3, :2]).T @ (2 * half)  # the face's extent along the marker's x, y
        faces.append(Quad(T, (float(in_plane[0]), float(in_plane[1])), WHITE_ALBEDO))
        assert np.isclose(abs(m.T_cube_marker[axis, 3]), half[axis])
        decals.append(Quad(T, (m.size_m, m.size_m), texture=MarkerTexture(name, m.marker_id)))
    return Solid(tuple(faces), tuple(decals))


def test_layout_of_two_dictionaries_round_trips_and_tells_its_markers_apart(tmp_path):
    layout = crate()
    assert layout.dictionaries == ("DICT_4X4_50", "DICT_5X5_100")
    assert layout.keys == {("DICT_4X4_50", 3), ("DICT_5X5_100", 3), ("DICT_4X4_50", 8)}
    assert layout.has_repeated_ids  # id 8 on two faces (id 3 is in two dictionaries: not repeated)
    assert list(layout.indices_of(3)) == [0, 1, 3] and list(layout.indices_of(3, "DICT_5X5_100")) == [1, 3]
    assert list(layout.indices_of(3, "DICT_4X4_50")) == [0] and not len(layout.indices_of(8, "DICT_5X5_100"))
    write_layout(layout, tmp_path / "crate.toml")
    back = read_layout(tmp_path / "crate.toml")
    assert ([(m.face, m.marker_id, m.size_m) for m in back.markers]
            == [(m.face, m.marker_id, m.size_m) for m in layout.markers])
    assert back.marker_dictionaries == layout.marker_dictionaries
    assert "DICT_5X5_100" in (tmp_path / "crate.toml").read_text()
    # a world marker of the other dictionary with the body's id there: refused by the config check
    write_toml(tracker_config_to_table(WorldConfig("DICT_5X5_100", 3), [], [("crate", "crate.toml")]),
               tmp_path / "config.toml")
    with pytest.raises(ConfigError, match="robot 'crate' uses DICT_5X5_100 id 3, already used by the world marker"):
        read_tracker_config(tmp_path / "config.toml")


@pytest.mark.parametrize("yaw_deg", [20.0, 115.0, 200.0, 290.0])
def test_the_tracker_stages_estimate_a_crate_of_two_dictionaries(yaw_deg):
    """From 1.6 m, 35 deg down: the detector (both dictionaries) finds the visible faces, the
    matcher puts each detection on its face (the 5x5 id 3 never on the 4x4 top, the repeated id 8
    on the face that faces the camera) and the single-camera estimate is within 1 cm / 1.5 deg."""
    layout = crate()
    T_world_body = make_T(R_from_rotvec([0.0, 0.0, np.radians(yaw_deg)]), [0.1, -0.05, 0.25])
    T_world_cam = look_at((1.3, 0.0, 1.2), (0.1, -0.05, 0.25))
    image = Camera(LENS, T_world_cam, [body_solid(layout, T_world_body)]).image(blur_px=0.6, noise_std=2.0)
    detections = Detector(dictionaries=layout.dictionaries).detect(image)
    mine = body_detections(detections, layout)
    assert {d.dictionary for d in mine} <= set(layout.dictionaries) and len(mine) >= 2
    matches = match_faces(mine, layout, LENS, T_world_cam, T_world_body)
    for match in matches:
        marker = layout.markers[match.marker]
        assert (layout.marker_dictionaries[match.marker], marker.marker_id) == (match.detection.dictionary,
                                                                                match.detection.marker_id)
    seen_as = [np.linalg.inv(T_world_cam) @ T_world_body @ m.T_cube_marker for m in layout.markers]
    facing = {m.face for m, T in zip(layout.markers, seen_as, strict=True)
              if T[:3, 2] @ T[:3, 3] / np.linalg.norm(T[:3, 3]) < -0.5}
    assert {m.face for m in matches} == facing  # every face seen within 60 deg of head-on
    est = estimate_cube(detections, layout, LENS, T_world_cam, camera="c", robot="crate", seq=0,
                        capture_time_s=0.0, arrival_time_s=0.0)
    assert est is not None
    assert np.linalg.norm(est.T_world_cube[:3, 3] - T_world_body[:3, 3]) < 0.01  # a wrong face: decimetres
    assert rotation_angle(est.T_world_cube[:3, :3], T_world_body[:3, :3], "deg") < 1.5
