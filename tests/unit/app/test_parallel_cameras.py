"""Camera worker processes (cubetrack.app.camera_workers): the forecast a worker process plans
frames with reproduces the fusion's constant-velocity predictions, and the cameras are shared
among the processes. The processes themselves run end to end in tests/e2e/test_live.py."""

import numpy as np
import pytest

from cubetrack.app.camera_workers import deal_cameras
from cubetrack.core.geometry import R_from_rotvec, make_T
from cubetrack.estimate.reprojection import moved_pose
from cubetrack.fuse.forecast import FORECAST_SPAN_S, Forecast, forecast_of


class ConstantVelocityFusion:
    """The two Fusion methods planning uses: one robot moving at constant velocity, one not tracked."""

    def __init__(self, t0, T0, v, w, lost_after_s=10.0):
        self.t0, self.T0, self.v, self.w, self.lost_after_s = t0, T0, v, w, lost_after_s

    def predicted_pose(self, robot, time_s):
        if robot != "tracked" or time_s - self.t0 > self.lost_after_s:
            return None
        return moved_pose(self.T0, self.v, self.w, time_s - self.t0)

    def needs_estimate(self, robot):
        return robot != "tracked"


@pytest.fixture
def fusion():
    T0 = make_T(R_from_rotvec(np.array([0.3, -0.2, 1.1])), np.array([0.5, -0.4, 0.1]))
    return ConstantVelocityFusion(100.0, T0, np.array([0.4, -0.1, 0.02]), np.array([0.0, 0.2, 1.5]))


def test_a_forecast_predicts_what_the_fusion_predicts(fusion):
    forecast = forecast_of(fusion, ["tracked", "lost"], 100.2)
    for t in (100.15, 100.2, 100.23, 100.26):  # frames planned a little before and after the forecast
        np.testing.assert_allclose(forecast.predicted_pose("tracked", t), fusion.predicted_pose("tracked", t),
                                   atol=1e-9)
    assert forecast.predicted_pose("lost", 100.2) is None
    assert forecast.needs_estimate("lost") and not forecast.needs_estimate("tracked")
    assert forecast.estimate_robots == frozenset({"lost"})


def test_a_robot_lost_within_the_span_is_forecast_standing_still(fusion):
    fusion.lost_after_s = 0.25  # predicted at 100.2, no longer 0.1 s later
    forecast = forecast_of(fusion, ["tracked"], 100.2)
    np.testing.assert_allclose(forecast.predicted_pose("tracked", 100.3), fusion.predicted_pose("tracked", 100.2))
    assert FORECAST_SPAN_S > 0.05


def test_a_forecast_crosses_to_the_workers_as_plain_values_unchanged(fusion):
    """Forecast.plain (what the tracker's process sends its camera worker processes) pickles and
    comes back through Forecast.from_plain predicting the same poses to the bit, with writable arrays."""
    import pickle

    forecast = forecast_of(fusion, ["tracked", "lost"], 100.2)
    back = Forecast.from_plain(pickle.loads(pickle.dumps(forecast.plain())))
    assert back.estimate_robots == forecast.estimate_robots and set(back.motions) == {"tracked"}
    for t in (100.15, 100.26):
        assert back.predicted_pose("tracked", t).tobytes() == forecast.predicted_pose("tracked", t).tobytes()
    assert all(a.flags.writeable for a in back.motions["tracked"][1:])


def test_an_empty_forecast_plans_whole_frames_and_asks_for_every_estimate():
    forecast = Forecast({}, frozenset({"a", "b"}))
    assert forecast.predicted_pose("a", 1.0) is None and forecast.needs_estimate("b")


@pytest.mark.parametrize("count", [1, 2, 3, 16, 20])
def test_every_camera_goes_to_exactly_one_process(count):
    urls = {f"cam{k}": f"http://127.0.0.1:{8000 + k}/stream" for k in range(1, 17)}
    shares = deal_cameras(urls, count)
    assert len(shares) == min(count, 16) and all(shares)
    seen = [name for share in shares for name in share]
    assert sorted(seen) == sorted(urls) and len(seen) == len(set(seen))
    assert max(map(len, shares)) - min(map(len, shares)) <= 1
    assert all(share[name] == urls[name] for share in shares for name in share)
