"""Every input the fuzzers (benchmarks/fuzz_campaign.py) and the property tests found that broke a
reader, as a regression test: each one used to escape as a raw Python exception (or exhaust
memory) and must now be the project's one-line error, or a skipped and counted row."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from cubetrack.core.errors import CameraInfoError, ConfigError, RecordingError
from cubetrack.core.layout import read_layout
from cubetrack.io.camera_info import read_camera_info
from cubetrack.io.config import read_extrinsics, read_tracker_config
from cubetrack.io.recording import Recording

INDEX_HEADER = b"seq,device_time,host_time,file\n"
CLOCK_HEADER = b"host_send,device_time,host_recv\n"
ROS_K = "camera_matrix: {data: [500, 0, 320, 0, 500, 240, 0, 0, 1]}\n"
OPENCV_K = ("camera_matrix: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n"
            "  data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\n")


def recording(tmp_path: Path, index: bytes = INDEX_HEADER + b"1,1.0,2.0,a.jpg\n", clock: bytes | None = None,
              meta: bytes | None = None) -> Recording:
    (tmp_path / "cam").mkdir(exist_ok=True)
    (tmp_path / "recording.json").write_bytes(meta or json.dumps(
        {"format": "cubetrack.recording", "version": 1, "cameras": [{"name": "cam"}]}).encode())
    (tmp_path / "cam" / "index.csv").write_bytes(index)
    if clock is not None:
        (tmp_path / "cam" / "clock.csv").write_bytes(clock)
    return Recording.open(tmp_path)


def test_a_clock_csv_that_is_not_utf8_is_a_recording_error(tmp_path):
    rec = recording(tmp_path, clock=CLOCK_HEADER + b"1.0,2.0,\x91\xff\n")
    with pytest.raises(RecordingError, match="clock.csv: unreadable"):
        rec.clock_samples("cam")


@pytest.mark.parametrize("row", [b"2,nan,3.0,b.jpg", b"2,1.0,inf,b.jpg", b"2,-inf,3.0,b.jpg"])
def test_index_rows_with_non_finite_times_are_skipped_and_counted(tmp_path, row):
    rec = recording(tmp_path, INDEX_HEADER + b"1,1.0,2.0,a.jpg\n" + row + b"\n")
    assert [r.seq for r in rec.index("cam")] == [1]
    assert rec.skipped == {"bad index row": 1}


def test_clock_rows_with_non_finite_times_are_skipped_and_counted(tmp_path):
    rec = recording(tmp_path, clock=CLOCK_HEADER + b"1.0,nan,1.1\ninf,2.0,2.1\n3.0,4.0,3.1\n")
    assert [s.device_time_s for s in rec.clock_samples("cam")] == [4.0]
    assert rec.skipped == {"bad clock row": 2}


def test_a_deeply_nested_recording_json_is_a_recording_error(tmp_path):
    with pytest.raises(RecordingError, match="not valid JSON"):
        recording(tmp_path, meta=b"[" * 5_000)


def test_an_alias_bomb_camera_info_is_refused_without_building_it(tmp_path):
    """400 bytes of YAML whose aliases expand to 9^10 numbers (28 GB of floats): before the fix it
    was handed to numpy whole (MemoryError, or the machine swapping)."""
    text, prev = "a: &a [1,1,1,1,1,1,1,1,1]\n", "a"
    for name in "bcdefghij":
        text += f"{name}: &{name} [" + ",".join([f"*{prev}"] * 9) + "]\n"
        prev = name
    path = tmp_path / "bomb.yaml"
    path.write_text(text + f"camera_matrix: {{data: *{prev}}}\nimage_width: 1\nimage_height: 1\n")
    with pytest.raises(CameraInfoError, match="camera_matrix must hold 9 numbers"):
        read_camera_info(path)


@pytest.mark.parametrize("text,message", [
    (ROS_K + "image_width: .inf\nimage_height: 480\n", "integer image_width"),
    ("[" * 1_000 + "]" * 1_000, "nested too deeply"),
    ("%YAML:1.0\n: : [\n", "not valid YAML"),
    ("%YAML:1.0\ncamera_matrix: {}\ndistortion_coefficients: {}\n", "camera_matrix must hold 9 numbers"),
    ("%YAML:1.0\ncamera_matrix: !!opencv-matrix\n  rows: 2\n  cols: 2\n  dt: d\n  data: [1, 2, 3, 4]\n",
     "camera_matrix must hold 9 numbers, has 4"),
    ("%YAML:1.0\n" + OPENCV_K + "image_width: .inf\nimage_height: 480\n", "integer image_width"),
    ("%YAML:1.0\ncamera_matrix: !!opencv-matrix [1, 2]\n", "not valid YAML"),
    (ROS_K + "distortion_coefficients: {data: {a: 1}}\nimage_width: 1\nimage_height: 1\n",
     "distortion_coefficients must hold a list of numbers"),
])
def test_malformed_camera_info_files_are_camera_info_errors(tmp_path, text, message):
    path = tmp_path / "cam.yaml"
    path.write_text(text)
    with pytest.raises(CameraInfoError, match=message):
        read_camera_info(path)


def test_a_malformed_opencv_matrix_does_not_abort_the_process(tmp_path):
    """The fuzzer's file: OpenCV's FileStorage reader (5.0.0) corrupted its heap on this matrix
    node and the process died of SIGABRT; OpenCV files are now read with PyYAML."""
    path = tmp_path / "cam.yaml"
    path.write_text("%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   `ols: 3\n   dt: d\n"
                    "   data: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\n")
    code = ("import sys\nfrom cubetrack.core.errors import CameraInfoError\nfrom cubetrack.io.camera_info import "
            "read_camera_info\ntry:\n    read_camera_info(sys.argv[1])\nexcept CameraInfoError as e:\n    print(e)\n")
    proc = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "not valid YAML" in proc.stdout


def test_older_opencv_files_without_a_size_still_read(tmp_path):
    path = tmp_path / "cam.yaml"
    path.write_text("%YAML:1.0\n" + OPENCV_K + "distortion_coefficients: !!opencv-matrix\n  rows: 5\n  cols: 1\n"
                    "  dt: d\n  data: [0.1, -0.2, 0.0, 0.0, 0.0]\n")
    intr = read_camera_info(path)
    assert (intr.width, intr.height) == (641, 481) and intr.K[0, 0] == 500 and intr.dist[1] == -0.2


LAYOUT = '[[markers]]\nface = "top"\nid = 1\nsize = 0.08\nposition = [0, 0, 0.055]\nquaternion_xyzw = [0, 0, 0, 1]\n'
ROBOT = '[[robots]]\nname = "bot"\nlayout = "cube.toml"\n'


@pytest.mark.parametrize("config,message", [
    ("cameras = 5\n" + ROBOT, "cameras must be"),
    ('robots = "bot"\n', "robots must be"),
    ('[[cameras]]\nname = "cam1"\ncamera_info = 5\n' + ROBOT, r"cameras\[0\].camera_info must be a file name"),
    ('[world]\nmarker_size = inf\n' + ROBOT, "marker_size.* must be a positive number"),
    ('[[robots]]\nname = "bot"\nlayout = "."\n', "cannot read the cube layout"),
    ("a = " + "[" * 5_000, "nested too deeply"),
])
def test_malformed_tracker_configs_are_config_errors(tmp_path, config, message):
    (tmp_path / "cube.toml").write_text(LAYOUT)
    (tmp_path / "tracker.toml").write_text(config)
    with pytest.raises(ConfigError, match=message):
        read_tracker_config(tmp_path / "tracker.toml")


@pytest.mark.parametrize("layout,message", [
    ("markers = [1, 2]\n", r"markers\[0\] must be a \[\[markers\]\] table"),
    ("markers = " + "[" * 5_000, "nested too deeply"),
])
def test_malformed_cube_layouts_are_config_errors(tmp_path, layout, message):
    (tmp_path / "cube.toml").write_text(layout)
    with pytest.raises(ConfigError, match=message):
        read_layout(tmp_path / "cube.toml")


@pytest.mark.parametrize("extra", ['samples = "x"', "samples = inf", 'spread_position_m = "x"',
                                   "spread_rotation_deg = [1]"])
def test_malformed_extrinsics_are_config_errors(tmp_path, extra):
    path = tmp_path / "e.toml"
    path.write_text(f"[cam1]\nposition = [0, 0, 1]\nquaternion_xyzw = [0, 0, 0, 1]\n{extra}\n")
    with pytest.raises(ConfigError, match=r"\[cam1\]: samples must be an integer"):
        read_extrinsics(path)
