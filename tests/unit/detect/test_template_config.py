"""The template refinement's config: [detector] corner_refinement = "template" reaches the
tracker's detector and changes nothing else in the filter than the edge fit's per-corner noise law
(the template fit's corners do not follow it) unless the [filter] says otherwise; a [filter] that
trusts the corners gets a one-line warning unless the corners are template-fitted and every cube's
layout is calibrated (a layout as designed: a marker 1 mm off reads as a turned cube)."""

import dataclasses
import logging

import numpy as np
import pytest

from cubetrack.app.config import config_params, is_as_designed, load_config
from cubetrack.app.tracker import FrameProcessor
from cubetrack.core.cameras import WorldConfig
from cubetrack.core.geometry import R_from_rotvec, make_T
from cubetrack.core.layout import CubeLayout, LayoutMarker, paper_cube_layout, write_layout
from cubetrack.detect.detector import CornerRefinement
from cubetrack.fuse.corner_filter import FilterParams
from cubetrack.io.config import read_tracker_config

TRUSTING = "[filter]\ncorner_noise_px = 0.05\nangular_accel_noise = 5.0\n"
TEMPLATE = '[detector]\ncorner_refinement = "template"\n'


def measured(layout: CubeLayout) -> CubeLayout:
    """``layout`` as calibrate-body leaves it: each marker a fraction of a millimetre and degree off."""
    rng = np.random.default_rng(3)
    return CubeLayout(layout.dictionary, tuple(
        LayoutMarker(m.face, m.marker_id, m.size_m, m.T_cube_marker @ make_T(R_from_rotvec(rng.normal(0, 2e-3, 3)),
                                                                              rng.normal(0, 3e-4, 3)))
        for m in layout.markers))


def config_file(tmp_path, layout: CubeLayout, *sections: str):
    write_layout(layout, tmp_path / "cube.toml")
    path = tmp_path / "config.toml"
    path.write_text('cameras = [{ name = "cam1", url = "" }]\nrobots = [{ name = "bot", layout = "cube.toml" }]\n'
                    '[world]\ndictionary = "DICT_4X4_50"\nmarker_id = 0\nmarker_size = 0.25\n' + "\n".join(sections),
                    encoding="utf-8")
    return path


def test_the_switch_reaches_the_detector_and_leaves_the_filter_as_it_was(tmp_path):
    config, params = load_config(config_file(tmp_path, paper_cube_layout(), TEMPLATE))
    assert params.detector.corner_refinement is CornerRefinement.TEMPLATE
    # no trusting filter behind the user's back; only the edge fit's per-corner noise law is off
    assert params.filter == dataclasses.replace(FilterParams(), corner_noise_by_width=False)
    worker = FrameProcessor({}, WorldConfig("DICT_4X4_50", 0, 0.25), config.robots, {}, params.stages)
    assert worker.detector.params.corner_refinement is CornerRefinement.TEMPLATE


@pytest.mark.parametrize("sections,by_width", [
    ((), True),                                                        # the edge fit: its law
    (('[detector]\ncorner_refinement = "subpix"\n',), False),        # another refinement: every corner the same
    ((TEMPLATE,), False),
    ((TEMPLATE, "[filter]\ncorner_noise_by_width = true\n"), True),  # the user's word stands
    (("[filter]\ncorner_noise_by_width = false\n",), False),
])
def test_the_per_corner_noise_law_is_the_edge_fits_unless_the_filter_says(tmp_path, sections, by_width):
    assert config_params(read_tracker_config(config_file(tmp_path, paper_cube_layout(), *sections))
                         ).filter.corner_noise_by_width is by_width


@pytest.mark.parametrize("sections,calibrated,warned", [
    ((), False, None),                         # defaults: nothing trusted
    ((TEMPLATE,), False, None),                # the switch alone: the filter stays as it was
    ((TRUSTING,), True, "measures them"),      # edge corners trusted: warned even with a calibrated body
    ((TEMPLATE, TRUSTING), False, "as designed"),  # template corners trusted on a nominal cube: warned
    ((TEMPLATE, TRUSTING), True, None),        # the recommended setting: template, calibrated body, trusting filter
])
def test_a_filter_that_trusts_the_corners_is_warned_about_unless_it_may(tmp_path, caplog, sections, calibrated, warned):
    layout = measured(paper_cube_layout()) if calibrated else paper_cube_layout()
    assert is_as_designed(layout) is not calibrated
    with caplog.at_level(logging.WARNING, logger="cubetrack.app.config"):
        config_params(read_tracker_config(config_file(tmp_path, layout, *sections)))
    lines = [r.getMessage() for r in caplog.records]
    if warned is None:
        assert lines == []
    else:
        assert len(lines) == 1 and warned in lines[0] and "\n" not in lines[0]


def test_a_layout_with_faces_of_its_own_is_not_taken_for_a_designed_cube():
    layout = paper_cube_layout()
    own = CubeLayout(layout.dictionary, (LayoutMarker("lid", 1, 0.08, layout.markers[0].T_cube_marker),))
    assert is_as_designed(layout) and not is_as_designed(own)
