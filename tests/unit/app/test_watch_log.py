"""cubetrack.app.watch_log on a folder that is not fresh (issue 27, docs/calibration.md "Keeping what
was learnt"): an earlier session's versioned extrinsics are never written over, and a file that
cannot be written costs one error line, never the session nor an event (the run record keeps it)."""

from __future__ import annotations

import json
import logging

import numpy as np

from cubetrack.app.watch_log import EVENTS_FILE, WatchLog
from cubetrack.core.cameras import CameraExtrinsics
from cubetrack.core.geometry import make_T
from cubetrack.fuse.camera_watch import EventKind, WatchEvent
from cubetrack.io.config import read_extrinsics, write_extrinsics

CAMERAS = {"cam1": make_T(np.eye(3), [2.0, 0.0, 1.0]), "cam2": make_T(np.eye(3), [0.0, 2.0, 1.0])}
NEW = make_T(np.eye(3), [0.02, 2.0, 1.0])  # cam2 after a 2 cm bump
T0 = 1.75e9


def _session(log_: WatchLog, camera: str = "cam2", at_s: float = 3.0) -> None:
    """One bump of ``camera``: declared moved, then rejoined at NEW."""
    log_(WatchEvent(EventKind.MOVED, camera, T0 + at_s, 0.021, 0.9, NEW))
    log_(WatchEvent(EventKind.REJOINED, camera, T0 + at_s + 20.0, 0.02, 0.1, NEW, 150))


def _extrinsics() -> dict[str, CameraExtrinsics]:
    return {c: CameraExtrinsics(T, method="marker") for c, T in CAMERAS.items()}


def test_an_earlier_sessions_versioned_extrinsics_are_never_written_over(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    write_extrinsics(_extrinsics(), out / "extrinsics.watch-1.toml")
    write_extrinsics(_extrinsics(), out / "extrinsics.watch-3.toml")
    (out / EVENTS_FILE).write_text('{"event": "moved", "camera": "cam1"}\n', encoding="utf-8")
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    log_ = WatchLog(out, _extrinsics())
    _session(log_)
    _session(log_, at_s=40.0)

    assert [p.name for p in log_.written] == ["extrinsics.watch-4.toml", "extrinsics.watch-5.toml"]
    for name, data in before.items():  # the earlier session's files: untouched (its events kept, ours after them)
        assert (out / name).read_bytes()[:len(data)] == data, name
    lines = [json.loads(x) for x in (out / EVENTS_FILE).read_text(encoding="utf-8").splitlines()]
    assert [x.get("extrinsics") for x in lines] == [None, None, "extrinsics.watch-4.toml", None,
                                                    "extrinsics.watch-5.toml"]
    assert lines[1:] == log_.summary()["camera_watch"]
    assert np.allclose(read_extrinsics(out / "extrinsics.watch-4.toml")["cam2"].T_world_cam, NEW, atol=1e-9)


def test_files_that_cannot_be_written_cost_an_error_line_not_an_event(tmp_path, caplog):
    """The events file and the user's extrinsics file blocked (a folder where each should be): the
    versioned file is still written, each failure is one error line, every event is in the record."""
    out = tmp_path / "out"
    (out / EVENTS_FILE).mkdir(parents=True)
    user_file = tmp_path / "extrinsics.toml"
    user_file.mkdir()
    log_ = WatchLog(out, _extrinsics(), update_path=user_file)
    with caplog.at_level(logging.WARNING, logger="cubetrack.app.watch_log"):
        _session(log_)
        _session(log_, camera="cam1", at_s=40.0)

    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert len([e for e in errors if EVENTS_FILE in e]) == 1, errors  # said once, not per event
    assert len([e for e in errors if "not updated" in e]) == 2, errors
    assert all(e.count("\n") == 0 for e in errors)
    records = log_.summary()["camera_watch"]
    assert [(r["event"], r["camera"]) for r in records] == [("moved", "cam2"), ("rejoined", "cam2"),
                                                            ("moved", "cam1"), ("rejoined", "cam1")]
    assert [r["extrinsics"] for r in records[1::2]] == ["extrinsics.watch-1.toml", "extrinsics.watch-2.toml"]
    written = read_extrinsics(out / "extrinsics.watch-2.toml")  # both re-calibrated cameras at their new pose
    assert np.allclose(written["cam1"].T_world_cam, NEW) and np.allclose(written["cam2"].T_world_cam, NEW)
    assert (out / EVENTS_FILE).is_dir() and user_file.is_dir() and not list(user_file.iterdir())


def test_an_output_folder_that_cannot_be_made_keeps_the_pose_in_the_record(tmp_path, caplog):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("keep me", encoding="utf-8")
    log_ = WatchLog(blocker / "out", _extrinsics())
    with caplog.at_level(logging.ERROR, logger="cubetrack.app.watch_log"):
        _session(log_)
    rejoined = log_.summary()["camera_watch"][1]
    assert "extrinsics" not in rejoined and "cannot write" in rejoined["extrinsics_error"]
    assert np.allclose(rejoined["position"], NEW[:3, 3]) and log_.written == []
    assert blocker.read_text(encoding="utf-8") == "keep me"
    assert len(caplog.records) == 2  # the events file, the extrinsics file: one line each


def test_update_extrinsics_without_an_extrinsics_file_is_one_error_line(tmp_path, capsys):
    from cubetrack.cli.main import main

    assert main(["track", "--config", str(tmp_path / "lab.toml"), "--uncalibrated", "--recording", str(tmp_path),
                 "--out", str(tmp_path / "out"), "--update-extrinsics"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--update-extrinsics" in err and "give --extrinsics" in err, err
    assert not (tmp_path / "out").exists()
