"""`cubetrack detect IMAGE`: JSON out (contracts §6), one-line errors naming the file, exit 1."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scenes import render_in_front

import cubetrack.cli.main as cli_main
from cubetrack.core.cameras import CameraIntrinsics
from cubetrack.core.geometry import R_from_quat_xyzw, make_T, rotation_angle
from cubetrack.io.camera_info import write_camera_info

K = np.array([[520.0, 0.0, 319.5], [0.0, 520.0, 239.5], [0.0, 0.0, 1.0]])
T_CAM_MARKER = make_T(np.diag([1.0, -1.0, -1.0]) @ cv2.Rodrigues(np.array([0.3, 0.4, 0.1]))[0],
                      [0.03, -0.02, 0.7])


@pytest.fixture()
def files(tmp_path, monkeypatch):
    monkeypatch.setattr(cli_main, "COMMANDS", {"detect": "detect"})  # only this command's module
    img = render_in_front(CameraIntrinsics(640, 480, K, np.zeros(5)), [(T_CAM_MARKER, "DICT_6X6_250", 17, 0.05, 0.025)],
                          blur_px=0.6)
    image = tmp_path / "frame.jpg"
    cv2.imwrite(str(image), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
    ros = tmp_path / "cam_ros.yaml"
    write_camera_info(CameraIntrinsics(640, 480, K, np.zeros(5), "cam"), ros)
    opencv = tmp_path / "cam_opencv.yml"
    fs = cv2.FileStorage(str(opencv), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.zeros((1, 5)))
    fs.release()
    return tmp_path, image, ros, opencv


@pytest.mark.parametrize("info", ["cam_ros.yaml", "cam_opencv.yml"])
def test_detect_prints_markers_with_poses(files, capsys, info):
    folder, image, _ros, _opencv = files
    rc = cli_main.main(["detect", str(image), "--camera-info", str(folder / info),
                        "--dictionary", "DICT_6X6_250", "--marker-size", "0.05"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["corner_refinement"] == "edge" and out["width"] == 640
    [marker] = out["markers"]
    assert marker["id"] == 17 and marker["dictionary"] == "DICT_6X6_250"
    assert np.array(marker["corners_px"]).shape == (4, 2) and marker["area_px2"] > 100
    pose = marker["pose"]
    assert np.allclose(pose["position"], T_CAM_MARKER[:3, 3], atol=2e-3)
    R = R_from_quat_xyzw(np.array(pose["quaternion_xyzw"]))
    assert rotation_angle(R, T_CAM_MARKER[:3, :3], "deg") < 1.0
    assert pose["reprojection_error_px"] < 0.5


def test_detect_without_intrinsics_prints_no_pose(files, capsys):
    _folder, image, _ros, _opencv = files
    assert cli_main.main(["detect", str(image), "--dictionary", "DICT_6X6_250",
                          "--refinement", "subpix", "--indent", "0"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["corner_refinement"] == "subpix"
    assert [m["id"] for m in out["markers"]] == [17] and "pose" not in out["markers"][0]


@pytest.mark.parametrize("make_args, needle", [
    (lambda f: ["detect", str(f[0] / "missing.jpg")], "missing.jpg: image file not found"),
    (lambda f: ["detect", str(f[0] / "broken.jpg")], "broken.jpg: truncated JPEG"),
    (lambda f: ["detect", str(f[1]), "--dictionary", "DICT_9X9_1"], "valid names: DICT_4X4_100"),
    (lambda f: ["detect", str(f[1]), "--camera-info", str(f[0] / "none.yaml"), "--marker-size", "0.05"],
     "none.yaml: camera_info file not found"),
    (lambda f: ["detect", str(f[1]), "--camera-info", str(f[2])], "--marker-size"),
])
def test_bad_input_is_one_line_and_exit_1(files, capsys, make_args, needle):
    (files[0] / "broken.jpg").write_bytes(files[1].read_bytes()[:2000])
    assert cli_main.main(make_args(files)) == 1
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1 and err.startswith("cubetrack detect: error:")


def test_detect_inverted_finds_a_white_on_black_marker_with_its_pose(files, capsys):
    folder, image, ros, _opencv = files
    negative = folder / "negative.png"
    cv2.imwrite(str(negative), 255 - cv2.imread(str(image), cv2.IMREAD_GRAYSCALE))
    args = ["detect", str(negative), "--camera-info", str(ros), "--dictionary", "DICT_6X6_250", "--marker-size", "0.05"]
    assert cli_main.main(args) == 0
    assert json.loads(capsys.readouterr().out)["markers"] == []
    assert cli_main.main([*args, "--inverted"]) == 0
    out = json.loads(capsys.readouterr().out)
    [marker] = out["markers"]
    assert marker["id"] == 17 and out["dropped"] == {}
    assert np.allclose(marker["pose"]["position"], T_CAM_MARKER[:3, 3], atol=2e-3)
