import json

import numpy as np
import pytest

from cubetrack.core.errors import TrajectoryError
from cubetrack.core.records import TrackedPose
from cubetrack.io.trajectory import PoseWriter, Trajectory, read_tum, write_tum


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    q = rng.normal(size=(5, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    traj = Trajectory(1.7e9 + np.arange(5) * 0.1, rng.normal(size=(5, 3)), q)
    write_tum(traj, tmp_path / "t.tum")
    back = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(back.times_s, traj.times_s, atol=1e-6)
    np.testing.assert_allclose(back.positions_m, traj.positions_m, atol=1e-6)
    np.testing.assert_allclose(back.quats_xyzw, traj.quats_xyzw, atol=1e-9)


def test_bad_tum_line_names_file_and_line(tmp_path):
    p = tmp_path / "t.tum"
    p.write_text("# comment\n1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryError, match=r"t\.tum:3: expected 8 numbers"):
        read_tum(p)


def test_empty_tum_is_refused(tmp_path):
    p = tmp_path / "t.tum"
    p.write_text("# nothing\n")
    with pytest.raises(TrajectoryError, match="no poses"):
        read_tum(p)


def test_pose_writer_writes_tum_and_jsonl(tmp_path):
    pose = TrackedPose("bot", 12.5, np.array([1.0, 2.0, 3.0]), np.array([0, 0, 0, 1.0]),
                       ("cam1", "cam2"), ("cam1:top",), 0.04)
    with PoseWriter(tmp_path, "bot") as w:
        w.write(pose)
    assert read_tum(tmp_path / "bot.tum").positions_m.tolist() == [[1.0, 2.0, 3.0]]
    obj = json.loads((tmp_path / "bot.jsonl").read_text())
    assert obj["robot"] == "bot" and obj["cameras"] == ["cam1", "cam2"] and obj["latency"] == 0.04
    assert obj["quaternion_xyzw"] == [0, 0, 0, 1.0]


def test_the_smoother_fields_are_the_jsonl_objects_last_keys_only_when_set(tmp_path):
    """contracts §5: a smoothed pose adds "smoothed": true, a fixed-lag one also "smooth_lag_s", after
    the other keys; a causal pose has neither."""
    import dataclasses

    causal = TrackedPose("bot", 12.5, np.array([1.0, 2.0, 3.0]), np.array([0, 0, 0, 1.0]), ("cam1",), (), 0.04,
                         arrival_latency_s=0.01)
    whole = dataclasses.replace(causal, time_s=12.6, smoothed=True)
    lagged = dataclasses.replace(causal, time_s=12.7, smoothed=True, smooth_lag_s=0.05)
    with PoseWriter(tmp_path, "bot") as w:
        for pose in (causal, whole, lagged):
            w.write(pose)
    objects = [json.loads(line) for line in (tmp_path / "bot.jsonl").read_text().splitlines()]
    assert [list(o)[-2:] for o in objects] == [["latency", "arrival_latency"], ["arrival_latency", "smoothed"],
                                               ["smoothed", "smooth_lag_s"]]
    assert objects[1]["smoothed"] is True and objects[2]["smooth_lag_s"] == 0.05


@pytest.mark.parametrize("failing", ["tum", "jsonl"])
def test_a_pose_line_the_disk_refuses_is_an_error_naming_its_file(tmp_path, monkeypatch, failing):
    """PoseWriter writes both lines under one error handler: a refused write names the file it was
    writing (not the other), in one line with the system's reason."""
    import errno

    from cubetrack.io.files import LineFile

    write_line = LineFile.write_line

    def refusing(self, line):
        if self.path.suffix == f".{failing}":
            raise OSError(errno.ENOSPC, "No space left on device")
        write_line(self, line)

    pose = TrackedPose("bot", 12.5, np.array([1.0, 2.0, 3.0]), np.array([0, 0, 0, 1.0]), ("cam1",), (), 0.04)
    with PoseWriter(tmp_path, "bot") as w:
        monkeypatch.setattr(LineFile, "write_line", refusing)
        with pytest.raises(TrajectoryError) as caught:
            w.write(pose)
    assert str(caught.value) == f"{tmp_path / ('bot.' + failing)}: cannot write: No space left on device"
