import numpy as np
import pytest

from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.core.errors import ConfigError
from cubetrack.core.geometry import T_from_position_quat
from cubetrack.core.layout import paper_cube_layout, write_layout
from cubetrack.io.config import read_extrinsics, read_tracker_config, write_extrinsics


def write_config(tmp_path, body):
    write_layout(paper_cube_layout(), tmp_path / "cube.toml")
    p = tmp_path / "tracker.toml"
    p.write_text(body)
    return p


def test_config_resolves_relative_paths(tmp_path):
    p = write_config(tmp_path, """
[world]
marker_size = 0.2
[[cameras]]
name = "cam1"
url = "http://10.0.0.2/stream"
camera_info = "calib/cam1.yaml"
[[robots]]
name = "bot"
layout = "cube.toml"
[fusion]
method = "weighted"
""")
    cfg = read_tracker_config(p)
    assert cfg.world.marker_size_m == 0.2 and cfg.world.marker_id == 0
    assert cfg.cameras[0].camera_info == tmp_path / "calib" / "cam1.yaml"
    assert cfg.robots[0].layout.has_repeated_ids
    assert cfg.section("fusion") == {"method": "weighted"}
    assert cfg.section("filter") == {}  # sections are kept raw: app.config turns them into params


@pytest.mark.parametrize("body,match", [
    ("bogus = 1\n[[robots]]\nname='a'\nlayout='cube.toml'\n", r"bogus must be a \[bogus\] table"),
    ("[world]\nmarker_size = -1\n[[robots]]\nname='a'\nlayout='cube.toml'\n", "marker_size"),
    ("", "at least one"),
    ("[[robots]]\nname='a'\nlayout='missing.toml'\n", "missing.toml: cube layout file not found"),
    ("[[robots]\nname='a'", "not valid TOML"),
])
def test_bad_configs_are_refused(tmp_path, body, match):
    with pytest.raises(ConfigError, match=match):
        read_tracker_config(write_config(tmp_path, body))


def test_extrinsics_round_trip(tmp_path):
    T = T_from_position_quat(np.array([1.0, -2.0, 1.2]), np.array([0.1, 0.7, -0.2, 0.3]))
    write_extrinsics({"cam1": CameraExtrinsics(T, 200, 0.004, 0.1, "robust")}, tmp_path / "e.toml")
    back = read_extrinsics(tmp_path / "e.toml")["cam1"]
    np.testing.assert_allclose(back.T_world_cam, T, atol=1e-12)
    assert (back.samples, back.method) == (200, "robust")


def test_extrinsics_without_quaternion_is_refused(tmp_path):
    (tmp_path / "e.toml").write_text("[cam1]\nposition = [0, 0, 1]\n")
    with pytest.raises(ConfigError, match="quaternion_xyzw"):
        read_extrinsics(tmp_path / "e.toml")


def test_robots_sharing_a_marker_id_are_refused(tmp_path):
    p = write_config(tmp_path, "[[robots]]\nname='a'\nlayout='cube.toml'\n[[robots]]\nname='b'\nlayout='cube.toml'\n")
    with pytest.raises(ConfigError, match="robot 'b' uses DICT_4X4_50 id 1, already used by robot 'a'"):
        read_tracker_config(p)


def test_cube_using_the_world_marker_id_is_refused(tmp_path):
    p = write_config(tmp_path, "[world]\nmarker_id = 1\n[[robots]]\nname='a'\nlayout='cube.toml'\n")
    with pytest.raises(ConfigError, match="already used by the world marker"):
        read_tracker_config(p)
