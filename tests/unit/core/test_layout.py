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


def test_bad_layout_names_the_file(tmp_path):
    p = tmp_path / "cube.toml"
    p.write_text('[[markers]]\nface = "top"\nid = 1\nsize = 0.08\nposition = [0, 0]\nquaternion_xyzw = [0, 0, 0, 1]\n')
    with pytest.raises(ConfigError, match=r"cube\.toml: markers\[0\]\.position"):
        read_layout(p)


def test_marker_bigger_than_cube_is_refused():
    with pytest.raises(ConfigError):
        paper_cube_layout(cube_size_m=0.05, marker_size_m=0.08)
