"""`cubetrack import caliscope`: a small made-up caliscope project (two cameras, three frames each)
converted into a recording, camera_info, extrinsics, a board body and a config the tracker reads;
bad projects give one line naming the file and exit 1, and write no config."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tomli_w

import cubetrack.cli.main as cli_main
from cubetrack.app.config import load_config
from cubetrack.app.import_rig import import_caliscope
from cubetrack.core.errors import ConfigError
from cubetrack.core.geometry import make_T
from cubetrack.io.config import read_extrinsics
from cubetrack.io.recording import Recording

SIZE = (64, 48)
ROTATION = cv2.Rodrigues(np.array([0.2, -1.1, 0.4]))[0]
TRANSLATION = np.array([0.1, -0.2, 0.7])


def write_project(folder, frames=3, rows=3, size=SIZE):
    (folder / "calibration").mkdir(parents=True)
    (folder / "video").mkdir()
    cameras = {str(c): {"size": list(SIZE), "matrix": [[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]],
                        "distortions": [0.01, 0, 0, 0, 0], "rotation": ROTATION.tolist(),
                        "translation": TRANSLATION.tolist()} for c in (0, 1)}
    (folder / "calibration" / "camera_array.toml").write_text(tomli_w.dumps({"cameras": cameras}))
    (folder / "calibration" / "charuco.toml").write_text(tomli_w.dumps(
        {"columns": 4, "rows": 5, "dictionary": "DICT_4X4_1000", "aruco_scale": 0.75,
         "square_size_override_cm": 5.4, "inverted": True}))
    lines = ["sync_index,cam_id,frame_index,frame_time"]
    for c in (0, 1):
        writer = cv2.VideoWriter(str(folder / "video" / f"cam_{c}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 6, size)
        for i in range(frames):
            writer.write(np.full((size[1], size[0], 3), 40 * i, np.uint8))
        writer.release()
        lines += [f"{i},{c},{i},{10.0 + i / 6 + 0.003 * c}" for i in range(rows)]
    (folder / "video" / "timestamps.csv").write_text("\n".join(lines) + "\n")
    return folder


def test_a_caliscope_project_becomes_what_track_reads(tmp_path):
    result = import_caliscope(write_project(tmp_path / "project"), tmp_path / "out")
    assert result.frames == {"cam0": 3, "cam1": 3}
    recording = Recording.open(result.recording)
    assert [f.device_time_s for f in recording.frames("cam1")] == pytest.approx([10.003, 10.003 + 1 / 6,
                                                                                 10.003 + 2 / 6])
    assert all(s.host_send_s == s.device_time_s == s.host_recv_s for s in recording.clock_samples("cam0"))
    T = read_extrinsics(result.extrinsics)["cam1"].T_world_cam   # x_cam = R x_world + t
    np.testing.assert_allclose(T, np.linalg.inv(make_T(ROTATION, TRANSLATION)), atol=1e-9)
    config, params = load_config(result.config)
    layout = config.robots[0].layout
    assert sorted(layout.ids) == list(range(10)) and layout.sizes_m[0] == pytest.approx(0.0405)
    assert np.ptp(layout.corners_m[..., 2]) == pytest.approx(0.0)        # a flat board
    assert params.detector.detect_inverted_marker and not params.estimator.use_upright_prior
    assert config.world.dictionary == "DICT_4X4_1000" and config.world.marker_id not in layout.ids


@pytest.mark.parametrize(("change", "message"), [
    ({"rows": 2}, "more frames than its 2 rows in timestamps.csv"),
    ({"frames": 2}, "2 frames, but timestamps.csv has 3 rows"),
    ({"size": (32, 24)}, "frames are 32x24, the calibration's 64x48"),
])
def test_a_project_that_does_not_add_up_is_refused_in_one_line(tmp_path, capsys, change, message):
    project = write_project(tmp_path / "project", **change)
    with pytest.raises(ConfigError, match=message):
        import_caliscope(project, tmp_path / "out")
    assert cli_main.main(["import", "caliscope", str(project), "--out", str(tmp_path / "again")]) == 1
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]   # beside progress lines
    assert len(errors) == 1 and message in errors[0]
    assert not (tmp_path / "again" / "config.toml").exists()
