"""Adding a provisioned camera to a tracker config: other content (and comments) stays."""

from __future__ import annotations

import tomllib

import pytest

from cubecam.configfile import set_camera
from cubecam.errors import CubecamError

CONFIG = """\
# lab setup, hand-written
[world]
dictionary = "DICT_4X4_50"
marker_size = 0.25   # metres

[[cameras]]
name = "cam1"
url = "http://192.168.1.21/stream"
camera_info = "calib/cam1.yaml"

[[robots]]
name = "robot"
layout = "cube.toml"

[fusion]
method = "mean"
"""


@pytest.fixture
def config(tmp_path):
    path = tmp_path / "tracker.toml"
    path.write_text(CONFIG)
    return path


def test_new_camera_is_appended_and_the_rest_is_kept_verbatim(config):
    assert set_camera(config, "cam2", "http://192.168.1.22/stream") == "added"
    text = config.read_text()
    assert text.startswith(CONFIG)
    doc = tomllib.loads(text)
    assert [c["name"] for c in doc["cameras"]] == ["cam1", "cam2"]
    assert doc["cameras"][1]["url"] == "http://192.168.1.22/stream"
    assert doc["fusion"] == {"method": "mean"}


def test_existing_camera_gets_its_url_replaced_in_place(config):
    assert set_camera(config, "cam1", "http://10.0.0.5/stream") == "updated"
    text = config.read_text()
    assert text == CONFIG.replace("http://192.168.1.21/stream", "http://10.0.0.5/stream")
    assert set_camera(config, "cam1", "http://10.0.0.5/stream") == "unchanged"


def test_missing_config_is_created(tmp_path):
    path = tmp_path / "new.toml"
    assert set_camera(path, "cam1", "http://x/stream") == "added"
    assert tomllib.loads(path.read_text()) == {"cameras": [{"name": "cam1", "url": "http://x/stream"}]}


def test_camera_table_without_url_gets_one(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('[[cameras]]\nname = "cam1"\ncamera_info = "a.yaml"\n\n[[cameras]]\nname = "cam2"\n')
    assert set_camera(path, "cam2", "http://y/stream") == "updated"
    doc = tomllib.loads(path.read_text())
    assert doc["cameras"] == [{"name": "cam1", "camera_info": "a.yaml"}, {"name": "cam2", "url": "http://y/stream"}]


def test_inline_camera_array_falls_back_to_a_rewrite(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('cameras = [{name = "cam1", url = "http://old/stream"}]\n')
    assert set_camera(path, "cam1", "http://new/stream") == "updated"
    assert tomllib.loads(path.read_text())["cameras"] == [{"name": "cam1", "url": "http://new/stream"}]


def test_invalid_toml_is_a_clear_error(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[[cameras]\n")
    with pytest.raises(CubecamError, match="not valid TOML"):
        set_camera(path, "cam1", "http://x/stream")
