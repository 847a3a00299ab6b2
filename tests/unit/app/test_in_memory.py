"""Issue 8's done-when: the library functions of calibration, bundle adjustment and tracking run
on frames held in memory, with no file on disk. A short simulated session is read into memory
once, its folder deleted, and the in-memory calls must give exactly what the file workflows
(``cubetrack.app.calibrate``, ``cubetrack.app.track``) gave on the folder."""

import heapq
import shutil

import numpy as np
import pytest

from cubetrack.app.calibrate import adjust_recording_extrinsics, calibrate_recording
from cubetrack.app.config import load_config, recording_intrinsics
from cubetrack.app.track import track_frames, track_recording
from cubetrack.calib.bundle import adjust_extrinsics
from cubetrack.calib.extrinsics import calibrate_cameras, extrinsics_errors
from cubetrack.io.config import read_extrinsics
from cubetrack.io.recording import Recording
from cubetrack.simulate import SimulationParams, simulate
from cubetrack.sink.base import Sink


class Collect(Sink):
    """A sink that keeps every pose in memory."""

    in_line = True

    def __init__(self):
        self.poses = []

    def pose(self, pose):
        self.poses.append(pose)


def _frames(recording):
    return {c: list(recording.frames(c)) for c in recording.camera_names}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """(in-memory copy of the session, what the file workflows produced from it)."""
    root = tmp_path_factory.mktemp("in_memory")
    rec = root / "rec"
    simulate(SimulationParams(duration_s=4, calibration_frames=20, seed=3), rec)
    config, settings = load_config(rec / "config.toml")
    recording, calibration = Recording.open(rec), Recording.open(rec / "calibration")
    memory = {
        "world": config.world,
        "layouts": {r.name: r.layout for r in config.robots},
        "intrinsics": recording_intrinsics(config, recording),
        "frames": _frames(recording),
        "calibration_frames": _frames(calibration),
        "clock": {c: recording.clock_samples(c) for c in recording.camera_names},
        "truth": read_extrinsics(rec / "true_extrinsics.toml"),
        "settings": settings,
    }
    files = {"calibration": calibrate_recording(config, calibration)}
    files["adjusted"] = adjust_recording_extrinsics(config, Recording.open(rec), files["calibration"].extrinsics,
                                                    Recording.open(rec / "calibration"))
    collected = Collect()
    files["track"] = track_recording(config, Recording.open(rec), files["adjusted"].extrinsics, root / "out",
                                     sinks=[collected])
    files["poses"] = collected.poses
    shutil.rmtree(root)  # from here on there is no file to read
    return memory, files


def _same_extrinsics(a, b):
    assert set(a) == set(b)
    for name in a:
        np.testing.assert_array_equal(a[name].T_world_cam, b[name].T_world_cam)
        assert a[name].samples == b[name].samples and a[name].method == b[name].method


def test_calibration_runs_on_frames_in_memory(session):
    memory, files = session
    report = calibrate_cameras(memory["calibration_frames"], memory["intrinsics"], memory["world"],
                               memory["settings"].calibration, memory["settings"].detector)
    _same_extrinsics(report.extrinsics, files["calibration"].extrinsics)
    for pos_m, rot_deg in extrinsics_errors(report.extrinsics, memory["truth"]).values():
        assert pos_m < 0.01 and rot_deg < 0.2


def test_bundle_adjustment_runs_on_frames_in_memory(session):
    memory, files = session
    report = adjust_extrinsics(memory["frames"], files["calibration"].extrinsics, memory["intrinsics"],
                               memory["layouts"], memory["world"], clock_samples=memory["clock"],
                               world_frames=memory["calibration_frames"])
    assert report.instants == files["adjusted"].instants > 10
    _same_extrinsics(report.extrinsics, files["adjusted"].extrinsics)
    for pos_m, rot_deg in extrinsics_errors(report.extrinsics, memory["truth"]).values():
        assert pos_m < 0.02 and rot_deg < 0.3


def test_tracking_runs_on_frames_in_memory(session):
    memory, files = session
    frames = heapq.merge(*memory["frames"].values(), key=lambda f: (f.host_time_s, f.camera))
    out = Collect()
    stats = track_frames(frames, memory["intrinsics"], memory["world"], memory["layouts"],
                         files["adjusted"].extrinsics, out, memory["settings"].stages, clock_samples=memory["clock"])
    assert stats.frames == files["track"].stats.frames and stats.poses == files["track"].stats.poses
    assert len(out.poses) == len(files["poses"]) > 20
    for mine, theirs in zip(out.poses, files["poses"], strict=True):
        assert (mine.robot, mine.time_s) == (theirs.robot, theirs.time_s)
        np.testing.assert_array_equal(mine.position_m, theirs.position_m)
