"""A short simulated session shared by the simulate tests (rendered once per test run)."""

from __future__ import annotations

import pytest

from cubetrack.simulate import SimulationParams, simulate

# Short, with frequent drops and latency spikes so the timing properties are exercised.
SESSION = SimulationParams(duration_s=6.0, calibration_frames=12, drop_rate=0.1, spike_rate=0.1, seed=11)


@pytest.fixture(scope="session")
def session(tmp_path_factory):
    """(SimulationResult, path) of a 3-camera, 6 s recording with a 12-frame calibration recording."""
    out = tmp_path_factory.mktemp("sim") / "rec"
    return simulate(SESSION, out)


# Every effect of the realistic preset, short: two cameras, 3 s.
REALISTIC_SESSION = SimulationParams.realistic(cameras=2, duration_s=3.0, calibration_frames=4, seed=5)


@pytest.fixture(scope="session")
def realistic_session(tmp_path_factory):
    """SimulationResult of a 2-camera, 3 s recording of the realistic preset."""
    out = tmp_path_factory.mktemp("sim") / "realistic"
    return simulate(REALISTIC_SESSION, out)
