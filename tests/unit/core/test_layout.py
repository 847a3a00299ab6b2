import numpy as np
import pytest

from cubetrack.core.errors import ConfigError
from cubetrack.core.layout import FACES, paper_cube_layout, read_layout, write_layout


def test_paper_scheme_up_axes_are_distinct():
    layout = paper_cube_layout()
    ups = {m.face: tuple(np.round(m.T_cube_marker[:3, :3].T @ [0, 0, 1]).astype(int)) for m in layout.markers}
    assert ups == {"top": (0, 0, 1), "front": (0, 1, 0), "left": (1, 0, 0), "back": (0, -1, 0), "right": (-1, 0, 0)}
    assert layout.has_repeated_ids and layout.ids == {1}


def test_marker_normals_point_out_of_the_cube_and_sit_on_its_faces():
    layout = paper_cube_layout(cube_size_m=0.11, marker_size_m=0.08)
    for m in layout.markers:
        normal = m.T_cube_marker[:3, 2]
        centre = m.T_cube_marker[:3, 3]
        assert np.dot(normal, centre) == pytest.approx(0.055)
        assert np.allclose(np.abs(m.corners_cube_m()).max(), 0.055)


def test_distinct_ids():
    layout = paper_cube_layout(marker_id=10, distinct_ids=True)
    assert sorted(m.marker_id for m in layout.markers) == [10, 11, 12, 13, 14]


def test_layout_toml_round_trip(tmp_path):
    layout = paper_cube_layout(distinct_ids=True)
    write_layout(layout, tmp_path / "cube.toml")
    back = read_layout(tmp_path / "cube.toml")
    assert [m.face for m in back.markers] == list(FACES)
    for a, b in zip(layout.markers, back.markers, strict=True):
        np.testing.assert_allclose(a.T_cube_marker, b.T_cube_marker, atol=1e-9)


def test_a_layouts_motion_is_kept_and_checked(tmp_path):
    """``motion`` (issue 25: "floor", the default, or "free") survives the file; anything else is refused."""
    import dataclasses

    write_layout(dataclasses.replace(paper_cube_layout(), motion="free"), tmp_path / "cube.toml")
    assert read_layout(tmp_path / "cube.toml").motion == "free"
    write_layout(paper_cube_layout(), tmp_path / "floor.toml")
    assert read_layout(tmp_path / "floor.toml").motion == "floor"
    assert "motion" not in (tmp_path / "floor.toml").read_text()  # files without the switch stay as they were
    (tmp_path / "bad.toml").write_text('motion = "hand"\n' + (tmp_path / "floor.toml").read_text())
    with pytest.raises(ConfigError, match=r"bad\.toml: a cube layout's motion must be one of floor, free, got 'hand'"):
        read_layout(tmp_path / "bad.toml")


def test_bad_layout_names_the_file(tmp_path):
    p = tmp_path / "cube.toml"
    p.write_text('[[markers]]\nface = "top"\nid = 1\nsize = 0.08\nposition = [0, 0]\nquaternion_xyzw = [0, 0, 0, 1]\n')
    with pytest.raises(ConfigError, match=r"cube\.toml: markers\[0\]\.position"):
        read_layout(p)


def test_marker_bigger_than_cube_is_refused():
    with pytest.raises(ConfigError):
        paper_cube_layout(cube_size_m=0.05, marker_size_m=0.08)


def test_markers_of_different_dictionaries_with_one_pattern_are_named():
    from cubetrack.core.layout import marker_bits, pattern_collisions

    assert np.array_equal(marker_bits("DICT_4X4_50", 0), marker_bits("DICT_4X4_1000", 0))
    owners = {("DICT_4X4_50", 0): "the world marker", ("DICT_4X4_1000", 0): "robot 'board'",
              ("DICT_4X4_1000", 7): "robot 'other'", ("DICT_5X5_50", 0): "robot 'big'"}
    (line,) = pattern_collisions(owners)
    assert "the world marker (DICT_4X4_50 id 0)" in line and "robot 'board' (DICT_4X4_1000 id 0)" in line
    # the predefined 4x4 dictionaries share their first patterns
    assert pattern_collisions({("DICT_4X4_50", 3): "a", ("DICT_4X4_100", 3): "b"})
    with pytest.raises(ConfigError, match="ids 0..49"):
        marker_bits("DICT_4X4_50", 50)


def test_a_config_whose_world_marker_is_a_body_marker_of_another_dictionary_is_refused(tmp_path):
    from cubetrack.io.config import read_tracker_config

    layout = paper_cube_layout(dictionary="DICT_4X4_1000", marker_id=0)
    write_layout(layout, tmp_path / "cube.toml")
    (tmp_path / "config.toml").write_text('[[robots]]\nname = "bot"\nlayout = "cube.toml"\n')
    collision = r"robot 'bot' \(DICT_4X4_1000 id 0\) and the world marker \(DICT_4X4_50 id 0\)"
    with pytest.raises(ConfigError, match=collision):
        read_tracker_config(tmp_path / "config.toml")
    write_layout(paper_cube_layout(dictionary="DICT_4X4_1000", marker_id=60), tmp_path / "cube.toml")
    assert read_tracker_config(tmp_path / "config.toml").robots[0].layout.ids == {60}
