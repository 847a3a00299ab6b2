"""Fixtures for the output tests; the helpers live in sink_helpers.py (importable from other folders)."""

import numpy as np
import pytest
from sink_helpers import (  # noqa: F401  (re-exported for the tests of this folder)
    INTRINSICS,
    free_port,
    look_at,
    open_router,
    peer,
    tracked,
    wait_connected,
)

from cubetrack.core.cameras import WorldConfig
from cubetrack.core.layout import paper_cube_layout
from cubetrack.sink.base import CameraSetup, SessionInfo


@pytest.fixture
def router():
    """:func:`open_router`; yields its locator."""
    session, locator = open_router()
    yield locator
    session.close()


@pytest.fixture
def session_info() -> SessionInfo:
    """Robots ``robot 1!`` and ``2nd`` (names no ROS or VRPN tool accepts as they are), cameras
    ``cam-a`` and ``cam b`` (calibrated) and ``cam_c`` (not yet)."""
    cameras = (CameraSetup("cam-a", look_at(np.array([1.0, 0.0, 1.0]), [0, 0, 0]), INTRINSICS),
               CameraSetup("cam b", look_at(np.array([0.0, 1.0, 1.0]), [0, 0, 0]), INTRINSICS),
               CameraSetup("cam_c", None, INTRINSICS))
    layout = paper_cube_layout()
    return SessionInfo(WorldConfig(), cameras, {"robot 1!": layout, "2nd": paper_cube_layout(marker_id=5)})
