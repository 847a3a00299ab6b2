"""benchmarks/camera_watch.py's rejoin error in the calibrated world (issue 27): the never-moved
cameras' calibrated poses are a rigid copy of their truth, moved and a few millimetres off, and a
rejoined camera's error there leaves that copy out while its absolute error keeps it."""

import importlib
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from cubetrack.core.geometry import make_T, position_quat_from_T
from cubetrack.io.trajectory import Trajectory, write_tum

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def _pose(rng: np.random.Generator) -> np.ndarray:
    return make_T(Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), rng.normal(size=3))


def test_a_pose_in_the_calibrated_world_leaves_out_the_rigid_copy_not_the_rest(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    bench = importlib.import_module("camera_watch")
    rng = np.random.default_rng(3)
    truth = {f"cam{i}": _pose(rng) for i in range(1, 5)}
    (tmp_path / "true_camera_poses").mkdir()
    for camera, T in truth.items():
        position, q = position_quat_from_T(T)
        write_tum(Trajectory(np.array([0.0]), np.array([position]), np.array([q])),
                  tmp_path / "true_camera_poses" / f"{camera}.tum")
    G = make_T(Rotation.from_euler("z", 2.0, degrees=True).as_matrix(), [0.03, -0.01, 0.02])  # the world's copy
    nudge = make_T(np.eye(3), [0.004, 0.0, 0.0])  # one still camera 4 mm off the copy
    extrinsics = {c: SimpleNamespace(T_world_cam=G @ T) for c, T in truth.items()}
    extrinsics["cam3"] = SimpleNamespace(T_world_cam=nudge @ G @ truth["cam3"])

    found, rms_m = bench.calibrated_world(tmp_path, extrinsics, ["cam1", "cam2", "cam3"])
    exact, exact_rms_m = bench.calibrated_world(tmp_path, extrinsics, ["cam1", "cam2"])
    np.testing.assert_allclose(exact, G, atol=1e-5)  # (the TUM files keep micrometres)
    assert exact_rms_m < 1e-5
    assert 0.001 < rms_m < 0.004   # the nudged camera's 4 mm, shared out over the three
    # cam4 rejoined exactly where the copy puts its truth: no error in the world, the copy's in absolute terms
    step_m, turn_deg = bench.pose_error(exact @ truth["cam4"], G @ truth["cam4"])
    assert step_m < 1e-5 and turn_deg < 1e-3
    step_m, turn_deg = bench.pose_error(truth["cam4"], G @ truth["cam4"])
    assert step_m > 0.01 and math.isclose(turn_deg, 2.0, abs_tol=1e-3)


def test_an_unbumped_session_has_no_bump_rows_and_needs_no_true_camera_poses(tmp_path, monkeypatch):
    """``--long`` (the 10-minute false-alarm run): nothing was bumped, so the recording has no
    true_camera_poses/ folder (the simulator writes it only for cameras that move); the watched
    replay's bump rows are empty instead of a crash reading it."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    bench = importlib.import_module("camera_watch")
    extrinsics = {f"cam{i}": SimpleNamespace(T_world_cam=np.eye(4)) for i in range(1, 4)}
    assert bench.bump_rows(tmp_path, [], bench.Moves(), 0.0, extrinsics) == {}
