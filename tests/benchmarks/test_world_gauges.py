"""benchmarks/world_gauges.py: the floor gauge is the world turn that levels the drive's plane (its
sign and size on a known plane), and on the clean preset (level floor, exact camera_info) both
gauges are zero while the realistic preset's floor bumps and camera_info errors give both a tilt.
No image is rendered."""

import importlib
import math
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture
def bench(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    return importlib.import_module("world_gauges")


class _PlaneScene:
    """A cube circling on the plane z = 0.2 + a x + b y."""

    def __init__(self, a: float, b: float):
        self.a, self.b = a, b

    def T_world_cube(self, t_s: float) -> np.ndarray:
        x, y = 0.4 * math.cos(t_s), 0.25 * math.sin(1.3 * t_s)
        T = np.eye(4)
        T[:3, 3] = [x, y, 0.2 + self.a * x + self.b * y]
        return T


def test_the_floor_gauge_is_the_turn_that_levels_the_drives_plane(bench):
    tilt = bench.floor_tilt_deg(_PlaneScene(0.01, -0.004), 0.0, 20.0)
    # a world turned by +atan(dz/dy) about x and -atan(dz/dx) about y sees this plane level
    assert tilt == pytest.approx([math.degrees(math.atan(-0.004)), -math.degrees(math.atan(0.01))], abs=1e-6)
    # true-from-estimated: the estimated world's up is the plane's normal in the true world
    up = bench.Rotation.from_rotvec(np.radians([*tilt, 0.0])).apply([0.0, 0.0, 1.0])
    assert up / up[2] == pytest.approx([-0.01, 0.004, 1.0], abs=1e-5)


def test_clean_gauges_are_level_and_realistic_ones_are_not(bench):
    clean_floor, clean_marker = bench.gauges("clean", 1, 7, 2.0, 6.0)
    assert np.abs(clean_floor).max() < 1e-3 and np.abs(clean_marker).max() < 1e-3
    floor, marker = bench.gauges("realistic", 1, 7, 2.0, 6.0)
    assert np.hypot(*floor) > 0.02 and np.hypot(*marker) > 0.02
