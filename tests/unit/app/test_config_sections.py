"""The body calibration's settings are a section of their own, ``[body_calibration]`` (issue 23);
a config that still sets them as ``[bundle_adjustment] body_*`` keys is refused with one line
saying where each moved, before anything runs."""

import pytest

from cubetrack.app.config import load_config
from cubetrack.calib.bundle import BodyCalibrationParams, BundleAdjustmentParams
from cubetrack.core.errors import ConfigError
from cubetrack.core.layout import paper_cube_layout, write_layout

ROBOT = '[[robots]]\nname = "r"\nlayout = "cube.toml"\n'


def config(tmp_path, text: str):
    write_layout(paper_cube_layout(), tmp_path / "cube.toml")
    (tmp_path / "c.toml").write_text(ROBOT + text)
    return tmp_path / "c.toml"


def test_the_body_calibration_section_sets_the_body_settings(tmp_path):
    _, settings = load_config(config(tmp_path, "[body_calibration]\nknot_s = 0.0\nedge_corners = false\n"))
    assert settings.body_calibration == BodyCalibrationParams(knot_s=0.0, edge_corners=False)
    assert settings.bundle_adjustment == BundleAdjustmentParams()
    with pytest.raises(ConfigError, match=r"c\.toml: \[body_calibration\]: knot_s must not be negative"):
        load_config(config(tmp_path, "[body_calibration]\nknot_s = -1.0\n"))


def test_an_old_body_key_is_refused_with_where_it_moved(tmp_path):
    path = config(tmp_path, "[bundle_adjustment]\nmax_span_s = 0.2\nbody_knot_s = 0.0\nbody_edge_corners = false\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(err.value) == (f"{path}: [bundle_adjustment] body_knot_s, body_edge_corners moved to "
                              "[body_calibration] as knot_s, edge_corners (the same meaning and values)")
