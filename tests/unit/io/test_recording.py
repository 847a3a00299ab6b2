import json

import cv2
import numpy as np
import pytest

from cubetrack.core.cameras import ClockSample
from cubetrack.core.errors import RecordingError
from cubetrack.io.recording import CameraEntry, Recording, RecordingWriter


def jpeg(value: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", np.full((8, 8), value, np.uint8))
    assert ok
    return buf.tobytes()


def make(tmp_path, cameras=("cam1", "cam2")):
    rec = tmp_path / "rec"
    with RecordingWriter(rec, [CameraEntry(c, f"http://{c}/stream") for c in cameras]) as w:
        w.add_frame("cam1", 5, 10.000001, 1700000000.25, jpeg(10))
        w.add_frame("cam1", 7, 10.266667, 1700000000.50, jpeg(20))
        w.add_frame("cam2", 1, 3.5, 1700000000.30, jpeg(30))
        w.add_clock_sample("cam1", ClockSample(1700000000.0, 9.75, 1700000000.01))
    return rec


def test_round_trip_keeps_every_field(tmp_path):
    rec = Recording.open(make(tmp_path))
    assert rec.camera_names == ("cam1", "cam2")
    assert rec.cameras[0].source == "http://cam1/stream"
    frames = list(rec.frames("cam1"))
    assert [f.seq for f in frames] == [5, 7]
    assert frames[0].device_time_s == pytest.approx(10.000001, abs=1e-9)
    assert frames[1].host_time_s == pytest.approx(1700000000.5, abs=1e-6)
    assert cv2.imdecode(np.frombuffer(frames[1].jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)[0, 0] == pytest.approx(20, abs=2)
    assert rec.clock_samples("cam1") == [ClockSample(1700000000.0, 9.75, 1700000000.01)]
    assert rec.clock_samples("cam2") == []


def test_merged_frames_follow_arrival_order(tmp_path):
    rec = Recording.open(make(tmp_path))
    assert [(f.camera, f.seq) for f in rec.merged_frames()] == [("cam1", 5), ("cam2", 1), ("cam1", 7)]


def test_missing_frame_file_is_skipped_and_counted(tmp_path):
    path = make(tmp_path)
    (path / "cam1" / "00000005.jpg").unlink()
    rec = Recording.open(path)
    assert [f.seq for f in rec.frames("cam1")] == [7]
    assert rec.skipped["missing frame file"] == 1


def test_malformed_index_rows_are_skipped_and_counted(tmp_path):
    path = make(tmp_path)
    with (path / "cam1" / "index.csv").open("a") as f:
        f.write("garbage\n8,notanumber,1.0,x.jpg\n9,1.0,2.0,../escape.jpg\n")
    rec = Recording.open(path)
    assert len(rec.index("cam1")) == 2
    assert rec.skipped["bad index row"] == 3


def test_each_skipped_row_or_file_is_counted_once_however_often_it_is_read(tmp_path):
    """Reading a camera's index, clock or frames again (calibration, then tracking) does not
    report one bad row as two."""
    path = make(tmp_path)
    with (path / "cam1" / "index.csv").open("a") as f:
        f.write("garbage\n")
    with (path / "cam1" / "clock.csv").open("a") as f:
        f.write("1.0,oops,2.0\n")
    (path / "cam1" / "00000005.jpg").unlink()
    rec = Recording.open(path)
    for _ in range(3):
        assert len(rec.index("cam1")) == 2
        assert len(rec.clock_samples("cam1")) == 1
        assert [f.seq for f in rec.frames("cam1")] == [7]
    assert list(rec.merged_frames()) and rec.skipped == {"bad index row": 1, "bad clock row": 1,
                                                         "missing frame file": 1}


def test_empty_index_is_an_error_naming_the_file(tmp_path):
    path = make(tmp_path)
    (path / "cam2" / "index.csv").write_text("seq,device_time,host_time,file\n")
    with pytest.raises(RecordingError, match=r"cam2.index\.csv.*empty index"):
        Recording.open(path).index("cam2")


@pytest.mark.parametrize("content,match", [
    (None, "missing"),
    ("{not json", "not valid JSON"),
    (json.dumps({"format": "other", "version": 1, "cameras": []}), "format"),
    (json.dumps({"format": "cubetrack.recording", "version": 9, "cameras": [{"name": "a"}]}), "version"),
    (json.dumps({"format": "cubetrack.recording", "version": 1, "cameras": [{"name": "../x"}]}), "folder name"),
])
def test_bad_recording_json_is_refused(tmp_path, content, match):
    path = make(tmp_path)
    meta = path / "recording.json"
    if content is None:
        meta.unlink()
    else:
        meta.write_text(content)
    with pytest.raises(RecordingError, match=match):
        Recording.open(path)


def test_writer_refuses_to_overwrite_a_recording(tmp_path):
    path = make(tmp_path)
    with pytest.raises(RecordingError, match="already holds a recording"):
        RecordingWriter(path, [CameraEntry("cam1")])
    assert len(Recording.open(path).index("cam1")) == 2  # nothing lost


def test_cut_short_recording_stays_readable(tmp_path):
    path = tmp_path / "rec"
    w = RecordingWriter(path, [CameraEntry("cam1")])
    w.add_frame("cam1", 1, 0.1, 100.0, jpeg(5))
    # no close(): a crash; rows were flushed as written
    assert [f.seq for f in Recording.open(path).frames("cam1")] == [1]
    w.close()
