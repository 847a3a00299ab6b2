"""Every fusion implements the Fusion protocol of fuse/base.py exactly: the same methods with the
same parameters, so the workflow layer calls any fusion without asking which one it is."""

import inspect

import numpy as np
import pytest
from test_fuse import estimate

from cubetrack.core.layout import paper_cube_layout
from cubetrack.core.records import CubeSighting
from cubetrack.fuse.base import Fusion
from cubetrack.fuse.fusion import FilterFusion, FusionParams, LatestEstimateFusion

PROTOCOL = ("needs_estimate", "add", "predicted_pose", "flush", "release")


def fusions():
    return [LatestEstimateFusion(FusionParams()), FilterFusion({"bot": paper_cube_layout()})]


@pytest.mark.parametrize("fusion", fusions(), ids=lambda f: type(f).__name__)
def test_methods_and_parameters_match_the_protocol(fusion):
    for name in PROTOCOL:
        expected = inspect.signature(getattr(Fusion, name))
        actual = inspect.signature(getattr(type(fusion), name))
        assert list(actual.parameters) == list(expected.parameters), name
        # no defaults beyond the protocol's: a caller that leaves one out works with no fusion
        assert all(p.default is inspect.Parameter.empty for p in actual.parameters.values()), name


@pytest.mark.parametrize("fusion", fusions(), ids=lambda f: type(f).__name__)
def test_untracked_robot_is_not_predicted_and_flush_returns_poses(fusion):
    assert fusion.predicted_pose("bot", 10.0) is None
    assert fusion.flush(10.0) == []


def test_latest_estimate_fusion_answers_at_once_and_holds_nothing_back():
    fusion = LatestEstimateFusion(FusionParams())
    e = estimate("cam1", 10.0, 0.5)
    sighting = CubeSighting("cam1", "bot", 0, 10.0, 10.05, (), e, np.eye(4), None)
    poses = fusion.add(sighting, 10.07)
    assert len(poses) == 1 and poses[0].position_m[0] == pytest.approx(0.5)
    assert fusion.predicted_pose("bot", 10.1) is None  # no motion model, even with a track
    assert fusion.flush(10.2) == [] and fusion.release(10.2) == []
