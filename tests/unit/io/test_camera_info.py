from pathlib import Path

import numpy as np
import pytest

from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.errors import CameraInfoError
from cubetrack.io.camera_info import read_camera_info, write_camera_info

REAL = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "real" / "opencv-aruco-tutorial"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"{REAL} not present")


def test_ros_yaml_round_trip(tmp_path):
    K = np.array([[520.0, 0, 319.5], [0, 521.0, 239.5], [0, 0, 1]])
    intr = CameraIntrinsics(640, 480, K, np.array([0.1, -0.2, 0.001, 0.002, 0.05]), "cam1")
    write_camera_info(intr, tmp_path / "c.yaml")
    back = read_camera_info(tmp_path / "c.yaml")
    assert (back.width, back.height, back.camera_name) == (640, 480, "cam1")
    np.testing.assert_allclose(back.K, K)
    np.testing.assert_allclose(back.dist, intr.dist)
    text = (tmp_path / "c.yaml").read_text()
    for key in ("camera_matrix", "distortion_model: plumb_bob", "rectification_matrix", "projection_matrix"):
        assert key in text
    assert back.readout_s == 0.0 and "rolling_shutter" not in text  # a global shutter: plain ROS camera_info


def test_rolling_shutter_readout_round_trip_and_bad_values(tmp_path):
    K = np.array([[520.0, 0, 319.5], [0, 520.0, 239.5], [0, 0, 1]])
    write_camera_info(CameraIntrinsics(640, 480, K, np.zeros(5), "cam1", readout_s=0.03), tmp_path / "c.yaml")
    assert read_camera_info(tmp_path / "c.yaml").readout_s == 0.03
    text = (tmp_path / "c.yaml").read_text()
    for bad in ("-0.01", "'fast'", "2.0"):
        (tmp_path / "bad.yaml").write_text(text.replace("rolling_shutter_readout_s: 0.03",
                                                        f"rolling_shutter_readout_s: {bad}"))
        with pytest.raises(CameraInfoError, match="bad.yaml: rolling_shutter_readout_s"):
            read_camera_info(tmp_path / "bad.yaml")


@needs_real
def test_opencv_filestorage_yaml():
    intr = read_camera_info(REAL / "tutorial_camera_charuco.yml")
    assert (intr.width, intr.height) == (640, 480)
    assert intr.K[0, 0] == pytest.approx(452.51072219637672)
    assert intr.K[1, 2] == pytest.approx(277.75155919135995)
    assert intr.dist.shape == (5,)


@needs_real
def test_opencv_filestorage_without_size_infers_it():
    intr = read_camera_info(REAL / "tutorial_camera_params.yml")
    assert intr.K[0, 0] == pytest.approx(628.158)
    assert intr.width > 600 and intr.height > 500


@pytest.mark.parametrize("text,match", [
    ("image_width: 640\n", "not a ROS camera_info"),
    ("camera_matrix: {data: [1, 2]}\nimage_width: 1\nimage_height: 1\n", "9 numbers"),
    ("a: [\n", "not valid YAML"),
])
def test_bad_camera_info_is_refused_naming_the_file(tmp_path, text, match):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(CameraInfoError, match=match) as err:
        read_camera_info(p)
    assert "bad.yaml" in str(err.value)


def test_missing_camera_info(tmp_path):
    with pytest.raises(CameraInfoError, match="not found"):
        read_camera_info(tmp_path / "nope.yaml")
